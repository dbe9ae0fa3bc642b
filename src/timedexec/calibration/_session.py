"""One run of a calibration sweep: the driver, the gyro buffer, the trial motion.

Shared by the runner (trials, still recording) and the pre-flight (the same motion, checked
instead of recorded), so that the check moves the robot exactly as the first trial will.
"""

from __future__ import annotations

import math
import time
from collections import deque
from typing import Protocol

import numpy as np

from timedexec._types import FloatArray
from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import DriverTimeout
from timedexec.recording import SweepProtocol
from timedexec.sensors import GyroSamples

__all__ = ["GyroSource", "Pulse", "Session", "gyro_name"]


class GyroSource(Protocol):
    """What the runner needs of a gyro: samples that have arrived, with raw counts."""

    def read(self, n: int | None = None, *, timeout_s: float | None = 1.0) -> GyroSamples: ...


def gyro_name(gyro: object) -> str:
    """How messages name the gyro: its URL (``'/dev/ttyUSB0'``, ``'sim://'``) if it has
    one, else what it is (the simulated robot's virtual gyro)."""
    url = getattr(gyro, "url", None)
    if isinstance(url, str) and url:
        return repr(url)
    if type(gyro).__name__ == "VirtualGyro":
        return "the simulated robot's virtual gyro"
    return f"the gyro ({type(gyro).__name__})"


def _no_samples() -> GyroSamples:
    return GyroSamples(
        counter_unwrapped=np.zeros(0, np.int64),
        host_time_s=np.zeros(0),
        rate_rad_s=np.zeros((0, 3)),
        raw=np.zeros((0, 3), np.int16),
        arrival_s=np.zeros(0),
    )


class Pulse:
    """The out-and-back motion of one trial, as sent: trigger, send time, packages."""

    def __init__(self, trigger: RobotState, t_send: float, packages: list[RobotState]) -> None:
        self.trigger = trigger
        self.t0 = trigger.host_time_s
        self.t_send = t_send
        self.packages = packages


