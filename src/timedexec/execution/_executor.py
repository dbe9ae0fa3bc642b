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
motion, and a state stream older than ``stale_periods`` periods is a fault: the robot is
stopped at once and :class:`StaleStateError` raised.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import (
    ConfigError,
    DriverError,
    DriverTimeout,
    ModelError,
    StaleStateError,
    UnreachableError,
)
from timedexec.execution._bounds import TimingBounds, check_confidence, delay_cdf, delay_quantile
from timedexec.execution._model import (
    DelayPredictions,
    DelayPredictor,
    check_model_robot,
    load_delay_model,
    predict_delays,
)
from timedexec.execution._plan import ExecutionLimits, JointPlan, check_target, plan_motion
from timedexec.robots import RobotSpec, get_robot

__all__ = [
    "CycleLog",
    "ExecutionResult",
    "MeetPlan",
    "StaleStateError",
    "StateEstimate",
    "TimedExecutor",
    "UnreachableError",
]

FloatArray = NDArray[np.float64]


#: Window of the lower-envelope clock model (arrival minus controller time), s.
ENVELOPE_S = 0.5


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


@dataclass(frozen=True)
class MeetPlan:
    """A plan that reaches ``plan.q_end_rad`` by ``deadline_s`` with probability
    ``confidence`` (see :meth:`TimedExecutor.plan_to_meet`).

    Attributes
    ----------
    plan : JointPlan
        The trajectory, scheduled (``plan.start_time_s`` is when the physical motion
        starts).
    deadline_s : float
        Host time by which the target must be reached, s.
    confidence : float
        Requested probability of arriving by the deadline.
    first_send_s : float
        Host time the first command must leave (plan start minus the largest predicted
        actuation delay), s.
    slack_s : float
        How much later than planned the motion could still start, s (>= 0).
    arrival : TimingBounds
        Per joint (6,): central ``confidence`` interval of the arrival time.
    probability : float
        Predicted probability that every moving joint arrives by the deadline (the
        slowest joint's).
    """

    plan: JointPlan
    deadline_s: float
    confidence: float
    first_send_s: float
    slack_s: float
    arrival: TimingBounds
    probability: float

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        return {
            "deadline_s": self.deadline_s,
            "confidence": self.confidence,
            "start_time_s": self.plan.start_time_s,
            "duration_s": self.plan.duration_s,
            "first_send_s": self.first_send_s,
            "slack_s": self.slack_s,
            "probability": self.probability,
            "arrival": self.arrival.to_dict(),
        }


