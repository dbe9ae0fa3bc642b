"""The simulated gyro: sensor model, device-side framing, pty streaming, fault injection."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from timedexec.errors import ConfigError, SensorError
from timedexec.sensors import FRAME_SIZE, FrameParser, encode_frames
from timedexec.sim import (
    DEFAULT_BIAS_DPS,
    FULL_SCALE_SENSITIVITY,
    GyroFrameSource,
    constant_rate_source,
    device_frames,
    sine_rate_source,
    step_rate_source,
)
from timedexec.twins import GyroTwin, Twin


def _decode(data: bytes) -> tuple[np.ndarray, np.ndarray, FrameParser]:
    parser = FrameParser()
    a = parser.feed(data)
    b = parser.flush()
    return np.r_[a.counter, b.counter], np.r_[a.raw, b.raw], parser


@settings(max_examples=50, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 300))
def test_device_encoder_matches_host_encoder(seed: int, n: int) -> None:
    """The twin's firmware-style encoder and timedexec.sensors.encode_frames produce the
    same bytes: both implement docs/gyro-protocol.md."""
    rng = np.random.default_rng(seed)
    counter = rng.integers(0, 65536, n).astype(np.uint16)
    raw = rng.integers(-32768, 32768, (n, 3)).astype(np.int16)
    assert device_frames(counter, raw) == encode_frames(counter, raw)


def test_sensitivities_agree_with_the_sensor_layer() -> None:
    """The twin and the reader use the same datasheet sensitivities."""
    from timedexec.sensors import SENSITIVITY_LSB_PER_DPS

    assert FULL_SCALE_SENSITIVITY == SENSITIVITY_LSB_PER_DPS


def test_frame_source_noise_bias_and_counter() -> None:
    """Still sensor, 80,000 samples: counters run k % 65536; the mean is the bias (within
    4 standard errors, 0.316/√80000 °/s each, plus half an LSB of rounding); the std
    matches the noise density times √(f/2) within 2 % (sampling error of a std over 80,000
    samples is 0.25 %; quantisation adds (1/65.5)²/12, negligible)."""
    source = GyroFrameSource(seed=3)
    counter, raw, _ = _decode(source.generate(80_000))
    np.testing.assert_array_equal(counter, np.arange(80_000) % 65536)
    dps = raw / 65.5
    sigma = 0.005 * math.sqrt(4000)
    np.testing.assert_allclose(
        dps.mean(axis=0), DEFAULT_BIAS_DPS, atol=4 * sigma / math.sqrt(80_000) + 0.5 / 65.5
    )
    np.testing.assert_allclose(dps.std(axis=0), sigma, rtol=0.02)
    assert source.true_rate_hz == pytest.approx(8024.0)
    assert source.samples_due(0.0) == 1
    assert source.samples_due(1.0) == 8025
    assert source.samples_due(-0.1) == 0


def test_frame_source_rate_source_shapes_and_group_delay() -> None:
    """A (3,) source is constant; a (k, 3) grid is interpolated to the sample times; the
    content is delayed by the DLPF group delay; wrong shapes are rejected."""
    calls: list[tuple[float, float]] = []

    def ramp(t0: float, t1: float) -> np.ndarray:
        calls.append((t0, t1))
        t = t0 + np.arange(50) * (t1 - t0) / 50
        return np.stack([t, 2 * t, np.zeros_like(t)], axis=1)

    source = GyroFrameSource(
        ramp, record_truth=True, noise_density_dps_rthz=0.0, bias_dps=(0, 0, 0)
    )
    source.generate(40)
    k, truth = source.truth()
    t_content = k / source.true_rate_hz - 0.98e-3
    np.testing.assert_allclose(truth[:, 0], t_content, atol=1e-12)
    np.testing.assert_allclose(truth[:, 1], 2 * t_content, atol=1e-12)
    assert calls[0][0] == pytest.approx(-0.98e-3)

    const = GyroFrameSource(constant_rate_source([0.1, 0.2, 0.3]), noise_density_dps_rthz=0)
    const.bias_dps[:] = 0
    _, raw, _ = _decode(const.generate(10))
    np.testing.assert_allclose(raw / 65.5, np.degrees([[0.1, 0.2, 0.3]] * 10), atol=0.5 / 65.5)

    bad = GyroFrameSource(lambda t0, t1: np.zeros((4, 2)))
    with pytest.raises(ConfigError, match=r"\(4, 2\)"):
        bad.generate(5)


def test_full_scale_saturates_like_int16() -> None:
    """Rates beyond the range clip to the int16 limits instead of wrapping around."""
    source = GyroFrameSource(constant_rate_source([math.radians(600), math.radians(-600), 0]))
    _, raw, _ = _decode(source.generate(5))
    assert (raw[:, 0] == 32767).all()
    assert (raw[:, 1] == -32768).all()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"full_scale_dps": 300}, r"full_scale_dps=300 .*250, 500, 1000, 2000"),
        ({"clock_error_ppm": 2e5}, "clock_error_ppm=200000"),
        ({"noise_density_dps_rthz": -1}, "noise_density_dps_rthz=-1"),
        ({"bias_dps": (1, 2)}, "bias_dps must be 3"),
        ({"burst_period_s": 1.0}, "burst_period_s=1.0"),
    ],
)
def test_twin_rejects_bad_settings(kwargs: dict, message: str) -> None:  # type: ignore[type-arg]
    """Every bad setting raises ConfigError naming the value and what is allowed."""
    with pytest.raises(ConfigError, match=message):
        GyroTwin(**kwargs)


def test_sources_validate_axis() -> None:
    """Helper sources reject an axis outside x, y, z."""
    with pytest.raises(ConfigError, match="axis=3"):
        sine_rate_source(1.0, 1.0, axis=3)
    with pytest.raises(ConfigError, match="axis=-1"):
        step_rate_source(1.0, 1.0, axis=-1)


def test_twin_streams_8bit_clean_frames_in_real_time(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Over ~1 s through the pty, read with pyserial: every byte value survives (no CR/LF
    translation, no XON/XOFF, no echo: zero checksum errors over ~88,000 bytes of random
    payload), counters are consecutive, and the number of samples sent matches the true
    rate times the elapsed time within 2 bursts (timing band, not a point)."""
    link = tmp_path / "gyro"
    with GyroTwin(link_path=str(link), noise_density_dps_rthz=5.0, seed=4) as twin:
        assert os.path.islink(link)
        assert os.path.realpath(link) == os.path.realpath(twin.slave_path)
        assert twin.port == str(link)
        with serial.Serial(twin.port, timeout=0.05) as port:
            t0 = time.monotonic()
            data = bytearray()
            while time.monotonic() - t0 < 1.0:
                data += port.read(max(port.in_waiting, 1))
        elapsed = time.monotonic() - twin.start_time_s
        sent = twin.samples_sent
        assert abs(sent - twin.true_rate_hz * elapsed) < 2 * 8.1 + 80  # 2 bursts + read lag
    assert not os.path.lexists(link)
    counter, _, parser = _decode(bytes(data))
    assert parser.checksum_errors == 0
    assert len(counter) > 7000
    assert np.all(np.diff(counter.astype(np.int64)) % 65536 == 1)
    assert set(bytes(data)) == set(range(256))  # every byte value went through


