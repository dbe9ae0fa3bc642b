"""The deadline arithmetic: predicted delays of a plan, its timing bounds, ``plan_to_meet``.

:class:`PredictionCache` asks the delay model once per configuration and directions;
:func:`prepare_plan` attaches the predictions of a plan's start configuration to the plan
(``plan.meta``); :func:`onset_bounds` and :func:`arrival_bounds` turn a prepared, scheduled
plan into :class:`~timedexec.execution.TimingBounds`; :func:`meet_deadline` schedules a
prepared plan so that it arrives by a deadline with a given probability (:class:`MeetPlan`).
All of it is arithmetic on the plan and the predictions: no driver, no loop state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError, ModelError, UnreachableError
from timedexec.execution._bounds import TimingBounds, check_confidence, delay_cdf, delay_quantile
from timedexec.execution._model import DelayPredictions, DelayPredictor, predict_delays
from timedexec.execution._plan import JointPlan

__all__ = [
    "CACHE_DECIMALS",
    "CACHE_SIZE",
    "MeetPlan",
    "PredictionCache",
    "arrival_bounds",
    "check_start",
    "execution_end_s",
    "meet_deadline",
    "onset_bounds",
    "plan_lead_s",
    "prepare_plan",
    "require_scheduled",
]


#: Configurations are cached to this many decimals of a radian (4: 0.1 mrad).
CACHE_DECIMALS = 4
#: The cache is emptied once it holds more than this many entries.
CACHE_SIZE = 256
#: Joints a model covers when it does not say (a sweep of joints 1, 2, 3, 5).
_DEFAULT_JOINTS = (1, 2, 3, 5)


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


class PredictionCache:
    """A delay model's predictions for all six joints, cached per configuration.

    A model query may take milliseconds and a plan is prepared more than once, so
    predictions are kept per configuration (rounded to :data:`CACHE_DECIMALS` decimals of a
    radian) and directions; the cache is emptied once it holds more than
    :data:`CACHE_SIZE` entries.

    Parameters
    ----------
    model : DelayPredictor
        The delay model (already loaded).
    """

    def __init__(self, model: DelayPredictor) -> None:
        self.model = model
        self._cache: dict[tuple[bytes, bytes], DelayPredictions] = {}

    def predict(self, q_rad: ArrayLike, directions: ArrayLike | None = None) -> DelayPredictions:
        """Predicted delays of joints 1..6 at ``q_rad`` (6,), rad, for ``directions`` (6,)
        (+1/-1; default all +1), s.

        Joints the model does not cover (a sweep of joints 1, 2, 3, 5) get the mean of the
        covered joints' predictions.
        """
        q = np.asarray(q_rad, dtype=float).reshape(6)
        d = np.ones(6, np.int64) if directions is None else np.asarray(directions, np.int64)
        key = (np.round(q, CACHE_DECIMALS).tobytes(), d.tobytes())
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        out = self._predict_uncached(q, d)
        if len(self._cache) > CACHE_SIZE:
            self._cache.clear()
        self._cache[key] = out
        return out

    def response_s(self, q_rad: ArrayLike) -> float:
        """The response delay to back-date states by at ``q_rad``: the median over the
        joints of the predicted mean, s."""
        return float(np.median(self.predict(q_rad).response_mean))

    def _predict_uncached(self, q: FloatArray, d: NDArray[np.int64]) -> DelayPredictions:
        joints = np.arange(1, 7)
        try:
            return predict_delays(self.model, joints, d, np.tile(q, (6, 1)))
        except (ConfigError, ModelError, KeyError, IndexError, ValueError):
            covered = np.array(getattr(self.model, "joints", _DEFAULT_JOINTS), dtype=np.int64)
            part = predict_delays(
                self.model, covered, d[covered - 1], np.tile(q, (len(covered), 1))
            )
            out = {}
            for name in ("actuation_mean", "actuation_std", "response_mean", "response_std"):
                v = getattr(part, name)
                full = np.full(6, float(np.mean(v)))
                full[covered - 1] = v
                out[name] = full
            return DelayPredictions(**out)


def prepare_plan(plan: JointPlan, predictions: PredictionCache, *, compensate: bool) -> JointPlan:
    """``plan`` with the predicted delays of its start configuration and directions.

    Parameters
    ----------
    plan : JointPlan
        Scheduled or not; a plan that already carries ``actuation_s`` is returned as is.
    predictions : PredictionCache
        Where the predictions come from.
    compensate : bool
        False: the shift ``actuation_s`` is zero (the "none" strategy); the prediction is
        still attached as ``predicted_actuation_s``.

    Returns
    -------
    JointPlan
        A copy whose ``meta`` holds ``actuation_s`` (6,) (the shift applied to each joint's
        command stream: the predicted actuation delay of a moving joint, else 0), s;
        ``predicted_actuation_s`` (6,), s; ``actuation_std_s`` (6,) (single trial), s;
        ``response_s`` (the median predicted response delay), s; ``directions`` (6,);
        ``moving`` (6,) bool.
    """
    if "actuation_s" in plan.meta:
        return plan
    dirs = plan.directions()
    p = predictions.predict(plan.q_start_rad, dirs)
    out = plan.at(plan.start_time_s)
    moving = plan.moving_joints()
    out.meta.update(
        actuation_s=np.where(moving, p.actuation_mean, 0.0) if compensate else np.zeros(6),
        predicted_actuation_s=p.actuation_mean,
        actuation_std_s=p.actuation_std,
        response_s=float(np.median(p.response_mean)),
        directions=dirs,
        moving=moving,
    )
    return out


def require_scheduled(plan: JointPlan | None) -> JointPlan:
    """``plan``, if there is one and it is scheduled (a finite ``start_time_s``).

    Raises
    ------
    ConfigError
        No plan, or a plan not scheduled; the message says how to schedule it.
    """
    if plan is None:
        raise ConfigError("no plan: pass one (scheduled with plan.at(start_time_s))")
    if not math.isfinite(plan.start_time_s):
        raise ConfigError("the plan is not scheduled; use plan.at(start_time_s)")
    return plan


def plan_lead_s(plan: JointPlan) -> float:
    """How long before a prepared plan's start its first command must leave (the largest
    shift), s."""
    return float(np.max(plan.meta["actuation_s"]))


def execution_end_s(
    plan: JointPlan, *, until_s: float | None, settle_s: float | None, period_s: float
) -> float:
    """Host time an execution of a prepared, scheduled plan streams until, s: ``until_s``,
    else the plan's end plus ``settle_s`` (default: the largest shift plus three periods).

    Raises
    ------
    ConfigError
        No ``until_s`` for a plan that ends moving (a conveyor cruise), or an ``until_s``
        not after the plan's start (it used to return at once, having done nothing).
    """
    if until_s is not None:
        if until_s <= plan.start_time_s:
            raise ConfigError(
                f"until_s={until_s!r} is not after the plan's start at {plan.start_time_s!r} "
                "(host time, s): nothing would run; give a later until_s, or None to run "
                "until the plan has settled"
            )
        return until_s
    if np.any(plan.qd_end_rad_s != 0):
        raise ConfigError("this plan ends moving (a cruise); give until_s")
    settle = plan_lead_s(plan) + 3 * period_s if settle_s is None else settle_s
    return plan.end_time_s + settle


def check_start(plan: JointPlan, *, now_s: float, period_s: float) -> None:
    """Refuse a prepared, scheduled plan whose first command should have left already.

    The first command leaves on the next package (one period ``period_s`` after ``now_s``,
    s) and must leave :func:`plan_lead_s` before the plan's start.

    Raises
    ------
    ConfigError
        The start is too soon; the message says by how many milliseconds.
    """
    lead = plan_lead_s(plan)
    late = now_s + period_s - (plan.start_time_s - lead)
    if late > 0:
        raise ConfigError(
            f"start time too soon: the first command had to leave {late * 1e3:.1f} ms ago "
            f"(actuation delay {lead * 1e3:.1f} ms plus one period); start at least "
            f"{late * 1e3:.1f} ms later"
        )


def onset_bounds(
    plan: JointPlan,
    joint: int,
    confidence: float,
    period_s: float,
    *,
    level_rad_s: float | None = None,
) -> TimingBounds:
    """Interval (host time) in which ``joint``'s physical motion starts.

    Parameters
    ----------
    plan : JointPlan
        Prepared (:func:`prepare_plan`) and scheduled.
    joint : int
        1..6.
    confidence : float
        Probability of the central interval.
    period_s : float
        Controller period, s (the cycle quantisation of the bounds).
    level_rad_s : float, optional
        Speed that defines the onset, rad/s (default: 10 % of the joint's peak planned
        speed). The expected onset is the planned one plus the part of the predicted
        actuation delay not shifted away (all of it without compensation).

    Raises
    ------
    ConfigError
        ``joint`` outside 1..6, or a joint that does not move in this plan.
    """
    if joint not in range(1, 7):
        raise ConfigError(f"joint={joint!r} outside 1..6")
    t_on = plan.onset_times(level_rad_s)[joint - 1]
    if not math.isfinite(t_on):
        raise ConfigError(f"joint {joint} does not move in this plan")
    late = plan.meta["predicted_actuation_s"][joint - 1] - plan.meta["actuation_s"][joint - 1]
    return TimingBounds.around(
        plan.start_time_s + t_on + late,
        plan.meta["actuation_std_s"][joint - 1],
        confidence,
        period_s,
    )


def arrival_bounds(plan: JointPlan, confidence: float, period_s: float) -> TimingBounds:
    """Per joint (6,): interval (host time, s) in which each joint reaches its planned end
    state; ``plan`` prepared and scheduled, ``period_s`` the controller period, s. A joint
    that does not move "arrives" at the plan's start with zero spread."""
    late = plan.meta["predicted_actuation_s"] - plan.meta["actuation_s"]
    expected = np.where(plan.meta["moving"], plan.end_time_s + late, plan.start_time_s)
    std = np.where(plan.meta["moving"], plan.meta["actuation_std_s"], 0.0)
    return TimingBounds.around(expected, std, confidence, period_s)


