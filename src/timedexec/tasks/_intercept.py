"""Interception: the tool where a moving object will be, by a chosen time.

An object moves on a known trajectory; the robot must have its tool at the object's
position at a chosen time. :func:`intercept` solves the position inverse kinematics for the
meeting point, asks :meth:`~timedexec.execution.TimedExecutor.plan_to_meet` for the latest
plan that arrives by the meeting time with the requested probability, and runs it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.drivers import RobotState
from timedexec.errors import ConfigError
from timedexec.execution import ExecutionResult, MeetPlan, TimedExecutor
from timedexec.robots import RobotSpec, check_configuration, forward_kinematics
from timedexec.tasks._truth import physical_probe

__all__ = ["InterceptResult", "intercept", "solve_position_ik"]


def solve_position_ik(
    spec: RobotSpec,
    target_m: ArrayLike,
    q_seed_rad: ArrayLike,
    *,
    joints: tuple[int, ...] = (1, 2, 3),
    tol_m: float = 1e-5,
) -> FloatArray:
    """Joint angles that put the flange origin at ``target_m`` (base frame, m).

    Damped least squares on ``joints`` (others stay at the seed), inside the joint limits.

    Raises
    ------
    ConfigError
        If no solution within ``tol_m`` is found from this seed (target out of reach).
    """
    from scipy.optimize import least_squares

    target = np.asarray(target_m, dtype=float).reshape(3)
    seed = check_configuration(spec, q_seed_rad).astype(float)
    idx = np.asarray(joints) - 1

    def residual(x: FloatArray) -> FloatArray:
        q = seed.copy()
        q[idx] = x
        return np.asarray(forward_kinematics(spec, q)[6, :3, 3] - target)

    lo = np.asarray(spec.q_min_rad)[idx]
    hi = np.asarray(spec.q_max_rad)[idx]
    sol = least_squares(residual, np.clip(seed[idx], lo, hi), bounds=(lo, hi), xtol=1e-12)
    err = float(np.linalg.norm(sol.fun))
    if err > tol_m:
        raise ConfigError(
            f"no joint configuration puts the flange at {target.round(4).tolist()} m from this "
            f"seed (closest {err * 1e3:.1f} mm away); the point is out of reach"
        )
    q = seed.copy()
    q[idx] = sol.x
    return q


@dataclass(frozen=True)
class InterceptResult:
    """Outcome of :func:`intercept`.

    Attributes
    ----------
    meet_time_s : float
        Chosen meeting time (host clock), s.
    meet : MeetPlan
        The plan (arrival bounds, probability, first send time).
    target_q_rad : ndarray (6,)
        Meeting configuration.
    distance_m : float
        Tool-object distance at the meeting time, m (physical for ``sim://`` drivers, else
        from the executor's estimate).
    arrival_s : float
        When the tool came within ``arrival_tol_m`` of the meeting point and stayed, s
        (NaN: never).
    physical : bool
        Whether the figures are the simulator's physical truth.
    """

    meet_time_s: float
    meet: MeetPlan
    target_q_rad: FloatArray
    distance_m: float
    arrival_s: float
    physical: bool
    execution: ExecutionResult = field(repr=False)

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        return {
            "meet_time_s": self.meet_time_s,
            "distance_mm": self.distance_m * 1e3,
            "arrival_before_meet_ms": (self.meet_time_s - self.arrival_s) * 1e3,
            "probability": self.meet.probability,
            "physical": self.physical,
        }


def intercept(
    executor: TimedExecutor,
    object_position: Callable[[float], ArrayLike],
    meet_time_s: float,
    *,
    confidence: float = 0.95,
    arrival_tol_m: float = 0.002,
) -> InterceptResult:
    """Put the tool where the object will be at ``meet_time_s`` (host clock), by then.

    ``object_position(t)`` gives the object's position (m, base frame) at host time ``t``.

    Raises
    ------
    ConfigError, UnreachableError
        Before any motion, if the point is out of reach, outside the limits or cannot be
        reached in time at ``confidence`` (the message says by how much it misses).
    """
    spec = executor.spec
    point = np.asarray(object_position(meet_time_s), dtype=float)
    q0 = executor.estimate().q_rad
    q_target = solve_position_ik(spec, point, q0)
    meet = executor.plan_to_meet(q_target, meet_time_s, confidence)
    probe = physical_probe(executor)
    samples: list[tuple[float, FloatArray]] = []

    def record(state: RobotState) -> None:
        if probe is not None:
            samples.append(probe())
        else:
            t = executor.now()
            samples.append((t, executor.estimate(t).q_rad))

    result = executor.execute(meet, until_s=meet_time_s + 0.05, on_step=record)
    t = np.asarray([s[0] for s in samples])
    q = np.asarray([s[1] for s in samples])
    tool = forward_kinematics(spec, q)[:, 6, :3, 3]
    dist = np.linalg.norm(tool - point, axis=1)
    k = int(np.searchsorted(t, meet_time_s))
    k = min(max(k, 0), len(t) - 1)
    if k > 0 and t[k] != meet_time_s:
        f = (meet_time_s - t[k - 1]) / (t[k] - t[k - 1])
        tool_at = (1 - f) * tool[k - 1] + f * tool[k]
    else:
        tool_at = tool[k]
    obj_at = point
    far = np.flatnonzero(dist > arrival_tol_m)
    arrival = float(t[far[-1] + 1]) if len(far) and far[-1] + 1 < len(t) else math.nan
    if not len(far):
        arrival = float(t[0])
    return InterceptResult(
        meet_time_s=float(meet_time_s),
        meet=meet,
        target_q_rad=q_target,
        distance_m=float(np.linalg.norm(tool_at - obj_at)),
        arrival_s=arrival,
        physical=probe is not None,
        execution=result,
    )
