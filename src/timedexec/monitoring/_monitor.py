"""DelayMonitor: per-joint CUSUMs of observed lag minus the model's actuation + response.

Per move: residual ``r = lag - (actuation_mean + response_mean)`` (the model's prediction
for the joint, direction and start configuration). The first ``warmup_moves`` moves of a
joint fix its reference: the absolute gap to the model (their median) and the residual
distribution, whose empirical quantiles map later residuals to normal scores
``z = Phi^-1(F_warm(r))`` (the standardization). A two-sided CUSUM with reference ``k`` runs
on ``z``; its threshold gives the false-alarm rate asked for (``arl0_moves``, Siegmund's
approximation averaged over the warm-up's own estimation error, :mod:`._cusum`).

A second CUSUM per joint runs on its *contrast* with the joints of the same plan (moves
from rest of distinct joints whose first commands left within ``PLAN_WINDOW_S`` of the
plan's first: the executor sends each joint's share of a trajectory early by that joint's
predicted actuation delay, so one trajectory's moves start cycles apart): its residual
centred on its own warm-up, minus the median of the others'. Timing noise common to a
move (host send times, the publisher's phase) cancels in it; a change common to all joints
stays with the first ("level") test. Each test gets half the false-alarm budget. A level
alarm whose joint moved by less than half of its shift against the other joints over the
same span is reported as a *common* shift of those joints (response delay, network, host
timing: not one drive), and their level references move to the new level. See
``docs/monitor.md``.

Two departures from independent normal residuals are met on real cells and in an
independently written generator of executor logs (``tests/independent_cycle_log.py``), and
each made false alarms 3-10x more frequent than the design rate:

* heavy tails in bursts: a command that misses the controller's intake (host late) or a
  host stall delays a whole plan by a period, often for several plans in a row. Scores are
  clipped at ``SCORE_CLIP`` standard deviations (a Huber-type CUSUM): a burst of such moves
  adds at most ``SCORE_CLIP - k`` per move. Clipping shrinks the scores' spread, so the
  threshold (set for unclipped scores) is conservative;
* serial correlation: host timing that wanders slowly is shared by consecutive plans and so
  by consecutive moves of a joint. The scores are divided by the square root of their
  long-run variance ``1 + 2 sum_l (1 - l/(L+1)) rho_l`` (Bartlett, ``L = LRV_LAGS``,
  estimated on the warm-up, never below 1): a CUSUM of correlated scores then wanders
  as one of independent ones.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.monitoring._cusum import check_arl0, false_alarm_rate, threshold_for_arl
from timedexec.monitoring._moves import PLAN_WINDOW_S, Move, MoveExtractor

__all__ = [
    "Alert",
    "Cusum",
    "DelayMonitor",
    "JointState",
    "RecalibrationPlan",
    "describe_alert",
    "standardize",
    "warmup_reference",
]


#: Smallest warm-up: the quantile map and the threshold's correction need it.
MIN_WARMUP = 20
#: Target half-width of a re-measured shift (95 %), ms, for the suggested trial count.
RECAL_PRECISION_MS = 0.25
#: Largest standardized score a move adds (Huber's 1.345 .. 2 are the usual choices; 1.5:
#: bursts of plans delayed by a period stay below the threshold for >= 9 moves).
SCORE_CLIP = 1.5
#: Lags of the warm-up's autocorrelation in the long-run variance (Bartlett weights).
LRV_LAGS = 5


@dataclass(frozen=True)
class RecalibrationPlan:
    """The calibration sweep that re-fits what an alert says changed.

    Attributes
    ----------
    joints : tuple of int
        The joint(s) to sweep (only these).
    delay : str
        What to re-fit: the state stream cannot separate actuation from response, so
        "actuation" when one joint moved alone (response is shared by the joints), else
        "actuation or response"; "response" for a common shift (first check the host's
        timing and the network, which the sweep would measure as well).
    trials : int
        Trials: enough for the shift to +-``RECAL_PRECISION_MS`` (95 %) at the model's
        single-trial std, in whole conditions (2 directions x 10 repeats), at least 200.
    command : str
        How to run it.
    """

    joints: tuple[int, ...]
    delay: str
    trials: int
    command: str

    def sweep_plan(self, robot: str, *, seed: int = 0) -> Any:
        """The :class:`~timedexec.recording.SweepPlan` of this sweep (save its
        ``to_arrays()`` with ``numpy.savez`` for ``timedexec calibrate --plan``)."""
        from timedexec.recording import SweepPlan

        return SweepPlan.generate(robot, self.trials, seed=seed, joints=self.joints)


@dataclass(frozen=True)
class Alert:
    """A detected change of one joint's observed lag.

    Attributes
    ----------
    joint : int
        The joint, 1-based.
    shift_ms : float
        Estimated shift since the warm-up, ms (Hodges-Lehmann: median of the pairwise
        differences of the residuals since the change and the warm-up's).
    ci_ms : (float, float)
        Its 95 % confidence interval, ms (distribution-free, Mann-Whitney).
    statistic : float
        The CUSUM that crossed; ``threshold`` the threshold it crossed.
    side : str
        "later" (lags grew) or "earlier".
    move : int
        The joint's move count at the alarm (warm-up included).
    moves_since_change : int
        Moves since the estimated change (the last move the CUSUM was zero).
    false_alarm_rate : float
        The false-alarm rate the threshold was set for, per move.
    arl0_moves : float
        Its inverse.
    gap_to_model_ms : float
        The warm-up's median residual: the absolute gap between the observed lag and the
        model's actuation + response (offsets of the method included).
    recalibrate : RecalibrationPlan
        What to sweep to re-fit it.
    test : str
        Which CUSUM crossed: "level" (the joint's residuals) or "contrast" (its residuals
        minus the median of the joints moved with it: a change of this joint against the
        others, blind to one they share). For "contrast", the shift, the interval and
        ``moves_since_change`` are of the contrast (moves with other joints only).
        "common": the joint's level crossed, but the other joints' levels moved alike over
        the same span (``common_ms``; less than half of the shift is left against them): a
        change of the lag shared by the moves (response delay, network, host timing), not
        this joint's drive. The joints stay under watch, their level references moved to
        the new level.
    crossed_joint : int
        The joint whose CUSUM crossed. A contrast alarm goes to the joint whose contrast
        moved alone in its direction, or most (one joint's change moves the others'
        contrasts too, the other way), which may not be the one that crossed first.
    """

    joint: int
    shift_ms: float
    ci_ms: tuple[float, float]
    statistic: float
    threshold: float
    side: str
    move: int
    moves_since_change: int
    false_alarm_rate: float
    arl0_moves: float
    gap_to_model_ms: float
    recalibrate: RecalibrationPlan
    test: str = "level"
    crossed_joint: int = 0
    common_ms: dict[int, float] = field(default_factory=dict)

    def message(self) -> str:
        """One line for people (:func:`describe_alert`)."""
        return describe_alert(self.to_dict())

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        d = asdict(self)
        d["ci_ms"] = list(self.ci_ms)
        d["recalibrate"]["joints"] = list(self.recalibrate.joints)
        d["common_ms"] = {str(j): v for j, v in self.common_ms.items()}
        return d


def describe_alert(alert: dict[str, Any]) -> str:
    """One line for people from an alert's JSON form (:meth:`Alert.to_dict`, or the
    ``alerts`` of a saved ``timedexec monitor --json``)."""
    a = alert
    lo, hi = a["ci_ms"]
    rec = a["recalibrate"]
    joints = ",".join(str(j) for j in rec["joints"])
    redo = f"recalibrate {rec['delay']} of joint(s) {joints} with {rec['trials']} trials: "
    if a.get("test") == "common":
        each = ", ".join(f"joint {j} {v:+.2f}" for j, v in a["common_ms"].items())
        return (
            f"joints {', '.join(a['common_ms'])}: lag {a['side']} together ({each} ms; joint "
            f"{a['joint']} {a['shift_ms']:+.2f}, 95 % CI {lo:+.2f} .. {hi:+.2f}) — a change "
            "common to the moves (response delay, network or host timing), not one joint's "
            f"drive; joint {a['joint']}'s level CUSUM {a['statistic']:.1f} > "
            f"{a['threshold']:.1f} after {a['moves_since_change']} moves; references moved to "
            f"the new level; check the host and network first, then {redo}{rec['command']}"
        )
    test = a.get("test", "level")
    against = " than the joints moved with it" if test == "contrast" else ""
    crossed = a.get("crossed_joint", 0)
    which = f"{test} CUSUM" if crossed in (0, a["joint"]) else f"joint {crossed}'s {test} CUSUM"
    return (
        f"joint {a['joint']}: lag {a['side']}{against} by {a['shift_ms']:+.2f} ms "
        f"(95 % CI {lo:+.2f} .. {hi:+.2f}) — {which} {a['statistic']:.1f} > "
        f"{a['threshold']:.1f} after {a['moves_since_change']} moves since the change (move "
        f"{a['move']}); threshold set for 1 false alarm per {a['arl0_moves']:,.0f} moves; "
        f"{redo}{rec['command']}"
    )


@dataclass
class Cusum:
    """One two-sided CUSUM on standardized residuals, with the warm-up that standardizes
    them (module docstring). ``n`` counts its residuals since its warm-up began, which was
    at ``residual_s[start]``."""

    n: int = 0
    start: int = 0
    warm: FloatArray | None = None  # sorted warm-up residuals, s
    lrv: float = 1.0  # long-run variance factor of the warm-up's scores (serial correlation)
    up: float = 0.0
    down: float = 0.0
    up_zero: int = 0  # residual count at which `up` was last zero
    down_zero: int = 0
    residual_s: list[float] = field(default_factory=list)
    up_hist: list[float] = field(default_factory=list)
    down_hist: list[float] = field(default_factory=list)

    def step(self, r: float, warmup: int, k: float, h: float) -> str | None:
        """Add residual ``r`` (s); "later"/"earlier" when a side is above ``h``."""
        self.n += 1
        self.residual_s.append(r)
        if self.warm is None:
            self.up_hist.append(0.0)
            self.down_hist.append(0.0)
            if self.n >= warmup:
                self.warm, self.lrv = warmup_reference(self.residual_s[-warmup:])
                self.up_zero = self.down_zero = self.n
            return None
        z = float(standardize(r, self.warm, self.lrv))
        self.up = max(0.0, self.up + z - k)
        self.down = max(0.0, self.down - z - k)
        if self.up == 0.0:
            self.up_zero = self.n
        if self.down == 0.0:
            self.down_zero = self.n
        self.up_hist.append(self.up)
        self.down_hist.append(self.down)
        if max(self.up, self.down) <= h:
            return None
        return "later" if self.up > h else "earlier"

    def since_change(self, side: str) -> int:
        """Residuals since the side's statistic was last zero."""
        return self.n - (self.up_zero if side == "later" else self.down_zero)

    def rewarm(self) -> None:
        """Forget the reference: the next ``warmup`` residuals fix a new one."""
        self.warm = None
        self.n = self.up_zero = self.down_zero = 0
        self.up = self.down = 0.0
        self.start = len(self.residual_s)


