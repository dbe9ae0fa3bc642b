"""A ROS ``JointTrajectory`` as a :class:`~timedexec.execution.JointPlan`, interpolated as
ros2_control's joint_trajectory_controller does (no rclpy needed).

joint_trajectory_controller (JTC) samples a trajectory piecewise between its points, by
what both ends of a segment carry: positions only, linear; positions and velocities, a
cubic; positions, velocities and accelerations, a quintic. Before the first point it
interpolates from the state at the trajectory's start (here: the arm at rest where it is)
to the first point, the same way; after the last point it holds the last point. This module
builds that piecewise polynomial once (:class:`PointsTrajectory`, Ruckig's ``duration`` /
``at_time`` interface, which is what a ``JointPlan`` uses of a trajectory) and checks it
against the robot's limits before anything moves (:func:`plan_from_points`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec._validation import N_JOINTS
from timedexec.errors import ConfigError
from timedexec.execution import JointPlan
from timedexec.robots import RobotSpec

__all__ = ["PointsTrajectory", "order_joints", "plan_from_points", "spline_kind"]


#: Grid on which a trajectory is checked against the limits, s (the e-Series cycle; the
#: CB3's 8 ms cycle sees a smoother command than this).
CHECK_STEP_S = 0.002
#: Slack on the spec's speed and acceleration limits when checking a received trajectory
#: (a spline sampled from a limit-respecting plan overshoots it by rounding only).
LIMIT_SLACK = 1.02


def spline_kind(has_velocities: bool, has_accelerations: bool) -> str:
    """JTC's interpolation for points that carry these fields: ``"linear"`` (positions),
    ``"cubic"`` (and velocities), ``"quintic"`` (and accelerations)."""
    if has_velocities and has_accelerations:
        return "quintic"
    return "cubic" if has_velocities else "linear"


def _coefficients(
    kind: str,
    T: float,
    p0: FloatArray,
    v0: FloatArray,
    a0: FloatArray,
    p1: FloatArray,
    v1: FloatArray,
    a1: FloatArray,
) -> FloatArray:
    """Polynomial coefficients c0..c5 (rows) of one segment of duration ``T`` > 0, (6, 6)."""
    c = np.zeros((6, N_JOINTS))
    c[0] = p0
    if kind == "linear":
        c[1] = (p1 - p0) / T
        return c
    c[1] = v0
    if kind == "cubic":  # Hermite: positions and speeds at both ends
        c[2] = (3.0 * (p1 - p0) - (2.0 * v0 + v1) * T) / T**2
        c[3] = (2.0 * (p0 - p1) + (v0 + v1) * T) / T**3
        return c
    # quintic: positions, speeds and accelerations at both ends
    c[2] = 0.5 * a0
    c[3] = (20.0 * (p1 - p0) - (8.0 * v1 + 12.0 * v0) * T - (3.0 * a0 - a1) * T**2) / (2 * T**3)
    c[4] = (30.0 * (p0 - p1) + (14.0 * v1 + 16.0 * v0) * T + (3.0 * a0 - 2.0 * a1) * T**2) / (
        2 * T**4
    )
    c[5] = (12.0 * (p1 - p0) - 6.0 * (v1 + v0) * T - (a0 - a1) * T**2) / (2 * T**5)
    return c


class PointsTrajectory:
    """Trajectory points joined as joint_trajectory_controller joins them.

    Parameters
    ----------
    q_start_rad : array_like (6,)
        The arm's position at plan time 0 (at rest), rad.
    times_s : array_like (n,)
        Each point's ``time_from_start``, s, strictly increasing, >= 0.
    positions_rad : array_like (n, 6)
    velocities_rad_s, accelerations_rad_s2 : array_like (n, 6) or None
        As the points carry them (None: the points have none).

    Attributes
    ----------
    duration : float
        The last point's ``time_from_start``, s (Ruckig's name: :class:`JointPlan` reads it).
    kind : str
        ``"linear"``, ``"cubic"`` or ``"quintic"`` (:func:`spline_kind`).
    """

    def __init__(
        self,
        q_start_rad: ArrayLike,
        times_s: ArrayLike,
        positions_rad: ArrayLike,
        velocities_rad_s: ArrayLike | None = None,
        accelerations_rad_s2: ArrayLike | None = None,
    ) -> None:
        t = np.asarray(times_s, dtype=float).reshape(-1)
        p = np.asarray(positions_rad, dtype=float).reshape(len(t), N_JOINTS)
        self.kind = spline_kind(velocities_rad_s is not None, accelerations_rad_s2 is not None)
        zeros = np.zeros_like(p)
        v = (
            zeros
            if velocities_rad_s is None
            else np.asarray(velocities_rad_s, float).reshape(p.shape)
        )
        a = zeros if accelerations_rad_s2 is None else np.asarray(accelerations_rad_s2, float).reshape(p.shape)  # fmt: skip
        q0 = np.asarray(q_start_rad, dtype=float)
        if len(t) == 0 or not np.all(np.isfinite(t)) or t[0] < 0 or np.any(np.diff(t) <= 0):
            raise ConfigError(
                f"time_from_start {t.tolist()!r} s: give at least one point, times >= 0 and "
                "strictly increasing"
            )
        for name, arr in (("positions", p), ("velocities", v), ("accelerations", a)):
            if not np.all(np.isfinite(arr)):
                raise ConfigError(
                    f"trajectory {name} hold a value that is not finite; send numbers"
                )
        # Knots: the start state (at rest) unless the first point is at time 0.
        if t[0] > 0:
            t = np.concatenate([[0.0], t])
            p = np.vstack([q0, p])
            v = np.vstack([np.zeros(N_JOINTS), v])
            a = np.vstack([np.zeros(N_JOINTS), a])
        self.knots_s = t
        self.duration = float(t[-1])
        self.q_end_rad = p[-1].copy()
        self.qd_end_rad_s = v[-1].copy()
        self.qdd_end_rad_s2 = a[-1].copy()
        self.q_first_rad = p[0].copy()
        self.qd_first_rad_s = v[0].copy()
        self._coef = np.stack(
            [
                _coefficients(self.kind, float(t[i + 1] - t[i]), p[i], v[i], a[i], p[i + 1], v[i + 1], a[i + 1])
                for i in range(len(t) - 1)
            ]
        ) if len(t) > 1 else np.zeros((0, 6, N_JOINTS))  # fmt: skip

    def at_time(self, t_s: float) -> tuple[list[float], list[float], list[float]]:
        """Position, velocity and acceleration at plan time ``t_s`` (held outside
        ``0 .. duration``), lists of 6."""
        if len(self._coef) == 0 or t_s >= self.duration:
            return self.q_end_rad.tolist(), self.qd_end_rad_s.tolist(), self.qdd_end_rad_s2.tolist()
        if t_s <= 0.0:
            return self.q_first_rad.tolist(), self.qd_first_rad_s.tolist(), [0.0] * N_JOINTS
        i = int(np.searchsorted(self.knots_s, t_s, side="right")) - 1
        c = self._coef[i]
        s = t_s - self.knots_s[i]
        q = ((((c[5] * s + c[4]) * s + c[3]) * s + c[2]) * s + c[1]) * s + c[0]
        v = (((5 * c[5] * s + 4 * c[4]) * s + 3 * c[3]) * s + 2 * c[2]) * s + c[1]
        acc = ((20 * c[5] * s + 12 * c[4]) * s + 6 * c[3]) * s + 2 * c[2]
        return q.tolist(), v.tolist(), acc.tolist()


def order_joints(names: Sequence[str], robot_names: Sequence[str]) -> NDArray[np.int64]:
    """Column order that maps a message's joints onto the robot's: ``index[k]`` is the
    message column of robot joint ``k``.

    Raises
    ------
    ConfigError
        The message does not name each of the robot's six joints exactly once.
    """
    names = list(names)
    if sorted(names) != sorted(robot_names):
        raise ConfigError(
            f"joint_names {names!r} are not the robot's {list(robot_names)!r} (each once, any "
            "order); send every joint (a partial trajectory is not followed)"
        )
    return np.array([names.index(n) for n in robot_names], dtype=np.int64)


def plan_from_points(
    spec: RobotSpec,
    q_start_rad: ArrayLike,
    times_s: ArrayLike,
    positions_rad: ArrayLike,
    velocities_rad_s: ArrayLike | None = None,
    accelerations_rad_s2: ArrayLike | None = None,
) -> JointPlan:
    """An unscheduled :class:`JointPlan` that follows trajectory points from rest at
    ``q_start_rad`` as joint_trajectory_controller interpolates them.

    Returns
    -------
    JointPlan
        Plan time 0 is the trajectory's ``header.stamp``; schedule it with ``plan.at``.

    Raises
    ------
    ConfigError
        Malformed points; a trajectory that ends moving; or one the robot cannot follow:
        a position outside the joint limits, a speed or an acceleration (including a jump
        in speed where linear segments meet or leave rest) above the spec's limits. The
        message names the joint, the time, the value and the limit.
    """
    traj = PointsTrajectory(
        q_start_rad, times_s, positions_rad, velocities_rad_s, accelerations_rad_s2
    )
    if np.any(np.abs(traj.qd_end_rad_s) > 1e-9):
        raise ConfigError(
            f"the last point has velocities {traj.qd_end_rad_s.tolist()!r} rad/s: a trajectory "
            "must end at rest (joint_trajectory_controller holds the last point)"
        )
    n = max(2, math.ceil(traj.duration / CHECK_STEP_S) + 1)
    grid = np.linspace(0.0, traj.duration, n)
    q = np.empty((n, N_JOINTS))
    v = np.empty((n, N_JOINTS))
    for i, ti in enumerate(grid):
        qi, vi, _ = traj.at_time(float(ti))
        q[i], v[i] = qi, vi
    if n > 1:  # the speed inside the first segment, not the held start
        v[0] = traj.at_time(1e-9)[1]
    lo, hi = np.asarray(spec.q_min_rad), np.asarray(spec.q_max_rad)
    vmax, amax = np.asarray(spec.qd_max_rad_s), np.asarray(spec.qdd_max_rad_s2)
    _refuse_where(q < lo, grid, q, "position", lo, "rad", spec, "outside the joint range from")
    _refuse_where(q > hi, grid, q, "position", hi, "rad", spec, "outside the joint range to")
    _refuse_where(np.abs(v) > vmax * LIMIT_SLACK, grid, v, "speed", vmax, "rad/s", spec, "above the limit")  # fmt: skip
    # Accelerations as the controller sees them: speed changes between grid samples, from
    # rest before the start (a linear first segment steps its speed).
    dv = np.diff(np.vstack([np.zeros(N_JOINTS), v]), axis=0)
    dt = np.diff(np.concatenate([[grid[0] - CHECK_STEP_S], grid]))
    acc = dv / np.maximum(dt, CHECK_STEP_S)[:, None]
    _refuse_where(np.abs(acc) > amax * LIMIT_SLACK, grid, acc, "acceleration", amax, "rad/s²", spec, "above the limit")  # fmt: skip
    q0 = np.asarray(q_start_rad, dtype=float)
    return JointPlan(traj, q0, np.zeros(N_JOINTS), traj.q_end_rad.copy(), np.zeros(N_JOINTS))


def _refuse_where(
    bad: NDArray[np.bool_],
    grid: FloatArray,
    value: FloatArray,
    what: str,
    limit: FloatArray,
    unit: str,
    spec: RobotSpec,
    relation: str,
) -> None:
    if not bad.any():
        return
    i, j = (int(k) for k in np.argwhere(bad)[0])
    raise ConfigError(
        f"infeasible trajectory: joint {j + 1} {what} {value[i, j]:.6g} {unit} at "
        f"time_from_start {grid[i]:.3f} s is {relation} {limit[j]:.6g} {unit} of {spec.name}; "
        "send a slower trajectory (or one inside the limits)"
    )
