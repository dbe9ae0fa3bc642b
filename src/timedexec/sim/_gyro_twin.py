"""Simulated MPU-6000 gyro streaming 11-byte frames over a pseudo-terminal.

The twin plays the device: it samples a true angular rate at 8 kHz × (1 + clock error) on its
own clock, adds bias and white noise, quantises to the full-scale range, frames the samples as
described in ``docs/gyro-protocol.md`` and writes them to the master side of a pty in
USB-like bursts (every ``burst_period_s``). A reader opens the slave path with pyserial as if
it were ``/dev/ttyUSB0``.

Time base: the twin's time ``t`` is seconds since :attr:`GyroTwin.start_time_s` on the host's
``time.monotonic()`` clock (the same clock in every process on Linux). Sample ``k`` is taken at
``t_k = k / true_rate_hz`` and, like the real sensor with DLPF_CFG=0, carries the true rate at
``t_k - dlpf_group_delay_s``. It is written at the first burst at or after ``t_k``.

The frame encoder here is the device side and deliberately independent of
``timedexec.sensors`` (which sits below ``sim`` in the layer order); a test checks that both
produce identical bytes.

Run ``python -m timedexec.sim._gyro_twin --help`` to start a twin in its own process.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import math
import os
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError, SensorError

__all__ = [
    "DEFAULT_BIAS_DPS",
    "FULL_SCALE_SENSITIVITY",
    "GyroFrameSource",
    "GyroTwin",
    "RateSource",
    "constant_rate_source",
    "main",
    "sine_rate_source",
    "step_rate_source",
]

#: ``rate_source(t0_s, t1_s)`` -> true angular rate, rad/s, tool frame; see GyroTwin.
RateSource = Callable[[float, float], NDArray[np.float64]]

#: Sensitivity per full-scale range, LSB per °/s (MPU-6000 datasheet, ±3 %).
FULL_SCALE_SENSITIVITY: dict[int, float] = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
#: Default zero-rate offset of the simulated sensor, °/s per axis.
DEFAULT_BIAS_DPS: tuple[float, float, float] = (0.8, -0.5, 0.3)

_WRAP = 65536
_FRAME_DTYPE = np.dtype(
    [("sync", "u1", (2,)), ("counter", "<u2"), ("rate", "<i2", (3,)), ("crc", "u1")]
)


def _crc8_table() -> NDArray[np.uint8]:
    """CRC-8, polynomial 0x07, MSB first (the device firmware's table)."""
    out = np.zeros(256, dtype=np.uint8)
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = (c << 1) ^ (0x107 << 8) if c & 0x8000 else c << 1
        out[i] = (c >> 8) & 0xFF
    return out


_CRC_TABLE = _crc8_table()


def _device_encode(counter: NDArray[np.uint16], raw: NDArray[np.int16]) -> bytes:
    """Frame samples the way the device firmware does (column-wise CRC loop)."""
    rec = np.empty(counter.shape[0], dtype=_FRAME_DTYPE)
    rec["sync"] = (0xA5, 0x5A)
    rec["counter"] = counter
    rec["rate"] = raw
    as_bytes = rec.view(np.uint8).reshape(-1, _FRAME_DTYPE.itemsize)
    crc = np.zeros(counter.shape[0], dtype=np.uint8)
    for col in range(2, 10):
        crc = _CRC_TABLE[crc ^ as_bytes[:, col]]
    rec["crc"] = crc
    return rec.tobytes()


def _validate_common(
    *,
    clock_error_ppm: float,
    noise_density_dps_rthz: float,
    bias_dps: Sequence[float],
    full_scale_dps: int,
    nominal_rate_hz: float,
    dlpf_group_delay_s: float,
) -> NDArray[np.float64]:
    if full_scale_dps not in FULL_SCALE_SENSITIVITY:
        raise ConfigError(
            f"full_scale_dps={full_scale_dps!r} is not an MPU-6000 range; use one of "
            f"{sorted(FULL_SCALE_SENSITIVITY)} (°/s)"
        )
    if not (math.isfinite(clock_error_ppm) and abs(clock_error_ppm) < 100_000):
        raise ConfigError(
            f"clock_error_ppm={clock_error_ppm!r} must be finite and within ±100000 ppm "
            "(a real MEMS clock is within about ±10000)"
        )
    if not (math.isfinite(noise_density_dps_rthz) and noise_density_dps_rthz >= 0):
        raise ConfigError(
            f"noise_density_dps_rthz={noise_density_dps_rthz!r} must be >= 0 "
            "(MPU-6000: about 0.005 °/s/√Hz)"
        )
    bias = np.asarray(bias_dps, dtype=np.float64)
    if bias.shape != (3,) or not np.all(np.isfinite(bias)):
        raise ConfigError(f"bias_dps must be 3 finite values (°/s, x y z), got {bias_dps!r}")
    if not (math.isfinite(nominal_rate_hz) and nominal_rate_hz > 0):
        raise ConfigError(f"nominal_rate_hz={nominal_rate_hz!r} must be positive, Hz")
    if not (math.isfinite(dlpf_group_delay_s) and dlpf_group_delay_s >= 0):
        raise ConfigError(
            f"dlpf_group_delay_s={dlpf_group_delay_s!r} must be >= 0 s (0.98e-3 with DLPF_CFG=0)"
        )
    return bias


class GyroFrameSource:
    """The sensor itself, without transport: turns true rates into frame bytes.

    Pure computation, no threads and no clock reads; the pty twin (:class:`GyroTwin`) and
    the in-process ``sim://`` port of ``timedexec.sensors`` both drive one.

    Parameters
    ----------
    rate_source : callable, optional
        ``rate_source(t0_s, t1_s)`` -> true angular rate in rad/s for the samples in
        ``[t0_s, t1_s)``: shape (3,) (constant over the interval) or (k, 3) (values at
        ``t0_s + i·(t1_s - t0_s)/k``, i = 0..k-1, interpolated linearly to the sample times;
        exact when k equals the number of samples). None = still.
    clock_error_ppm : float
        Sensor clock error: the true sample rate is ``nominal_rate_hz·(1 + ppm·1e-6)``.
    noise_density_dps_rthz : float
        White rate-noise density, °/s/√Hz; per-sample std = density·√(nominal_rate_hz/2).
    bias_dps : sequence of 3 float
        Zero-rate offset, °/s.
    full_scale_dps : int
        Range, one of 250, 500, 1000, 2000 °/s.
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    dlpf_group_delay_s : float
        Sample k carries the true rate at ``t_k - dlpf_group_delay_s``, s.
    seed : int
        Seed of the noise generator.
    record_truth : bool
        Keep the true rate of every sample (see :meth:`truth`).
    """

    def __init__(
        self,
        rate_source: RateSource | None = None,
        *,
        clock_error_ppm: float = 3000.0,
        noise_density_dps_rthz: float = 0.005,
        bias_dps: Sequence[float] = DEFAULT_BIAS_DPS,
        full_scale_dps: int = 500,
        nominal_rate_hz: float = 8000.0,
        dlpf_group_delay_s: float = 0.98e-3,
        seed: int = 0,
        record_truth: bool = False,
    ) -> None:
        self.bias_dps = _validate_common(
            clock_error_ppm=clock_error_ppm,
            noise_density_dps_rthz=noise_density_dps_rthz,
            bias_dps=bias_dps,
            full_scale_dps=full_scale_dps,
            nominal_rate_hz=nominal_rate_hz,
            dlpf_group_delay_s=dlpf_group_delay_s,
        )
        self.rate_source = rate_source
        self.clock_error_ppm = float(clock_error_ppm)
        self.noise_density_dps_rthz = float(noise_density_dps_rthz)
        self.full_scale_dps = int(full_scale_dps)
        self.nominal_rate_hz = float(nominal_rate_hz)
        self.dlpf_group_delay_s = float(dlpf_group_delay_s)
        self.sensitivity_lsb_per_dps = FULL_SCALE_SENSITIVITY[self.full_scale_dps]
        self.noise_std_dps = self.noise_density_dps_rthz * math.sqrt(self.nominal_rate_hz / 2)
        self._rng = np.random.default_rng(seed)
        self._record = record_truth
        self._truth: list[NDArray[np.float64]] = []
        self.samples_generated = 0

    @property
    def true_rate_hz(self) -> float:
        """The sensor's actual sample rate, Hz."""
        return self.nominal_rate_hz * (1e6 + self.clock_error_ppm) / 1e6

    def sample_time_s(self, k: ArrayLike) -> NDArray[np.float64]:
        """Time at which sample ``k`` is taken, on the twin's time base, s."""
        return np.asarray(k, dtype=np.float64) / self.true_rate_hz

    def samples_due(self, elapsed_s: float) -> int:
        """Number of samples taken at or before ``elapsed_s`` (t_k <= elapsed_s)."""
        if elapsed_s < 0:
            return 0
        return math.floor(elapsed_s * self.true_rate_hz) + 1

    def true_rates(self, k0: int, m: int) -> NDArray[np.float64]:
        """True rate carried by samples k0..k0+m-1, rad/s, shape (m, 3)."""
        f = self.true_rate_hz
        t_content = np.arange(k0, k0 + m, dtype=np.float64) / f - self.dlpf_group_delay_s
        if self.rate_source is None or m == 0:
            return np.zeros((m, 3))
        t0 = k0 / f - self.dlpf_group_delay_s
        t1 = (k0 + m) / f - self.dlpf_group_delay_s
        out = np.asarray(self.rate_source(t0, t1), dtype=np.float64)
        if out.shape == (3,):
            return np.broadcast_to(out, (m, 3)).copy()
        if out.ndim != 2 or out.shape[1] != 3 or out.shape[0] < 1:
            raise ConfigError(
                f"rate_source returned shape {out.shape}; it must return (3,) or (k, 3) "
                "angular rates in rad/s"
            )
        k = out.shape[0]
        if k == m:
            return out
        grid = t0 + np.arange(k) * ((t1 - t0) / k)
        return np.stack([np.interp(t_content, grid, out[:, a]) for a in range(3)], axis=1)

    def generate(self, m: int) -> bytes:
        """Frame the next ``m`` samples.

        Returns
        -------
        bytes
            ``11·m`` bytes of frames for samples ``samples_generated`` .. ``+ m - 1``.
        """
        k0 = self.samples_generated
        rates = self.true_rates(k0, m)
        if self._record:
            self._truth.append(rates)
        dps = np.degrees(rates) + self.bias_dps
        if self.noise_std_dps > 0:
            dps = dps + self._rng.normal(0.0, self.noise_std_dps, size=(m, 3))
        raw = np.clip(np.rint(dps * self.sensitivity_lsb_per_dps), -32768, 32767).astype(np.int16)
        counter = (np.arange(k0, k0 + m) % _WRAP).astype(np.uint16)
        self.samples_generated = k0 + m
        return _device_encode(counter, raw)

    def truth(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Recorded ground truth (needs ``record_truth=True``).

        Returns
        -------
        index : ndarray of int64, shape (n,)
            Sample index k (counter = k % 65536).
        rate_rad_s : ndarray of float64, shape (n, 3)
            True rate each sample carries (at ``t_k - dlpf_group_delay_s``), rad/s, before
            bias, noise and quantisation.
        """
        if not self._record:
            raise ConfigError("truth() needs record_truth=True when the source is built")
        rates = np.concatenate(self._truth) if self._truth else np.zeros((0, 3))
        return np.arange(rates.shape[0], dtype=np.int64), rates


class GyroTwin:
    """A simulated gyro on a pseudo-terminal, streaming in real time from a thread.

    Parameters
    ----------
    rate_source : callable, optional
        ``rate_source(t0_s, t1_s)`` -> true angular rate (rad/s, tool frame, 3 axes) for the
        samples in ``[t0_s, t1_s)`` on the twin's time base; see :class:`GyroFrameSource`
        for the accepted shapes. Called once per burst from the twin's thread. None = still
        (zero rate plus bias and noise).
    link_path : str, optional
        Also expose the slave as this symlink (like a udev ``/dev/gyro`` rule); removed on
        close.
    clock_error_ppm, noise_density_dps_rthz, bias_dps, full_scale_dps, seed
        Sensor model, as for :class:`GyroFrameSource`.
    burst_period_s : float
        Write period (USB full-speed CDC delivers every 1 ms), s.
    dlpf_group_delay_s : float
        Content delay of every sample, s.
    record_truth : bool
        Keep the true rate of every sample sent.
    max_backlog_s : float
        When nobody reads, keep at most this much unsent data, s; older bytes are dropped
        (counted in :attr:`bytes_dropped_overflow`), as a USB device does.

    Examples
    --------
    >>> with GyroTwin() as twin:  # doctest: +SKIP
    ...     with open_gyro(twin.slave_path) as gyro:
    ...         samples = gyro.read(8000)
    """

    def __init__(
        self,
        rate_source: RateSource | None = None,
        *,
        link_path: str | None = None,
        clock_error_ppm: float = 3000.0,
        noise_density_dps_rthz: float = 0.005,
        bias_dps: Sequence[float] = DEFAULT_BIAS_DPS,
        full_scale_dps: int = 500,
        seed: int = 0,
        burst_period_s: float = 1e-3,
        dlpf_group_delay_s: float = 0.98e-3,
        record_truth: bool = False,
        max_backlog_s: float = 0.5,
    ) -> None:
        if not (math.isfinite(burst_period_s) and 1e-4 <= burst_period_s <= 0.1):
            raise ConfigError(
                f"burst_period_s={burst_period_s!r} must be within 1e-4..0.1 s (USB: 1e-3)"
            )
        if not max_backlog_s > 0:
            raise ConfigError(f"max_backlog_s={max_backlog_s!r} must be positive, s")
        self.source = GyroFrameSource(
            rate_source,
            clock_error_ppm=clock_error_ppm,
            noise_density_dps_rthz=noise_density_dps_rthz,
            bias_dps=bias_dps,
            full_scale_dps=full_scale_dps,
            dlpf_group_delay_s=dlpf_group_delay_s,
            seed=seed,
            record_truth=record_truth,
        )
        self.link_path = link_path
        self.burst_period_s = float(burst_period_s)
        self._max_backlog = int(max_backlog_s * self.source.true_rate_hz) * 11
        self._fault_rng = np.random.default_rng(seed + 1)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_path: str | None = None
        self._linked = False
        self._corrupt_left = 0
        self._corrupt_skip = 0
        self._drop_left = 0
        self._garbage = b""
        self.fault_log: list[tuple[str, int, int]] = []
        """(kind, stream offset of the first affected generated byte, bytes) per fault."""
        self.start_time_s = math.nan
        """``time.monotonic()`` at sample 0, s."""
        self.samples_sent = 0
        """Samples generated and queued for the pty."""
        self.bytes_written = 0
        """Bytes accepted by the pty."""
        self.bytes_dropped_overflow = 0
        """Bytes dropped because nobody read them in time."""
        self.error: BaseException | None = None
        """The exception that stopped the streaming thread, if any."""

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Open the pty pair and start streaming."""
        if self._thread is not None:
            raise SensorError("the gyro twin is already running; close it before restarting")
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # 8-bit clean, no echo, before any reader touches it
            flags = fcntl.fcntl(master, fcntl.F_GETFL)
            fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
            slave_path = os.ttyname(slave)
            if self.link_path is not None:
                if os.path.lexists(self.link_path):
                    if not os.path.islink(self.link_path):
                        raise ConfigError(
                            f"link_path={self.link_path!r} exists and is not a symlink; "
                            "choose a free path"
                        )
                    os.unlink(self.link_path)
                os.symlink(slave_path, self.link_path)
                self._linked = True
        except BaseException:
            os.close(master)
            os.close(slave)
            raise
        self._master, self._slave, self._slave_path = master, slave, slave_path
        self._stop.clear()
        self.start_time_s = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="gyro-twin", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop streaming, close the pty pair and remove the symlink. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        if self._linked and self.link_path is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.link_path)
            self._linked = False

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- ground truth ----------------------------------------------------------------

    @property
    def slave_path(self) -> str:
        """Path of the pty slave to open with pyserial (``/dev/pts/N``)."""
        if self._slave_path is None:
            raise SensorError("the gyro twin is not started; use it as a context manager")
        return self._slave_path

    @property
    def port(self) -> str:
        """The path a reader should open: the symlink if one was asked for, else the slave."""
        return self.link_path if self.link_path is not None else self.slave_path

    @property
    def true_rate_hz(self) -> float:
        """The simulated sensor's actual sample rate, Hz."""
        return self.source.true_rate_hz

    @property
    def clock_error_ppm(self) -> float:
        """Simulated clock error, ppm."""
        return self.source.clock_error_ppm

    def true_sample_time_s(self, k: ArrayLike) -> NDArray[np.float64]:
        """Host ``time.monotonic()`` at which sample ``k`` was taken, s."""
        return self.start_time_s + self.source.sample_time_s(k)

    def truth(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """True rate of every sample sent (needs ``record_truth=True``); see
        :meth:`GyroFrameSource.truth`."""
        with self._lock:
            return self.source.truth()

    # -- fault injection -------------------------------------------------------------

    def inject_corruption(self, n_bytes: int, *, skip_bytes: int = 0) -> None:
        """XOR ``n_bytes`` consecutive bytes with random non-zero values, starting
        ``skip_bytes`` into the upcoming stream (bursts start at a frame boundary, so
        ``skip_bytes=0`` hits a sync byte and 2..10 a payload byte)."""
        with self._lock:
            self._corrupt_left += self._check_count(n_bytes, "n_bytes")
            self._corrupt_skip = self._check_count(skip_bytes, "skip_bytes")

    def drop_bytes(self, n: int) -> None:
        """Do not send the next ``n`` bytes (a lost USB packet or UART overrun)."""
        with self._lock:
            self._drop_left += self._check_count(n, "n")

    def insert_garbage(self, n_bytes: int) -> None:
        """Send ``n_bytes`` random bytes before the next burst."""
        with self._lock:
            count = self._check_count(n_bytes, "n_bytes")
            self._garbage += self._fault_rng.integers(0, 256, count, dtype=np.uint8).tobytes()

    @staticmethod
    def _check_count(n: int, name: str) -> int:
        if not isinstance(n, int | np.integer) or n < 0:
            raise ConfigError(f"{name}={n!r} must be a non-negative number of bytes")
        return int(n)

    def _apply_faults(self, data: bytes, offset: int) -> bytes:
        with self._lock:
            if not (self._corrupt_left or self._drop_left or self._garbage):
                return data
            buf = bytearray(data)
            if self._drop_left:
                k = min(self._drop_left, len(buf))
                del buf[:k]
                self._drop_left -= k
                self.fault_log.append(("drop", offset, k))
                offset += k
            if self._corrupt_left and buf:
                skip = min(self._corrupt_skip, len(buf))
                self._corrupt_skip -= skip
                k = min(self._corrupt_left, len(buf) - skip)
                if k:
                    mask = self._fault_rng.integers(1, 256, k, dtype=np.uint8)
                    hit = np.frombuffer(bytes(buf[skip : skip + k]), dtype=np.uint8) ^ mask
                    buf[skip : skip + k] = hit.tobytes()
                    self._corrupt_left -= k
                    self.fault_log.append(("corrupt", offset + skip, k))
            if self._garbage:
                self.fault_log.append(("garbage", offset, len(self._garbage)))
                buf[:0] = self._garbage
                self._garbage = b""
            return bytes(buf)

    # -- streaming thread ------------------------------------------------------------

    def _run(self) -> None:
        master = self._master
        assert master is not None
        pending = bytearray()
        generated_bytes = 0
        next_wake = self.start_time_s
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                due = self.source.samples_due(now - self.start_time_s)
                if due > self.samples_sent:
                    with self._lock:
                        data = self.source.generate(due - self.samples_sent)
                        self.samples_sent = due
                    offset = generated_bytes
                    generated_bytes += len(data)
                    pending += self._apply_faults(data, offset)
                if pending:
                    try:
                        written = os.write(master, pending)
                    except BlockingIOError:
                        written = 0
                    del pending[:written]
                    self.bytes_written += written
                    if len(pending) > self._max_backlog:
                        excess = len(pending) - self._max_backlog
                        del pending[:excess]
                        self.bytes_dropped_overflow += excess
                next_wake += self.burst_period_s
                delay = next_wake - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -0.1:
                    next_wake = time.monotonic()  # fell far behind (suspended): catch up once
        except BaseException as exc:  # reported through .error; the thread must not die silently
            self.error = exc


def constant_rate_source(rate_rad_s: Sequence[float]) -> RateSource:
    """A source returning the same rate (rad/s, shape (3,)) at all times."""
    value = np.asarray(rate_rad_s, dtype=np.float64)
    if value.shape != (3,):
        raise ConfigError(f"rate_rad_s must be 3 values (rad/s), got {rate_rad_s!r}")

    def source(t0_s: float, t1_s: float) -> NDArray[np.float64]:
        return value

    return source


def _grid(t0_s: float, t1_s: float, grid_hz: float) -> NDArray[np.float64]:
    k = max(math.ceil((t1_s - t0_s) * grid_hz), 1)
    grid: NDArray[np.float64] = t0_s + np.arange(k, dtype=np.float64) * ((t1_s - t0_s) / k)
    return grid


def sine_rate_source(
    amplitude_rad_s: float,
    frequency_hz: float,
    *,
    axis: int = 2,
    phase_rad: float = 0.0,
    grid_hz: float = 64_000.0,
) -> RateSource:
    """Rate ``amplitude·sin(2π·f·t + phase)`` on one axis (0, 1, 2 = x, y, z), rad/s."""
    if axis not in (0, 1, 2):
        raise ConfigError(f"axis={axis!r} must be 0, 1 or 2 (x, y, z)")
    omega = 2.0 * math.pi * frequency_hz

    def source(t0_s: float, t1_s: float) -> NDArray[np.float64]:
        t = _grid(t0_s, t1_s, grid_hz)
        out = np.zeros((t.shape[0], 3))
        out[:, axis] = amplitude_rad_s * np.sin(omega * t + phase_rad)
        return out

    return source


def step_rate_source(
    rate_rad_s: float,
    step_time_s: float,
    *,
    axis: int = 2,
    duration_s: float = math.inf,
    grid_hz: float = 64_000.0,
) -> RateSource:
    """Rate ``rate_rad_s`` on one axis during ``[step_time_s, step_time_s + duration_s)``."""
    if axis not in (0, 1, 2):
        raise ConfigError(f"axis={axis!r} must be 0, 1 or 2 (x, y, z)")

    def source(t0_s: float, t1_s: float) -> NDArray[np.float64]:
        t = _grid(t0_s, t1_s, grid_hz)
        out = np.zeros((t.shape[0], 3))
        on = (t >= step_time_s) & (t < step_time_s + duration_s)
        out[on, axis] = rate_rad_s
        return out

    return source


def main(argv: Sequence[str] | None = None) -> int:
    """Run a gyro twin in this process until ``--duration-s`` elapses or SIGTERM/SIGINT.

    Prints one JSON line on stdout when streaming starts (``slave_path``, ``port``,
    ``start_time_s``, ``true_rate_hz``) and one summary line when it stops.
    """
    parser = argparse.ArgumentParser(
        prog="python -m timedexec.sim._gyro_twin", description=main.__doc__
    )
    parser.add_argument("--link", help="also expose the pty slave as this symlink")
    parser.add_argument("--duration-s", type=float, default=math.inf)
    parser.add_argument("--clock-error-ppm", type=float, default=3000.0)
    parser.add_argument("--noise-density-dps-rthz", type=float, default=0.005)
    parser.add_argument("--bias-dps", type=float, nargs=3, default=list(DEFAULT_BIAS_DPS))
    parser.add_argument("--full-scale-dps", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", choices=("still", "sine", "step"), default="still")
    parser.add_argument("--amplitude-dps", type=float, default=30.0)
    parser.add_argument("--frequency-hz", type=float, default=1.0)
    parser.add_argument("--step-time-s", type=float, default=1.0)
    parser.add_argument("--axis", type=int, default=2)
    args = parser.parse_args(argv)

    source: RateSource | None = None
    if args.profile == "sine":
        source = sine_rate_source(
            math.radians(args.amplitude_dps), args.frequency_hz, axis=args.axis
        )
    elif args.profile == "step":
        source = step_rate_source(
            math.radians(args.amplitude_dps), args.step_time_s, axis=args.axis
        )

    stop = threading.Event()

    def _on_signal(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    try:
        twin = GyroTwin(
            source,
            link_path=args.link,
            clock_error_ppm=args.clock_error_ppm,
            noise_density_dps_rthz=args.noise_density_dps_rthz,
            bias_dps=args.bias_dps,
            full_scale_dps=args.full_scale_dps,
            seed=args.seed,
        )
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with twin:
        ready = {
            "slave_path": twin.slave_path,
            "port": twin.port,
            "start_time_s": twin.start_time_s,
            "true_rate_hz": twin.true_rate_hz,
            "pid": os.getpid(),
        }
        print(json.dumps(ready), flush=True)
        stop.wait(None if math.isinf(args.duration_s) else args.duration_s)
    cpu = time.process_time()
    summary = {
        "samples_sent": twin.samples_sent,
        "bytes_written": twin.bytes_written,
        "bytes_dropped_overflow": twin.bytes_dropped_overflow,
        "cpu_s": cpu,
        "error": None if twin.error is None else repr(twin.error),
    }
    print(json.dumps(summary), flush=True)
    return 0 if twin.error is None else 1


if __name__ == "__main__":
    sys.exit(main())