@dataclass
class JointState:
    """The monitor's state of one joint (see :meth:`DelayMonitor.states`): the CUSUM of its
    residuals (``level``) and of its contrasts with the joints moved with it
    (``contrast``)."""

    joint: int
    moves: int = 0
    skipped: int = 0
    level: Cusum = field(default_factory=Cusum)
    contrast: Cusum = field(default_factory=Cusum)
    alarm: Alert | None = None
    lag_s: list[float] = field(default_factory=list)
    send_s: list[float] = field(default_factory=list)
    act_std_s: list[float] = field(default_factory=list)
    contrast_move: list[int] = field(default_factory=list)  # move count of each contrast

    @property
    def residual_s(self) -> list[float]:
        """Residuals (lag minus the model's prediction) per move, s."""
        return self.level.residual_s

    @property
    def warm(self) -> FloatArray | None:
        """Sorted warm-up residuals, s (None during the warm-up)."""
        return self.level.warm

    @property
    def status(self) -> str:
        """ "warm-up", "ok" or "alarm"."""
        if self.alarm is not None:
            return "alarm"
        return "warm-up" if self.warm is None else "ok"


@functools.cache
def _normal_scores(n: int) -> FloatArray:
    from statistics import NormalDist

    nd = NormalDist()
    return np.array([nd.inv_cdf((i + 0.5) / n) for i in range(n)])


