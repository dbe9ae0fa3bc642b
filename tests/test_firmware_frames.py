"""The firmware's frame encoder (firmware/src/gyro_frame.c), compiled natively, against the
host side of docs/gyro-protocol.md: the same bytes as ``timedexec.sensors.encode_frames``,
and a stream that ``FrameParser`` decodes whole, over 10^5 random samples with counter wraps
and sync patterns inside the payload."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from tests.firmware_build import host_compiler, make

from timedexec.sensors import FRAME_SIZE, FrameParser, crc8, encode_frames

N_SAMPLES = 100_000


@pytest.fixture(scope="module")
def encoder(tmp_path_factory: pytest.TempPathFactory) -> ctypes.CDLL:
    """firmware/src/gyro_frame.c as a host shared library (``make host-lib``)."""
    host_compiler()
    build = tmp_path_factory.mktemp("firmware-host")
    make(build, "host-lib", timeout_s=120)
    lib = ctypes.CDLL(str(build / "libgyroframe.so"))
    lib.gyro_crc8.argtypes = [ctypes.c_char_p, ctypes.c_uint8]
    lib.gyro_crc8.restype = ctypes.c_uint8
    lib.gyro_frame_encode.argtypes = [
        ctypes.c_void_p,
        ctypes.c_uint16,
        ctypes.c_int16,
        ctypes.c_int16,
        ctypes.c_int16,
    ]
    lib.gyro_frame_encode.restype = None
    return lib


def _encode_with_c(lib: ctypes.CDLL, counter: np.ndarray, raw: np.ndarray) -> bytes:
    out = ctypes.create_string_buffer(FRAME_SIZE * counter.shape[0])
    base = ctypes.addressof(out)
    encode = lib.gyro_frame_encode
    for i, (c, (x, y, z)) in enumerate(zip(counter.tolist(), raw.tolist(), strict=True)):
        encode(base + FRAME_SIZE * i, c, x, y, z)
    return out.raw


def _samples(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """10^5 samples: a consecutive counter from 60,000 (it wraps at 65536 twice), random
    rates, and one rate in eight replaced by a value whose bytes are a sync pattern
    (0x5AA5 is A5 5A little-endian; 0xA55A, 0x00A5 and 0x5A00 put the pair across two
    fields)."""
    rng = np.random.default_rng(seed)
    counter = ((60_000 + np.arange(N_SAMPLES)) % 65536).astype(np.uint16)
    raw = rng.integers(-32768, 32768, (N_SAMPLES, 3)).astype(np.int16)
    sync_like = np.array([0x5AA5, 0xA55A - 65536, 0x00A5, 0x5A00], dtype=np.int16)
    pick = rng.random((N_SAMPLES, 3)) < 1 / 8
    raw[pick] = rng.choice(sync_like, int(pick.sum()))
    return counter, raw


def test_crc_check_value(encoder: ctypes.CDLL) -> None:
    """The C CRC is CRC-8/SMBUS: check value 0xF4, and equal to the host's crc8 on random
    messages of every length up to 255 bytes."""
    assert encoder.gyro_crc8(b"123456789", 9) == 0xF4
    rng = np.random.default_rng(7)
    for n in range(256):
        msg = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert encoder.gyro_crc8(msg, n) == crc8(msg)


def test_c_encoder_bytes_equal_the_python_encoder(encoder: ctypes.CDLL) -> None:
    """Over 10^5 samples (counter wraps twice, sync-like payloads) the C encoder's bytes
    equal encode_frames' byte for byte; also for random, non-consecutive counters and the
    int16 extremes."""
    counter, raw = _samples(seed=1)
    assert _encode_with_c(encoder, counter, raw) == encode_frames(counter, raw)
    rng = np.random.default_rng(2)
    odd = rng.integers(0, 65536, 2000).astype(np.uint16)
    extremes = np.array([[-32768, 32767, 0], [32767, -32768, -1], [-1, 1, 0x5AA5]] * 667)[:2000]
    raw2 = extremes.astype(np.int16)
    assert _encode_with_c(encoder, odd, raw2) == encode_frames(odd, raw2)


def test_parser_decodes_the_c_stream_whole_in_any_chunking(encoder: ctypes.CDLL) -> None:
    """The C-encoded stream, fed to FrameParser in random chunks of 1..4096 bytes, decodes
    to every sample in order: no checksum error, no byte skipped, the counters with their
    two wraps, the rates exactly, although one rate in eight holds a sync pattern."""
    counter, raw = _samples(seed=3)
    stream = _encode_with_c(encoder, counter, raw)
    # one sync pair per frame, plus ~3/8 x 1/4 x N = 9,400 expected inside payloads (0x5AA5)
    assert stream.count(b"\xa5\x5a") - N_SAMPLES > 8000
    rng = np.random.default_rng(4)
    parser = FrameParser()
    got_counter, got_raw = [], []
    pos = 0
    while pos < len(stream):
        step = int(rng.integers(1, 4097))
        part = parser.feed(stream[pos : pos + step])
        got_counter.append(part.counter)
        got_raw.append(part.raw)
        pos += step
    tail = parser.flush()
    got_counter.append(tail.counter)
    got_raw.append(tail.raw)
    np.testing.assert_array_equal(np.concatenate(got_counter), counter)
    np.testing.assert_array_equal(np.concatenate(got_raw), raw)
    assert parser.frames_ok == N_SAMPLES
    assert parser.checksum_errors == 0
    assert parser.resync_bytes_skipped == 0
    wraps = np.flatnonzero(np.diff(counter.astype(np.int64)) < 0)
    assert wraps.size == 2
