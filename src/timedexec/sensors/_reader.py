"""GyroReader: the gyro stream over pyserial, parsed and time-stamped in a background thread.

``open_gyro(url)`` picks the port backend from the URL, like ``serial.serial_for_url``
(a device path or ``sim://``; see :mod:`timedexec.sensors._ports`).

A reader thread cycles every ``read_period_s`` (20 ms): it sleeps, reads everything
``in_waiting`` (blocking for one byte only when nothing is there), and stamps the read with
``time.monotonic()`` on return. pyserial's ``read(size)`` loop would wake once per 1 ms USB
frame; on a virtualised host each wake-up costs tens of microseconds of CPU, which is what
the budget is spent on. The thread then parses the frames (vectorised), unwraps the counter,
feeds the clock model with the newest sample of each read and appends the samples to a ring
buffer. Conversion to rad/s and host times happens in :meth:`GyroReader.read`, in the
caller's thread, with the most recent clock fit.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from types import TracebackType
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError, DriverTimeout, SensorError
from timedexec.sensors._clock import ClockFit, SensorClock
from timedexec.sensors._frames import FrameParser
from timedexec.sensors._ports import Port, open_port
from timedexec.sensors._settings import (
    SENSITIVITY_LSB_PER_DPS,
    GyroSettings,
    check_positive_in,
)
from timedexec.sensors._unwrap import CounterUnwrapper

__all__ = [
    "GyroReader",
    "GyroSamples",
    "GyroStats",
    "ZeroRateCalibration",
    "open_gyro",
    "raw_to_rad_s",
]

_CHUNK_HISTORY = 64  # reads remembered to time-stamp frames finished by an earlier read


def raw_to_rad_s(
    raw: ArrayLike, full_scale_dps: int, bias_rad_s: ArrayLike | None = None
) -> NDArray[np.float64]:
    """Convert raw gyro LSB to rad/s.

    Parameters
    ----------
    raw : array_like of int, shape (n, 3)
        Raw rates, LSB.
    full_scale_dps : int
        Configured range, one of 250, 500, 1000, 2000 °/s.
    bias_rad_s : array_like of float, shape (3,), optional
        Zero-rate offset to subtract, rad/s.

    Returns
    -------
    ndarray of float64, shape (n, 3)
        Angular rate, rad/s.
    """
    try:
        sensitivity = SENSITIVITY_LSB_PER_DPS[full_scale_dps]
    except KeyError:
        raise ConfigError(
            f"full_scale_dps={full_scale_dps!r} is not an MPU-6000 range; use one of "
            f"{sorted(SENSITIVITY_LSB_PER_DPS)} (°/s)"
        ) from None
    rate = np.asarray(raw, dtype=np.float64) * (math.pi / 180.0 / sensitivity)
    if bias_rad_s is not None:
        rate -= np.asarray(bias_rad_s, dtype=np.float64)
    return rate


@dataclass(frozen=True, kw_only=True, eq=False)
class GyroSamples:
    """Samples handed out by :meth:`GyroReader.read`; unpacks as ``host_time_s, rate_rad_s``.

    Attributes
    ----------
    counter_unwrapped : ndarray of int64, shape (n,)
        Unwrapped sample index (``% 65536`` gives the counter sent).
    host_time_s : ndarray of float64, shape (n,)
        Host time of each sample from the clock model (minimum-latency arrival line), s.
        The motion it describes happened ``dlpf_group_delay_s`` plus the (unobservable,
        constant) minimum transport latency earlier.
    rate_rad_s : ndarray of float64, shape (n, 3)
        Angular rate, tool frame x y z, zero-rate offset removed, rad/s.
    raw : ndarray of int16, shape (n, 3)
        Raw rates as sent, LSB.
    arrival_s : ndarray of float64, shape (n,)
        Host time at which the read that delivered the sample returned, s.
    """

    counter_unwrapped: NDArray[np.int64]
    host_time_s: NDArray[np.float64]
    rate_rad_s: NDArray[np.float64]
    raw: NDArray[np.int16]
    arrival_s: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.counter_unwrapped.shape[0])

    def __iter__(self):  # type: ignore[no-untyped-def]
        """Unpack as ``host_time_s, rate_rad_s``."""
        return iter((self.host_time_s, self.rate_rad_s))

    @classmethod
    def concatenate(cls, parts: Sequence[GyroSamples]) -> GyroSamples:
        """The samples of ``parts`` in order, as one."""
        if len(parts) == 1:
            return parts[0]
        return cls(
            counter_unwrapped=np.concatenate([p.counter_unwrapped for p in parts]),
            host_time_s=np.concatenate([p.host_time_s for p in parts]),
            rate_rad_s=np.concatenate([p.rate_rad_s for p in parts]).reshape(-1, 3),
            raw=np.concatenate([p.raw for p in parts]).reshape(-1, 3),
            arrival_s=np.concatenate([p.arrival_s for p in parts]),
        )

    def select(self, mask: NDArray[np.bool_] | slice) -> GyroSamples:
        """The samples where ``mask`` holds (or a slice of them)."""
        return GyroSamples(
            counter_unwrapped=self.counter_unwrapped[mask],
            host_time_s=self.host_time_s[mask],
            rate_rad_s=self.rate_rad_s[mask],
            raw=self.raw[mask],
            arrival_s=self.arrival_s[mask],
        )


@dataclass(frozen=True, kw_only=True)
class GyroStats:
    """Counters of a gyro stream since it was opened.

    Attributes
    ----------
    frames_ok : int
        Valid frames parsed.
    checksum_errors : int
        Sync patterns whose CRC failed.
    resync_bytes_skipped : int
        Bytes outside valid frames.
    gaps : int
        Runs of missing samples.
    missing_samples : int
        Samples missing in total.
    dropped_frames : int
        Valid-CRC frames dropped because their counter did not fit the sequence.
    discontinuities : int
        Counter restarts (sensor resets).
    overflow_samples : int
        Samples dropped because nobody read them within ``buffer_s``.
    samples_received : int
        Samples appended to the buffer.
    samples_buffered : int
        Samples waiting to be read.
    bytes_read : int
        Bytes read from the port.
    reads : int
        Port reads that returned data.
    reader_cpu_s : float
        CPU time of the reader thread (``time.thread_time``), s.
    reader_wall_s : float
        Wall time since the reader thread started, s.
    """

    frames_ok: int
    checksum_errors: int
    resync_bytes_skipped: int
    gaps: int
    missing_samples: int
    dropped_frames: int
    discontinuities: int
    overflow_samples: int
    samples_received: int
    samples_buffered: int
    bytes_read: int
    reads: int
    reader_cpu_s: float
    reader_wall_s: float

    @property
    def reader_cpu_fraction(self) -> float:
        """Reader-thread CPU as a fraction of one core."""
        return self.reader_cpu_s / self.reader_wall_s if self.reader_wall_s > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation."""
        return asdict(self)