class CycleLog:
    """Per-cycle record of the loop: one row per state package handled.

    Columns (numpy arrays from :meth:`arrays`): ``arrival_s`` (host arrival), ``controller_s``
    (controller time stamp of the cycle commanded), ``sequence``, ``send_s`` (host time the
    command left; NaN when none was sent), ``qd_cmd`` (n, 6), ``q`` (n, 6) reported,
    ``clipped`` (a limit clipped the command), ``coasted`` (the cycle's package was late: the
    command went out from the estimate, the row repeats the previous package).
    """

    def __init__(self) -> None:
        self._rows: list[tuple[float, float, int, float, bool, bool]] = []
        self._qd: list[FloatArray] = []
        self._q: list[FloatArray] = []

    def __len__(self) -> int:
        return len(self._rows)

    def add(
        self,
        state: RobotState,
        send_s: float,
        qd_cmd: FloatArray | None,
        clipped: bool,
        *,
        controller_s: float | None = None,
    ) -> None:
        """Append a row (``controller_s``: the cycle commanded, default the package's)."""
        ctrl = state.controller_time_s if controller_s is None else controller_s
        coasted = controller_s is not None and controller_s != state.controller_time_s
        self._rows.append((state.host_time_s, ctrl, state.sequence, send_s, clipped, coasted))
        self._qd.append(np.full(6, np.nan) if qd_cmd is None else qd_cmd)
        self._q.append(state.q)

    def clear(self) -> None:
        """Forget every row."""
        self._rows.clear()
        self._qd.clear()
        self._q.clear()

    def arrays(self, start: int = 0) -> dict[str, NDArray[Any]]:
        """The log from row ``start`` on as arrays."""
        rows = self._rows[start:]
        if not rows:
            z = np.zeros(0)
            return {
                "arrival_s": z,
                "controller_s": z,
                "sequence": np.zeros(0, np.int64),
                "send_s": z,
                "clipped": np.zeros(0, bool),
                "coasted": np.zeros(0, bool),
                "qd_cmd": np.zeros((0, 6)),
                "q": np.zeros((0, 6)),
            }
        a = np.asarray([r[0] for r in rows])
        return {
            "arrival_s": a,
            "controller_s": np.asarray([r[1] for r in rows]),
            "sequence": np.asarray([r[2] for r in rows], dtype=np.int64),
            "send_s": np.asarray([r[3] for r in rows]),
            "clipped": np.asarray([r[4] for r in rows], dtype=bool),
            "coasted": np.asarray([r[5] for r in rows], dtype=bool),
            "qd_cmd": np.asarray(self._qd[start:]),
            "q": np.asarray(self._q[start:]),
        }

    def timing(self, start: int = 0, *, window_s: float = 0.5) -> dict[str, Any]:
        """Send-time statistics of the loop.

        The ideal send time of the command answering package ``k`` is the earliest the
        package can arrive: its controller time stamp mapped to the host clock by a
        lower-envelope clock model (the minimum of arrival minus controller time over a
        sliding ``window_s``). The send-time error is the actual send time minus that
        (network, client polling and the executor's own work). ``missed`` counts controller
        cycles without a handled package (sequence gaps).
        """
        from scipy.ndimage import minimum_filter1d

        arr = self.arrays(start)
        if len(arr["arrival_s"]) < 2:
            return {"cycles": len(arr["arrival_s"]), "missed": 0}
        ctrl = arr["controller_s"]
        period = float(np.median(np.diff(ctrl)))
        off = np.where(arr["coasted"], np.inf, arr["arrival_s"] - ctrl)
        size = max(1, round(window_s / period))
        env = minimum_filter1d(off, size=size, mode="nearest")
        sent = np.isfinite(arr["send_s"])
        err = (arr["send_s"] - (ctrl + env))[sent]
        proc = (arr["send_s"] - arr["arrival_s"])[sent & ~arr["coasted"]]
        gaps = np.diff(arr["sequence"][~arr["coasted"]])
        q = [50, 90, 99, 99.9]
        return {
            "cycles": len(ctrl),
            "expected_cycles": int(arr["sequence"][-1] - arr["sequence"][0] + 1),
            "missed": int(np.sum(np.maximum(gaps - 1, 0))),
            "commands": int(sent.sum()),
            "coasted": int(arr["coasted"].sum()),
            "period_s": period,
            "send_error_s": {f"p{p:g}": float(np.percentile(err, p)) for p in q}
            | {"mean": float(err.mean()), "max": float(err.max())},
            "processing_s": {f"p{p:g}": float(np.percentile(proc, p)) for p in q}
            | {"max": float(proc.max())},
        }


@dataclass
class ExecutionResult:
    """What :meth:`TimedExecutor.execute` did.

    Attributes
    ----------
    plan : JointPlan
        The executed plan (scheduled).
    actuation_s, actuation_std_s : ndarray (6,)
        The per-joint shift applied and its predicted single-trial std, s.
    response_s : float
        The response delay states were back-dated by, s.
    first_send_s, last_send_s : float
        Host times of the first and last command, s.
    log : dict
        :meth:`CycleLog.arrays` of the execution.
    """

    plan: JointPlan
    actuation_s: FloatArray
    actuation_std_s: FloatArray
    response_s: float
    first_send_s: float
    last_send_s: float
    log: dict[str, NDArray[Any]] = field(repr=False)

    @property
    def missed_cycles(self) -> int:
        """Controller cycles without a handled package during the execution."""
        seq = self.log["sequence"]
        return int(np.sum(np.maximum(np.diff(seq) - 1, 0))) if len(seq) > 1 else 0