def test_fault_injection_shows_up_in_the_parser() -> None:
    """Corrupted, dropped and inserted bytes reach the reader as checksum errors, lost
    frames and skipped bytes; the fault log records each fault."""
    faults = ["inject_corruption", "drop_bytes", "insert_garbage"]
    arguments = {"drop_bytes": 5, "insert_garbage": 30}
    data = bytearray()
    with GyroTwin() as twin, serial.Serial(twin.slave_path, timeout=0.01) as port:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.4:
            data += port.read(max(port.in_waiting, 1))
            due = int((time.monotonic() - t0) / 0.08)  # one fault every 80 ms
            if faults and due > 3 - len(faults):
                name = faults.pop(0)
                if name == "inject_corruption":
                    twin.inject_corruption(1, skip_bytes=6)  # a payload byte: CRC error
                else:
                    getattr(twin, name)(arguments[name])
    assert not faults
    kinds = [kind for kind, _, _ in twin.fault_log]
    assert kinds == ["corrupt", "drop", "garbage"]
    counter, _, parser = _decode(bytes(data))
    steps = np.diff(counter.astype(np.int64)) % 65536
    # Corruption costs 1 frame; 5 dropped bytes cost the frame they cut.
    assert 2 <= int((steps - 1).sum()) <= 3
    assert parser.checksum_errors >= 1
    assert parser.resync_bytes_skipped >= 30


