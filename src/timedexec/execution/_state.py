"""Reported state: back-dating, the controller clock seen from the host, and staleness.

A state package describes the robot as it was the predicted response delay before it
arrived. :class:`StateTracker` keeps the newest package back-dated to that instant, the
lower-envelope clock model (the smallest arrival minus controller time of the last
:data:`ENVELOPE_S`: the host time of each controller cycle boundary plus the shortest
sampling-to-arrival time; for the cycle lock also over minutes as a line,
:class:`~timedexec.execution.BoundaryLine`), the controller cycle numbering and the
stream's measured jitter (:class:`StreamJitter`: recent inter-arrival gaps and lateness),
and extrapolates the physical state to any host time (:class:`StateEstimate`).

:class:`StalenessLimits` says when the state is too old to command from, judged by time and
by the measured jitter of the stream:

- the **stall limit**: while streaming, no package for this long is a fault (a silent
  stream; it also bounds how long the loop may coast on its estimate). Default
  ``min(0.08 s, max(0.05 s, 2 x p99 of the last 1000 gaps))``;
- the **late limit**: a package that arrives this much later than the fastest packages
  (the clock model) is a fault (a congested or queued stream: the package is there but
  old). The same rule on the packages' lateness.

A stream whose packages arrive with 6-24 ms gaps at 500 Hz keeps the 50 ms floor (twice
its largest gap: no false stop, also before any gap is measured; 2 x p99 = 48 ms); a quiet
stream too; a stream jittering more gets up to the 80 ms ceiling, within which a dead
stream is noticed whatever the jitter (and before the controller watchdog's default 0.1 s:
while the loop waits for a package it sends nothing). The legacy fixed limits (``stale_periods``, ``stall_periods``, ``late_periods``
of the executor, in controller periods) still work and replace the adaptive ones.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NoReturn

import numpy as np

from timedexec._types import FloatArray
from timedexec._validation import DictMixin, check_known_keys
from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import ConfigError, DriverError, DriverTimeout
from timedexec.execution._cycle import BoundaryLine, IntakeFix, SendPhase
from timedexec.execution._plan import JointPlan

__all__ = [
    "COMMAND_HOLD_MARGIN_PERIODS",
    "ENVELOPE_S",
    "GAP_FACTOR",
    "GAP_QUANTILE",
    "GAP_WINDOW",
    "IDLE_READ_TIMEOUT_S",
    "STALL_CEILING_S",
    "STALL_FLOOR_S",
    "StalenessLimits",
    "StateEstimate",
    "StateTracker",
    "StreamJitter",
    "read_fresh_state",
]


#: Window of the lower-envelope clock model (arrival minus controller time), s.
ENVELOPE_S = 0.5
#: Each speed command is held this many periods longer than the longest stall limit: the
#: fault stop goes out within two periods of the limit, so it reaches a controller that
#: honours the duration before the last regular command runs out.
COMMAND_HOLD_MARGIN_PERIODS = 2.0
#: Default smallest stall / late limit, s: twice a 24 ms gap, before any gap is measured.
STALL_FLOOR_S = 0.05
#: Default largest stall / late limit, s: a dead stream is noticed within it, and the
#: executor's own fault stop still goes out before the controller watchdog's default 0.1 s
#: runs out (the loop sends nothing while it waits for a package).
STALL_CEILING_S = 0.08
#: Default multiple of the measured quantile.
GAP_FACTOR = 2.0
#: Default quantile of the recent gaps / lateness.
GAP_QUANTILE = 0.99
#: Default number of recent packages the quantiles look back over (2 s at 500 Hz).
GAP_WINDOW = 1000
#: Fewest samples before the measured quantile counts (below: the floor).
MIN_JITTER_SAMPLES = 50
#: The adaptive limits are never below this many controller periods.
MIN_LIMIT_PERIODS = 3.0
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
        delay, or its sampling boundary where the intake is probed), s.
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
    boundary : BoundaryLine
        The same over minutes, as a line: what the cycle lock aims by once it has one
        (:meth:`earliest_arrival_s`).
    controller_ref_s : float
        Controller time of the first package: cycle 0 of the numbering, s.
    sample : tuple or None
        ``(t_phys, q, qd)`` of the newest package: the host time it describes (s), its
        joint positions (rad) and speeds (rad/s), (6,) each.
    jitter : StreamJitter
        The stream's recent gaps and lateness (gaps up to ``max_gap_s``, s).
    intake : IntakeFix or None
        The controller's probed command deadline, dated (:meth:`IntakeFix.dated`):
        packages are then dated at the cycle boundary they were sampled at
        (:meth:`IntakeFix.sampled_s`), not by ``response_s``, which carries the
        publisher's phase.
    """

    def __init__(
        self,
        *,
        envelope_s: float = ENVELOPE_S,
        jitter: StreamJitter | None = None,
        max_gap_s: float = STALL_CEILING_S,
    ) -> None:
        self.envelope_s = envelope_s
        self.jitter = jitter if jitter is not None else StreamJitter()
        self.max_gap_s = float(max_gap_s)
        self.response_s = 0.0
        self.last: RobotState | None = None
        self.last_arrival_s = math.nan
        self.offset_min_s = math.inf
        self.controller_ref_s = math.nan
        self.sample: tuple[float, FloatArray, FloatArray] | None = None
        self._envelope: deque[tuple[float, float]] = deque()
        self.boundary = BoundaryLine()
        self.intake: IntakeFix | None = None

    def ingest(self, state: RobotState) -> None:
        """Take ``state`` as the newest package: update the clock model and back-date it."""
        previous = self.last_arrival_s
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
        self.boundary.add(state.host_time_s, off)
        gap = state.host_time_s - previous
        # Gaps longer than the ceiling are the caller's (idle, not stepping), not the
        # stream's: only the shorter ones teach the limits.
        if gap <= self.max_gap_s:
            self.jitter.add(gap, off - self.offset_min_s)
        if not math.isfinite(self.controller_ref_s):
            self.controller_ref_s = state.controller_time_s
        t_phys = state.host_time_s - self.response_s
        if self.intake is not None and math.isfinite(self.intake.sample_offset_s):
            line = self.boundary.line
            rate = line[2] if line is not None else 0.0
            t_phys = self.intake.sampled_s(state.controller_time_s, rate)
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
        """Earliest host time the package of cycle ``cycle`` can arrive (clock model), s:
        by the long-term line where there is one (:class:`BoundaryLine`; never later than
        the short envelope), else by the short envelope."""
        t = self.controller_ref_s + cycle * period_s
        line = self.boundary.offset_s(t + self.offset_min_s)
        return t + (line if line < self.offset_min_s else self.offset_min_s)

    def send_target_s(self, phase: SendPhase, cycle: int, period_s: float) -> float:
        """Host send time of the command answering the package of ``cycle`` (cycle lock:
        :meth:`SendPhase.aim_s` by the clock model and the clock line's drift), s."""
        line = self.boundary.line
        return phase.aim_s(
            self.controller_time_of(cycle, period_s),
            self.earliest_arrival_s(cycle, period_s),
            line[2] if line is not None else 0.0,
        )

    def coast_at_s(self, phase: SendPhase | None, cycle: int, period_s: float) -> float:
        """Host time after which a coasting loop stops waiting for the package of
        ``cycle`` and commands that cycle from the estimate, s: its send time less the
        command's recent work (cycle lock), else half a period after its earliest arrival."""
        if phase is not None:
            return self.send_target_s(phase, cycle, period_s) - phase.coast_lead_s
        return self.earliest_arrival_s(cycle, period_s) + 0.5 * period_s

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
        raise ConfigError(
            f"{name}={value!r} must be >= 1 controller period; give e.g. 3, or leave it None "
            "for the adaptive limits (StalenessLimits)"
        )
    return float(value)


