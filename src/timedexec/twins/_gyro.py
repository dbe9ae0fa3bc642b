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

The sensor model and frame encoder are :class:`timedexec.sim.GyroFrameSource`'s; this module
is the transport (the pty, USB-like bursts, overflow) and the process entry point.

Run ``python -m timedexec.twins gyro --help`` to start a twin in its own process.
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
from collections.abc import Sequence
from typing import Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError, SensorError
from timedexec.sim import (
    DEFAULT_BIAS_DPS,
    GyroFrameSource,
    RateSource,
    sine_rate_source,
    step_rate_source,
)
from timedexec.twins._lifecycle import Twin

__all__ = ["GyroTwin", "main"]


class GyroTwin(Twin):
    """A simulated gyro on a pseudo-terminal, streaming in real time from a thread.

    Driven by the verbs every twin shares (:class:`~timedexec.twins.Twin`): ``start``,
    ``stop`` (also :meth:`close`), ``kill`` (the device vanishes: the pty closes) and
    ``stall`` (nothing is delivered for a while; the sensor keeps sampling, and the
    backlog, up to ``max_backlog_s``, follows in one burst). A serial link has no
    connections, so ``drop`` has no meaning; :meth:`drop_bytes` loses data instead.

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
    nominal_rate_hz : float
        Nominal sample rate, Hz (8000; 1000 plays a sensor with its DLPF on).
    frame_loss : float
        Probability that a sample's frame is never sent (a device that drops samples: the
        host sees counter gaps), 0..1; counted in :attr:`frames_lost`.
    byte_error_rate : float
        Probability that a byte is replaced by a random one (a noisy line; 1 sends nothing
        but garbage), 0..1.

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
        nominal_rate_hz: float = 8000.0,
        frame_loss: float = 0.0,
        byte_error_rate: float = 0.0,
    ) -> None:
        if not (math.isfinite(burst_period_s) and 1e-4 <= burst_period_s <= 0.1):
            raise ConfigError(
                f"burst_period_s={burst_period_s!r} must be within 1e-4..0.1 s (USB: 1e-3)"
            )
        if not max_backlog_s > 0:
            raise ConfigError(f"max_backlog_s={max_backlog_s!r} must be positive, s")
        for name, value in (("frame_loss", frame_loss), ("byte_error_rate", byte_error_rate)):
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"{name}={value!r} must be a probability in 0..1")
        self.source = GyroFrameSource(
            rate_source,
            clock_error_ppm=clock_error_ppm,
            noise_density_dps_rthz=noise_density_dps_rthz,
            bias_dps=bias_dps,
            full_scale_dps=full_scale_dps,
            nominal_rate_hz=nominal_rate_hz,
            dlpf_group_delay_s=dlpf_group_delay_s,
            seed=seed,
            record_truth=record_truth,
        )
        self.frame_loss = float(frame_loss)
        self.byte_error_rate = float(byte_error_rate)
        self.frames_lost = 0
        """Frames not sent because of ``frame_loss``."""
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
        self._stall_until = -math.inf
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

    def start(self) -> Self:
        """Open the pty pair and start streaming; returns the twin.

        Raises
        ------
        SensorError
            If the twin already runs.
        """
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
        return self

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

    def stop(self) -> None:
        """Stop streaming and close the pty (the same as :meth:`close`). Idempotent."""
        self.close()

    def kill(self) -> None:
        """The device vanishes at once, as an unplugged sensor: the pty closes (for a
        thread this is :meth:`close`; no data is flushed)."""
        self.close()

    @property
    def is_alive(self) -> bool:
        """Whether the streaming thread runs."""
        return self._thread is not None and self._thread.is_alive()

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

    def _stall(self, seconds: float) -> None:
        if self._thread is None:
            raise SensorError("the gyro twin is not started; start() it before stall()")
        with self._lock:
            self._stall_until = time.monotonic() + seconds

    def drop(self) -> None:
        """A serial link has no connections to drop: raises NotImplementedError.

        Raises
        ------
        NotImplementedError
            Always; lose data with :meth:`drop_bytes` or stop delivery with :meth:`stall`.
        """
        raise NotImplementedError(
            "GyroTwin.drop(): a serial link has no connections; use drop_bytes(n) or stall(seconds)"
        )

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

    def _degrade(self, data: bytes) -> bytes:
        """The steady faults of a bad device: lost frames, then damaged bytes."""
        if self.frame_loss > 0:
            frames = np.frombuffer(data, dtype=np.uint8).reshape(-1, 11)
            keep = self._fault_rng.random(frames.shape[0]) >= self.frame_loss
            self.frames_lost += int(frames.shape[0] - np.count_nonzero(keep))
            data = frames[keep].tobytes()
        if self.byte_error_rate > 0 and data:
            buf = np.frombuffer(data, dtype=np.uint8).copy()
            hit = self._fault_rng.random(buf.shape[0]) < self.byte_error_rate
            buf[hit] = self._fault_rng.integers(0, 256, int(np.count_nonzero(hit)), dtype=np.uint8)
            data = buf.tobytes()
        return data

    def _apply_faults(self, data: bytes, offset: int) -> bytes:
        data = self._degrade(data)
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
                    if now < self._stall_until:
                        written = 0  # stalled: the device keeps sampling into its buffer
                    else:
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


def main(argv: Sequence[str] | None = None) -> int:
    """Run a gyro twin in this process until ``--duration-s`` elapses or SIGTERM/SIGINT.

    Prints one JSON line on stdout when streaming starts (``slave_path``, ``port``,
    ``start_time_s``, ``true_rate_hz``) and one summary line when it stops.
    """
    parser = argparse.ArgumentParser(
        prog="python -m timedexec.twins gyro", description=main.__doc__
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
    parser.add_argument("--nominal-rate-hz", type=float, default=8000.0)
    parser.add_argument("--frame-loss", type=float, default=0.0)
    parser.add_argument("--byte-error-rate", type=float, default=0.0)
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
            nominal_rate_hz=args.nominal_rate_hz,
            frame_loss=args.frame_loss,
            byte_error_rate=args.byte_error_rate,
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