def test_fault_counts_are_validated() -> None:
    """Negative byte counts are rejected."""
    twin = GyroTwin()
    with pytest.raises(ConfigError, match="n_bytes=-1"):
        twin.inject_corruption(-1)
    with pytest.raises(SensorError, match="not started"):
        _ = twin.slave_path


def test_link_path_must_not_clobber_a_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A link_path that is a regular file is refused, and the file is left alone."""
    target = tmp_path / "precious"
    target.write_text("keep")
    with pytest.raises(ConfigError, match="not a symlink"), GyroTwin(link_path=str(target)):
        pass
    assert target.read_text() == "keep"


def test_unread_backlog_is_dropped_like_a_usb_device() -> None:
    """With nobody reading, the pty buffer fills and the twin drops the oldest bytes
    instead of blocking or growing without bound."""
    with GyroTwin(max_backlog_s=0.02) as twin:
        deadline = time.monotonic() + 5.0
        while twin.bytes_dropped_overflow == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert twin.bytes_dropped_overflow > 0
        assert twin.error is None


def test_twin_lifecycle_stall_kill_and_drop() -> None:
    """GyroTwin is driven like every twin: stall(s) delivers nothing for s seconds while the
    sensor keeps sampling, then the backlog follows (counters without a gap); kill() makes
    the device vanish; drop() has no meaning on a serial link and says what to use; a
    stall before start or with a NaN duration is refused."""
    twin = GyroTwin()
    assert isinstance(twin, Twin)
    with pytest.raises(NotImplementedError, match="drop_bytes"):
        twin.drop()
    with pytest.raises(ConfigError, match="must be >= 0"):
        twin.stall(math.nan)
    with pytest.raises(SensorError, match="not started"):
        twin.stall(0.1)
    stall_s = 0.4  # below max_backlog_s (0.5 s): the stalled data is kept, not dropped
    data = bytearray()
    with twin, serial.Serial(twin.slave_path, timeout=0.01) as port:
        assert twin.is_alive
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.1:
            data += port.read(max(port.in_waiting, 1))
        twin.stall(stall_s)
        t_stall = time.monotonic()
        # Poll the delivery counter inside the stall (after the burst that may have been
        # on its way when stall() was called, before the stall ends).
        polls = []
        while time.monotonic() < t_stall + stall_s + 0.3:
            data += port.read(max(port.in_waiting, 1))
            polls.append((time.monotonic(), twin.bytes_written, twin.samples_sent))
        twin.kill()
        assert not twin.is_alive
    inside = [(w, s) for t, w, s in polls if t_stall + 0.05 <= t <= t_stall + stall_s - 0.02]
    assert len(inside) >= 2  # polled every ~10 ms; a handful even on a loaded machine
    assert inside[0][0] == inside[-1][0]  # nothing delivered during the stall
    assert inside[-1][1] > inside[0][1]  # while the sensor kept sampling
    counter, _, parser = _decode(bytes(data))
    assert parser.checksum_errors == 0
    assert np.all(np.diff(counter.astype(np.int64)) % 65536 == 1)  # the backlog came through
    assert len(counter) > 8000 * (stall_s + 0.2)


def test_twin_cli_runs_in_its_own_process() -> None:
    """`python -m timedexec.twins gyro` prints a ready line with the port and the
    ground truth, streams, and prints a summary when its duration is over."""
    proc = subprocess.run(
        [sys.executable, "-m", "timedexec.twins", "gyro", "--duration-s", "0.3"],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    ready, summary = (json.loads(line) for line in proc.stdout.splitlines())
    assert ready["slave_path"].startswith("/dev/")
    assert ready["true_rate_hz"] == pytest.approx(8024.0)
    assert summary["samples_sent"] > 1000
    assert summary["error"] is None
    bad = subprocess.run(
        [sys.executable, "-m", "timedexec.twins", "gyro", "--full-scale-dps", "3"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert bad.returncode == 2
    assert "full_scale_dps=3" in bad.stderr


def test_sample_exact_frame_size() -> None:
    """Each sample is one 11-byte frame."""
    assert len(GyroFrameSource().generate(7)) == 7 * FRAME_SIZE
