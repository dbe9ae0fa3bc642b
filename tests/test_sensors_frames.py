"""Gyro frame format: CRC claims, encoder, and the resynchronising parser."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from timedexec.errors import ConfigError
from timedexec.sensors import FRAME_SIZE, SYNC, FrameParser, crc8, encode_frames


def _frame_ok(frame: bytes) -> bool:
    return frame[:2] == SYNC and crc8(frame[2:10]) == frame[10]


def _valid_starts(stream: bytes) -> list[int]:
    """Brute force: every position where a sync pattern starts a CRC-valid frame."""
    return [p for p in range(len(stream) - FRAME_SIZE + 1) if _frame_ok(stream[p : p + FRAME_SIZE])]


def _parse_all(stream: bytes, chunk_sizes: list[int] | None = None):  # type: ignore[no-untyped-def]
    parser = FrameParser()
    pieces = []
    if chunk_sizes is None:
        pieces.append(parser.feed(stream))
    else:
        pos = 0
        sizes = itertools.cycle(chunk_sizes)
        while pos < len(stream):
            size = next(sizes)
            pieces.append(parser.feed(stream[pos : pos + size]))
            pos += size
    pieces.append(parser.flush())
    counter = np.concatenate([p.counter for p in pieces])
    raw = np.concatenate([p.raw for p in pieces])
    end = np.concatenate([p.end_offset for p in pieces])
    return parser, counter, raw, end


# -- CRC ------------------------------------------------------------------------------


def test_crc8_check_value() -> None:
    """The CRC is CRC-8/SMBUS: poly 0x07, init 0, check value 0xF4 for b"123456789"."""
    assert crc8(b"123456789") == 0xF4
    assert crc8(b"") == 0


def test_crc_detects_every_single_byte_and_small_bit_error() -> None:
    """Exhaustive check of what docs/gyro-protocol.md claims: every single-byte error and
    every 1-, 2- and 3-bit error in the 9 checked bytes (payload + CRC) is detected, and so is
    every swap of two different adjacent bytes."""
    rng = np.random.default_rng(1)
    for _ in range(3):
        frame = np.frombuffer(
            encode_frames(rng.integers(0, 65536, 1), rng.integers(-32768, 32768, (1, 3))),
            np.uint8,
        )
        base = frame[2:].copy()  # 8 payload bytes + CRC

        def ok(m: np.ndarray) -> bool:
            return crc8(bytes(m[:8])) == int(m[8])

        assert ok(base)
        for pos in range(9):
            for value in range(1, 256):
                m = base.copy()
                m[pos] ^= value
                assert not ok(m), (pos, value)
        flips = [(i // 8, 1 << (i % 8)) for i in range(72)]
        for count in (2, 3):
            for combo in itertools.combinations(range(72), count):
                m = base.copy()
                for bit in combo:
                    m[flips[bit][0]] ^= flips[bit][1]
                assert not ok(m), combo
        for pos in range(8):
            if base[pos] != base[pos + 1]:
                m = base.copy()
                m[pos], m[pos + 1] = m[pos + 1], m[pos]
                assert not ok(m), pos


# -- encoder --------------------------------------------------------------------------


def test_encode_layout_is_little_endian_with_sync_and_crc() -> None:
    """One frame, byte by byte: sync, uint16 LE counter, 3 x int16 LE, CRC-8 of bytes 2..9."""
    data = encode_frames([0x1234], [[1, -2, 0x7FFF]])
    assert len(data) == FRAME_SIZE
    assert data[:2] == b"\xa5\x5a"
    assert data[2:4] == b"\x34\x12"
    assert data[4:10] == b"\x01\x00\xfe\xff\xff\x7f"
    assert data[10] == crc8(data[2:10])


@pytest.mark.parametrize(
    ("counter", "raw", "message"),
    [
        ([[1, 2]], [[0, 0, 0]], "shape (n,)"),
        ([1, 2], [[0, 0, 0]], "(2, 3)"),
        ([70000], [[0, 0, 0]], "0..65535"),
        ([-1], [[0, 0, 0]], "0..65535"),
        ([1], [[0, 40000, 0]], "-32768..32767"),
        ([1.5], [[0, 0, 0]], "integers"),
    ],
)
def test_encode_rejects_bad_input(counter: list, raw: list, message: str) -> None:  # type: ignore[type-arg]
    """Bad shapes and out-of-range values raise ConfigError naming the constraint."""
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        encode_frames(counter, raw)


# -- parser: deterministic cases ------------------------------------------------------


def test_roundtrip_clean_stream_any_chunking() -> None:
    """A clean stream decodes to exactly what was encoded, fed whole or byte by byte."""
    rng = np.random.default_rng(2)
    counter = (np.arange(500) + 65400) % 65536
    raw = rng.integers(-32768, 32768, (500, 3))
    stream = encode_frames(counter, raw)
    for chunks in (None, [1], [7, 3, 50], [4096]):
        parser, c, r, end = _parse_all(stream, chunks)
        np.testing.assert_array_equal(c, counter)
        np.testing.assert_array_equal(r, raw)
        np.testing.assert_array_equal(end, np.arange(1, 501) * FRAME_SIZE)
        assert parser.frames_ok == 500
        assert parser.checksum_errors == 0
        assert parser.resync_bytes_skipped == 0


def test_feed_holds_back_at_most_two_frames() -> None:
    """feed() decides every frame except those within the last 21 bytes (so that it sees
    both neighbours of each candidate); flush() decides the rest."""
    stream = encode_frames(np.arange(10), np.zeros((10, 3), np.int16))
    parser = FrameParser()
    first = parser.feed(stream)
    assert len(first) == 9  # start 99 + 22 > 110: the last frame waits
    assert parser.pending_bytes == FRAME_SIZE
    assert len(parser.flush()) == 1


def test_sync_pattern_inside_payload_does_not_break_alignment() -> None:
    """Raw values whose bytes spell the sync pattern (0xA5 0x5A) are decoded normally."""
    sync_as_int16 = int(np.frombuffer(SYNC, "<i2")[0])
    counter = np.arange(50)
    raw = np.full((50, 3), sync_as_int16)
    raw[:, 1] = 0x5AA5 - 65536 if 0x5AA5 > 32767 else 0x5AA5
    _, c, r, _ = _parse_all(encode_frames(counter, raw), [13])
    np.testing.assert_array_equal(c, counter)
    np.testing.assert_array_equal(r, raw)


def test_corrupted_payload_byte_costs_one_frame() -> None:
    """A flipped payload byte: that frame is dropped with one checksum error and its 11
    bytes skipped; every other frame is recovered."""
    stream = bytearray(encode_frames(np.arange(20), np.ones((20, 3), np.int16)))
    stream[5 * FRAME_SIZE + 6] ^= 0x10
    parser, c, _, _ = _parse_all(bytes(stream), [16])
    np.testing.assert_array_equal(c, np.delete(np.arange(20), 5))
    assert parser.checksum_errors == 1
    assert parser.resync_bytes_skipped == FRAME_SIZE


def test_truncated_frame_and_garbage_resync() -> None:
    """A frame cut after 6 bytes and 37 bytes of garbage in front are skipped; the parser
    resynchronises on the next intact frame."""
    frames = encode_frames(np.arange(10), np.zeros((10, 3), np.int16))
    garbage = bytes(np.random.default_rng(3).integers(0, 256, 37, dtype=np.uint8))
    stream = garbage + frames[: 3 * FRAME_SIZE + 6] + frames[4 * FRAME_SIZE :]
    parser, c, _, _ = _parse_all(stream, [5])
    np.testing.assert_array_equal(c, [0, 1, 2, 4, 5, 6, 7, 8, 9])
    # Everything that is not a decoded frame was skipped, nothing is left over.
    assert parser.resync_bytes_skipped + FRAME_SIZE * 9 + parser.pending_bytes == len(stream)


def test_never_raises_on_pure_garbage() -> None:
    """Random bytes: no exception, the byte balance holds, and whatever is decoded is a
    CRC-valid frame (about one chance match per 65536 · 256 positions)."""
    rng = np.random.default_rng(4)
    stream = rng.integers(0, 256, 200_000, dtype=np.uint8).tobytes()
    parser, c, _, end = _parse_all(stream, [1000, 17])
    for e in end.tolist():
        assert _frame_ok(stream[e - FRAME_SIZE : e])
    assert parser.resync_bytes_skipped + FRAME_SIZE * len(c) + parser.pending_bytes == len(stream)


def test_parsing_is_fast_enough_for_8khz() -> None:
    """10 s of stream (880 kB) in 20 ms chunks parses in well under 10 s of one core.

    Hot, the parser needs about 50 µs per 20 ms chunk (0.25 %); the 0.5 s band leaves
    room for a loaded CI machine and still fails a per-byte Python parser (about 2 s).
    """
    n = 80_000
    stream = encode_frames(np.arange(n) % 65536, np.zeros((n, 3), np.int16))
    parser = FrameParser()
    t0 = time.process_time()
    for i in range(0, len(stream), 1760):
        parser.feed(stream[i : i + 1760])
    parser.flush()
    elapsed = time.process_time() - t0
    assert parser.frames_ok == n
    assert elapsed < 0.5


def test_statistics_on_a_faulty_stream() -> None:
    """20,000 frames with 1 % of them hit by a fault (truncation, corrupted byte, inserted
    garbage): every frame not hit is recovered, bar at most a handful lost to chance CRC
    matches (expected about 200 faults / 256 collisions, each costing at most one frame)."""
    rng = np.random.default_rng(5)
    n = 20_000
    frames = encode_frames(np.arange(n) % 65536, rng.integers(-2000, 2000, (n, 3)))
    out = bytearray()
    intact = []
    for k in range(n):
        frame = frames[k * FRAME_SIZE : (k + 1) * FRAME_SIZE]
        u = rng.random()
        if u < 0.0033:
            out += frame[: rng.integers(1, FRAME_SIZE)]
        elif u < 0.0066:
            bad = bytearray(frame)
            bad[rng.integers(0, FRAME_SIZE)] ^= int(rng.integers(1, 256))
            out += bad
        elif u < 0.01:
            out += rng.integers(0, 256, rng.integers(1, 30), dtype=np.uint8).tobytes() + frame
            intact.append(k)
        else:
            out += frame
            intact.append(k)
    _, c, _, _ = _parse_all(bytes(out), [1760])
    recovered = set(c.tolist())
    lost = [k for k in intact if k % 65536 not in recovered]
    assert len(lost) <= 3


# -- parser: fuzzing ------------------------------------------------------------------

_fault = st.one_of(
    st.tuples(st.just("ok")),
    st.tuples(st.just("truncate"), st.integers(1, FRAME_SIZE - 1)),
    st.tuples(st.just("corrupt"), st.integers(0, FRAME_SIZE - 1), st.integers(1, 255)),
    st.tuples(st.just("garbage"), st.binary(min_size=1, max_size=40)),
    st.tuples(st.just("drop_sync")),
)


@settings(
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
@given(
    faults=st.lists(_fault, min_size=1, max_size=60),
    raw_seed=st.integers(0, 2**32 - 1),
    chunks=st.lists(st.integers(1, 64), min_size=1, max_size=8),
)
def test_fuzz_parser_recovers_every_unambiguous_intact_frame(
    faults: list[tuple],
    raw_seed: int,
    chunks: list[int],  # type: ignore[type-arg]
) -> None:
    """Random streams of frames, truncations, corrupted bytes, garbage and lost sync bytes,
    fed in random chunk sizes: the parser never raises; every decoded frame is a CRC-valid
    frame in the stream and decoded frames do not overlap; every intact frame that no other
    CRC-valid candidate overlaps is recovered; the byte balance holds; and the result does
    not depend on how the stream was chunked."""
    rng = np.random.default_rng(raw_seed)
    n = len(faults)
    raw = rng.integers(-32768, 32768, (n, 3))
    frames = encode_frames(np.arange(n), raw)
    stream = bytearray()
    intact_at: list[int] = []
    for k, fault in enumerate(faults):
        frame = bytearray(frames[k * FRAME_SIZE : (k + 1) * FRAME_SIZE])
        kind = fault[0]
        if kind == "ok":
            intact_at.append(len(stream))
            stream += frame
        elif kind == "truncate":
            stream += frame[: fault[1]]
        elif kind == "corrupt":
            frame[fault[1]] ^= fault[2]
            stream += frame
        elif kind == "garbage":
            stream += fault[1]
        else:
            stream += frame[1:]
    data = bytes(stream)
    parser, c, r, end = _parse_all(data, chunks)
    starts = (end - FRAME_SIZE).tolist()
    valid = _valid_starts(data)
    valid_set = set(valid)
    assert all(s in valid_set for s in starts)
    assert all(b - a >= FRAME_SIZE for a, b in itertools.pairwise(starts))
    decoded = set(starts)
    for p in intact_at:
        if not any(q != p and abs(q - p) < FRAME_SIZE for q in valid):
            assert p in decoded
    assert parser.frames_ok == len(starts)
    assert parser.resync_bytes_skipped + FRAME_SIZE * len(starts) + parser.pending_bytes == len(
        data
    )
    _, c_whole, r_whole, end_whole = _parse_all(data, None)
    np.testing.assert_array_equal(end_whole, end)
    np.testing.assert_array_equal(c_whole, c)
    np.testing.assert_array_equal(r_whole, r)


def _search(predicate, rng, tries=20_000):  # type: ignore[no-untyped-def]
    for _ in range(tries):
        found = predicate(rng)
        if found is not None:
            return found
    raise AssertionError("no example found")  # pragma: no cover


def test_chance_crc_match_across_truncation_prefers_the_intact_frame() -> None:
    """A truncated frame whose first 11 bytes (its 7 bytes plus the next frame's first 4)
    happen to pass the CRC overlaps the intact frame after it. Both have one valid
    neighbour; the tie goes to the later candidate, which is the intact frame."""
    rng = np.random.default_rng(6)
    before = encode_frames(np.arange(3), np.zeros((3, 3), np.int16))
    after = encode_frames(np.arange(4, 8), np.zeros((4, 3), np.int16))

    def attempt(rng: np.random.Generator) -> bytes | None:
        cut = encode_frames([3], rng.integers(-32768, 32768, (1, 3)))[:7]
        return cut if _frame_ok(cut + after[:4]) else None

    cut = _search(attempt, rng)
    stream = before + cut + after
    assert _valid_starts(stream).count(33) == 1  # the chance match exists
    for chunks in (None, [1], [9], [30]):
        _, c, _, _ = _parse_all(stream, chunks)
        np.testing.assert_array_equal(c, [0, 1, 2, 4, 5, 6, 7])


def test_chance_match_inside_a_payload_loses_to_the_chain() -> None:
    """A sync pattern inside an intact frame's payload that also passes the CRC (with bytes
    taken from the next frame) overlaps two chained frames; the chain wins."""
    sync_word = int(np.frombuffer(SYNC, "<i2")[0])
    raw = np.random.default_rng(7).integers(-32768, 32768, (6, 3))
    raw[2, 0] = sync_word  # frame 2, bytes 4..5 spell the sync pattern
    for high in range(256):  # frame 3's counter high byte is the window's CRC byte
        counter = np.array([0, 1, 2, 3 + 256 * high, 4, 5])
        stream = encode_frames(counter, raw)
        if _frame_ok(stream[2 * FRAME_SIZE + 4 : 3 * FRAME_SIZE + 4]):
            break
    else:  # pragma: no cover
        raise AssertionError("no chance match found")
    assert 2 * FRAME_SIZE + 4 in _valid_starts(stream)
    for chunks in (None, [1], [12]):
        _, c, _, _ = _parse_all(stream, chunks)
        np.testing.assert_array_equal(c, counter)