def standardize(residuals: ArrayLike, warm_sorted: FloatArray, lrv: float = 1.0) -> FloatArray:
    """The CUSUM's scores of ``residuals`` against a warm-up (module docstring): the
    quantile map of the sorted warm-up residuals to normal scores, clipped at
    ``SCORE_CLIP``, divided by ``sqrt(lrv)``."""
    z = np.interp(np.asarray(residuals, dtype=float), warm_sorted, _normal_scores(len(warm_sorted)))
    return np.asarray(np.clip(z, -SCORE_CLIP, SCORE_CLIP) / math.sqrt(lrv))


def warmup_reference(residuals_in_order: ArrayLike) -> tuple[FloatArray, float]:
    """``(sorted residuals, long-run variance factor)`` of a warm-up given in the order
    the moves ran (the factor from their clipped scores, Bartlett over ``LRV_LAGS``)."""
    x = np.asarray(residuals_in_order, dtype=float)
    warm = np.sort(x)
    return warm, _long_run_variance(standardize(x, warm), LRV_LAGS)


def _plans(moves: list[Move]) -> list[list[int]]:
    """Indices of ``moves`` (in send order) grouped into plans: distinct joints whose sends
    lie within ``PLAN_WINDOW_S`` of the plan's first."""
    plans: list[list[int]] = []
    first = -math.inf
    joints: set[int] = set()
    for i, m in enumerate(moves):
        if m.send_s - first > PLAN_WINDOW_S or m.joint in joints or m.send_s < first:
            plans.append([])
            first, joints = m.send_s, set()
        plans[-1].append(i)
        joints.add(m.joint)
    return plans