class StreamJitter:
    """The measured jitter of the state stream: recent inter-arrival gaps and lateness.

    Two preallocated rings of the last ``window`` samples; their ``quantile`` is refreshed
    every ``refresh`` samples (an in-place partition of a preallocated scratch array), so
    adding a sample costs no allocation.

    Parameters
    ----------
    window : int
        Samples kept (1000: two seconds at 500 Hz).
    quantile : float
        The high quantile the limits scale (0.99).
    refresh : int
        Recompute the quantiles every this many samples.

    Attributes
    ----------
    gap_q_s, late_q_s : float
        The quantile of the inter-arrival gaps and of the lateness, s (0 until
        :data:`MIN_JITTER_SAMPLES` samples).
    """

    def __init__(self, window: int = 1000, quantile: float = 0.99, refresh: int = 25) -> None:
        if not window >= MIN_JITTER_SAMPLES:
            raise ConfigError(f"window={window!r} must be >= {MIN_JITTER_SAMPLES} samples")
        if not 0.5 <= quantile < 1:
            raise ConfigError(f"quantile={quantile!r} outside [0.5, 1); use e.g. 0.99")
        self.window = int(window)
        self.quantile = float(quantile)
        self.refresh = max(1, int(refresh))
        self._gaps = np.zeros(self.window)
        self._late = np.zeros(self.window)
        self._scratch = np.empty(self.window)
        self._n = 0
        self._i = 0
        self._since = 0
        self.gap_q_s = 0.0
        self.late_q_s = 0.0

    def __len__(self) -> int:
        return self._n

    def add(self, gap_s: float, late_s: float) -> None:
        """One package's gap since the previous one and its lateness, s."""
        i = self._i
        self._gaps[i] = gap_s
        self._late[i] = late_s
        self._i = (i + 1) % self.window
        if self._n < self.window:
            self._n += 1
        self._since += 1
        if self._since >= self.refresh and self._n >= MIN_JITTER_SAMPLES:
            self._since = 0
            self.gap_q_s = self._q(self._gaps)
            self.late_q_s = self._q(self._late)

    def _q(self, ring: FloatArray) -> float:
        n = self._n
        k = min(n - 1, math.ceil(self.quantile * (n - 1)))
        view = self._scratch[:n]
        np.copyto(view, ring[:n])
        view.partition(k)
        return float(view[k])


