"""Reported state: back-dating, the controller clock seen from the host, and staleness.

A state package describes the robot as it was the predicted response delay before it
arrived. :class:`StateTracker` keeps the newest package back-dated to that instant, the
lower-envelope clock model (the smallest arrival minus controller time of the last
:data:`ENVELOPE_S`: the host time of each controller cycle boundary plus the shortest
sampling-to-arrival time) and the controller cycle numbering, and extrapolates the physical
state to any host time (:class:`StateEstimate`).

:class:`StalenessLimits` says when the state is too old to command from. Three limits, in
controller periods, that :class:`~timedexec.execution.TimedExecutor`'s ``stale_periods``
sets together unless ``stall_periods`` / ``late_periods`` are given:

- ``stall_periods``: while streaming, no package for this long is a fault (a silent
  stream; it also bounds how long the loop may coast on its estimate);
- ``late_periods``: a package that arrives this much later than the fastest packages (the
  clock model) is a fault (a congested or queued stream: the package is there but old);
- ``command_hold_periods``: how long the controller keeps executing each speed command
  without a new one, its own watchdog if the host dies: the stall limit plus
  :data:`COMMAND_HOLD_MARGIN_PERIODS`, so the host's fault stop always comes first.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import NoReturn

import numpy as np
from numpy.typing import NDArray

from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import ConfigError, DriverError, DriverTimeout
from timedexec.execution._plan import JointPlan

__all__ = [
    "COMMAND_HOLD_MARGIN_PERIODS",
    "ENVELOPE_S",
    "IDLE_READ_TIMEOUT_S",
    "StalenessLimits",
    "StateEstimate",
    "StateTracker",
    "read_fresh_state",
]

FloatArray = NDArray[np.float64]

#: Window of the lower-envelope clock model (arrival minus controller time), s.
ENVELOPE_S = 0.5
#: Each speed command is held this many periods longer than the stall limit: the fault
#: stop goes out within two periods of the limit, so it reaches the controller before the
#: last regular command runs out.
COMMAND_HOLD_MARGIN_PERIODS = 2.0
#: While idle at rest a read waits at least this long (gaps are the caller's, no fault), s.
IDLE_READ_TIMEOUT_S = 0.5


@dataclass(frozen=True)
class StateEstimate:
    """The executor's belief of the physical joint state at ``time_s``.

    Attributes
    ----------
    time_s : float
        Host time the estimate is for, s.
    q_rad, qd_rad_s : ndarray (6,)
        Estimated physical joint positions and speeds.
    sample_time_s : float
        Host time the newest package describes (its arrival minus the predicted response
        delay), s.
    response_delay_s : float
        The predicted response delay used to back-date it, s.
    horizon_s : float
        ``time_s - sample_time_s``: how far the estimate extrapolates, s.
    """

    time_s: float
    q_rad: FloatArray
    qd_rad_s: FloatArray
    sample_time_s: float
    response_delay_s: float
    horizon_s: float


class StateTracker:
    """The reported state stream: the newest package, back-dated, and the clock model.

    Attributes
    ----------
    response_s : float
        Response delay packages are back-dated by, s (set by the executor from the
        model's prediction; applies to packages ingested from then on).
    last : RobotState or None
        The newest package as received.
    last_arrival_s : float
        Its host arrival time, s (NaN before the first).
    offset_min_s : float
        Lower envelope of arrival minus controller time over the last
        :data:`ENVELOPE_S`, s (inf before the first package).
    controller_ref_s : float
        Controller time of the first package: cycle 0 of the numbering, s.
    sample : tuple or None
        ``(t_phys, q, qd)`` of the newest package: the host time it describes (s), its
        joint positions (rad) and speeds (rad/s), (6,) each.
    """

    def __init__(self, *, envelope_s: float = ENVELOPE_S) -> None:
        self.envelope_s = envelope_s
        self.response_s = 0.0
        self.last: RobotState | None = None
        self.last_arrival_s = math.nan
        self.offset_min_s = math.inf
        self.controller_ref_s = math.nan
        self.sample: tuple[float, FloatArray, FloatArray] | None = None
        self._envelope: deque[tuple[float, float]] = deque()

    def ingest(self, state: RobotState) -> None:
        """Take ``state`` as the newest package: update the clock model and back-date it."""
        self.last = state
        self.last_arrival_s = state.host_time_s
        # Lower envelope of (arrival - controller time) over the last envelope_s: the
        # fastest packages' offset, i.e. the host time of each controller cycle boundary
        # plus the shortest sampling-to-arrival time (follows a slowly drifting phase).
        off = state.host_time_s - state.controller_time_s
        env = self._envelope
        while env and env[-1][1] >= off:
            env.pop()
        env.append((state.host_time_s, off))
        while env[0][0] < state.host_time_s - self.envelope_s:
            env.popleft()
        self.offset_min_s = env[0][1]
        if not math.isfinite(self.controller_ref_s):
            self.controller_ref_s = state.controller_time_s
        t_phys = state.host_time_s - self.response_s
        self.sample = (t_phys, np.asarray(state.q, float), np.asarray(state.qd, float))

    # ------------------------------------------------------------------ the clock model
    def lateness_s(self, state: RobotState) -> float:
        """How much later than the fastest packages ``state`` arrived, s (the clock
        model's view of its age beyond the shortest sampling-to-arrival time)."""
        return (state.host_time_s - state.controller_time_s) - self.offset_min_s

    def cycle_of(self, controller_time_s: float, period_s: float) -> int:
        """Number of the controller cycle stamped ``controller_time_s`` (0: the first
        package's)."""
        return round((controller_time_s - self.controller_ref_s) / period_s)

    def controller_time_of(self, cycle: int, period_s: float) -> float:
        """Controller time stamp of cycle ``cycle``, s."""
        return self.controller_ref_s + cycle * period_s

    def earliest_arrival_s(self, cycle: int, period_s: float) -> float:
        """Earliest host time the package of cycle ``cycle`` can arrive (clock model), s."""
        return self.controller_ref_s + cycle * period_s + self.offset_min_s

    # ------------------------------------------------------------------ back-dated state
    def newest(self) -> tuple[float, FloatArray, FloatArray]:
        """``(t_phys, q, qd)`` of the newest package (see :attr:`sample`).

        Raises
        ------
        DriverError
            No state received yet.
        """
        if self.sample is None:
            raise DriverError("no state received yet; connect() first")
        return self.sample

    def estimate(self, t_s: float, plan: JointPlan | None) -> StateEstimate:
        """The physical joint state at host time ``t_s``.

        From the instant the newest package describes, the estimate follows ``plan`` (when
        scheduled; keeping the offset between plan and robot seen in the package) or,
        without one, the reported speed.
        """
        t_phys, q, qd = self.newest()
        if plan is not None and math.isfinite(plan.start_time_s):
            q_then, _, _ = plan.sample(t_phys - plan.start_time_s)
            q_t, qd_t, _ = plan.sample(t_s - plan.start_time_s)
            q_est = q_t + (q - q_then)
            qd_est = qd_t
        else:
            q_est = q + qd * (t_s - t_phys)
            qd_est = qd
        return StateEstimate(
            time_s=t_s,
            q_rad=q_est,
            qd_rad_s=qd_est,
            sample_time_s=t_phys,
            response_delay_s=self.response_s,
            horizon_s=t_s - t_phys,
        )

    def q_per_joint(self, t_s: FloatArray, plan: JointPlan | None) -> FloatArray:
        """Estimated position of joint j at host time ``t_s[j]`` (6,), rad (as
        :meth:`estimate`, one instant per joint)."""
        t_phys, q, qd = self.newest()
        if plan is not None and math.isfinite(plan.start_time_s):
            q_then, _, _ = plan.sample(t_phys - plan.start_time_s)
            return plan.position_per_joint(t_s - plan.start_time_s) + (q - q_then)
        return q + qd * (t_s - t_phys)


def _check_periods(name: str, value: float) -> float:
    if not value >= 1:
        raise ConfigError(f"{name}={value!r} must be >= 1 controller period")
    return float(value)


@dataclass(frozen=True, kw_only=True)
class StalenessLimits:
    """When the reported state is too old to command from (see the module docstring).

    Attributes
    ----------
    stall_periods : float
        While streaming, no package for this many controller periods is a fault (>= 1).
        Also how long the loop may coast on its estimate, and (at least
        :data:`IDLE_READ_TIMEOUT_S`) how long an idle read waits.
    late_periods : float
        A package arriving this many periods later than the fastest packages is a fault
        (>= 1).
    """

    stall_periods: float
    late_periods: float

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "stall_periods", _check_periods("stall_periods", self.stall_periods)
        )
        object.__setattr__(self, "late_periods", _check_periods("late_periods", self.late_periods))

    @classmethod
    def from_stale_periods(
        cls,
        stale_periods: float,
        *,
        stall_periods: float | None = None,
        late_periods: float | None = None,
    ) -> StalenessLimits:
        """The limits the ``stale_periods`` knob sets, each overridable."""
        stale = _check_periods("stale_periods", stale_periods)
        return cls(
            stall_periods=stale if stall_periods is None else stall_periods,
            late_periods=stale if late_periods is None else late_periods,
        )

    @property
    def command_hold_periods(self) -> float:
        """How long each speed command is held without a new one, periods: the stall
        limit plus :data:`COMMAND_HOLD_MARGIN_PERIODS`."""
        return self.stall_periods + COMMAND_HOLD_MARGIN_PERIODS

    def idle_timeout_s(self, period_s: float) -> float:
        """How long a read waits while idle at rest (a timeout there is no fault), s."""
        return max(self.stall_periods * period_s, IDLE_READ_TIMEOUT_S)

    def stall_deadline_s(self, last_arrival_s: float, since_s: float, period_s: float) -> float:
        """Host time by which the next package must arrive, s: the stall limit after the
        later of the last arrival and ``since_s`` (when streaming began)."""
        return max(last_arrival_s, since_s) + self.stall_periods * period_s

    def silence_fault(self, silent_s: float, period_s: float) -> str:
        """Fault message: no package for ``silent_s`` (past the stall deadline already)."""
        return (
            f"no state package for {silent_s * 1e3:.1f} ms "
            f"(> {self.stall_periods:g} periods of {period_s * 1e3:g} ms); robot stopped"
        )

    def stall_fault(self, period_s: float, reason: object) -> str:
        """Fault message: a read waited until the stall deadline and got nothing."""
        return (
            f"the state stream stalled: no package within {self.stall_periods:g} periods "
            f"({self.stall_periods * period_s * 1e3:.1f} ms) of the last one ({reason}); "
            "robot stopped"
        )

    def late_fault(self, state: RobotState, lateness_s: float, period_s: float) -> str | None:
        """Fault message if ``state`` arrived more than the late limit after the fastest
        packages (``lateness_s``, :meth:`StateTracker.lateness_s`), else None."""
        if math.isfinite(lateness_s) and lateness_s > self.late_periods * period_s:
            return (
                f"stale state: package of controller time {state.controller_time_s:.4f} s "
                f"arrived {lateness_s * 1e3:.1f} ms later than the fastest packages "
                f"(> {self.late_periods:g} periods); robot stopped"
            )
        return None


def read_fresh_state(
    driver: RobotDriver,
    tracker: StateTracker,
    limits: StalenessLimits,
    *,
    clock: Callable[[], float],
    period_s: float,
    streaming_since_s: float,
    coast_at_s: float | None,
    fault: Callable[[str], NoReturn],
) -> RobotState | None:
    """While streaming: the next package, checked for staleness.

    Parameters
    ----------
    driver : RobotDriver
        Where the package comes from.
    tracker : StateTracker
        The packages so far (last arrival, clock model); not updated here.
    limits : StalenessLimits
        The stall and late limits.
    clock : callable
        The host clock the driver stamps with, s.
    period_s : float
        Controller period, s.
    streaming_since_s : float
        Host time streaming began, s (the stall limit counts from the later of it and the
        last arrival).
    coast_at_s : float, optional
        Give up waiting at this host time (before the stall deadline) and return None.
    fault : callable
        Called with the message when the stream stalled or the package is late; must
        raise (it is called inside the ``except`` of a timed-out read).

    Returns
    -------
    RobotState or None
        The package, or None when ``coast_at_s`` passed first.
    """
    last_arrival = tracker.last_arrival_s
    deadline = limits.stall_deadline_s(last_arrival, streaming_since_s, period_s)
    timeout = deadline - clock()
    if timeout <= 0:
        fault(limits.silence_fault(clock() - last_arrival, period_s))
    if coast_at_s is not None and coast_at_s < deadline:
        try:
            state = driver.read_state(timeout_s=max(coast_at_s - clock(), 0.0))
        except DriverTimeout:
            return None
    else:
        try:
            state = driver.read_state(timeout_s=timeout)
        except DriverTimeout as exc:
            fault(limits.stall_fault(period_s, exc))
    message = limits.late_fault(state, tracker.lateness_s(state), period_s)
    if message is not None:
        fault(message)
    return state
