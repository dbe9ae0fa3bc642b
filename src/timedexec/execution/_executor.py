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
only once the arm is at rest. The loop composes ``_settings`` (its options), ``_timing``
(predictions, bounds, deadlines), ``_state`` (back-dating, staleness, the clock model the
cycle lock aims by), ``_cycle`` and ``_intake`` (the cycle lock), ``_command`` (the feed,
the Smith predictor, the limits), ``_safety`` (watchdog, fault stop, stop to rest),
``_session`` (the driver, the real-time policies) and ``_log`` (the bookkeeping).
"""

from __future__ import annotations

import math
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import replace
from types import TracebackType
from typing import Any, NoReturn, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._realtime import GcPauses, wait_until
from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import ConfigError, DriverError, StaleStateError
from timedexec.execution._bounds import TimingBounds, check_confidence
from timedexec.execution._command import CommandStream, ramp_acceleration
from timedexec.execution._cycle import IntakeFix, SendPhase
from timedexec.execution._intake import probe_intake
from timedexec.execution._log import CycleLog, ExecutionResult
from timedexec.execution._model import (
    DelayPredictions,
    DelayPredictor,
    check_model_robot,
    load_delay_model,
    model_echo_depth,
)
from timedexec.execution._plan import JointPlan, check_target, plan_motion
from timedexec.execution._safety import (
    REST_PACKAGES,
    REST_SPEED_RAD_S,
    ControllerWatchdog,
    fault_stop,
    wait_for_rest,
)
from timedexec.execution._session import DriverSession
from timedexec.execution._settings import ExecutorSettings
from timedexec.execution._state import StateEstimate, StateTracker, read_fresh_state
from timedexec.execution._timing import (
    MeetPlan,
    PredictionCache,
    arrival_bounds,
    check_start,
    execution_end_s,
    meet_deadline,
    onset_bounds,
    plan_lead_s,
    prepare_plan,
    require_scheduled,
)
from timedexec.robots import RobotSpec, check_configuration, get_robot

__all__ = ["TimedExecutor"]


class TimedExecutor:
    """Delay-compensating trajectory execution around a :class:`RobotDriver`.

    What a user does with it, in the order of the class:

    * **connect**: :meth:`connect` / :meth:`close` (or ``with``), :meth:`now`,
      :attr:`spec`, :attr:`period_s`;
    * **plan**: :meth:`plan` (Ruckig, within the limits), :meth:`plan_to_meet` (the latest
      plan that arrives by a deadline at a confidence), :meth:`prepare` (attach the
      predicted delays), :meth:`lead_time_s`, :meth:`schedule` (make a plan the active one);
    * **execute**: :meth:`execute` (blocking, to the plan's end), :meth:`step` (one
      controller cycle), :meth:`idle` (hold still, reading);
    * **estimate**: :meth:`estimate` (the back-dated physical state), :attr:`last_state`,
      :meth:`predict` (the delays), :meth:`onset_bounds`, :meth:`arrival_bounds`;
    * **stop**: :meth:`stop` (returns at rest), :meth:`recover` (after a fault),
      :attr:`fault`, the staleness limits in force (:attr:`stall_limit_s`,
      :attr:`late_limit_s`);
    * **probe**: :meth:`probe_intake` (the controller's command deadline, for the cycle
      lock), :attr:`intake`, :attr:`clock_line`.

    Parameters
    ----------
    driver : RobotDriver
        Any driver (``sim://``, ``ur://``, ``rsi://``). The executor connects it if needed.
    model : DelayPredictor or path
        A delay model (:class:`timedexec.learning.DelayModel`, :class:`FixedDelays`) or a
        bundle directory. A model for another robot is refused before the driver connects
        when the driver names its robot (``URDriver(host, robot=...)``, every ``sim://`` and
        ``rsi://`` driver), else right after connecting, before any command.
    settings : ExecutorSettings, optional
        Every option (confidence, staleness, watchdog, cycle lock, round trip, real-time
        priority, limits, position gain, compensation, stop deceleration, coasting), with
        its default and range; default ``ExecutorSettings()``.

    Attributes
    ----------
    settings : ExecutorSettings
        The options in force.
    watchdog : ControllerWatchdog
        The controller watchdog (``armed_s``: the timeout in force or None; ``kicks``;
        ``rearm_s``: the cost of each re-arm after an idle trip).
    log : CycleLog
        One row per state package handled.
    coasted : int
        Cycles commanded from the estimate (``coast``); :attr:`clip_count`: commands a
        limit clipped.
    send_phase : SendPhase or None
        The cycle lock's sender once connected (``cycle_lock`` on a driver that can wait
        on its clock), else None; ``intake_error`` says why it aims by the package
        arrivals rather than a probed intake.
    realtime, fast_wakeup, gc_pauses
        The real-time policies in force while connected (:class:`ExecutorSettings`'s
        ``realtime_priority``; CPUs out of deep idle states, a quieted garbage collector:
        real-time drivers only; docs/execution.md).

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
        settings: ExecutorSettings | None = None,
    ) -> None:
        if settings is None:
            settings = ExecutorSettings()
        elif not isinstance(settings, ExecutorSettings):
            raise ConfigError(
                f"settings={settings!r} is not an ExecutorSettings; give "
                "ExecutorSettings(...) (or ExecutorSettings.from_dict(d) for a dict)"
            )
        self.settings = settings
        self.driver = driver
        self.model: DelayPredictor = load_delay_model(model)
        robot = str(getattr(driver, "robot", "") or "")
        if robot:  # refuse a model for another robot before connecting
            check_model_robot(self.model, robot)
        clock = getattr(driver, "clock", None)
        self._clock: Callable[[], float] = clock if callable(clock) else time.monotonic
        self._session = DriverSession(driver, self.model)
        self._period = math.nan
        self._predictions = PredictionCache(self.model)
        staleness = self._staleness = settings.staleness
        self._state = StateTracker(jitter=staleness.jitter(), max_gap_s=staleness.ceiling_s)
        self._cmd = CommandStream(settings.limits, settings.position_gain_1_s)
        self._plan: JointPlan | None = None
        self._last_plan: JointPlan | None = None
        self._fault: str | None = None
        self._streaming_since = -math.inf
        self._served = -1  # last controller cycle a command was sent for
        virtual = self._virtual = bool(getattr(driver, "virtual", False))
        by_default = bool(getattr(driver, "cycle_lock_default", False))
        lock = by_default if settings.cycle_lock is None else settings.cycle_lock
        coast = by_default if settings.coast is None else settings.coast
        self._coast = coast and not virtual
        # A virtual clock is waited on through its driver's wait_until.
        self._cycle_lock = lock and (not virtual or hasattr(driver, "wait_until"))
        self.watchdog = ControllerWatchdog(driver, settings.watchdog_timeout_s)
        self.send_phase: SendPhase | None = None
        self.intake_error: str | None = None
        self.coasted = 0
        self.log = CycleLog()

    # ------------------------------------------------------------------ connect
    def connect(self) -> None:
        """Connect the driver (if needed; under the settings' real-time priority), check
        the model against it, read a first state, arm the controller's watchdog and, with
        the cycle lock (a UR's default), probe the controller's intake where the state
        carries ``target_qd`` (0.2-0.7 s). When the probe cannot answer, the lock aims by
        the package arrivals and one :class:`RuntimeWarning` says why and what it costs
        (also when the lock is on by default and the state has no ``target_qd``)."""
        self._session.open(
            self._first_state,
            realtime_priority=self.settings.realtime_priority,
            real_time=not self._virtual,
        )
        try:
            self._period = self._session.period_s
            if self._cycle_lock:
                self.send_phase = SendPhase(self._period, self.settings.round_trip_s)
            self.watchdog.arm(self.now())
        except BaseException:
            self._session.close()
            raise
        if self.send_phase is not None and self._state.last is not None:
            if self._state.last.target_qd is not None:
                try:
                    self.probe_intake()
                except DriverError as exc:  # the lock aims by the package arrivals
                    self.intake_error = str(exc)
            else:
                self.intake_error = "the driver's state has no target_qd"
                if self.settings.cycle_lock is not None:
                    return  # a lock asked for by name aims by the arrivals, as documented
            if self.intake_error is not None:
                warnings.warn(_arrival_aiming_warning(self.intake_error), RuntimeWarning,
                              stacklevel=_caller_level())  # fmt: skip

    def close(self) -> None:
        """Stop any motion (returning at rest) and close the driver if the executor
        connected it."""
        moving = self._fault is None and self._cmd.moving
        self._session.close(self.stop if moving else None)

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
    def realtime(self) -> bool:
        """Whether the loop's thread has the settings' SCHED_FIFO priority (connected)."""
        return self._session.realtime

    @property
    def fast_wakeup(self) -> bool:
        """Whether the CPUs are kept out of deep idle states (real-time driver, connected)."""
        return self._session.fast_wakeup

    @property
    def gc_pauses(self) -> GcPauses | None:
        """The garbage collections while connected (real-time driver), else None."""
        return self._session.gc_pauses

    # ------------------------------------------------------------------ plan
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
            self.settings.limits,
            q0,
            target_q_rad,
            target_qd_rad_s=target_qd_rad_s,
            minimum_duration_s=minimum_duration_s,
        )

    def plan_to_meet(
        self,
        target_q_rad: ArrayLike,
        deadline_s: float,
        confidence: float = 0.95,
        *,
        target_qd_rad_s: ArrayLike | None = None,
    ) -> MeetPlan:
        """The trajectory and start time that reach the target by ``deadline_s`` (host time)
        with probability ``confidence``: the time-optimal plan, started as late as the
        slowest moving joint's timing error at ``confidence`` allows (``_timing``).

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

    def prepare(self, plan: JointPlan) -> JointPlan:
        """Attach the predicted delays of the plan's start configuration and directions
        (``plan.meta``: ``actuation_s``, ``actuation_std_s``, ``response_s``)."""
        return prepare_plan(plan, self._predictions, compensate=self.settings.compensate)

    def lead_time_s(self, plan: JointPlan) -> float:
        """How long before the plan's start its first command must leave, s."""
        return plan_lead_s(self.prepare(plan))

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
        if not self._cmd.moving:
            if self._plan is None:
                # Idle at rest: a watchdog trip while the caller was not stepping is harmless;
                # re-arm (the driver restarts the program) before the timing check.
                self.watchdog.rearm_if_tripped(self.now)
            # From rest: the first command must leave in time.
            check_start(p, now_s=self.now(), period_s=self._period)
        if self._plan is None and not self._cmd.moving:
            self._streaming_since = self.now()
        self._cmd.begin(p, new=p is not self._plan)
        self._plan = p
        self._last_plan = p
        self._state.response_s = float(p.meta["response_s"])
        return p

    # ------------------------------------------------------------------ execute
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
        until_s = execution_end_s(p, until_s=until_s, settle_s=settle_s, period_s=self._period)
        ends_at_rest = not np.any(p.qd_end_rad_s != 0)
        give_up = until_s + 1.0
        try:
            while self.now() < until_s or (
                ends_at_rest and self._cmd.moving and self.now() < give_up
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
            actuation_s=self._cmd.tau_s,
            actuation_std_s=self._cmd.tau_std_s,
            response_s=self._state.response_s,
        )

    def step(self) -> RobotState:
        """Handle one controller cycle: read its package (stale check), back-date it, and
        send the command of the active plan (nothing when idle and at rest). With
        ``coast``, a cycle whose package is late gets its command from the estimate."""
        plan = self._plan
        streaming = plan is not None or self._cmd.moving
        st = self._state
        coast_at = None
        if streaming and self._coast and math.isfinite(st.controller_ref_s) and self._served >= 0:
            coast_at = st.coast_at_s(self.send_phase, self._served + 1, self._period)
        if self._fault is not None:
            raise DriverError(self._fault_refusal())
        got: RobotState | None
        if not streaming:  # idle at rest: gaps in reading are the caller's, not the stream's
            got = self.driver.read_state(timeout_s=self._staleness.idle_timeout_s(self._period))
        else:  # faults (a stalled stream, a late package) through _fault_stop
            got = read_fresh_state(self.driver, st, self._staleness, clock=self.now,
                                   period_s=self._period, streaming_since_s=self._streaming_since,
                                   coast_at_s=coast_at, fault=self._fault_stop)  # fmt: skip
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

    def idle(self, until_s: float, *, until_rest: bool = False) -> None:
        """Handle packages (holding still) until host time ``until_s``; with ``until_rest``
        return as soon as the arm reports rest (every joint below 0.01 rad/s for three
        packages in a row), without commanding it (a motion still running out of the
        controller's pipeline is left to end where it ends)."""
        still = 0
        while self.now() < until_s:
            state = self.step()
            if until_rest:
                still = still + 1 if float(np.max(np.abs(state.qd))) < REST_SPEED_RAD_S else 0
                if still >= REST_PACKAGES:
                    return

    # ------------------------------------------------------------------ estimate
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

    def predict(self, q_rad: ArrayLike, directions: ArrayLike | None = None) -> DelayPredictions:
        """Predicted delays of joints 1..6 at ``q_rad`` for ``directions`` (6,), s.

        Joints the model does not cover (a sweep of joints 1, 2, 3, 5) get the mean of the
        covered joints' predictions. Cached per configuration (to 0.1 mrad) and directions.

        Raises
        ------
        ConfigError
            ``q_rad`` outside the robot's joint limits (or not 6 finite angles), or a
            direction that is not +1/-1: a model answers anywhere, but not with meaning.
        """
        spec = self._session.spec or get_robot(str(self.model.robot))
        q = check_configuration(spec, q_rad)
        if directions is not None:
            d = np.asarray(directions)
            if d.shape != (6,) or not np.isin(d, (1, -1)).all():
                raise ConfigError(f"directions={directions!r}: give six directions, each +1 or -1")
        return self._predictions.predict(q, directions)

    def onset_bounds(
        self,
        joint: int,
        plan: JointPlan | None = None,
        *,
        confidence: float | None = None,
        level_rad_s: float | None = None,
    ) -> TimingBounds:
        """Interval (host time) in which ``joint``'s physical motion starts, at ``confidence``
        (default: the settings').

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

    # ------------------------------------------------------------------ stop
    def stop(self, *, timeout_s: float | None = None) -> RobotState:
        """Drop the active plan, decelerate the arm and return once it is at rest.

        A zero ``speedj`` at the stop deceleration goes out on every package (it also
        feeds the controller's watchdog, which a blocking ``speedStop`` would starve)
        until every joint reports less than 0.01 rad/s for three consecutive packages;
        then the driver's ``stop()`` ends speed mode.

        Parameters
        ----------
        timeout_s : float, optional
            Give up after this long, s (default: the fastest joint's speed over the
            deceleration, plus 0.25 s and the rest packages).

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
        last = self._state.last
        reported = 0.0 if last is None else float(np.max(np.abs(last.qd)))
        try:
            return wait_for_rest(
                self.driver,
                deceleration_rad_s2=self._decel(),
                hold_s=self._hold_s,
                period_s=self._period,
                clock=self.now,
                speed_rad_s=max(float(np.max(np.abs(self._cmd.v_prev_rad_s))), reported),
                timeout_s=timeout_s,
                on_state=self._state.ingest,
                watchdog=self.watchdog,
            )
        finally:
            self._cmd.halt()

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
    def clip_count(self) -> int:
        """Commands a limit clipped."""
        return self._cmd.clip_count

    @property
    def fault(self) -> str | None:
        """The fault that stopped the executor, or None."""
        return self._fault

    @property
    def stall_limit_s(self) -> float:
        """The stall limit in force, s: no package for this long while streaming is a
        fault (adapted to the stream's measured gaps unless fixed)."""
        return self._staleness.stall_limit_s(self._period, self._state.jitter)

    @property
    def late_limit_s(self) -> float:
        """The late limit in force, s: a package this much later than the fastest
        packages is a fault."""
        return self._staleness.late_limit_s(self._period, self._state.jitter)

    # ------------------------------------------------------------------ probe
    def probe_intake(self) -> IntakeFix:
        """Find the controller's command deadline by probing it (arm at rest; ~20-32 tiny
        ``speedj`` commands, 0.2-0.7 s; :func:`~timedexec.execution.probe_intake`) and aim
        the cycle lock by it from now on. Done at connect with ``cycle_lock`` where the
        state carries ``target_qd`` (UR); call it again after a long idle time if the host
        clock drifts against the controller's before the clock line forms
        (:attr:`clock_line`).

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
        if self._plan is not None or self._cmd.moving or moving:
            raise DriverError("probe_intake needs the arm at rest with no plan running")
        amax = self.settings.limits.acceleration(self.spec)

        def read() -> RobotState:
            state = self.driver.read_state(timeout_s=self._staleness.idle_timeout_s(self._period))
            self._state.ingest(state)
            self.watchdog.kick_if_due(state.host_time_s)  # echoes take 7 cycles at 12 ms
            return state

        def send(v: NDArray[np.float64]) -> None:
            self.driver.speedj(
                v, ramp_acceleration(v, np.zeros(6), amax, self._period), self._hold_s
            )
            self.watchdog.fed(self.now())

        fix = probe_intake(read, send, self.now, self._period, self._state.offset_min_s,
                           wait=self._wait_until)  # fmt: skip
        depth = self.settings.echo_depth_cycles
        fix = replace(fix, echo_depth_cycles=model_echo_depth(self.model) if depth is None else depth)
        fix = fix.dated(self._state.response_s)
        self.send_phase.intake = self._state.intake = fix
        self.intake_error = None
        return fix

    @property
    def intake(self) -> IntakeFix | None:
        """The controller's command deadline the cycle lock aims by (:meth:`probe_intake`),
        or None (the lock aims by the package arrivals; ``intake_error`` says why)."""
        return self.send_phase.intake if self.send_phase is not None else None

    @property
    def clock_line(self) -> tuple[float, float, float] | None:
        """The cycle lock's long-term clock line ``(t_ref_s, offset_s, rate)`` (see
        :class:`~timedexec.execution.BoundaryLine`), None until it has one."""
        return self._state.boundary.line

    # ------------------------------------------------------------------ the loop's plumbing
    def _send(self, plan: JointPlan | None, state: RobotState, controller_s: float) -> None:
        t_work = time.perf_counter()
        now = self.now()
        target = math.nan
        phase = self.send_phase
        if phase is not None:
            # Aim at the middle of the intake window of the cycle after this package's; the
            # command is computed for the instant it leaves.
            cycle = self._state.cycle_of(controller_s, self._period)
            target = self._state.send_target_s(phase, cycle, self._period)
            now = max(now, target)
        v, a, clipped = self._cmd.command(
            plan, now, self._state, self._last_plan, self.spec, self._period
        )
        work = time.perf_counter() - t_work
        if phase is not None:
            phase.note_work(work)
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
            self._cmd.halt()
            raise
        self.watchdog.fed(now)
        self._cmd.sent(v, now)
        self.log.add(
            state, now, v, clipped, controller_s=controller_s, work_s=work, target_s=target
        )

    def _fault_stop(self, message: str) -> NoReturn:
        self._fault, self._plan = message, None
        self._cmd.halt()
        try:
            fault_stop(self.driver, self._decel(), message)
        except DriverError as exc:  # refused: the controller's watchdog stopped the arm
            self._fault = str(exc)
            raise
        raise StaleStateError(message)

    def _fault_refusal(self) -> str:
        return (
            f"the executor stopped after a fault ({self._fault}); call recover() (it waits "
            "until the arm is at rest and re-arms the controller's watchdog) or reconnect"
        )

    @property
    def _hold_s(self) -> float:
        if self.driver.speedj_duration_paces_updates:
            return self._period  # a UR takes the next target once this has passed
        return self._staleness.command_hold_s(self._period)

    def _decel(self) -> float:
        decel = self.settings.stop_deceleration_rad_s2
        return float(min(self.spec.qdd_max_rad_s2)) if decel is None else decel

    def _wait_until(self, t_s: float) -> float:
        if self._virtual:  # a virtual clock does not run while the host spins
            self.driver.wait_until(t_s)  # type: ignore[attr-defined]
            return self.now()
        return wait_until(t_s, self.now)

    def _first_state(self, state: RobotState) -> None:
        self._state.response_s = self._predictions.response_s(state.q)
        self._state.ingest(state)

    def _q_of(self, confidence: float | None) -> float:
        return self.settings.confidence if confidence is None else check_confidence(confidence)

    def _scheduled(self, plan: JointPlan | None) -> JointPlan:
        return self.prepare(require_scheduled(plan or self._plan or self._last_plan))


def _caller_level() -> int:
    """``stacklevel`` of the first frame outside timedexec (a warning names the user's line,
    however the executor was entered: ``with``, ``connect()`` or a task)."""
    level, frame = 2, sys._getframe(2)  # the frame that called our caller
    while frame.f_back is not None and frame.f_globals.get("__name__", "").startswith("timedexec."):
        frame, level = frame.f_back, level + 1
    return level


def _arrival_aiming_warning(why: str) -> str:
    """The one warning of a cycle lock whose intake could not be probed at connect."""
    why = why.removesuffix("; the cycle lock aims by the package arrivals instead")
    return (
        f"cycle lock: the controller's command intake could not be probed at connect ({why}). "
        "The lock aims by the package arrivals instead (half a period after the earliest "
        "arrival, less round_trip_s), which assumes the controller sends each package right "
        "after its cycle boundary; where it sends later, commands reach it near its deadline, "
        "some cycles take two and some none, and a speed stream integrates the difference "
        "(UR10e twin, 500 Hz: 7.1 % of the cycles missed and 19 % of the commands within "
        "0.3 ms of the intake, against 0.9 % and 0.2 % probed). Call probe_intake() with the "
        "arm at rest to try again, or pass ExecutorSettings(cycle_lock=False) to send on each "
        "package's arrival."
    )