@dataclass(frozen=True, kw_only=True)
class StalenessLimits(DictMixin):
    """When the reported state is too old to command from (see the module docstring).

    By default the limits adapt to the stream: the stall limit (no package for that long
    while streaming) is ``min(ceiling_s, max(floor_s, gap_factor · q))``, ``q`` the
    ``quantile`` of the last ``window`` inter-arrival gaps, and the late limit (a package
    that much later than the fastest packages) the same with the lateness of the last
    ``window`` packages. ``floor_s`` keeps a quiet stream's limit above the jitter it has
    not shown yet; ``ceiling_s`` bounds how long a dead or queued stream can go unnoticed.

    Attributes
    ----------
    floor_s : float
        Smallest stall/late limit, s (default 0.05: twice a 24 ms gap, so such gaps pass
        before any is measured; at least 3 controller periods at any rate).
    ceiling_s : float
        Largest stall/late limit, s (default 0.08: a dead stream is noticed within it
        however jittery the stream was, and the fault stop goes out before the controller
        watchdog's default 0.1 s runs out).
    gap_factor : float
        Multiple of the measured quantile (default 2).
    quantile : float
        Quantile of the recent gaps / lateness (default 0.99).
    window : int
        Packages the quantiles look back over (default 1000: 2 s at 500 Hz).
    stall_periods, late_periods : float, optional
        Legacy fixed limits in controller periods (>= 1); when given they replace the
        adaptive stall / late limit (:meth:`from_stale_periods`).
    """

    floor_s: float = STALL_FLOOR_S
    ceiling_s: float = STALL_CEILING_S
    gap_factor: float = GAP_FACTOR
    quantile: float = GAP_QUANTILE
    window: int = GAP_WINDOW
    stall_periods: float | None = None
    late_periods: float | None = None

    def __post_init__(self) -> None:
        if not 0 < self.floor_s <= self.ceiling_s:
            raise ConfigError(
                f"floor_s={self.floor_s!r} and ceiling_s={self.ceiling_s!r} must satisfy "
                "0 < floor_s <= ceiling_s (s); e.g. 0.05 and 0.08"
            )
        if not self.gap_factor >= 1:
            raise ConfigError(f"gap_factor={self.gap_factor!r} must be >= 1; e.g. 2")
        if not 0.5 <= self.quantile < 1:
            raise ConfigError(f"quantile={self.quantile!r} outside [0.5, 1); e.g. 0.99")
        if not self.window >= MIN_JITTER_SAMPLES:
            raise ConfigError(f"window={self.window!r} must be >= {MIN_JITTER_SAMPLES}")
        for name in ("stall_periods", "late_periods"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _check_periods(name, value))

    @classmethod
    def from_stale_periods(
        cls,
        stale_periods: float | None = None,
        *,
        stall_periods: float | None = None,
        late_periods: float | None = None,
    ) -> StalenessLimits:
        """The limits the legacy ``stale_periods`` knob sets (fixed, in controller periods),
        each overridable; all None: the adaptive defaults."""
        stale = None if stale_periods is None else _check_periods("stale_periods", stale_periods)
        return cls(
            stall_periods=stale if stall_periods is None else stall_periods,
            late_periods=stale if late_periods is None else late_periods,
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> StalenessLimits:
        """Inverse of :meth:`to_dict` (missing keys take their defaults).

        Raises
        ------
        ConfigError
            On unknown keys or invalid values.
        """
        check_known_keys(cls, data)
        return cls(**data)

    def jitter(self) -> StreamJitter:
        """A jitter tracker with this window and quantile."""
        return StreamJitter(self.window, self.quantile)

    def _floor(self, period_s: float) -> float:
        return max(self.floor_s, MIN_LIMIT_PERIODS * period_s)

    def _ceiling(self, period_s: float) -> float:
        return max(self.ceiling_s, self._floor(period_s))

    def _adaptive(self, q_s: float, period_s: float) -> float:
        return min(self._ceiling(period_s), max(self._floor(period_s), self.gap_factor * q_s))

    def stall_limit_s(self, period_s: float, jitter: StreamJitter | None = None) -> float:
        """The stall limit in force, s."""
        if self.stall_periods is not None:
            return self.stall_periods * period_s
        return self._adaptive(0.0 if jitter is None else jitter.gap_q_s, period_s)

    def late_limit_s(self, period_s: float, jitter: StreamJitter | None = None) -> float:
        """The late limit in force, s."""
        if self.late_periods is not None:
            return self.late_periods * period_s
        return self._adaptive(0.0 if jitter is None else jitter.late_q_s, period_s)

    def max_stall_s(self, period_s: float) -> float:
        """The longest the stall limit can become, s (the bound on noticing a dead stream)."""
        if self.stall_periods is not None:
            return self.stall_periods * period_s
        return self._ceiling(period_s)

    def command_hold_s(self, period_s: float) -> float:
        """``speedj`` duration, s: the longest stall limit plus
        :data:`COMMAND_HOLD_MARGIN_PERIODS`. Only a controller that honours the duration
        uses it (the UR control script re-issues ``speedj`` until ``speedStop``: there the
        controller watchdog is what stops a dead host)."""
        return self.max_stall_s(period_s) + COMMAND_HOLD_MARGIN_PERIODS * period_s

    def idle_timeout_s(self, period_s: float) -> float:
        """How long a read waits while idle at rest (a timeout there is no fault), s."""
        return max(self.max_stall_s(period_s), IDLE_READ_TIMEOUT_S)

    def stall_deadline_s(self, last_arrival_s: float, since_s: float, limit_s: float) -> float:
        """Host time by which the next package must arrive, s: ``limit_s`` after the later
        of the last arrival and ``since_s`` (when streaming began)."""
        return max(last_arrival_s, since_s) + limit_s

    def silence_fault(self, silent_s: float, limit_s: float) -> str:
        """Fault message: no package for ``silent_s`` (past the stall deadline already)."""
        return (
            f"no state package for {silent_s * 1e3:.1f} ms (> the stall limit of "
            f"{limit_s * 1e3:.1f} ms); robot stopped"
        )

    def stall_fault(self, limit_s: float, reason: object) -> str:
        """Fault message: a read waited until the stall deadline and got nothing."""
        return (
            f"the state stream stalled: no package within the stall limit of "
            f"{limit_s * 1e3:.1f} ms of the last one ({reason}); robot stopped"
        )

    def late_fault(self, state: RobotState, lateness_s: float, limit_s: float) -> str | None:
        """Fault message if ``state`` arrived more than ``limit_s`` after the fastest
        packages (``lateness_s``, :meth:`StateTracker.lateness_s`), else None."""
        if math.isfinite(lateness_s) and lateness_s > limit_s:
            return (
                f"stale state: package of controller time {state.controller_time_s:.4f} s "
                f"arrived {lateness_s * 1e3:.1f} ms later than the fastest packages "
                f"(> the late limit of {limit_s * 1e3:.1f} ms); robot stopped"
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
        The packages so far (last arrival, clock model, jitter); not updated here.
    limits : StalenessLimits
        The stall and late limits (adapted to ``tracker.jitter``).
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
    stall = limits.stall_limit_s(period_s, tracker.jitter)
    deadline = limits.stall_deadline_s(last_arrival, streaming_since_s, stall)
    timeout = deadline - clock()
    if timeout <= 0:
        # Past the deadline before reading (this host was busy): a package waiting now is
        # judged by its lateness below; only an empty stream is a stall.
        try:
            state = driver.read_state(timeout_s=0.0)
        except DriverTimeout:
            fault(limits.silence_fault(clock() - last_arrival, stall))
    elif coast_at_s is not None and coast_at_s < deadline:
        try:
            state = driver.read_state(timeout_s=max(coast_at_s - clock(), 0.0))
        except DriverTimeout:
            return None
    else:
        try:
            state = driver.read_state(timeout_s=timeout)
        except DriverTimeout as exc:
            fault(limits.stall_fault(stall, exc))
    late = limits.late_limit_s(period_s, tracker.jitter)
    message = limits.late_fault(state, tracker.lateness_s(state), late)
    if message is not None:
        fault(message)
    return state