class Session:
    """One run: the driver, the gyro buffer and the host clock origin.

    Parameters
    ----------
    driver : RobotDriver
        Connected driver.
    gyro : GyroSource
        The gyro on the flange.
    settings : SweepProtocol
        Motion, controller period and the gyro's constants.
    origin_s : float
        Host time of the sweep's time origin, s.
    """

    def __init__(
        self, driver: RobotDriver, gyro: GyroSource, settings: SweepProtocol, origin_s: float
    ) -> None:
        self.driver = driver
        self.gyro = gyro
        self.settings = settings
        self.origin_s = origin_s
        self.buffer: deque[GyroSamples] = deque()
        self.last: RobotState | None = None

    def clock(self) -> float:
        """The driver's host clock, s (virtual time on a virtual simulator)."""
        return float(getattr(self.driver, "clock", time.monotonic)())

    def state(self, timeout_s: float = 0.5) -> RobotState:
        """The next state package; the gyro samples that arrived meanwhile are buffered
        (the last 5 s)."""
        st = self.driver.read_state(timeout_s=timeout_s)
        self.last = st
        got = self.gyro.read(timeout_s=0.0)
        if len(got):
            self.buffer.append(got)
            horizon = st.host_time_s - 5.0
            while self.buffer and len(self.buffer[0]) and self.buffer[0].arrival_s[-1] < horizon:
                self.buffer.popleft()
        return st

    def catch_up(self, *, max_wait_s: float = 5.0) -> RobotState:
        """Read the state packages that queued up while nobody read (a driver that keeps
        every package, as the RSI driver does) until one is fresh: arrived within three
        controller periods of now. Motion must be planned on the robot's present state, and
        time measured on state packages must be the present too.

        Gives up after ``max_wait_s`` of wall time (a driver whose host times are on another
        clock never looks fresh) and returns the newest state read.
        """
        period = self.settings.controller_period_s
        give_up = time.monotonic() + max_wait_s
        st = self.state()
        while st.host_time_s < self.clock() - 3.0 * period and time.monotonic() < give_up:
            st = self.state()
        return st

    def samples(self) -> GyroSamples:
        """Every buffered gyro sample, oldest first."""
        if not self.buffer:
            return _no_samples()
        return GyroSamples.concatenate(list(self.buffer))

    def samples_since(self, t_s: float) -> GyroSamples:
        """The buffered gyro samples that arrived after host time ``t_s``."""
        s = self.samples()
        return s.select(s.arrival_s > t_s)

    def discard_gyro(self) -> None:
        """Forget every gyro sample that has arrived so far (buffered here or in the gyro)."""
        discard = getattr(self.gyro, "discard", None)
        if discard is not None:
            discard()
        else:
            self.gyro.read(timeout_s=0.0)
        self.buffer.clear()

    def wait_still(
        self, *, min_s: float, speed_eps: float = 2e-3, packages: int = 10
    ) -> RobotState:
        """Wait until the robot has been still (every joint below ``speed_eps`` rad/s) for
        ``packages`` packages and at least ``min_s`` s."""
        start = self.state()
        quiet = 0
        while True:
            st = self.state()
            quiet = quiet + 1 if np.abs(st.qd).max() < speed_eps else 0
            if quiet >= packages and st.host_time_s - start.host_time_s >= min_s:
                return st
            if st.host_time_s - start.host_time_s > 30.0:
                raise DriverTimeout(
                    "the robot did not come to rest within 30 s; check it is not moving"
                )

    def move_to(self, q_target: FloatArray, *, tol_rad: float = 5e-4, stuck_s: float = 3.0) -> None:
        """Drive to ``q_target`` with speed commands (works on every driver).

        Raises
        ------
        DriverTimeout
            The error has not shrunk by 0.1 mrad for ``stuck_s`` (or the move took over
            60 s): the message says what was seen — the driver's own diagnosis (RSI: a
            correction saturated at its limit, RSI stopped; a watchdog trip), else whether
            the reported position moved at all while speeds were commanded.
        """
        spec = self.settings.spec
        vmax = 0.5 * np.asarray(spec.qd_max_rad_s)
        st = self.state()
        t_start = st.host_time_s
        best, best_at, q_best = math.inf, t_start, st.q.copy()
        while True:
            err = q_target - st.q
            worst = float(np.abs(err).max())
            if worst < tol_rad and np.abs(st.qd).max() < 0.01:
                break
            if worst < best - 1e-4:
                best, best_at, q_best = worst, st.host_time_s, st.q.copy()
            elapsed = st.host_time_s - t_start
            if worst >= tol_rad and (st.host_time_s - best_at > stuck_s or elapsed > 60.0):
                self.driver.speedj(np.zeros(6), 4.0, 0.0)
                raise DriverTimeout(self._not_converging(err, st.q - q_best, elapsed))
            qd = np.clip(3.0 * err, -vmax, vmax)
            qd = np.where(np.abs(err) < tol_rad, 0.0, qd)
            self.driver.speedj(qd, 4.0, 0.0)
            st = self.state()
        self.driver.speedj(np.zeros(6), 4.0, 0.0)

    def _not_converging(self, err: FloatArray, moved: FloatArray, elapsed_s: float) -> str:
        """What a move to the start configuration that does not converge saw."""
        j = int(np.argmax(np.abs(err)))
        head = (
            f"moving to the start configuration stopped converging after {elapsed_s:.1f} s "
            f"(joint {j + 1} still {err[j]:+.4f} rad off)"
        )
        seen = self.driver.diagnose_motion()
        if seen:
            return f"{head}: {seen}"
        if float(np.abs(moved).max()) < 1e-4:
            return (
                f"{head}: no motion — the reported position did not change while speeds were "
                "commanded; check the robot is enabled, in remote/automatic mode and free to "
                "move"
            )
        return (
            f"{head}: the arm moves ({np.abs(moved).max():.4f} rad since the error last "
            "shrank) but not towards the target; check nothing holds or drives it"
        )

    def pulse(self, joint: int, direction: float) -> Pulse:
        """Move one joint out and back as a trial does, on the arrival of state packages.

        The command leaves on the arrival of a package (the trigger, trial time 0); the
        later segments (decelerate, pause, back, decelerate) on later arrivals. Returns when
        the recording window ``profile.record_s`` has passed, with every package of it.

        Parameters
        ----------
        joint : int
            The joint, 1-based.
        direction : float
            +1 or -1.
        """
        settings = self.settings
        prof = settings.profile
        period = settings.controller_period_s
        qd = np.zeros(6)
        qd[joint - 1] = direction * prof.speed_rad_s
        a = prof.acceleration_rad_s2
        ramp = prof.speed_rad_s / a
        trigger = self.state()
        t0 = trigger.host_time_s
        self.driver.speedj(qd, a, 0.0)
        t_send = float(getattr(self.driver, "last_send_s", self.clock()))
        if not math.isfinite(t_send) or t_send < t0:
            t_send = self.clock()
        pulse = prof.pulse_s
        segments = [
            (t_send + ramp + prof.hold_s, np.zeros(6)),
            (t_send + pulse + prof.pause_s, -qd),
            (t_send + 2 * pulse + prof.pause_s - ramp, np.zeros(6)),
        ]
        packages = [trigger]
        while True:
            st = self.state()
            if segments and st.host_time_s >= segments[0][0] - 0.5 * period:
                self.driver.speedj(segments.pop(0)[1], a, 0.0)
            if st.host_time_s >= t0 + prof.record_s:
                break
            packages.append(st)
        while segments:  # a slow stream: finish the motion anyway
            self.driver.speedj(segments.pop(0)[1], a, 0.0)
        return Pulse(trigger, t_send, packages)