def _long_run_variance(z: FloatArray, lags: int) -> float:
    """``1 + 2 sum_l (1 - l/(lags+1)) rho_l`` of a sequence (Bartlett), at least 1."""
    x = z - z.mean()
    var = float(np.dot(x, x))
    if var <= 0.0:
        return 1.0
    acf = [float(np.dot(x[:-lag], x[lag:])) / var for lag in range(1, lags + 1)]
    return max(1.0, 1.0 + 2.0 * sum((1.0 - lag / (lags + 1)) * r for lag, r in enumerate(acf, 1)))


def _cusum_summary(c: Cusum, warmup: int) -> dict[str, Any]:
    """Reference and shift of a warmed-up CUSUM, ms."""
    assert c.warm is not None
    res = np.array(c.residual_s[c.start + warmup :])
    med = float(np.median(c.warm))
    return {
        "gap_to_model_ms": med * 1e3,
        "serial_correlation_factor": c.lrv,
        "warmup_spread_ms": float(1.4826 * np.median(np.abs(c.warm - med)) * 1e3),
        "shift_ms": float(np.median(res) - med) * 1e3 if len(res) else None,
    }


def _hodges_lehmann(
    post: FloatArray, warm: FloatArray, conf: float = 0.95
) -> tuple[float, float, float]:
    """Shift estimate and distribution-free CI (s) of ``post`` against ``warm``."""
    from statistics import NormalDist

    diffs = np.sort((post[:, None] - warm[None, :]).ravel())
    m, n = len(post), len(warm)
    est = float(np.median(diffs))
    zq = NormalDist().inv_cdf(0.5 + conf / 2)
    c = math.floor(m * n / 2 - zq * math.sqrt(m * n * (m + n + 1) / 12.0))
    c = min(max(c, 0), len(diffs) - 1)
    return est, float(diffs[c]), float(diffs[len(diffs) - 1 - c])