@dataclass(frozen=True, kw_only=True)
class ZeroRateCalibration:
    """Zero-rate offset and noise from a still recording.

    Attributes
    ----------
    bias_rad_s : tuple of 3 float
        Mean rate per axis while still, rad/s; subtracted from every later sample.
    noise_std_rad_s : tuple of 3 float
        Sample standard deviation per axis, rad/s.
    noise_density_rad_s_rthz : tuple of 3 float
        ``noise_std / sqrt(rate / 2)``, rad/s/√Hz (white-noise assumption).
    n_samples : int
        Samples used.
    duration_s : float
        Duration of the recording, s.
    """

    bias_rad_s: tuple[float, float, float]
    noise_std_rad_s: tuple[float, float, float]
    noise_density_rad_s_rthz: tuple[float, float, float]
    n_samples: int
    duration_s: float

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ZeroRateCalibration:
        """Inverse of :meth:`to_dict`."""
        return cls(
            bias_rad_s=_triple(data["bias_rad_s"]),
            noise_std_rad_s=_triple(data["noise_std_rad_s"]),
            noise_density_rad_s_rthz=_triple(data["noise_density_rad_s_rthz"]),
            n_samples=int(data["n_samples"]),
            duration_s=float(data["duration_s"]),
        )


def _triple(values: ArrayLike) -> tuple[float, float, float]:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.shape != (3,):
        raise ConfigError(f"expected 3 values (x, y, z), got {arr.shape[0]}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


class _Ring:
    """Fixed-capacity FIFO of samples (index, arrival, raw)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.index = np.zeros(capacity, dtype=np.int64)
        self.arrival = np.zeros(capacity, dtype=np.float64)
        self.raw = np.zeros((capacity, 3), dtype=np.int16)
        self.written = 0
        self.consumed = 0
        self.overflow = 0

    @property
    def available(self) -> int:
        return self.written - self.consumed

    def append(
        self,
        index: NDArray[np.int64],
        arrival: float | NDArray[np.float64],
        raw: NDArray[np.int16],
    ) -> None:
        m = int(index.shape[0])
        if isinstance(arrival, float):
            arrival = np.full(m, arrival)
        if m > self.capacity:
            skip = m - self.capacity
            index, arrival, raw = index[skip:], arrival[skip:], raw[skip:]
            self.written += skip
            m = self.capacity
        pos = self.written % self.capacity
        first = min(m, self.capacity - pos)
        self.index[pos : pos + first] = index[:first]
        self.arrival[pos : pos + first] = arrival[:first]
        self.raw[pos : pos + first] = raw[:first]
        rest = m - first
        if rest:
            self.index[:rest] = index[first:]
            self.arrival[:rest] = arrival[first:]
            self.raw[:rest] = raw[first:]
        self.written += m
        if self.written - self.consumed > self.capacity:
            lost = self.written - self.capacity - self.consumed
            self.overflow += lost
            self.consumed += lost

    def take(self, k: int) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int16]]:
        pos = self.consumed % self.capacity
        first = min(k, self.capacity - pos)
        parts = [slice(pos, pos + first)]
        if k > first:
            parts.append(slice(0, k - first))
        self.consumed += k
        return (
            np.concatenate([self.index[s] for s in parts]),
            np.concatenate([self.arrival[s] for s in parts]),
            np.concatenate([self.raw[s] for s in parts]),
        )


class GyroReader:
    """A running gyro stream. Build it with :func:`open_gyro`; use it as a context manager.

    Parameters
    ----------
    port : pyserial ``Serial`` or compatible
        An open port (``read``, ``in_waiting``, ``close``; ``cancel_read`` if available).
    settings : GyroSettings
        Stream settings.
    url : str
        Where the port came from (used in messages).
    tap : callable, optional
        ``tap(data: bytes, arrival_s: float)`` called from the reader thread with every
        chunk read, before parsing (raw recording, benchmarks). Keep it fast.
    """

    def __init__(
        self,
        port: Port,
        settings: GyroSettings,
        *,
        url: str,
        tap: Callable[[bytes, float], None] | None = None,
    ) -> None:
        self._port = port
        self.settings = settings
        self.url = url
        self._tap = tap
        self._parser = FrameParser()
        self._unwrapper = CounterUnwrapper(nominal_rate_hz=settings.nominal_rate_hz)
        self.clock = SensorClock(settings.nominal_rate_hz, window_s=settings.clock_window_s)
        """The sensor-to-host clock model (lower-envelope fit)."""
        capacity = max(math.ceil(settings.buffer_s * settings.nominal_rate_hz * 1.02), 16)
        self._ring = _Ring(capacity)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._closed = False
        self._bias = np.zeros(3)
        self._stream_offset = 0
        self._chunks: deque[tuple[int, float]] = deque(maxlen=_CHUNK_HISTORY)
        self._bytes_read = 0
        self._reads = 0
        self._cpu_s = 0.0
        self._wall0 = math.nan

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Start the reader thread (``open_gyro`` does this)."""
        if self._thread is not None:
            return
        self._wall0 = time.monotonic()
        self._thread = threading.Thread(
            target=self._run, name=f"gyro-reader {self.url}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Stop the reader thread and close the port. Idempotent; buffered samples stay
        readable."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        cancel = getattr(self._port, "cancel_read", None)
        if cancel is not None:
            with contextlib.suppress(Exception):
                cancel()
        if self._thread is not None:
            self._thread.join(timeout=2.0 * self.settings.read_timeout_s + 2.0)
        with contextlib.suppress(Exception):
            self._port.close()
        with self._cond:
            self._cond.notify_all()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        """True while the reader thread runs."""
        return not self._closed and self._thread is not None and self._thread.is_alive()

    # -- reader thread ---------------------------------------------------------------

    def _run(self) -> None:
        port = self._port
        period = self.settings.read_period_s
        cpu0 = time.thread_time()
        try:
            while not self._stop.is_set():
                waiting = port.in_waiting
                if waiting:
                    data = port.read(waiting)  # already there: returns at once
                else:
                    data = port.read(1)  # nothing yet: block until the stream resumes
                    extra = port.in_waiting
                    if extra:
                        data += port.read(extra)
                arrival = time.monotonic()
                if data:
                    self._ingest(data, arrival)
                self._cpu_s = time.thread_time() - cpu0
                delay = arrival + period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        except Exception as exc:  # reported to the consumer by read()
            if not self._stop.is_set():
                self._error = exc
        finally:
            self._cpu_s = time.thread_time() - cpu0
            with self._cond:
                self._cond.notify_all()

    def _ingest(self, data: bytes, arrival: float) -> None:
        if self._tap is not None:
            self._tap(data, arrival)
        chunk_start = self._stream_offset
        self._bytes_read += len(data)
        self._reads += 1
        self._stream_offset += len(data)
        self._chunks.append((self._stream_offset, arrival))
        parsed = self._parser.feed(data)
        n = len(parsed)
        if not n:
            return
        if int(parsed.end_offset[0]) > chunk_start:
            # Every frame was completed by this read (the usual case): one time stamp.
            result = self._unwrapper.update(parsed.counter, arrival)
            if result.discontinuity:
                self.clock.reset()
            index = result.index
            if not index.shape[0]:
                return
            self.clock.add_point(int(index[-1]), arrival)
            raw = parsed.raw if index.shape[0] == n else parsed.raw[result.keep]
            with self._cond:
                self._ring.append(index, arrival, raw)
                self._cond.notify_all()
            return
        chunk_end = np.array([c[0] for c in self._chunks], dtype=np.int64)
        chunk_t = np.array([c[1] for c in self._chunks], dtype=np.float64)
        which = np.searchsorted(chunk_end, parsed.end_offset, side="left")
        frame_t = chunk_t[np.minimum(which, chunk_t.shape[0] - 1)]
        result = self._unwrapper.update(parsed.counter, frame_t)
        if result.discontinuity:
            self.clock.reset()
        index = result.index
        if not index.shape[0]:
            return
        kept_t = frame_t[result.keep]
        # Only the newest sample of each read can lie on the lower envelope.
        last_of_read = np.append(np.flatnonzero(np.diff(kept_t)), index.shape[0] - 1)
        for i in last_of_read.tolist():
            self.clock.add_point(int(index[i]), float(kept_t[i]))
        with self._cond:
            self._ring.append(index, kept_t, parsed.raw[result.keep])
            self._cond.notify_all()

    # -- consumer side ---------------------------------------------------------------

    def read(self, n: int | None = None, *, timeout_s: float | None = 1.0) -> GyroSamples:
        """Take the oldest unread samples.

        Parameters
        ----------
        n : int, optional
            Wait for exactly ``n`` samples. None: return every unread sample, waiting up to
            ``timeout_s`` for the first one (empty result if none came).
        timeout_s : float or None
            Longest wait, s; None waits forever, 0 does not wait.

        Returns
        -------
        GyroSamples

        Raises
        ------
        DriverTimeout
            If ``n`` samples did not arrive within ``timeout_s`` (they stay buffered).
        SensorError
            If the stream failed or the reader is closed and too few samples remain.
        """
        if n is not None and (isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1):
            raise ConfigError(f"n={n!r} must be a positive integer number of samples or None")
        if n is not None and n > self._ring.capacity:
            raise ConfigError(
                f"n={n} exceeds the buffer capacity of {self._ring.capacity} samples; raise "
                "buffer_s or read in smaller pieces"
            )
        if timeout_s is not None and not (math.isfinite(timeout_s) and timeout_s >= 0):
            raise ConfigError(f"timeout_s={timeout_s!r} must be >= 0 s or None")
        need = 1 if n is None else int(n)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while self._ring.available < need:
                if self._error is not None:
                    raise SensorError(
                        f"gyro stream on {self.url!r} failed: {self._error}; check the cable "
                        "or USB connection and that no other program uses the port"
                    ) from self._error
                if self._closed or (self._thread is not None and not self._thread.is_alive()):
                    if n is None:
                        break
                    raise SensorError(
                        f"gyro reader for {self.url!r} is closed; {self._ring.available} of "
                        f"{n} samples remain buffered"
                    )
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    if n is None:
                        break
                    raise DriverTimeout(
                        f"gyro on {self.url!r}: only {self._ring.available} of {n} samples "
                        f"within {timeout_s} s; check that the sensor streams "
                        f"(frames_ok={self._parser.frames_ok}, "
                        f"bytes_read={self._bytes_read})"
                    )
                self._cond.wait(remaining)
            take = self._ring.available if n is None else int(n)
            index, arrival, raw = self._ring.take(take)
            bias = self._bias.copy()
        if take:
            fit = self.clock.fit_if_stale(self.settings.clock_refit_s)
            host_time = fit.to_host_time(index)
        else:
            host_time = np.zeros(0)
        return GyroSamples(
            counter_unwrapped=index,
            host_time_s=host_time,
            rate_rad_s=raw_to_rad_s(raw, self.settings.full_scale_dps, bias),
            raw=raw,
            arrival_s=arrival,
        )

    def discard(self) -> int:
        """Drop every unread sample; returns how many."""
        with self._cond:
            k = self._ring.available
            self._ring.consumed += k
            return k

    def host_time(self, counter_unwrapped: ArrayLike) -> NDArray[np.float64]:
        """Host time of unwrapped sample indices under a fresh clock fit, s.

        Use it to re-time samples read early in a recording once more data has come in.
        """
        return self.clock.fit().to_host_time(counter_unwrapped)

    def clock_fit(self) -> ClockFit:
        """Refit the clock model now and return the line."""
        return self.clock.fit()

    @property
    def group_delay_s(self) -> float:
        """Sensor DLPF group delay to subtract from host times, s."""
        return self.settings.dlpf_group_delay_s

    @property
    def gaps(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Gaps so far: (first missing unwrapped index, samples missing), each shape (g,)."""
        with self._cond:
            return self._unwrapper.gaps

    @property
    def stats(self) -> GyroStats:
        """A snapshot of the stream counters."""
        with self._cond:
            unwrapper = self._unwrapper
            return GyroStats(
                frames_ok=self._parser.frames_ok,
                checksum_errors=self._parser.checksum_errors,
                resync_bytes_skipped=self._parser.resync_bytes_skipped,
                gaps=unwrapper.gap_count,
                missing_samples=unwrapper.missing_samples,
                dropped_frames=unwrapper.dropped_frames,
                discontinuities=unwrapper.discontinuities,
                overflow_samples=self._ring.overflow,
                samples_received=self._ring.written,
                samples_buffered=self._ring.available,
                bytes_read=self._bytes_read,
                reads=self._reads,
                reader_cpu_s=self._cpu_s,
                reader_wall_s=0.0 if math.isnan(self._wall0) else time.monotonic() - self._wall0,
            )

    # -- zero-rate calibration -------------------------------------------------------

    @property
    def zero_rate_rad_s(self) -> NDArray[np.float64]:
        """Zero-rate offset currently subtracted, rad/s, shape (3,)."""
        return self._bias.copy()

    def set_zero_rate(self, calibration: ZeroRateCalibration | ArrayLike) -> None:
        """Apply a stored zero-rate calibration (or a bias vector in rad/s)."""
        bias = (
            calibration.bias_rad_s if isinstance(calibration, ZeroRateCalibration) else calibration
        )
        with self._cond:
            self._bias = np.asarray(_triple(bias), dtype=np.float64)

    def calibrate_zero_rate(
        self,
        duration_s: float,
        *,
        max_noise_std_rad_s: float = 0.05,
        timeout_s: float | None = None,
    ) -> ZeroRateCalibration:
        """Measure the zero-rate offset from a still recording and apply it.

        Unread samples are discarded first; the next ``duration_s`` of samples are used.

        Parameters
        ----------
        duration_s : float
            Recording length, s (the paper used 60 s stationary recordings).
        max_noise_std_rad_s : float
            Reject the recording if any axis' std exceeds this, rad/s (default 0.05 rad/s =
            2.9 °/s, about nine times the MPU-6000's white noise at 8 kHz): the sensor moved.
        timeout_s : float, optional
            Longest wait; default ``1.5·duration_s + 1``.

        Returns
        -------
        ZeroRateCalibration

        Raises
        ------
        SensorError
            If the sensor moved during the recording.
        DriverTimeout
            If the samples did not arrive in time.
        """
        check_positive_in(duration_s, "duration_s", "s of still recording", upper=3600.0)
        check_positive_in(max_noise_std_rad_s, "max_noise_std_rad_s", "rad/s")
        self.discard()
        rate_hz = self.settings.nominal_rate_hz
        with contextlib.suppress(SensorError):
            rate_hz = self.clock.current.rate_hz
        need = max(round(duration_s * rate_hz), 2)
        wait = 1.5 * duration_s + 1.0 if timeout_s is None else timeout_s
        samples = self.read(need, timeout_s=wait)
        rate = raw_to_rad_s(samples.raw, self.settings.full_scale_dps)
        bias = rate.mean(axis=0)
        std = rate.std(axis=0, ddof=1)
        if np.any(std > max_noise_std_rad_s):
            raise SensorError(
                f"gyro on {self.url!r} moved during zero-rate calibration: noise std "
                f"{np.round(std, 4).tolist()} rad/s exceeds max_noise_std_rad_s="
                f"{max_noise_std_rad_s}; keep the sensor still and retry"
            )
        density = std / math.sqrt(rate_hz / 2.0)
        calibration = ZeroRateCalibration(
            bias_rad_s=_triple(bias),
            noise_std_rad_s=_triple(std),
            noise_density_rad_s_rthz=_triple(density),
            n_samples=need,
            duration_s=float(duration_s),
        )
        self.set_zero_rate(calibration)
        return calibration


def open_gyro(
    url: str,
    *,
    tap: Callable[[bytes, float], None] | None = None,
    **settings: Any,
) -> GyroReader:
    """Open a gyro stream and start reading it.

    Parameters
    ----------
    url : str
        ``/dev/ttyUSB0``, a pty path, ``COM3`` or ``sim://[?rate_dps=X,Y,Z&...]``
        (in-process simulated sensor).
    tap : callable, optional
        ``tap(data, arrival_s)`` sees every chunk read (see :class:`GyroReader`).
    **settings
        Fields of :class:`GyroSettings` (``full_scale_dps``, ``baudrate``, ...), or
        ``settings=GyroSettings(...)``.

    Returns
    -------
    GyroReader
        Running; close it (or use ``with``).

    Raises
    ------
    ConfigError
        Bad URL or setting (the message names the value and the allowed values).
    SensorError
        The port cannot be opened (the message names it and what to check).
    """
    if not isinstance(url, str) or not url.strip():
        raise ConfigError(
            f"gyro url={url!r} must be a non-empty string such as '/dev/ttyUSB0' or 'sim://'"
        )
    if "settings" in settings:
        given = settings.pop("settings")
        if settings:
            raise ConfigError("pass either settings=GyroSettings(...) or keywords, not both")
        if not isinstance(given, GyroSettings):
            raise ConfigError(f"settings must be a GyroSettings, got {type(given).__name__}")
        config = given
    else:
        allowed = {f.name for f in fields(GyroSettings)}
        unknown = sorted(set(settings) - allowed)
        if unknown:
            raise ConfigError(
                f"unknown gyro setting(s) {', '.join(map(repr, unknown))}; allowed: "
                + ", ".join(sorted(allowed))
            )
        config = GyroSettings(**settings)
    port = open_port(url, config)
    reader = GyroReader(port, config, url=url, tap=tap)
    reader.start()
    return reader