def _driver_spec(driver: RobotDriver, robot: str, period_s: float) -> RobotSpec:
    """The connected driver's robot spec (its own when it has one)."""
    spec = getattr(driver, "spec", None)
    if isinstance(spec, RobotSpec):
        return spec
    settings = getattr(driver, "settings", None)
    if isinstance(getattr(settings, "spec", None), RobotSpec):
        return settings.spec  # type: ignore[union-attr,no-any-return]
    return get_robot(robot, period_s=period_s)


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
    stale_periods : float
        A state package older than this many controller periods (or none for that long) is
        a fault: the robot is stopped and :class:`StaleStateError` raised.
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
        Deceleration of a fault stop (default: the spec's largest acceleration limit).
    coast : bool
        Experimental. While streaming, send each cycle's command on the controller's clock
        even when its package is late: if no package has arrived half a period after the earliest time
        the cycle's package can arrive (lower-envelope clock model), the command goes out
        from the estimate, and the late package is then only read (real-time drivers only;
        a virtual-time simulator never has late packages).

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
        stale_periods: float = 3.0,
        limits: ExecutionLimits | None = None,
        position_gain_1_s: float = 0.0,
        compensate: bool = True,
        stop_deceleration_rad_s2: float | None = None,
        coast: bool = False,
    ) -> None:
        self.confidence = check_confidence(confidence)
        if not stale_periods >= 1:
            raise ConfigError(f"stale_periods={stale_periods!r} must be >= 1 controller period")
        if not position_gain_1_s >= 0:
            raise ConfigError(f"position_gain_1_s={position_gain_1_s!r} must be >= 0")
        self.driver = driver
        self.model: DelayPredictor = load_delay_model(model)
        self.stale_periods = float(stale_periods)
        self.limits = limits or ExecutionLimits()
        self.position_gain_1_s = float(position_gain_1_s)
        self.compensate = bool(compensate)
        self._stop_decel = stop_deceleration_rad_s2
        robot = str(getattr(driver, "robot", "") or "")
        if robot:  # refuse a model for another robot before connecting
            check_model_robot(self.model, robot)
        clock = getattr(driver, "clock", None)
        self._clock: Callable[[], float] = clock if callable(clock) else time.monotonic
        self._spec: RobotSpec | None = None
        self._period = math.nan
        self._connected_here = False
        self._pin: Any = None  # the model's BLAS pin, held while connected
        self._last: RobotState | None = None
        self._last_arrival = math.nan
        self._offset_min = math.inf  # lower envelope of arrival - controller time, s
        self._samples: deque[tuple[float, FloatArray, FloatArray]] = deque(maxlen=256)
        self._response_s = 0.0
        self._plan: JointPlan | None = None
        self._last_plan: JointPlan | None = None
        self._tau = np.zeros(6)
        self._tau_std = np.zeros(6)
        self._v_prev = np.zeros(6)
        # Position corrections sent: (host send time, rad/s per joint), for the predictor.
        self._corrections: deque[tuple[float, FloatArray]] = deque(maxlen=4096)
        self._fault: str | None = None
        self._streaming_since = -math.inf
        self._last_send_s = math.nan
        self._cache: dict[tuple[bytes, bytes], DelayPredictions] = {}
        self._envelope: deque[tuple[float, float]] = deque()
        self._ctrl_ref = math.nan
        self._served = -1  # last controller cycle a command was sent for
        self.coast = bool(coast) and not bool(getattr(driver, "virtual", False))
        self.coasted = 0
        self.log = CycleLog()
        self.clip_count = 0

    # ------------------------------------------------------------------ lifecycle
    @property
    def spec(self) -> RobotSpec:
        """The robot spec (limits, period); known once connected."""
        if self._spec is None:
            raise DriverError("the executor is not connected; use it as a context manager")
        return self._spec

    @property
    def period_s(self) -> float:
        """Controller period, s."""
        return self._period

    def connect(self) -> None:
        """Connect the driver (if needed), check the model against it, read a first state."""
        if self._spec is not None:
            return
        self.driver.connect()
        self._connected_here = True
        try:
            robot = str(self.driver.robot)
            period = float(self.driver.controller_period_s)
            check_model_robot(self.model, robot, period)
            self._spec = _driver_spec(self.driver, robot, period)
            self._period = period
            state = self.driver.read_state(timeout_s=max(1.0, 10 * period))
            self._response_s = self._predict_response(state.q)
            self._ingest(state)
        except BaseException:
            self._spec = None
            self.driver.close()
            raise
        # A model with a BLAS pin (DelayModel) keeps BLAS on one thread while connected:
        # queries during the loop then skip the per-call pin and its thread wake-ups.
        pinned = getattr(self.model, "pinned", None)
        if callable(pinned) and self._pin is None:
            self._pin = pinned()
            self._pin.__enter__()

    def close(self) -> None:
        """Stop any motion and close the driver if the executor connected it."""
        try:
            if self._spec is not None and self._fault is None and np.any(self._v_prev != 0):
                self.driver.stop(self._decel())
        finally:
            self._spec = None
            if self._pin is not None:
                pin, self._pin = self._pin, None
                pin.__exit__(None, None, None)
            if self._connected_here:
                self.driver.close()

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

    def _decel(self) -> float:
        if self._stop_decel is not None:
            return float(self._stop_decel)
        return float(max(self.spec.qdd_max_rad_s2))

    # ------------------------------------------------------------------ predictions
    def predict(self, q_rad: ArrayLike, directions: ArrayLike | None = None) -> DelayPredictions:
        """Predicted delays of joints 1..6 at ``q_rad`` for ``directions`` (6,), s.

        Joints the model does not cover (a sweep of joints 1, 2, 3, 5) get the mean of the
        covered joints' predictions.
        """
        q = np.asarray(q_rad, dtype=float).reshape(6)
        d = np.ones(6, np.int64) if directions is None else np.asarray(directions, np.int64)
        # Predictions are cached per configuration (to 0.1 mrad) and directions: a model
        # query may take milliseconds, and a plan is prepared more than once.
        key = (np.round(q, 4).tobytes(), d.tobytes())
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        out = self._predict_uncached(q, d)
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = out
        return out

    def _predict_uncached(self, q: FloatArray, d: NDArray[np.int64]) -> DelayPredictions:
        joints = np.arange(1, 7)
        try:
            return predict_delays(self.model, joints, d, np.tile(q, (6, 1)))
        except (ConfigError, ModelError, KeyError, IndexError, ValueError):
            covered = np.array(getattr(self.model, "joints", (1, 2, 3, 5)), dtype=np.int64)
            part = predict_delays(self.model, covered, d[covered - 1], np.tile(q, (4, 1)))
            out = {}
            for name in ("actuation_mean", "actuation_std", "response_mean", "response_std"):
                v = getattr(part, name)
                full = np.full(6, float(np.mean(v)))
                full[covered - 1] = v
                out[name] = full
            return DelayPredictions(**out)

    def _predict_response(self, q: FloatArray) -> float:
        p = self.predict(q)
        return float(np.median(p.response_mean))

    # ------------------------------------------------------------------ state
    def _ingest(self, state: RobotState) -> None:
        self._last = state
        self._last_arrival = state.host_time_s
        # Lower envelope of (arrival - controller time) over the last ENVELOPE_S: the
        # fastest packages' offset, i.e. the host time of each controller cycle boundary
        # plus the shortest sampling-to-arrival time (follows a slowly drifting phase).
        off = state.host_time_s - state.controller_time_s
        env = self._envelope
        while env and env[-1][1] >= off:
            env.pop()
        env.append((state.host_time_s, off))
        while env[0][0] < state.host_time_s - ENVELOPE_S:
            env.popleft()
        self._offset_min = env[0][1]
        if not math.isfinite(self._ctrl_ref):
            self._ctrl_ref = state.controller_time_s
        t_phys = state.host_time_s - self._response_s
        self._samples.append((t_phys, np.asarray(state.q, float), np.asarray(state.qd, float)))

    def _fault_stop(self, message: str) -> None:
        self._fault = message
        self._plan = None
        decel = self._decel()
        try:
            # A zero-speed speedj goes out at once (realtime command); the drivers' stop()
            # may first wait for the controller's acknowledgement of the previous command
            # (ur_rtde's speedStop: ~30 ms when the stream has stalled).
            self.driver.speedj(np.zeros(6), decel, 0.0)
        finally:
            self._v_prev = np.zeros(6)
            with contextlib.suppress(DriverError):
                self.driver.stop(decel)
        raise StaleStateError(message)

    def _read(self, coast_at: float | None = None) -> RobotState | None:
        if self._fault is not None:
            raise DriverError(f"the executor stopped after a fault ({self._fault}); reconnect")
        limit = self.stale_periods * self._period
        if self._plan is None and not np.any(self._v_prev != 0):
            # Idle at rest: gaps in reading are the caller's, not the stream's.
            return self.driver.read_state(timeout_s=max(limit, 0.5))
        deadline = max(self._last_arrival, self._streaming_since) + limit
        timeout = deadline - self.now()
        if timeout <= 0:
            self._fault_stop(
                f"no state package for {(self.now() - self._last_arrival) * 1e3:.1f} ms "
                f"(> {self.stale_periods:g} periods of {self._period * 1e3:g} ms); robot stopped"
            )
        if coast_at is not None and coast_at < deadline:
            try:
                got = self.driver.read_state(timeout_s=max(coast_at - self.now(), 0.0))
            except DriverTimeout:
                return None
            return self._check_age(got)
        try:
            state = self.driver.read_state(timeout_s=timeout)
        except DriverTimeout as exc:
            self._fault_stop(
                f"the state stream stalled: no package within {self.stale_periods:g} periods "
                f"({limit * 1e3:.1f} ms) of the last one ({exc}); robot stopped"
            )
        return self._check_age(state)

    def _check_age(self, state: RobotState) -> RobotState:
        limit = self.stale_periods * self._period
        age = (state.host_time_s - state.controller_time_s) - self._offset_min
        if math.isfinite(age) and age > limit:
            self._fault_stop(
                f"stale state: package of controller time {state.controller_time_s:.4f} s arrived "
                f"{age * 1e3:.1f} ms later than the fastest packages (> {self.stale_periods:g} "
                "periods); robot stopped"
            )
        return state

    def estimate(self, t_s: float | None = None) -> StateEstimate:
        """The physical joint state at host time ``t_s`` (default: now).

        The newest package is back-dated by the predicted response delay; from that instant
        the estimate follows the active plan (keeping the offset between plan and robot
        seen in the package) or, without a plan, the reported speed.
        """
        if not self._samples:
            raise DriverError("no state received yet; connect() first")
        t = self.now() if t_s is None else float(t_s)
        t_phys, q, qd = self._samples[-1]
        plan = self._plan or self._last_plan
        if plan is not None and math.isfinite(plan.start_time_s):
            q_then, _, _ = plan.sample(t_phys - plan.start_time_s)
            q_t, qd_t, _ = plan.sample(t - plan.start_time_s)
            q_est = q_t + (q - q_then)
            qd_est = qd_t
        else:
            q_est = q + qd * (t - t_phys)
            qd_est = qd
        return StateEstimate(
            time_s=t,
            q_rad=q_est,
            qd_rad_s=qd_est,
            sample_time_s=t_phys,
            response_delay_s=self._response_s,
            horizon_s=t - t_phys,
        )

    def _q_per_joint(self, t_s: FloatArray) -> FloatArray:
        """Estimated position of joint j at host time ``t_s[j]``, rad (6,)."""
        t_phys, q, qd = self._samples[-1]
        plan = self._plan or self._last_plan
        if plan is not None and math.isfinite(plan.start_time_s):
            q_then, _, _ = plan.sample(t_phys - plan.start_time_s)
            return plan.position_per_joint(t_s - plan.start_time_s) + (q - q_then)
        return q + qd * (t_s - t_phys)

    @property
    def last_state(self) -> RobotState | None:
        """The newest package as received."""
        return self._last

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
        if "actuation_s" in plan.meta:
            return plan
        dirs = plan.directions()
        p = self.predict(plan.q_start_rad, dirs)
        out = plan.at(plan.start_time_s)
        moving = plan.moving_joints()
        out.meta.update(
            actuation_s=np.where(moving, p.actuation_mean, 0.0) if self.compensate else np.zeros(6),
            predicted_actuation_s=p.actuation_mean,
            actuation_std_s=p.actuation_std,
            response_s=float(np.median(p.response_mean)),
            directions=dirs,
            moving=moving,
        )
        return out

    def lead_time_s(self, plan: JointPlan) -> float:
        """How long before the plan's start its first command must leave, s."""
        tau = self.prepare(plan).meta["actuation_s"]
        return float(np.max(tau))

    # ------------------------------------------------------------------ bounds
    def _q_of(self, confidence: float | None) -> float:
        return self.confidence if confidence is None else check_confidence(confidence)

    def _scheduled(self, plan: JointPlan | None) -> JointPlan:
        plan = plan or self._plan or self._last_plan
        if plan is None:
            raise ConfigError("no plan: pass one (scheduled with plan.at(start_time_s))")
        if not math.isfinite(plan.start_time_s):
            raise ConfigError("the plan is not scheduled; use plan.at(start_time_s)")
        return self.prepare(plan)

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
        t_on = p.onset_times(level_rad_s)[joint - 1]
        if not math.isfinite(t_on):
            raise ConfigError(f"joint {joint} does not move in this plan")
        late = p.meta["predicted_actuation_s"][joint - 1] - p.meta["actuation_s"][joint - 1]
        return TimingBounds.around(
            p.start_time_s + t_on + late,
            p.meta["actuation_std_s"][joint - 1],
            self._q_of(confidence),
            self._period,
        )

    def arrival_bounds(
        self, plan: JointPlan | None = None, *, confidence: float | None = None
    ) -> TimingBounds:
        """Per joint (6,): interval in which each joint reaches its planned end state."""
        p = self._scheduled(plan)
        late = p.meta["predicted_actuation_s"] - p.meta["actuation_s"]
        expected = np.where(p.meta["moving"], p.end_time_s + late, p.start_time_s)
        std = np.where(p.meta["moving"], p.meta["actuation_std_s"], 0.0)
        return TimingBounds.around(expected, std, self._q_of(confidence), self._period)

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
        moving = plan.meta["moving"]
        if not moving.any():
            raise ConfigError("the robot is already at the target; nothing to plan")
        tau = plan.meta["actuation_s"]
        std = plan.meta["actuation_std_s"]
        u = np.where(moving, delay_quantile(np.full(6, c), std, self._period), -np.inf)
        margin = float(np.max(u))
        latest_start = float(deadline_s) - plan.duration_s - margin
        lead = float(np.max(np.where(moving, tau, 0.0)))
        # The first command leaves on the next package: one period, plus one of safety.
        earliest_start = self.now() + lead + 2.0 * self._period
        if latest_start < earliest_start:
            miss = earliest_start - latest_start
            raise UnreachableError(
                f"cannot reach the target by the deadline with probability {c:g}: it misses by "
                f"{miss * 1e3:.1f} ms (motion {plan.duration_s * 1e3:.1f} ms, actuation delay "
                f"up to {lead * 1e3:.1f} ms, {c:g} timing margin {margin * 1e3:.1f} ms, "
                f"deadline in {(deadline_s - self.now()) * 1e3:.1f} ms); move the deadline "
                f"{miss * 1e3:.1f} ms later, lower the confidence or choose a closer target",
                miss_s=miss,
            )
        scheduled = plan.at(latest_start)
        arrival = self.arrival_bounds(scheduled, confidence=c)
        cdf = delay_cdf(float(deadline_s) - scheduled.end_time_s, std, self._period)
        prob = float(np.min(np.where(moving, cdf, 1.0)))
        return MeetPlan(
            plan=scheduled,
            deadline_s=float(deadline_s),
            confidence=c,
            first_send_s=latest_start - lead,
            slack_s=latest_start - earliest_start,
            arrival=arrival,
            probability=prob,
        )

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
            raise DriverError(f"the executor stopped after a fault ({self._fault}); reconnect")
        if isinstance(plan, MeetPlan):
            p = plan.plan
        else:
            p = plan if start_time_s is None else plan.at(start_time_s)
        if not math.isfinite(p.start_time_s):
            raise ConfigError("give start_time_s (host time at which the motion should start)")
        p = self.prepare(p)
        lead = float(np.max(p.meta["actuation_s"]))
        late = self.now() + self._period - (p.start_time_s - lead)
        if late > 0 and np.all(self._v_prev == 0):
            raise ConfigError(
                f"start time too soon: the first command had to leave {late * 1e3:.1f} ms ago "
                f"(actuation delay {lead * 1e3:.1f} ms plus one period); start at least "
                f"{late * 1e3:.1f} ms later"
            )
        if self._plan is None and not np.any(self._v_prev != 0):
            self._streaming_since = self.now()
        if p is not self._plan:
            self._corrections.clear()
        self._plan = p
        self._last_plan = p
        self._tau = np.asarray(p.meta["actuation_s"], float)
        self._tau_std = np.asarray(p.meta["actuation_std_s"], float)
        self._response_s = float(p.meta["response_s"])
        return p

    def step(self) -> RobotState:
        """Handle one controller cycle: read its package (stale check), back-date it, and
        send the command of the active plan (nothing when idle and at rest). With
        ``coast``, a cycle whose package is late gets its command from the estimate."""
        plan = self._plan
        streaming = plan is not None or bool(np.any(self._v_prev != 0))
        coast_at = None
        if streaming and self.coast and math.isfinite(self._ctrl_ref) and self._served >= 0:
            due = self._ctrl_ref + (self._served + 1) * self._period + self._offset_min
            coast_at = due + 0.5 * self._period
        got = self._read(coast_at)
        if got is None:  # the cycle's package is late: command it from the estimate
            assert self._last is not None
            self._served += 1
            self.coasted += 1
            self._send(plan, self._last, self._ctrl_ref + self._served * self._period)
            return self._last
        state = got
        self._ingest(state)
        cycle = round((state.controller_time_s - self._ctrl_ref) / self._period)
        if not streaming:
            self._served = cycle
            self.log.add(state, math.nan, None, False)
            return state
        if cycle <= self._served:  # this cycle was already commanded (coasted)
            self.log.add(state, math.nan, None, False)
            return state
        self._served = cycle
        self._send(plan, state, state.controller_time_s)
        return state

    def _send(self, plan: JointPlan | None, state: RobotState, controller_s: float) -> None:
        now = self.now()
        v, clipped = self._command(plan, now)
        a = self._ramp_acceleration(v)
        self.driver.speedj(v, a, (self.stale_periods + 2.0) * self._period)
        self._v_prev = v
        self._last_send_s = now
        self.log.add(state, now, v, clipped, controller_s=controller_s)

    def _command(self, plan: JointPlan | None, now: float) -> tuple[FloatArray, bool]:
        spec = self.spec
        period = self._period
        correcting = plan is not None and self.position_gain_1_s > 0 and bool(self._samples)
        if plan is None:
            target = np.zeros(6)
        else:
            t_plan = now - plan.start_time_s + self._tau + period
            target = plan.velocity_per_joint(t_plan)
            feed_forward = target
            if correcting:
                target = target + self.position_gain_1_s * self._predicted_error(plan, now)
        vmax = self.limits.velocity(spec)
        amax = self.limits.acceleration(spec)
        v = np.clip(target, -vmax, vmax)
        # The speed may change by the acceleration limit times the time since the previous
        # command (more than one period when packages were missed).
        since = now - self._last_send_s if math.isfinite(self._last_send_s) else period
        step = amax * min(max(period, since), 4.0 * period)
        v = np.clip(v, self._v_prev - step, self._v_prev + step)
        # Position guard: where this command acts (after the joint's delay), the joint must
        # still be able to stop before its limit.
        q_act = self._q_per_joint(now + self._tau + period)
        lo = np.asarray(spec.q_min_rad)
        hi = np.asarray(spec.q_max_rad)
        room_hi = np.maximum(hi - q_act - v * period, 0.0)
        room_lo = np.maximum(q_act - lo + v * period, 0.0)
        v = np.minimum(v, np.sqrt(2.0 * amax * room_hi))
        v = np.maximum(v, -np.sqrt(2.0 * amax * room_lo))
        clipped = bool(np.any(np.abs(v - target) > 1e-12))
        if clipped:
            self.clip_count += 1
        if correcting:
            self._corrections.append((now, v - feed_forward))
        return v, clipped

    def _predicted_error(self, plan: JointPlan, now: float) -> FloatArray:
        """Plan minus physical position where the next command acts, rad (Smith predictor).

        The newest back-dated package shows the error at its physical instant ``t_phys``;
        corrections sent at ``s`` act over ``[s + tau, s_next + tau]``, so the part of
        them after ``t_phys`` is not in the package yet and is subtracted.
        """
        t_phys, q, _ = self._samples[-1]
        q_plan, _, _ = plan.sample(t_phys - plan.start_time_s)
        error = q_plan - q
        sends = self._corrections
        tau_max = float(np.max(self._tau))
        # A command acts until the next one is sent (plus tau): once that lies before the
        # package's instant it is fully visible, and so for every later package.
        while len(sends) > 1 and sends[1][0] + tau_max <= t_phys:
            sends.popleft()
        if not sends:
            return np.asarray(error)
        start = np.fromiter((c[0] for c in sends), float, len(sends))
        end = np.append(start[1:], now)
        u = np.stack([c[1] for c in sends])
        # Duration of each command's action after t_phys, per joint (tau differs).
        pending = np.clip(
            end[:, None] + self._tau - np.maximum(start[:, None] + self._tau, t_phys),
            0.0,
            (end - start)[:, None],
        )
        return np.asarray(error - np.sum(u * pending, axis=0))

    def _ramp_acceleration(self, v: FloatArray) -> float:
        """speedj acceleration: the leading joint's change over one period (clamped)."""
        amax = self.limits.acceleration(self.spec)
        need = float(np.max(np.abs(v - self._v_prev))) / self._period
        floor = 0.5 * float(np.min(amax))
        return float(min(max(need, floor), float(np.max(amax))))

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
        p = self.schedule(plan, start_time_s)
        start_row = len(self.log)
        if until_s is None:
            if np.any(p.qd_end_rad_s != 0):
                raise ConfigError("this plan ends moving (a cruise); give until_s")
            settle = float(np.max(self._tau)) + 3 * self._period if settle_s is None else settle_s
            until_s = p.end_time_s + settle
        first_send = math.nan
        ends_at_rest = not np.any(p.qd_end_rad_s != 0)
        give_up = until_s + 1.0
        try:
            while self.now() < until_s or (
                ends_at_rest and np.any(self._v_prev != 0) and self.now() < give_up
            ):
                state = self.step()
                if on_step is not None:
                    on_step(state)
                if not math.isfinite(first_send) and len(self.log) > start_row:
                    sent = self.log._rows[-1][3]
                    if math.isfinite(sent):
                        first_send = sent
        finally:
            if self._plan is p:
                self._plan = None
        if np.any(p.qd_end_rad_s != 0):
            # Ended while cruising: bring the arm to rest.
            self.stop()
        log = self.log.arrays(start_row)
        sends = log["send_s"][np.isfinite(log["send_s"])]
        return ExecutionResult(
            plan=p,
            actuation_s=self._tau.copy(),
            actuation_std_s=self._tau_std.copy(),
            response_s=self._response_s,
            first_send_s=float(sends[0]) if len(sends) else math.nan,
            last_send_s=float(sends[-1]) if len(sends) else math.nan,
            log=log,
        )

    def stop(self) -> None:
        """Drop the active plan and decelerate the arm to rest."""
        self._plan = None
        self.driver.stop(self._decel())
        self._v_prev = np.zeros(6)

    @property
    def fault(self) -> str | None:
        """The fault that stopped the executor, or None."""
        return self._fault