def meet_deadline(
    plan: JointPlan,
    deadline_s: float,
    confidence: float,
    *,
    now_s: float,
    period_s: float,
) -> MeetPlan:
    """Schedule a prepared plan to arrive by ``deadline_s`` with probability ``confidence``.

    The plan of duration ``D`` starts at ``deadline - D - u``, ``u`` the ``confidence``
    quantile of the slowest moving joint's timing error; its first command leaves ``max
    tau`` earlier. The earliest possible start is ``now_s + max tau + 2 T``: the first
    command leaves on the next package (one period ``T``), plus one period of safety.

    Parameters
    ----------
    plan : JointPlan
        Prepared (:func:`prepare_plan`), not necessarily scheduled.
    deadline_s : float
        Host time by which the target must be reached, s.
    confidence : float
        Probability in (0, 1).
    now_s : float
        The host time now, s.
    period_s : float
        Controller period, s.

    Raises
    ------
    ConfigError
        No joint moves in ``plan``, or the deadline is not finite.
    UnreachableError
        Even sending now, the robot would arrive late at this confidence; the message
        says by how many milliseconds (``miss_s``).
    """
    c = check_confidence(confidence)
    moving = plan.meta["moving"]
    if not moving.any():
        raise ConfigError("the robot is already at the target; nothing to plan")
    if not math.isfinite(deadline_s):
        raise ConfigError(f"deadline_s={deadline_s!r} must be a finite host time, s")
    tau = plan.meta["actuation_s"]
    std = plan.meta["actuation_std_s"]
    u = np.where(moving, delay_quantile(np.full(6, c), std, period_s), -np.inf)
    margin = float(np.max(u))
    latest_start = float(deadline_s) - plan.duration_s - margin
    lead = float(np.max(np.where(moving, tau, 0.0)))
    earliest_start = now_s + lead + 2.0 * period_s
    if latest_start < earliest_start:
        miss = earliest_start - latest_start
        raise UnreachableError(
            f"cannot reach the target by the deadline with probability {c:g}: it misses by "
            f"{miss * 1e3:.1f} ms (motion {plan.duration_s * 1e3:.1f} ms, actuation delay "
            f"up to {lead * 1e3:.1f} ms, {c:g} timing margin {margin * 1e3:.1f} ms, "
            f"deadline in {(deadline_s - now_s) * 1e3:.1f} ms); move the deadline "
            f"{miss * 1e3:.1f} ms later, lower the confidence or choose a closer target",
            miss_s=miss,
        )
    scheduled = plan.at(latest_start)
    arrival = arrival_bounds(scheduled, c, period_s)
    cdf = delay_cdf(float(deadline_s) - scheduled.end_time_s, std, period_s)
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
