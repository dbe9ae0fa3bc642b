"""Jerk-limited joint trajectories with Ruckig, inside the robot spec's limits.

Ruckig (community build) plans time-optimal jerk-limited motions between states; it ignores
position limits (a Pro feature), so :func:`plan_motion` checks the planned position extrema
itself. A :class:`JointPlan` is a Ruckig trajectory with a time origin: it can be sampled at
any time, before its start (the start state, held) and after its end (the end state,
extrapolated at the end velocity: a conveyor cruise).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec._validation import check_joint_array, check_known_keys
from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec

__all__ = ["ExecutionLimits", "JointPlan", "check_target", "plan_motion"]


#: Planned positions stay this far inside the joint limits, rad.
POSITION_MARGIN_RAD = 1e-6


@dataclass(frozen=True, kw_only=True)
class ExecutionLimits:
    """Fractions of the spec's limits the executor plans and commands with.

    Parameters
    ----------
    velocity_fraction, acceleration_fraction : float
        Fraction of the spec's joint speed and acceleration limits, in (0, 1].
    jerk_per_acceleration_1_s : float
        Jerk limit per joint as a multiple of its acceleration limit, 1/s (200: the full
        acceleration is reached in 5 ms, close to the constant-acceleration ramps the delay
        models were calibrated with).
    acceleration_cap_rad_s2 : float or None
        Upper bound on every joint's planned acceleration, rad/s². Default 8: the ramp of
        the calibration sweeps the delay models learned from. The actuation delay depends
        on the ramp (a joint breaks away sooner when its reference rises faster): on the
        simulated KR 5 a 15 rad/s² start moves the onset 3.8 ms earlier than the model
        predicts, a 8 rad/s² start 0.6-0.9 ms (``tests/test_execution.py``). None: the
        spec's limits.
    """

    velocity_fraction: float = 1.0
    acceleration_fraction: float = 1.0
    jerk_per_acceleration_1_s: float = 200.0
    acceleration_cap_rad_s2: float | None = 8.0

    def __post_init__(self) -> None:
        for name in ("velocity_fraction", "acceleration_fraction"):
            v = float(getattr(self, name))
            if not 0.0 < v <= 1.0:
                raise ConfigError(f"ExecutionLimits.{name}={v!r} outside (0, 1]")
        cap = self.acceleration_cap_rad_s2
        if cap is not None and not (math.isfinite(cap) and cap > 0):
            raise ConfigError(
                f"ExecutionLimits.acceleration_cap_rad_s2={cap!r} must be > 0 or None"
            )
        if not self.jerk_per_acceleration_1_s > 0:
            raise ConfigError(
                f"ExecutionLimits.jerk_per_acceleration_1_s={self.jerk_per_acceleration_1_s!r} "
                "must be > 0"
            )

    def position_range(self, spec: RobotSpec) -> tuple[FloatArray, FloatArray]:
        """Joint positions planned motions keep within, rad, (6,) each: the spec's limits
        less :data:`POSITION_MARGIN_RAD` (Ruckig ignores position limits; a planner checks
        its trajectory's extrema against these)."""
        lo = np.asarray(spec.q_min_rad) + POSITION_MARGIN_RAD
        hi = np.asarray(spec.q_max_rad) - POSITION_MARGIN_RAD
        return lo, hi

    def velocity(self, spec: RobotSpec) -> FloatArray:
        """Joint speed limits to plan with, rad/s, shape (6,)."""
        return np.asarray(spec.qd_max_rad_s) * self.velocity_fraction

    def acceleration(self, spec: RobotSpec) -> FloatArray:
        """Joint acceleration limits to plan with, rad/s², shape (6,)."""
        a = np.asarray(spec.qdd_max_rad_s2) * self.acceleration_fraction
        cap = self.acceleration_cap_rad_s2
        return a if cap is None else np.minimum(a, cap)

    def jerk(self, spec: RobotSpec) -> FloatArray:
        """Joint jerk limits, rad/s³, shape (6,)."""
        return self.acceleration(spec) * self.jerk_per_acceleration_1_s

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        return {
            "velocity_fraction": self.velocity_fraction,
            "acceleration_fraction": self.acceleration_fraction,
            "jerk_per_acceleration_1_s": self.jerk_per_acceleration_1_s,
            "acceleration_cap_rad_s2": self.acceleration_cap_rad_s2,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ExecutionLimits:
        """Inverse of :meth:`to_dict` (unknown keys: :class:`ConfigError`)."""
        check_known_keys(cls, d)
        return cls(**d)


def check_target(
    spec: RobotSpec, q_rad: ArrayLike, qd_rad_s: ArrayLike | None = None, *, what: str = "target"
) -> tuple[FloatArray, FloatArray]:
    """Validate a target state against the spec's position and speed limits.

    Raises
    ------
    ConfigError
        Naming the joint, the value and the allowed range.
    """
    q = check_joint_array(f"{what} position", q_rad)
    qd = np.zeros(6) if qd_rad_s is None else check_joint_array(f"{what} velocity", qd_rad_s)
    lo, hi = np.asarray(spec.q_min_rad), np.asarray(spec.q_max_rad)
    for j in range(6):
        if not lo[j] <= q[j] <= hi[j]:
            raise ConfigError(
                f"{what}: joint {j + 1} position {q[j]:.6g} rad ({math.degrees(q[j]):.2f}°) is "
                f"outside the range [{lo[j]:.6g}, {hi[j]:.6g}] rad of {spec.name}; choose a "
                "target inside the joint limits"
            )
    vmax = np.asarray(spec.qd_max_rad_s)
    for j in range(6):
        if abs(qd[j]) > vmax[j]:
            raise ConfigError(
                f"{what}: joint {j + 1} velocity {qd[j]:.6g} rad/s is outside the range "
                f"[{-vmax[j]:.6g}, {vmax[j]:.6g}] rad/s of {spec.name}; choose a slower target"
            )
    return q, qd


@dataclass(frozen=True)
class JointPlan:
    """A planned joint trajectory with its time origin (plan time 0 = ``start_time_s``).

    Attributes
    ----------
    trajectory : ruckig.Trajectory
        The Ruckig trajectory (plan time 0 .. ``duration_s``).
    q_start_rad, qd_start_rad_s : ndarray (6,)
        Start state.
    q_end_rad, qd_end_rad_s : ndarray (6,)
        End state; after the end the plan continues at ``qd_end_rad_s`` (cruise).
    start_time_s : float
        Host time at which the physical motion should follow plan time 0, s (NaN until
        scheduled with :meth:`at`).
    """

    trajectory: Any
    q_start_rad: FloatArray
    qd_start_rad_s: FloatArray
    q_end_rad: FloatArray
    qd_end_rad_s: FloatArray
    start_time_s: float = math.nan
    meta: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def duration_s(self) -> float:
        """Duration of the planned transition, s."""
        return float(self.trajectory.duration)

    @property
    def end_time_s(self) -> float:
        """Host time at which the transition ends, s."""
        return self.start_time_s + self.duration_s

    def at(self, start_time_s: float) -> JointPlan:
        """The same plan scheduled to start at host time ``start_time_s``."""
        return JointPlan(
            self.trajectory,
            self.q_start_rad,
            self.qd_start_rad_s,
            self.q_end_rad,
            self.qd_end_rad_s,
            float(start_time_s),
            dict(self.meta),
        )

    def sample(self, t_plan_s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Position, velocity and acceleration at plan time ``t_plan_s`` (scalar), each (6,).

        Raises ConfigError for a time that is not finite (Ruckig's ``at_time`` crashes the
        process on NaN, and an unscheduled plan's ``start_time_s`` is NaN).
        """
        if not math.isfinite(t_plan_s):
            raise ConfigError(
                f"plan time must be finite, got {t_plan_s!r} s (a plan time is a host time minus "
                "start_time_s, which is NaN until the plan is scheduled with JointPlan.at)"
            )
        if t_plan_s <= 0.0:
            return (
                self.q_start_rad + self.qd_start_rad_s * t_plan_s,
                self.qd_start_rad_s,
                np.zeros(6),
            )
        d = self.duration_s
        if t_plan_s >= d:
            return (
                self.q_end_rad + self.qd_end_rad_s * (t_plan_s - d),
                self.qd_end_rad_s,
                np.zeros(6),
            )
        p, v, a = self.trajectory.at_time(float(t_plan_s))
        return np.asarray(p), np.asarray(v), np.asarray(a)

    def velocity_per_joint(self, t_plan_s: FloatArray) -> FloatArray:
        """Velocity of joint j at plan time ``t_plan_s[j]`` (per-joint times), rad/s, (6,)."""
        out = np.empty(6)
        cache: dict[float, FloatArray] = {}
        for j in range(6):
            t = float(t_plan_s[j])
            if t not in cache:
                cache[t] = self.sample(t)[1]
            out[j] = cache[t][j]
        return out

    def position_per_joint(self, t_plan_s: FloatArray) -> FloatArray:
        """Position of joint j at plan time ``t_plan_s[j]``, rad, (6,)."""
        out = np.empty(6)
        for j in range(6):
            out[j] = self.sample(float(t_plan_s[j]))[0][j]
        return out

    def sample_many(self, t_plan_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Positions and velocities at many plan times, shapes (n, 6)."""
        t = np.atleast_1d(np.asarray(t_plan_s, dtype=float))
        q = np.empty((len(t), 6))
        v = np.empty((len(t), 6))
        for i, ti in enumerate(t):
            q[i], v[i], _ = self.sample(float(ti))
        return q, v

    def moving_joints(self, *, tol_rad: float = 1e-9) -> NDArray[np.bool_]:
        """Joints that move during the plan (displacement or end speed), (6,)."""
        return np.asarray(
            (np.abs(self.q_end_rad - self.q_start_rad) > tol_rad)
            | (np.abs(self.qd_end_rad_s) > 0)
            | (np.abs(self.qd_start_rad_s) > 0)
        )

    def directions(self) -> NDArray[np.int64]:
        """Direction (+1/-1) of each joint's first motion (+1 for still joints), (6,)."""
        out = np.ones(6, dtype=np.int64)
        n = max(8, int(self.duration_s / 0.002) + 2)
        _, v = self.sample_many(np.linspace(0.0, max(self.duration_s, 1e-6), n))
        for j in range(6):
            nz = np.flatnonzero(np.abs(v[:, j]) > 1e-9)
            if len(nz):
                out[j] = 1 if v[nz[0], j] > 0 else -1
        return out

    def onset_times(self, level_rad_s: ArrayLike | None = None) -> FloatArray:
        """Plan time at which each joint's speed first reaches ``level_rad_s``, s (6,).

        Default level: :data:`timedexec._signal.ONSET_FRACTION` of the joint's peak planned
        speed (the onset definition of the delay models). NaN for joints that do not move.
        """
        from timedexec._signal import ONSET_FRACTION

        d = max(self.duration_s, 1e-6)
        t = np.linspace(0.0, d, max(64, int(d / 0.0002) + 1))
        _, v = self.sample_many(t)
        speed = np.abs(v)
        peak = np.maximum(speed.max(axis=0), np.abs(self.qd_end_rad_s))
        level = (
            ONSET_FRACTION * peak
            if level_rad_s is None
            else np.broadcast_to(np.asarray(level_rad_s, dtype=float), (6,))
        )
        out = np.full(6, np.nan)
        for j in range(6):
            if peak[j] <= 0 or not np.isfinite(level[j]):
                continue
            idx = np.flatnonzero(speed[:, j] >= level[j])
            if not len(idx):
                continue
            i = int(idx[0])
            if i == 0:
                out[j] = 0.0
                continue
            # Linear interpolation between the samples around the crossing.
            s0, s1 = speed[i - 1, j], speed[i, j]
            frac = (level[j] - s0) / (s1 - s0) if s1 > s0 else 0.0
            out[j] = t[i - 1] + frac * (t[i] - t[i - 1])
        return out


def plan_motion(
    spec: RobotSpec,
    limits: ExecutionLimits,
    q_start_rad: ArrayLike,
    target_q_rad: ArrayLike,
    *,
    qd_start_rad_s: ArrayLike | None = None,
    target_qd_rad_s: ArrayLike | None = None,
    minimum_duration_s: float | None = None,
) -> JointPlan:
    """Plan a time-optimal (or ``minimum_duration_s``-long), phase-synchronised jerk-limited
    motion with Ruckig's position interface.

    Raises
    ------
    ConfigError
        If the target is outside the joint or speed limits, or the planned motion would
        leave the joint limits (Ruckig ignores position limits; this checks the extrema).
    """
    from ruckig import InputParameter, Result, Ruckig, Synchronization, Trajectory

    q0 = check_joint_array("start position", q_start_rad)
    qd0 = (
        np.zeros(6)
        if qd_start_rad_s is None
        else check_joint_array("start velocity", qd_start_rad_s)
    )
    q1, qd1 = check_target(spec, target_q_rad, target_qd_rad_s)
    vmax, amax, jmax = limits.velocity(spec), limits.acceleration(spec), limits.jerk(spec)
    over = np.abs(qd1) > vmax * (1 + 1e-12)
    if over.any():
        j = int(np.flatnonzero(over)[0])
        raise ConfigError(
            f"target: joint {j + 1} velocity {qd1[j]:.6g} rad/s exceeds the planning limit "
            f"±{vmax[j]:.6g} rad/s ({limits.velocity_fraction:g} of {spec.name}'s limit)"
        )
    inp = InputParameter(6)
    inp.current_position = q0.tolist()
    inp.current_velocity = np.clip(qd0, -vmax, vmax).tolist()
    inp.current_acceleration = [0.0] * 6
    inp.target_position = q1.tolist()
    inp.target_velocity = qd1.tolist()
    inp.target_acceleration = [0.0] * 6
    inp.max_velocity = vmax.tolist()
    inp.max_acceleration = amax.tolist()
    inp.max_jerk = jmax.tolist()
    inp.synchronization = Synchronization.Phase
    if minimum_duration_s is not None:
        if not minimum_duration_s >= 0:
            raise ConfigError(f"minimum_duration_s={minimum_duration_s!r} must be >= 0")
        inp.minimum_duration = float(minimum_duration_s)
    traj = Trajectory(6)
    try:
        result = Ruckig(6).calculate(inp, traj)
    except Exception as exc:  # ruckig.RuckigError: invalid input
        raise ConfigError(f"Ruckig cannot plan this motion: {exc}") from exc
    if result not in (Result.Working, Result.Finished):
        # Phase synchronisation is not always possible; fall back to time synchronisation.
        inp.synchronization = Synchronization.Time
        result = Ruckig(6).calculate(inp, traj)
        if result not in (Result.Working, Result.Finished):
            raise ConfigError(f"Ruckig cannot plan this motion (result {result})")
    lo, hi = limits.position_range(spec)
    for j, ext in enumerate(traj.position_extrema):
        if ext.min < lo[j] - 1e-9 or ext.max > hi[j] + 1e-9:
            bad = ext.min if ext.min < lo[j] else ext.max
            raise ConfigError(
                f"the planned motion would take joint {j + 1} to {bad:.6g} rad, outside the "
                f"range [{spec.q_min_rad[j]:.6g}, {spec.q_max_rad[j]:.6g}] rad of {spec.name} "
                "(overshoot while braking); choose a target further inside the limits or a "
                "lower target velocity"
            )
    return JointPlan(traj, q0, qd0, q1, qd1)