class DelayMonitor:
    """Watches a deployed delay model from the robot's own commands and states (no gyro).

    Parameters
    ----------
    model : DelayModel, DelayPredictor, str or path
        The deployed model (a bundle directory or a bundled name such as "ur10-sim").
    warmup_moves : int
        Moves per joint that fix the reference (>= 20; default 100): the monitor detects
        change relative to them.
    arl0_moves : float
        Wanted moves between false alarms per joint with no change (default 10,000).
    reference_k : float
        CUSUM reference, in standardized units, below ``SCORE_CLIP`` (the most a move adds).
        Default 0.4: fastest for a shift of 0.8 sd, what a 2 ms change is where residuals
        are wide and serially correlated (the independent generator's UR10e: 0.5 left 2 of
        24 seeded detections beyond 150 moves, 0.4 none; false alarms unchanged).
    joints : sequence of int, optional
        Joints to watch (default: every joint the moves show).
    sweep_time : bool
        Pass each move's ``sweep_time_s`` to a model with a time input (recordings); by
        default a time-input model predicts the warm robot.
    period_s : float, optional
        Controller period for cycle logs (default the model's ``period_s``).

    Examples
    --------
    >>> mon = DelayMonitor("ur10-sim")                             # doctest: +SKIP
    >>> alerts = mon.update(moves_from_recording("ur10.h5")[0])    # doctest: +SKIP
    >>> with TimedExecutor(open_driver("ur://10.0.0.2"), "ur10-sim") as ex:  # doctest: +SKIP
    ...     for plan in plans:
    ...         ex.execute(plan)
    ...         for alert in mon.follow(ex):
    ...             print(alert.message())
    """

    def __init__(
        self,
        model: Any,
        *,
        warmup_moves: int = 100,
        arl0_moves: float = 10_000.0,
        reference_k: float = 0.4,
        joints: Sequence[int] | None = None,
        sweep_time: bool = False,
        period_s: float | None = None,
    ) -> None:
        from timedexec.execution import load_delay_model

        if (
            isinstance(warmup_moves, bool)
            or not isinstance(warmup_moves, int)
            or warmup_moves < MIN_WARMUP
        ):
            raise ConfigError(
                f"warmup_moves={warmup_moves!r} is out of range; use an integer >= {MIN_WARMUP} "
                "(100 by default: the reference residuals of each joint)"
            )
        self.model = load_delay_model(model)
        self.warmup_moves = warmup_moves
        self.reference_k = float(reference_k)
        if not 0 < self.reference_k < SCORE_CLIP:
            raise ConfigError(
                f"reference_k={reference_k!r} is out of range; use 0 < k < {SCORE_CLIP} (scores "
                f"are clipped at {SCORE_CLIP}: a larger k could never alarm; 0.4 by default)"
            )
        self.arl0_moves = check_arl0(arl0_moves)
        # two tests per joint (level and contrast), each with half the false-alarm budget
        self.threshold = threshold_for_arl(2.0 * self.arl0_moves, self.reference_k, warmup_moves)
        self.nominal_arl0_moves = 1.0 / false_alarm_rate(self.threshold, self.reference_k)
        if joints is not None:
            bad = [j for j in joints if j not in range(1, 7)]
            if bad:
                raise ConfigError(f"joints {list(joints)}: {bad} not in 1..6; name joints 1-based")
        self.joints = None if joints is None else tuple(int(j) for j in joints)
        self.sweep_time = bool(sweep_time) and bool(getattr(self.model, "time_input", False))
        self.period_s = period_s if period_s is not None else getattr(self.model, "period_s", None)
        self._state: dict[int, JointState] = {}
        self._extractor: MoveExtractor | None = None
        self._followed = 0
        self.alerts: list[Alert] = []

    # ----------------------------------------------------------------- inputs
    def update(self, moves: Move | Iterable[Move]) -> list[Alert]:
        """Add moves (in the order they ran); return the alerts they raised.

        Moves without a lag (no package in the onset window) and joints outside ``joints``
        or unknown to the model are counted as skipped.
        """
        from timedexec.execution import predict_delays

        batch = [moves] if isinstance(moves, Move) else list(moves)
        if not batch:
            return []
        known = set(getattr(self.model, "joints", range(1, 7)))
        use = [
            m
            for m in batch
            if math.isfinite(m.lag_s)
            and (self.joints is None or m.joint in self.joints)
            and m.joint in known
        ]
        for m in batch:
            if not (math.isfinite(m.lag_s) and m.joint in known):
                self._joint(m.joint).skipped += 1
        if not use:
            return []
        t_s = np.array([m.sweep_time_s for m in use]) if self.sweep_time else None
        if t_s is not None and not np.all(np.isfinite(t_s)):
            t_s = None
        pred = predict_delays(
            self.model,
            [m.joint for m in use],
            [m.direction for m in use],
            np.array([m.q_start_rad for m in use]),
            t_s=t_s,
        )
        residual = np.array([m.lag_s for m in use]) - (pred.actuation_mean + pred.response_mean)
        new: list[Alert] = []
        for idx in _plans(use):
            # contrasts with the alarms as they stand before this plan
            contrast = self._contrasts([use[i] for i in idx], residual[idx])
            for i, c in zip(idx, contrast, strict=True):
                m = use[i]
                st = self._joint(m.joint)
                st.lag_s.append(m.lag_s)
                st.send_s.append(m.send_s)
                alert = self._step(st, float(residual[i]), float(c), float(pred.actuation_std[i]))
                if alert is not None:
                    new.append(alert)
        self.alerts.extend(new)
        return new

    def _contrasts(self, plan: list[Move], residual: FloatArray) -> FloatArray:
        """Each move's centred residual minus the median centred residual of the other
        joints of its plan; NaN for a joint moved alone. Centred: less the joint's own
        warm-up median (its running median while it warms up, from 5 moves on), so a
        contrast's level does not depend on which joints moved with it. Joints in alarm are
        left out of the others (their change would leak into the rest; the others'
        contrasts then re-learn their reference, see :meth:`_alarm`)."""
        out = np.full(len(plan), np.nan)
        if len(plan) < 2 or len({m.joint for m in plan}) < len(plan):
            return out  # moved alone, or not one plan (a joint twice)
        centred = np.full(len(plan), np.nan)
        for i, m in enumerate(plan):
            st = self._joint(m.joint)
            if st.warm is not None:
                centred[i] = residual[i] - float(np.median(st.warm))
            elif st.level.n >= 5:
                centred[i] = residual[i] - float(np.median(st.level.residual_s))
        usable = [
            i
            for i, m in enumerate(plan)
            if math.isfinite(centred[i]) and self._joint(m.joint).alarm is None
        ]
        for i in range(len(plan)):
            others = [centred[o] for o in usable if o != i]
            if others and math.isfinite(centred[i]):
                out[i] = centred[i] - float(np.median(others))
        return out

    def feed_log(self, arrays: dict[str, NDArray[Any]]) -> list[Alert]:
        """Add the next rows of a cycle log (:meth:`CycleLog.arrays` or a saved log)."""
        if self._extractor is None:
            if self.period_s is None:
                raise ConfigError(
                    "the controller period is unknown; give DelayMonitor(period_s=...)"
                )
            self._extractor = MoveExtractor(float(self.period_s))
        return self.update(self._extractor.feed(arrays))

    def follow(self, executor: Any) -> list[Alert]:
        """Consume the rows of ``executor.log`` added since the last call; return new alerts.

        Call it between executions (or from ``on_step`` every few hundred cycles): the cost
        is one pass over the new rows plus one model query per completed move.
        """
        log = executor.log
        n = len(log)
        if n < self._followed:  # the log was cleared
            self._followed = 0
        if n == self._followed:
            return []
        if self._extractor is None:
            period = getattr(executor, "period_s", None)
            if period is not None and math.isfinite(period):
                self.period_s = float(period)
        arrays = log.arrays(self._followed)
        self._followed = n
        return self.feed_log(arrays)

    # ----------------------------------------------------------------- the test
    def _joint(self, joint: int) -> JointState:
        st = self._state.get(joint)
        if st is None:
            st = self._state[joint] = JointState(joint)
        return st

    def _step(self, st: JointState, r: float, c: float, act_std_s: float) -> Alert | None:
        st.moves += 1
        st.act_std_s.append(act_std_s)
        args = (self.warmup_moves, self.reference_k, self.threshold)
        fired = st.level.step(r, *args)
        test = "level"
        if math.isfinite(c):
            st.contrast_move.append(st.moves)
            fired_c = st.contrast.step(c, *args)
            if fired is None and fired_c is not None:
                fired, test = fired_c, "contrast"
        if st.alarm is not None or fired is None:
            return None
        if test == "level":
            statistic = max(st.level.up, st.level.down)
            since = st.level.since_change(fired)
            common = self._common_shift(st, since)
            if common:
                return self._common_alarm(st, common, since, statistic, fired)
            return self._alarm(st, "level", st.level, since, st, statistic, fired)
        return self._contrast_alarm(st, st.contrast.since_change(fired))

    def _common_shift(self, st: JointState, since: int) -> dict[int, float]:
        """{joint: level shift, s} of the joints that moved over ``st``'s last ``since``
        moves, when ``st``'s level change is common to them: the others' levels moved the
        same way (their median by at least half of it), so that what is left of it against
        them is less than half; else {}. Each other joint needs 3 moves in the
        span (an alarmed one counts: its reference is from before its own change)."""
        if st.warm is None or since < 3:
            return {}
        level = float(np.median(st.level.residual_s[-since:]) - np.median(st.warm))
        span = st.send_s[-since:]
        t0, t1 = min(span) - PLAN_WINDOW_S, max(span) + PLAN_WINDOW_S
        others: dict[int, float] = {}
        for other in self._state.values():
            if other is st or other.warm is None:
                continue
            send = np.asarray(other.send_s)
            inside = np.asarray(other.residual_s)[(send >= t0) & (send <= t1)]
            if len(inside) >= 3:
                others[other.joint] = float(np.median(inside) - np.median(other.warm))
        if not others:
            return {}
        mid = float(np.median(list(others.values())))
        if mid * level <= 0 or abs(level - mid) >= 0.5 * abs(level):
            return {}  # the joint moved against the others: its own change
        return {st.joint: level, **others}

    def _common_alarm(
        self, st: JointState, shifts: dict[int, float], since: int, statistic: float, side: str
    ) -> Alert:
        """The alert of a common shift. The shift, one for the joints that moved over the
        span (the median of theirs), moves each one's level reference, so their contrasts
        stay centred; their level CUSUMs restart (alarmed joints stay in alarm)."""
        joints = sorted(shifts)
        alert = self._alert(
            st, "common", st.level, since, st, statistic, side,
            self._recalibration(joints, float(np.median(st.act_std_s)), "response"),
            {j: shifts[j] * 1e3 for j in joints},
        )  # fmt: skip
        common = float(np.median(list(shifts.values())))
        for j in shifts:
            level = self._state[j].level
            assert level.warm is not None
            level.warm = level.warm + common
            level.up = level.down = 0.0
            level.up_zero = level.down_zero = level.n
        return alert

    def _contrast_alarm(self, fired: JointState, since: int) -> Alert | None:
        """A contrast crossed: one joint changed against the joints moved with it, but its
        change also moved theirs, the other way (by half, with three joints: the
        contrasts of a plan sum to zero), and clipped scores cross at about the same time.
        The alarm goes to the joint whose recent contrasts (as many as the crossing one's
        since its change) moved alone in their direction, or, without such a joint (two
        joints, or no clear pattern), to the one that moved most: one joint changing is the
        simpler explanation than all the others changing together."""
        shifts: list[tuple[float, JointState]] = []
        for other in self._state.values():
            con = other.contrast
            recent = min(since, con.n - self.warmup_moves)  # contrasts after its warm-up
            if other.alarm is not None or con.warm is None or recent < min(since, 3):
                continue
            shift = float(np.median(con.residual_s[-recent:])) - float(np.median(con.warm))
            shifts.append((shift, other))
        if not shifts:
            return None
        best = max(shifts, key=lambda x: abs(x[0]))
        if len(shifts) >= 3:
            for sign in (1.0, -1.0):
                alone = [x for x in shifts if x[0] * sign > 0]
                if len(alone) == 1:
                    best = alone[0]
        st = best[1]
        statistic = max(fired.contrast.up, fired.contrast.down)  # before the re-warm
        return self._alarm(st, "contrast", st.contrast, since, fired, statistic)

    def _alarm(
        self,
        st: JointState,
        test: str,
        cusum: Cusum,
        since: int,
        fired: JointState,
        statistic: float,
        side: str | None = None,
    ) -> Alert:
        """The alarm of ``st`` (it stays in alarm); ``side`` is the crossing side when it
        is ``st``'s own CUSUM that crossed, else (an attributed contrast alarm) the sign of
        ``st``'s shift. The other joints' contrasts lose ``st`` from their plans' medians,
        which changes their spread: their contrast CUSUMs re-learn their reference."""
        recal = self._recalibration([st.joint], float(np.median(st.act_std_s)))
        alert = self._alert(st, test, cusum, since, fired, statistic, side, recal)
        st.alarm = alert
        for other in self._state.values():
            if other is not st and other.alarm is None:
                other.contrast.rewarm()
        return alert

    def _alert(
        self,
        st: JointState,
        test: str,
        cusum: Cusum,
        since: int,
        fired: JointState,
        statistic: float,
        side: str | None,
        recalibrate: RecalibrationPlan,
        common_ms: dict[int, float] | None = None,
    ) -> Alert:
        """An :class:`Alert` on ``st``: the shift of ``cusum``'s last ``since`` residuals."""
        assert cusum.warm is not None
        assert st.level.warm is not None
        est, lo, hi = _hodges_lehmann(np.array(cusum.residual_s[-since:]), cusum.warm)
        if side is None:
            side = "later" if est > 0 else "earlier"
        return Alert(
            joint=st.joint,
            shift_ms=est * 1e3,
            ci_ms=(lo * 1e3, hi * 1e3),
            statistic=statistic,
            threshold=self.threshold,
            side=side,
            move=st.moves,
            moves_since_change=since,
            false_alarm_rate=1.0 / self.arl0_moves,
            arl0_moves=self.arl0_moves,
            gap_to_model_ms=float(np.median(st.level.warm)) * 1e3,
            recalibrate=recalibrate,
            test=test,
            crossed_joint=fired.joint,
            common_ms=common_ms or {},
        )

    def _recalibration(
        self, joints: list[int], act_std_s: float, delay: str | None = None
    ) -> RecalibrationPlan:
        others = [
            s.joint for s in self._state.values() if s.alarm is not None and s.joint not in joints
        ]
        if delay is None:
            delay = "actuation" if not others else "actuation or response"
        n = math.ceil((1.96 * act_std_s * 1e3 / RECAL_PRECISION_MS) ** 2 / 20.0) * 20
        n = max(200, n)
        js = ",".join(str(j) for j in joints)
        robot = str(getattr(self.model, "robot", "ROBOT"))
        cmd = (
            f'python -c "import numpy as np; from timedexec.recording import SweepPlan; '
            f"np.savez('recal-j{js}.npz', **SweepPlan.generate('{robot}', {n}, seed=1, "
            f'joints=({js},)).to_arrays())" && timedexec calibrate --robot-url URL --imu PORT '
            f"--plan recal-j{js}.npz --out recal-j{js}.h5; then extract it and retrain joint "
            f"{js} on its new rows"
        )
        return RecalibrationPlan(joints=tuple(joints), delay=delay, trials=n, command=cmd)

    def rebaseline(self, joint: int) -> None:
        """Forget a joint's reference and alarm (after recalibrating): a new warm-up starts."""
        self._state.pop(int(joint), None)

    # ----------------------------------------------------------------- outputs
    def states(self) -> list[JointState]:
        """Per joint, in joint order."""
        return [self._state[j] for j in sorted(self._state)]

    def history(self, joint: int) -> dict[str, FloatArray]:
        """``residual_ms``, ``upper``, ``lower`` per move of ``joint`` (warm-up included);
        ``contrast_ms``, ``contrast_upper``, ``contrast_lower`` per move with other joints,
        ``contrast_move`` the joint's move count of each."""
        st = self._state[joint]
        return {
            "residual_ms": np.array(st.level.residual_s) * 1e3,
            "upper": np.array(st.level.up_hist),
            "lower": np.array(st.level.down_hist),
            "contrast_ms": np.array(st.contrast.residual_s) * 1e3,
            "contrast_upper": np.array(st.contrast.up_hist),
            "contrast_lower": np.array(st.contrast.down_hist),
            "contrast_move": np.array(st.contrast_move),
        }

    def verdict(self) -> str:
        """What the monitor can say now: ``"alarm"`` (an alert fired), ``"ok"`` (at least
        one joint past its warm-up and no alert), ``"warming up"`` (moves measured, but no
        joint has its reference yet: no change could have been detected) or ``"nothing
        measured"`` (no move from rest with a measurable lag). Only ``"ok"`` is an all-clear.
        """
        if self.alerts:
            return "alarm"
        states = self.states()
        if not any(st.moves for st in states):
            return "nothing measured"
        if all(st.warm is None for st in states):
            return "warming up"
        return "ok"

    def summary(self) -> dict[str, Any]:
        """JSON-safe state: the verdict (:meth:`verdict`), settings, per joint status, and
        the alerts."""
        joints = []
        for st in self.states():
            row: dict[str, Any] = {
                "joint": st.joint,
                "status": st.status,
                "moves": st.moves,
                "skipped": st.skipped,
                "upper": st.level.up,
                "lower": st.level.down,
            }
            if st.warm is not None:
                row.update(_cusum_summary(st.level, self.warmup_moves))
            if st.contrast.warm is not None:
                row["contrast"] = {
                    "moves": st.contrast.n,
                    "upper": st.contrast.up,
                    "lower": st.contrast.down,
                    **_cusum_summary(st.contrast, self.warmup_moves),
                }
            if st.alarm is not None:
                row["alert"] = st.alarm.to_dict()
            hist = self.history(st.joint)
            # the statistics over moves, for the monitor figure (rounded: a figure's worth)
            row["history"] = {
                k: np.round(hist[k], 3).tolist()
                for k in ("upper", "lower", "contrast_upper", "contrast_lower", "contrast_move")
            }
            joints.append(row)
        return {
            "verdict": self.verdict(),
            "warmup_moves": self.warmup_moves,
            "reference_k": self.reference_k,
            "score_clip": SCORE_CLIP,
            "threshold": self.threshold,
            "arl0_moves": self.arl0_moves,
            "nominal_arl0_moves": self.nominal_arl0_moves,
            "false_alarm_rate_per_move": 1.0 / self.arl0_moves,
            "joints": joints,
            "alerts": [a.to_dict() for a in self.alerts],
        }
