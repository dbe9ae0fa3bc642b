"""TimedExecutor: delay-compensated joint-velocity streaming on the controller's clock.

The loop runs once per state package (so on the controller's clock): read the package,
back-date it by the predicted response delay, and send one ``speedj`` whose target speed
for joint ``j`` is the plan's speed at ``now + tau_j + T`` — ``tau_j`` the predicted
actuation delay of joint ``j`` (for the plan's start configuration and the joint's
direction), ``T`` the controller period the controller's speed ramp takes (the speedj
acceleration is chosen so the leading joint ramps over exactly one period). The physical
motion then follows the plan on time: the delay models define the actuation delay from the
host's send time to the physical onset, and that is what is shifted away.

Safety: commands never exceed the spec's speed and acceleration limits (clipped, counted in
the log), a joint approaching a position limit is slowed so it can stop before it, targets
outside the limits are refused with a :class:`~timedexec.errors.ConfigError` before any
motion, a state stream silent (or late) beyond the staleness limits adapted to its measured
jitter is a fault: the robot is stopped at once and
:class:`~timedexec.errors.StaleStateError` raised; the controller's watchdog stops the arm
when the host dies, hangs or is paused (``watchdog_timeout_s``), and :meth:`stop` returns
only once the arm is at rest. The loop composes ``_timing`` (predictions, bounds,
deadlines), ``_state`` (back-dating, staleness), ``_command`` (the Smith predictor, the
limits), ``_safety`` (watchdog, stop to rest) and ``_log`` (the bookkeeping).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from contextlib import ExitStack
from types import TracebackType
from typing import Any, NoReturn, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._realtime import GcPauses, fast_wakeup, quiet_gc, realtime
from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import ConfigError, DriverError, StaleStateError
from timedexec.execution._bounds import TimingBounds, check_confidence
from timedexec.execution._command import (
    FrictionFeed,
    SmithPredictor,
    limit_command,
    ramp_acceleration,
)
from timedexec.execution._cycle import DEFAULT_ROUND_TRIP_S, IntakeFix, SendPhase, wait_until
from timedexec.execution._intake import probe_intake
from timedexec.execution._log import CycleLog, ExecutionResult
from timedexec.execution._model import (
    DelayPredictions,
    DelayPredictor,
    check_model_robot,
    load_delay_model,
)
from timedexec.execution._plan import ExecutionLimits, JointPlan, check_target, plan_motion
from timedexec.execution._safety import (
    DEFAULT_WATCHDOG_TIMEOUT_S,
    REST_PACKAGES,
    REST_SPEED_RAD_S,
    ControllerWatchdog,
    wait_for_rest,
)
from timedexec.execution._session import DriverSession
from timedexec.execution._state import (
    StalenessLimits,
    StateEstimate,
    StateTracker,
    read_fresh_state,
)
from timedexec.execution._timing import (
    MeetPlan,
    PredictionCache,
    arrival_bounds,
    check_start,
    meet_deadline,
    onset_bounds,
    plan_lead_s,
    prepare_plan,
    require_scheduled,
)
from timedexec.robots import RobotSpec

__all__ = ["TimedExecutor"]

FloatArray = NDArray[np.float64]


class TimedExecutor:
    """Delay-compensating trajectory execution around a :class:`RobotDriver`.

    Parameters
    ----------
    driver : RobotDriver
        Any driver (``sim://``, ``ur://``, ``rsi://``). The executor connects it if needed.
    model : DelayPredictor or path
        A delay model (:class:`timedexec.learning.DelayModel`, :class:`FixedDelays`) or a
        bundle directory. A model for another robot is refused before the driver connects
        when the driver names its robot (``URDriver(host, robot=...)``, every ``sim://`` and
        ``rsi://`` driver), else right after connecting, before any command.
    confidence : float
        Default confidence of the timing bounds.
    staleness : StalenessLimits, optional
        When the state is too old to command from (default: limits adapted to the
        stream's measured jitter, ``StalenessLimits()``: stall limit ``min(0.08 s, max(0.05
        s, 2 x p99 of the recent gaps))``, the same for lateness). A fault stops the robot
        at once and raises :class:`~timedexec.errors.StaleStateError`.
    stale_periods, stall_periods, late_periods : float, optional
        Legacy (deprecated in favour of ``staleness``): fixed limits in controller periods
        (>= 1): ``stale_periods`` the default of the other two; while streaming, no package
        for ``stall_periods``, or one ``late_periods`` later than the fastest packages
        (lower-envelope clock model), is a fault.
    watchdog_timeout_s : float or None
        Arm the controller's watchdog with this timeout on connect, s (default 0.1; None:
        do not arm). The controller stops the program, and so the arm, when no command or
        kick reaches it for that long: a killed, hung or paused host. While idle each
        handled package kicks it (at most five times per timeout); if the caller does not
        step the executor for longer while idle it trips harmlessly and the next motion
        re-arms it. A trip while moving raises :class:`~timedexec.errors.DriverError`
        (recover with :meth:`recover`). Drivers without a watchdog ignore it.
    limits : ExecutionLimits, optional
        Fractions of the spec's limits to plan and command with.
    position_gain_1_s : float
        Gain of an optional position correction, 1/s (0: pure delay-compensated
        feed-forward, the default). The back-dated reported position is compared with the
        plan at the instant it describes; corrections already sent but not yet visible in
        that package (sent less than the actuation delay before the instant it describes)
        are subtracted — a Smith predictor, so the loop's ~100 ms delay does not make it
        oscillate — and ``gain · error`` is added to the speed command. The error then
        decays with time constant ``1/gain`` once seen. Useful for tracking (conveyors),
        where the velocity loop's recovery of the motion lost to breakaway leaves an
        onset-compensated joint slightly ahead.
    compensate : bool
        False streams the plan without any shift (the "none" strategy).
    stop_deceleration_rad_s2 : float, optional
        Deceleration of a fault stop, rad/s² (default: the spec's smallest joint
        acceleration limit, which every joint and every driver accepts: a driver that checks
        per joint, as the RSI driver does, refuses a stop above a joint's own limit).
    cycle_lock : bool
        Send each command at a fixed phase of the controller's cycle, aimed at the middle
        of its intake window: half a period before the controller's command deadline,
        found at connect by probing it (:meth:`probe_intake`; a UR's ``target_qd``), else
        the earliest arrival of the cycle's package plus half a period minus
        ``round_trip_s`` (:mod:`timedexec.execution._cycle`); in virtual time the driver
        waits (the clock jumps). Opt-in, the recommended setting for a UR: with the probe,
        ``coast`` and ``realtime_priority=5`` it missed 0.03-0.19 % of the cycles where
        ur_rtde's ``initPeriod``/``waitPeriod`` pattern missed 1.8-6.1 % (independent UR
        peer and UR10e twin; not yet a real controller or RSI; docs/execution.md).
    round_trip_s : float
        Shortest boundary-to-package-to-command-arrival time, s (0.4 ms: the loopback twin's).
    realtime_priority : int, optional
        SCHED_FIFO priority for the calling thread while connected (and the driver's
        threads it starts, which inherit it), where the OS allows it (Linux, root or
        CAP_SYS_NICE; otherwise normal scheduling, ``ex.realtime`` False). None: never ask.
    coast : bool
        While streaming, send each cycle's command on the controller's clock even when its
        package is late: if none has arrived by the send time (clock model), the command
        goes out from the estimate and the late package is only read (real-time drivers;
        a virtual-time simulator has no late packages). The stall limit still counts from
        the last package. With ``cycle_lock`` the send-time p99 fell from 0.40-1.15 ms to
        0.24-0.35 ms against the independent peer (docs/execution.md).

    Attributes
    ----------
    staleness : StalenessLimits
        The limits (:meth:`stall_limit_s` / :meth:`late_limit_s` give the ones in force).
    watchdog : ControllerWatchdog
        The controller watchdog (``armed_s``: the timeout in force or None; ``kicks``;
        ``rearm_s``: the cost of each re-arm after an idle trip).
    log : CycleLog
        One row per state package handled.
    clip_count, coasted : int
        Commands a limit clipped; cycles commanded from the estimate (``coast``).
    gc_pauses : GcPauses or None
        With a real-time driver: the garbage collections while connected (``count``,
        ``max_s``). Everything alive at connect is frozen (``gc.freeze``) until close, so a
        collection only walks what the loop made since.
    fast_wakeup : bool
        With a real-time driver: whether the CPUs are kept out of deep idle states while
        connected (``/dev/cpu_dma_latency`` held at 0 µs: root or a udev rule). Without it
        a 2 ms wait woke 0.3-3.7 ms late at p99 on a quiet VM, 0.003-0.23 ms with it.

    Examples
    --------
    >>> from timedexec.drivers import open_driver                    # doctest: +SKIP
    >>> with TimedExecutor(open_driver("sim://ur10"), "ur10-sim") as ex:
    ...     plan = ex.plan([0.3, -1.2, 1.4, -1.6, -1.6, 0.0])
    ...     ex.execute(plan, start_time_s=ex.now() + 0.1)
    """

    def __init__(
        self,
        driver: RobotDriver,
        model: DelayPredictor | Any,
        *,
        confidence: float = 0.95,
        staleness: StalenessLimits | None = None,
        stale_periods: float | None = None,
        stall_periods: float | None = None,
        late_periods: float | None = None,
        watchdog_timeout_s: float | None = DEFAULT_WATCHDOG_TIMEOUT_S,
        cycle_lock: bool = False,
        round_trip_s: float = DEFAULT_ROUND_TRIP_S,
        realtime_priority: int | None = None,
        limits: ExecutionLimits | None = None,
        position_gain_1_s: float = 0.0,
        compensate: bool = True,
        stop_deceleration_rad_s2: float | None = None,
        coast: bool = False,
    ) -> None:
        self.confidence = check_confidence(confidence)
        legacy = (stale_periods, stall_periods, late_periods)
        if staleness is not None and any(v is not None for v in legacy):
            raise ConfigError(
                "give either staleness=StalenessLimits(...) or the legacy stale_periods / "
                "stall_periods / late_periods, not both"
            )
        self.staleness = staleness or StalenessLimits.from_stale_periods(
            stale_periods, stall_periods=stall_periods, late_periods=late_periods
        )
        if not position_gain_1_s >= 0:
            raise ConfigError(f"position_gain_1_s={position_gain_1_s!r} must be >= 0")
        self.driver = driver
        self.model: DelayPredictor = load_delay_model(model)
        self.stale_periods = None if stale_periods is None else float(stale_periods)
        self.watchdog = ControllerWatchdog(driver, watchdog_timeout_s)
        self.limits = limits or ExecutionLimits()
        self.position_gain_1_s = float(position_gain_1_s)
        self.compensate = bool(compensate)
        self._stop_decel = stop_deceleration_rad_s2
        robot = str(getattr(driver, "robot", "") or "")
        if robot:  # refuse a model for another robot before connecting
            check_model_robot(self.model, robot)
        clock = getattr(driver, "clock", None)
        self._clock: Callable[[], float] = clock if callable(clock) else time.monotonic
        self._session = DriverSession(driver, self.model)
        self._period = math.nan
        self._predictions = PredictionCache(self.model)
        self._state = StateTracker(
            jitter=self.staleness.jitter(), max_gap_s=self.staleness.ceiling_s
        )
        self._correction = SmithPredictor()
        self._plan: JointPlan | None = None
        self._last_plan: JointPlan | None = None
        self._tau, self._tau_std, self._v_prev = np.zeros(6), np.zeros(6), np.zeros(6)
        self._feed = FrictionFeed(np.zeros(6))
        self._fault: str | None = None
        self._streaming_since = -math.inf
        self._last_send_s = math.nan
        self._served = -1  # last controller cycle a command was sent for
        virtual = self._virtual = bool(getattr(driver, "virtual", False))
        self.coast = bool(coast) and not virtual
        # A virtual clock is waited on through its driver's wait_until.
        self.cycle_lock = bool(cycle_lock) and (not virtual or hasattr(driver, "wait_until"))
        self.round_trip_s = float(round_trip_s)
        self.send_phase: SendPhase | None = None
        self.intake_error: str | None = None
        self.realtime_priority = realtime_priority
        self.realtime = self.fast_wakeup = False
        self.gc_pauses: GcPauses | None = None
        self._rt = ExitStack()
        self.coasted = 0
        self.log = CycleLog()
        self.clip_count = 0

    # ------------------------------------------------------------------ lifecycle
    @property
    def spec(self) -> RobotSpec:
        """The robot spec (limits, period); known once connected."""
        if self._session.spec is None:
            raise DriverError("the executor is not connected; use it as a context manager")
        return self._session.spec

    @property
    def period_s(self) -> float:
        """Controller period, s."""
        return self._period

    @property
    def clock_line(self) -> tuple[float, float, float] | None:
        """The cycle lock's long-term clock line ``(t_ref_s, offset_s, rate)`` (see
        :class:`~timedexec.execution.BoundaryLine`), None until it has one."""
        return self._state.boundary.line

    def connect(self) -> None:
        """Connect the driver (if needed), check the model against it, read a first state,
        arm the controller's watchdog."""
        if self._session.spec is None:
            # Before the driver starts its threads: they inherit the policy.
            self.realtime = self._rt.enter_context(realtime(self.realtime_priority))
            if not self._virtual:
                # What is alive now (numpy, SciPy, the model) is never scanned again while
                # connected: a full collection no longer stalls a cycle by 10-35 ms.
                self.gc_pauses = self._rt.enter_context(quiet_gc())
                self.fast_wakeup = self._rt.enter_context(fast_wakeup())
        try:
            self._session.open(self._first_state)
            self._period = self._session.period_s
            if self.cycle_lock:
                self.send_phase = SendPhase(self._period, self.round_trip_s)
        except BaseException:
            self._rt.close()
            raise
        try:
            self.watchdog.arm(self.now())
        except BaseException:
            self._session.close()
            self._rt.close()
            raise
        if self.send_phase is not None and self._state.last is not None:
            if self._state.last.target_qd is not None:
                try:
                    self.probe_intake()
                except DriverError as exc:  # the lock aims by the package arrivals
                    self.intake_error = str(exc)
            else:
                self.intake_error = "the driver's state has no target_qd"

    def probe_intake(self) -> IntakeFix:
        """Find the controller's command deadline by probing it (arm at rest; ~16 tiny
        ``speedj`` commands, 0.2-0.7 s; :mod:`timedexec.execution._intake`) and aim the cycle
        lock by it from now on. Done at connect with ``cycle_lock`` where the state carries
        ``target_qd`` (UR); call it again after a long idle time if the host clock drifts
        against the controller's before the clock line forms (:attr:`clock_line`).

        Raises
        ------
        DriverError
            Not at rest, no ``cycle_lock``, or no clean answer (the lock keeps what it had;
            at connect the message goes to ``intake_error`` and the lock aims by the
            package arrivals).
        """
        if self.send_phase is None:
            raise DriverError("probe_intake needs cycle_lock=True and a real-time driver")
        last = self._state.last
        moving = last is not None and float(np.max(np.abs(last.qd))) > REST_SPEED_RAD_S
        if self._plan is not None or np.any(self._v_prev != 0) or moving:
            raise DriverError("probe_intake needs the arm at rest with no plan running")
        amax = self.limits.acceleration(self.spec)

        def read() -> RobotState:
            state = self.driver.read_state(timeout_s=self.staleness.idle_timeout_s(self._period))
            self._state.ingest(state)
            self.watchdog.kick_if_due(state.host_time_s)  # echoes take 7 cycles at 12 ms
            return state

        def send(v: NDArray[np.float64]) -> None:
            self.driver.speedj(
                v, ramp_acceleration(v, np.zeros(6), amax, self._period), self._hold_s
            )
            self.watchdog.fed(self.now())

        fix = probe_intake(read, send, self.now, self._period, self._state.offset_min_s,
                           wait=self._wait_until).dated(self._state.response_s)  # fmt: skip
        self.send_phase.intake = self._state.intake = fix
        self.intake_error = None
        return fix

    @property
    def intake(self) -> IntakeFix | None:
        """The controller's command deadline the cycle lock aims by (:meth:`probe_intake`),
        or None (the lock aims by the package arrivals; ``intake_error`` says why)."""
        return self.send_phase.intake if self.send_phase is not None else None

    def _send_target_s(self, cycle: int) -> float:
        """Host send time of the command answering the package of ``cycle`` (cycle lock)."""
        assert self.send_phase is not None
        st = self._state
        line = st.boundary.line
        return self.send_phase.aim_s(
            st.controller_time_of(cycle, self._period),
            st.earliest_arrival_s(cycle, self._period),
            line[2] if line is not None else 0.0,
        )

    def _first_state(self, state: RobotState) -> None:
        self._state.response_s = self._predictions.response_s(state.q)
        self._state.ingest(state)

    def close(self) -> None:
        """Stop any motion (returning at rest) and close the driver if the executor
        connected it."""
        moving = self._fault is None and bool(np.any(self._v_prev != 0))
        try:
            self._session.close(self._stop_for_close if moving else None)
        finally:
            self._rt.close()
            self.realtime = self.fast_wakeup = False

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def now(self) -> float:
        """The host clock the driver stamps with, s."""
        return self._clock()

    def _wait_until(self, t_s: float) -> float:
        if self._virtual:  # a virtual clock does not run while the host spins
            self.driver.wait_until(t_s)  # type: ignore[attr-defined]
            return self.now()
        return wait_until(t_s, self.now)

    def _decel(self) -> float:
        if self._stop_decel is not None:
            return float(self._stop_decel)
        return float(min(self.spec.qdd_max_rad_s2))

    # ------------------------------------------------------------------ predictions
    def predict(self, q_rad: ArrayLike, directions: ArrayLike | None = None) -> DelayPredictions:
        """Predicted delays of joints 1..6 at ``q_rad`` for ``directions`` (6,), s.

        Joints the model does not cover (a sweep of joints 1, 2, 3, 5) get the mean of the
        covered joints' predictions. Cached per configuration (to 0.1 mrad) and directions.
        """
        return self._predictions.predict(q_rad, directions)

    # ------------------------------------------------------------------ state
    def estimate(self, t_s: float | None = None) -> StateEstimate:
        """The physical joint state at host time ``t_s`` (default: now).

        The newest package is back-dated by the predicted response delay; from that instant
        the estimate follows the active plan (keeping the offset between plan and robot
        seen in the package) or, without a plan, the reported speed.
        """
        self._state.newest()  # no state yet: DriverError before reading the clock
        t = self.now() if t_s is None else float(t_s)
        return self._state.estimate(t, self._plan or self._last_plan)

    @property
    def last_state(self) -> RobotState | None:
        """The newest package as received."""
        return self._state.last

    # ------------------------------------------------------------------ planning
    def plan(
        self,
        target_q_rad: ArrayLike,
        *,
        target_qd_rad_s: ArrayLike | None = None,
        minimum_duration_s: float | None = None,
        start_q_rad: ArrayLike | None = None,
    ) -> JointPlan:
        """A time-optimal jerk-limited plan from the robot's (estimated, at rest) state.

        Raises
        ------
        ConfigError
            Target outside the joint or speed limits, or a motion leaving the limits.
        """
        spec = self.spec
        check_target(spec, target_q_rad, target_qd_rad_s)
        q0 = self.estimate().q_rad if start_q_rad is None else np.asarray(start_q_rad, float)
        q0 = np.clip(q0, spec.q_min_rad, spec.q_max_rad)
        return plan_motion(
            spec,
            self.limits,
            q0,
            target_q_rad,
            target_qd_rad_s=target_qd_rad_s,
            minimum_duration_s=minimum_duration_s,
        )

    def prepare(self, plan: JointPlan) -> JointPlan:
        """Attach the predicted delays of the plan's start configuration and directions
        (``plan.meta``: ``actuation_s``, ``actuation_std_s``, ``response_s``)."""
        return prepare_plan(plan, self._predictions, compensate=self.compensate)

    def lead_time_s(self, plan: JointPlan) -> float:
        """How long before the plan's start its first command must leave, s."""
        return plan_lead_s(self.prepare(plan))

    # ------------------------------------------------------------------ bounds
    def _q_of(self, confidence: float | None) -> float:
        return self.confidence if confidence is None else check_confidence(confidence)

    def _scheduled(self, plan: JointPlan | None) -> JointPlan:
        return self.prepare(require_scheduled(plan or self._plan or self._last_plan))

    def onset_bounds(
        self,
        joint: int,
        plan: JointPlan | None = None,
        *,
        confidence: float | None = None,
        level_rad_s: float | None = None,
    ) -> TimingBounds:
        """Interval (host time) in which ``joint``'s physical motion starts, at ``confidence``.

        The onset is when the joint's speed reaches ``level_rad_s`` (default: the delay
        models' onset level, 10 % of the joint's peak planned speed). With compensation
        the expected onset is the planned one; without, it is the planned one plus the
        predicted actuation delay.
        """
        if joint not in range(1, 7):
            raise ConfigError(f"joint={joint!r} outside 1..6")
        p = self._scheduled(plan)
        return onset_bounds(p, joint, self._q_of(confidence), self._period, level_rad_s=level_rad_s)

    def arrival_bounds(
        self, plan: JointPlan | None = None, *, confidence: float | None = None
    ) -> TimingBounds:
        """Per joint (6,): interval in which each joint reaches its planned end state."""
        return arrival_bounds(self._scheduled(plan), self._q_of(confidence), self._period)

    # ------------------------------------------------------------------ the inverse question
    def plan_to_meet(
        self,
        target_q_rad: ArrayLike,
        deadline_s: float,
        confidence: float = 0.95,
        *,
        target_qd_rad_s: ArrayLike | None = None,
    ) -> MeetPlan:
        """The trajectory and start time that reach the target by ``deadline_s`` (host time)
        with probability ``confidence``.

        The time-optimal plan of duration ``D`` starts at ``deadline - D - u``, ``u`` the
        ``confidence`` quantile of the slowest moving joint's timing error; its first
        command leaves ``max tau`` earlier (the latest send time: ``deadline - D - (mean +
        quantile)`` of the actuation delay).

        Raises
        ------
        ConfigError
            The target is outside the joint or speed limits (before any motion).
        UnreachableError
            Even sending now, the robot would arrive late at this confidence; the message
            says by how many milliseconds (``miss_s``).
        """
        c = check_confidence(confidence)
        plan = self.prepare(self.plan(target_q_rad, target_qd_rad_s=target_qd_rad_s))
        return meet_deadline(plan, deadline_s, c, now_s=self.now(), period_s=self._period)

    # ------------------------------------------------------------------ the loop
    def schedule(self, plan: JointPlan | MeetPlan, start_time_s: float | None = None) -> JointPlan:
        """Make ``plan`` the active plan (non-blocking; :meth:`step` streams it).

        Raises
        ------
        ConfigError
            If the start is too soon for the slowest joint's shifted command (or the
            meeting plan's first send time has passed): nothing is sent.
        """
        if self._fault is not None:
            raise DriverError(self._fault_refusal())
        if isinstance(plan, MeetPlan):
            p = plan.plan
        else:
            p = plan if start_time_s is None else plan.at(start_time_s)
        if not math.isfinite(p.start_time_s):
            raise ConfigError("give start_time_s (host time at which the motion should start)")
        p = self.prepare(p)
        if np.all(self._v_prev == 0):
            if self._plan is None:
                # Idle at rest: a watchdog trip while the caller was not stepping is harmless;
                # re-arm (the driver restarts the program) before the timing check.
                self.watchdog.rearm_if_tripped(self.now)
            # From rest: the first command must leave in time.
            check_start(p, now_s=self.now(), period_s=self._period)
        if self._plan is None and not np.any(self._v_prev != 0):
            self._streaming_since = self.now()
        if p is not self._plan:
            self._correction.clear()
            self._feed = FrictionFeed(p.meta.get("friction_rad", np.zeros(6)))
        self._plan = p
        self._last_plan = p
        self._tau = np.asarray(p.meta["actuation_s"], float)
        self._tau_std = np.asarray(p.meta["actuation_std_s"], float)
        self._state.response_s = float(p.meta["response_s"])
        return p

    def step(self) -> RobotState:
        """Handle one controller cycle: read its package (stale check), back-date it, and
        send the command of the active plan (nothing when idle and at rest). With
        ``coast``, a cycle whose package is late gets its command from the estimate."""
        plan = self._plan
        streaming = plan is not None or bool(np.any(self._v_prev != 0))
        st = self._state
        coast_at = None
        if streaming and self.coast and math.isfinite(st.controller_ref_s) and self._served >= 0:
            if self.send_phase is not None:
                lead = self.send_phase.coast_lead_s  # the command is ready when due
                coast_at = self._send_target_s(self._served + 1) - lead
            else:
                coast_at = (
                    st.earliest_arrival_s(self._served + 1, self._period) + 0.5 * self._period
                )
        got = self._read(coast_at)
        if got is None:  # the cycle's package is late: command it from the estimate
            assert st.last is not None
            self._served += 1
            self.coasted += 1
            self._send(plan, st.last, st.controller_time_of(self._served, self._period))
            return st.last
        state = got
        st.ingest(state)
        cycle = st.cycle_of(state.controller_time_s, self._period)
        if not streaming:
            self._served = cycle
            self.watchdog.kick_if_due(state.host_time_s)
            self.log.add(state, math.nan, None, False)
            return state
        if cycle <= self._served:  # this cycle was already commanded (coasted)
            self.log.add(state, math.nan, None, False)
            return state
        self._served = cycle
        self._send(plan, state, state.controller_time_s)
        return state

    def _fault_stop(self, message: str) -> NoReturn:
        self._fault = message
        self._plan = None
        decel = self._decel()
        try:
            # A zero-speed speedj goes out at once (realtime command); the drivers' stop()
            # may first wait for the controller's acknowledgement of the previous command
            # (ur_rtde's speedStop: ~30 ms when the stream has stalled).
            self.driver.speedj(np.zeros(6), decel, 0.0)
        except DriverError as exc:
            # The controller refused it: its watchdog already stopped the program (the
            # host was paused past the timeout), which stopped the arm.
            self._fault = f"{message}; {exc}"
            self._v_prev = np.zeros(6)
            raise DriverError(self._fault) from exc
        finally:
            self._v_prev = np.zeros(6)
            with contextlib.suppress(DriverError):
                self.driver.stop(decel)
        raise StaleStateError(message)

    def _read(self, coast_at: float | None = None) -> RobotState | None:
        """The next package; None when ``coast_at`` (host time) passes first. Faults
        (:meth:`_fault_stop`) when the stream stalls or the package is late."""
        if self._fault is not None:
            raise DriverError(self._fault_refusal())
        if self._plan is None and not np.any(self._v_prev != 0):
            # Idle at rest: gaps in reading are the caller's, not the stream's.
            timeout = self.staleness.idle_timeout_s(self._period)
            return self.driver.read_state(timeout_s=timeout)
        return read_fresh_state(
            self.driver,
            self._state,
            self.staleness,
            clock=self.now,
            period_s=self._period,
            streaming_since_s=self._streaming_since,
            coast_at_s=coast_at,
            fault=self._fault_stop,
        )

    def _send(self, plan: JointPlan | None, state: RobotState, controller_s: float) -> None:
        t_work = time.perf_counter()
        now = self.now()
        target = math.nan
        if self.send_phase is not None:
            # Aim at the middle of the intake window of the cycle after this package's; the
            # command is computed for the instant it leaves.
            target = self._send_target_s(self._state.cycle_of(controller_s, self._period))
            now = max(now, target)
        v, clipped = self._command(plan, now)
        amax = self.limits.acceleration(self.spec)
        a = ramp_acceleration(v, self._v_prev, amax, self._period)
        work = time.perf_counter() - t_work
        if self.send_phase is not None:
            self.send_phase.note_work(work)
            # The send time logged is when it leaves: after the target, or now if the work
            # overran it (the command's content stays computed for the target).
            clock = self.now()
            now = self._wait_until(target) if target > clock else clock
        try:
            self.driver.speedj(v, a, self._hold_s)
        except DriverError as exc:
            # Refused mid-stream (the controller's watchdog stopped the program, or the
            # link is gone): a fault; the executor refuses to go on until recover().
            self._fault = str(exc)
            self._plan = None
            self._v_prev = np.zeros(6)
            raise
        self.watchdog.fed(now)
        self._v_prev = v
        self._last_send_s = now
        self.log.add(
            state, now, v, clipped, controller_s=controller_s, work_s=work, target_s=target
        )

    def _command(self, plan: JointPlan | None, now: float) -> tuple[FloatArray, bool]:
        """This cycle's speed command (6,), rad/s, and whether a limit clipped it."""
        period = self._period
        target = feed_forward = np.zeros(6)
        correcting = False
        if plan is not None:
            # Joint j gets the plan's speed where its command acts: tau_j plus the ramp later.
            t_act = now - plan.start_time_s + self._tau + period
            target = feed_forward = self._feed.speed(plan, t_act, period)
            sample = self._state.sample
            if self.position_gain_1_s > 0 and sample is not None:
                correcting = True
                t_phys, q, _ = sample
                error = self._correction.predicted_error(plan, t_phys, q, self._tau, now)
                target = feed_forward + self.position_gain_1_s * error
        since = now - self._last_send_s if math.isfinite(self._last_send_s) else period
        # Where this command acts (after each joint's delay) the joint must be able to stop.
        q_act = self._state.q_per_joint(now + self._tau + period, self._plan or self._last_plan)
        v = limit_command(
            target,
            v_prev_rad_s=self._v_prev,
            since_s=since,
            q_act_rad=q_act,
            spec=self.spec,
            limits=self.limits,
            period_s=period,
        )
        if plan is not None:  # what a limit clipped is owed once: to the correction if any
            self._feed.commanded(feed_forward if correcting else v, period)
        clipped = bool(np.any(np.abs(v - target) > 1e-12))
        if clipped:
            self.clip_count += 1
        if correcting:
            self._correction.record(now, v - feed_forward)
        return v, clipped

    def idle(self, until_s: float) -> None:
        """Handle packages (holding still) until host time ``until_s``."""
        while self.now() < until_s:
            self.step()

    def execute(
        self,
        plan: JointPlan | MeetPlan,
        *,
        start_time_s: float | None = None,
        until_s: float | None = None,
        settle_s: float | None = None,
        on_step: Callable[[RobotState], None] | None = None,
    ) -> ExecutionResult:
        """Run ``plan`` to its end (blocking) and return what was done.

        Parameters
        ----------
        plan : JointPlan or MeetPlan
            A plan (scheduled, or with ``start_time_s``) or a :meth:`plan_to_meet` result.
        start_time_s : float, optional
            Host time at which the physical motion should start.
        until_s : float, optional
            Keep streaming until this host time (required for plans that end moving, e.g.
            a conveyor cruise); default: the plan's end plus ``settle_s``.
        settle_s : float, optional
            Time after the end to keep handling packages (default: the largest shift plus
            three periods).
        on_step : callable, optional
            Called with each package after its command left (logging, ground truth).
        """
        if until_s is not None and not math.isfinite(until_s):
            raise ConfigError(
                f"until_s={until_s!r} is not a time; give the host time (s, time.monotonic) "
                "at which execution ends, or None to run until the plan has settled"
            )
        p = self.schedule(plan, start_time_s)
        start_row = len(self.log)
        if until_s is None:
            if np.any(p.qd_end_rad_s != 0):
                raise ConfigError("this plan ends moving (a cruise); give until_s")
            settle = float(np.max(self._tau)) + 3 * self._period if settle_s is None else settle_s
            until_s = p.end_time_s + settle
        ends_at_rest = not np.any(p.qd_end_rad_s != 0)
        give_up = until_s + 1.0
        try:
            while self.now() < until_s or (
                ends_at_rest and np.any(self._v_prev != 0) and self.now() < give_up
            ):
                state = self.step()
                if on_step is not None:
                    on_step(state)
        finally:
            if self._plan is p:
                self._plan = None
        if np.any(p.qd_end_rad_s != 0):
            # Ended while cruising: bring the arm to rest.
            self.stop()
        return ExecutionResult.from_log(
            p,
            self.log.arrays(start_row),
            actuation_s=self._tau,
            actuation_std_s=self._tau_std,
            response_s=self._state.response_s,
        )

    def _fault_refusal(self) -> str:
        return (
            f"the executor stopped after a fault ({self._fault}); call recover() (it waits "
            "until the arm is at rest and re-arms the controller's watchdog) or reconnect"
        )

    @property
    def stall_limit_s(self) -> float:
        """The stall limit in force, s: no package for this long while streaming is a
        fault (adapted to the stream's measured gaps unless fixed)."""
        return self.staleness.stall_limit_s(self._period, self._state.jitter)

    @property
    def late_limit_s(self) -> float:
        """The late limit in force, s: a package this much later than the fastest
        packages is a fault."""
        return self.staleness.late_limit_s(self._period, self._state.jitter)

    @property
    def _hold_s(self) -> float:
        if self.driver.speedj_duration_paces_updates:
            return self._period  # a UR takes the next target once this has passed
        return self.staleness.command_hold_s(self._period)

    def stop(
        self,
        *,
        timeout_s: float | None = None,
        rest_speed_rad_s: float = REST_SPEED_RAD_S,
        rest_packages: int = REST_PACKAGES,
    ) -> RobotState:
        """Drop the active plan, decelerate the arm and return once it is at rest.

        A zero ``speedj`` at the stop deceleration goes out on every package (it also
        feeds the controller's watchdog, which a blocking ``speedStop`` would starve)
        until every joint reports less than ``rest_speed_rad_s`` for ``rest_packages``
        consecutive packages; then the driver's ``stop()`` ends speed mode.

        Parameters
        ----------
        timeout_s : float, optional
            Give up after this long, s (default: the fastest joint's speed over the
            deceleration, plus 0.25 s and the rest packages).
        rest_speed_rad_s : float
            Reported speed below which a joint counts as at rest, rad/s.
        rest_packages : int
            Consecutive packages at rest required.

        Returns
        -------
        RobotState
            The first package of the run at rest.

        Raises
        ------
        DriverError
            The arm still moves when the timeout runs out (speed, joint and time named).
        """
        self._plan = None
        decel = self._decel()
        last = self._state.last
        reported = 0.0 if last is None else float(np.max(np.abs(last.qd)))
        speed = max(float(np.max(np.abs(self._v_prev))), reported)
        try:
            state = wait_for_rest(
                self.driver,
                deceleration_rad_s2=decel,
                hold_s=self._hold_s,
                period_s=self._period,
                clock=self.now,
                speed_rad_s=speed,
                timeout_s=timeout_s,
                rest_speed_rad_s=rest_speed_rad_s,
                rest_packages=rest_packages,
                on_state=self._state.ingest,
            )
        finally:
            self._v_prev = np.zeros(6)
        self.watchdog.fed(self.now())
        self.driver.stop(decel)
        return state

    def _stop_for_close(self) -> None:
        self.stop()

    def recover(self) -> RobotState:
        """Clear a fault (a stale stream, a watchdog trip) once the arm is at rest: re-arm
        the controller's watchdog (restarting the program where it stopped) and return the
        newest package.

        Raises
        ------
        DriverError
            The arm still moves (see :meth:`stop`), or the program cannot be restarted.
        """
        self.watchdog.arm(self.now())
        self._fault = None
        self._plan = None
        return self.stop()

    @property
    def fault(self) -> str | None:
        """The fault that stopped the executor, or None."""
        return self._fault
