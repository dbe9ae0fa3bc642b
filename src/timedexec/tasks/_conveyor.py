"""Welding on a straight conveyor: the seam in space and time, and the joint plan that follows it.

Geometry (base frame, m; z up)
------------------------------
A **straight belt** (:class:`Conveyor`) carries the part at ``speed_m_s`` along a horizontal
unit vector ``direction``. The **seam** (:class:`Seam`) is a curve on the part's top face: in
the part's own frame (x along the belt, y to its left, z up) it starts at the origin with
its tangent at ``angle_rad`` to the belt (default 90°: across the belt) and is either
straight or an arc of ``radius_m``. The torch travels along it at ``weld_speed_m_s``
relative to the part, its orientation held. At host time ``t`` the seam point the torch must
be on is

    target(t) = start + direction · speed · (t - t_sync) + seam(weld_speed · (t - t_sync))

so the torch's speed in the world is the belt's plus the weld's, and a timing error ``δ``
of the arm puts the torch ``δ · (belt + weld velocity)`` off: across the seam for the belt
part (the seam runs across the belt), along it for the weld part.

The plan (:func:`plan_seam`)
----------------------------
The inverse kinematics (:func:`timedexec.robots.solve_ik`, full pose, warm-started sample
after sample on a 2 ms grid) turns the moving target into joint angles; a cubic spline per
joint gives positions, speeds and accelerations in between. Ruckig plans the approach: from
rest to the seam's joint state (position, speed *and* acceleration) at the meeting instant
``t_sync``, jerk-limited within the executor's limits; after the weld Ruckig brings every
joint to rest (velocity interface). The result is a :class:`~timedexec.execution.JointPlan`
that any :class:`~timedexec.execution.TimedExecutor` streams; every joint moves.

A :class:`WeldCell` fixes where the belt runs for a robot (the work point at the middle of
the weld, the torch pointing down, the belt passing across the robot's reach):
:func:`default_cell`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.execution import ExecutionLimits, JointPlan
from timedexec.robots import RobotSpec, get_robot, get_robot_entry, solve_ik, tool_pose

__all__ = [
    "SEAM_KINDS",
    "Conveyor",
    "Seam",
    "SeamPlan",
    "WeldCell",
    "default_cell",
    "plan_seam",
]


#: Seam shapes :class:`Seam` knows.
SEAM_KINDS = ("straight", "curved")

#: Sampling step of the inverse kinematics along the seam, s (a cubic spline in between:
#: its error is O(h⁴), far below a micrometre for these paths).
IK_STEP_S = 0.002


@dataclass(frozen=True, kw_only=True)
class Conveyor:
    """A straight belt.

    Parameters
    ----------
    direction : 3 floats
        Direction of travel in the base frame (made horizontal and unit length).
    speed_m_s : float
        Belt speed, m/s (> 0).
    """

    direction: tuple[float, float, float] = (0.0, 1.0, 0.0)
    speed_m_s: float = 0.5

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=float).reshape(-1)
        if d.shape != (3,) or not np.all(np.isfinite(d)):
            raise ConfigError(f"Conveyor.direction={self.direction!r} must be 3 finite numbers")
        d[2] = 0.0
        n = float(np.linalg.norm(d))
        if n < 1e-9:
            raise ConfigError(
                f"Conveyor.direction={self.direction!r} has no horizontal part; a belt runs "
                "horizontally (give x and y)"
            )
        object.__setattr__(self, "direction", tuple(float(x) for x in d / n))
        if not (math.isfinite(self.speed_m_s) and self.speed_m_s > 0):
            raise ConfigError(f"Conveyor.speed_m_s={self.speed_m_s!r} must be a speed > 0 m/s")

    @property
    def velocity_m_s(self) -> FloatArray:
        """Belt velocity (3,), m/s."""
        return np.asarray(self.direction) * self.speed_m_s


@dataclass(frozen=True, kw_only=True)
class Seam:
    """A seam on the part's top face, in the part's frame (x along the belt, y left, z up).

    Parameters
    ----------
    kind : {"straight", "curved"}
        A line, or an arc of ``radius_m`` turning left.
    angle_rad : float
        Angle of the seam's start tangent from the belt direction, rad (π/2: across the
        belt, the default).
    weld_speed_m_s : float
        Torch speed along the seam relative to the part, m/s (>= 0; 0.05 = 3 m/min).
    radius_m : float
        Radius of the curved seam, m (> 0).
    """

    kind: Literal["straight", "curved"] = "straight"
    angle_rad: float = math.pi / 2
    weld_speed_m_s: float = 0.05
    radius_m: float = 0.04

    def __post_init__(self) -> None:
        if self.kind not in SEAM_KINDS:
            raise ConfigError(f"Seam.kind={self.kind!r}; choose one of {', '.join(SEAM_KINDS)}")
        if not math.isfinite(self.angle_rad):
            raise ConfigError(f"Seam.angle_rad={self.angle_rad!r} must be finite")
        if not (math.isfinite(self.weld_speed_m_s) and self.weld_speed_m_s >= 0):
            raise ConfigError(f"Seam.weld_speed_m_s={self.weld_speed_m_s!r} must be >= 0 m/s")
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise ConfigError(f"Seam.radius_m={self.radius_m!r} must be > 0 m")

    def point(self, s_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Seam points and unit tangents at arc length ``s_m`` (n,), part frame: (n, 3) each.

        Before the start (``s < 0``) the seam continues straight along its start tangent.
        """
        s = np.atleast_1d(np.asarray(s_m, dtype=float))[:, None]
        a = self.angle_rad
        t0 = np.array([math.cos(a), math.sin(a), 0.0])
        n0 = np.array([-math.sin(a), math.cos(a), 0.0])
        if self.kind == "curved":
            phi = np.maximum(s, 0.0) / self.radius_m  # straight along t0 before the start
            sin, cos = np.sin(phi), np.cos(phi)
            p = np.where(s > 0, self.radius_m * (sin * t0 + (1.0 - cos) * n0), s * t0)
            return p, cos * t0 + sin * n0
        return s * t0, np.broadcast_to(t0, (len(s), 3)).copy()

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        return {
            "kind": self.kind,
            "angle_rad": self.angle_rad,
            "weld_speed_m_s": self.weld_speed_m_s,
            "radius_m": self.radius_m,
        }


@dataclass(frozen=True, kw_only=True)
class WeldCell:
    """Where the weld happens for one robot.

    Parameters
    ----------
    robot : str
        Robot spec name.
    work_point_m : 3 floats
        Torch tip at the middle of the measured cruise, base frame, m.
    torch_rotation : 3 x 3 nested floats
        Orientation of the torch (held), base frame; its z axis points out of the torch tip.
    tool_m : 3 floats
        Torch tip (TCP) in the flange frame, m.
    seed_q_rad : 6 floats
        A configuration near the work point: the inverse kinematics' branch (elbow, wrist).
    conveyor : Conveyor
    """

    robot: str
    work_point_m: tuple[float, float, float]
    torch_rotation: tuple[tuple[float, float, float], ...]
    tool_m: tuple[float, float, float] = (0.0, 0.0, 0.15)
    seed_q_rad: tuple[float, ...]
    conveyor: Conveyor = field(default_factory=Conveyor)

    @property
    def spec(self) -> RobotSpec:
        """The robot."""
        return get_robot(self.robot)

    def with_speed(self, speed_m_s: float) -> WeldCell:
        """The same cell with another belt speed, m/s."""
        conv = Conveyor(direction=self.conveyor.direction, speed_m_s=speed_m_s)
        return WeldCell(
            robot=self.robot,
            work_point_m=self.work_point_m,
            torch_rotation=self.torch_rotation,
            tool_m=self.tool_m,
            seed_q_rad=self.seed_q_rad,
            conveyor=conv,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        return {
            "robot": self.robot,
            "work_point_m": list(self.work_point_m),
            "torch_rotation": [list(r) for r in self.torch_rotation],
            "tool_m": list(self.tool_m),
            "seed_q_rad": list(self.seed_q_rad),
            "belt_direction": list(self.conveyor.direction),
            "belt_speed_m_s": self.conveyor.speed_m_s,
        }


#: Torch tilt from vertical of the built-in cells, rad, about a horizontal axis at 45° to
#: the belt: a push angle and a work angle together, as a torch is held on a fillet weld.
#: A vertical torch would leave a wrist joint still (the arm's plane contains the torch).
TORCH_TILT_RAD = math.radians(25.0)


def default_cell(
    robot: str, *, speed_m_s: float = 0.5, tilt_rad: float = TORCH_TILT_RAD
) -> WeldCell:
    """The built-in weld cell of a robot (see the module docstring), belt at ``speed_m_s``.

    The torch points down, tilted by ``tilt_rad`` (rad) about a horizontal axis at 45° to
    the belt; the work point is 0.2 m off the robot's centre line. Every joint moves; on
    the KR 5 joints 2 and 3, on the UR joint 4 reverse during the weld (the reach passes a
    minimum) and stick there for a moment (docs/welding.md).

    The seed pose and the work point are the robot's catalog entry's
    (:class:`~timedexec.robots.WorkCell`).

    Raises
    ------
    ConfigError
        For a robot the catalog does not hold.
    """
    entry = get_robot_entry(robot)
    spec, seed, point = entry.spec, entry.cell.seed_q_rad, entry.cell.work_point_m
    tool = (0.0, 0.0, 0.15)
    from scipy.spatial.transform import Rotation

    down = tool_pose(spec, np.asarray(seed), tool)[:3, :3]
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    rot = Rotation.from_rotvec(axis * tilt_rad).as_matrix() @ down
    target = np.eye(4)
    target[:3, :3] = rot
    target[:3, 3] = point
    q = solve_ik(spec, target, seed, tool=tool)
    return WeldCell(
        robot=spec.name,
        work_point_m=point,
        torch_rotation=tuple((float(r[0]), float(r[1]), float(r[2])) for r in rot),
        tool_m=tool,
        seed_q_rad=tuple(float(x) for x in q),
        conveyor=Conveyor(direction=(0.0, 1.0, 0.0), speed_m_s=speed_m_s),
    )


class _SeamTrajectory:
    """Ruckig approach + spline along the seam + Ruckig stop, as one Ruckig-like trajectory.

    ``duration``, ``at_time(t) -> (p, v, a)`` (lists of 6) and ``position_extrema`` (objects
    with ``min``/``max``), which is what :class:`JointPlan` uses of a trajectory.
    """

    def __init__(
        self, approach: Any, spline: Any, t_seam_s: float, seam_s: float, stop: Any
    ) -> None:
        self.approach = approach
        self.spline = spline
        self.d_spline = spline.derivative(1)
        self.dd_spline = spline.derivative(2)
        self.t1 = float(approach.duration)  # start of the seam (plan time)
        self.t_seam0 = float(t_seam_s)  # spline time at t1
        self.t2 = self.t1 + float(seam_s)  # start of the stop
        self.stop = stop
        self.duration = self.t2 + float(stop.duration)
        self._extrema: list[Any] | None = None

    def at_time(self, t: float) -> tuple[list[float], list[float], list[float]]:
        if t < self.t1:
            p, v, a = self.approach.at_time(max(t, 0.0))
            return list(p), list(v), list(a)
        if t < self.t2:
            x = t - self.t1 + self.t_seam0
            return (
                self.spline(x).tolist(),
                self.d_spline(x).tolist(),
                self.dd_spline(x).tolist(),
            )
        p, v, a = self.stop.at_time(min(t - self.t2, float(self.stop.duration)))
        return list(p), list(v), list(a)

    @property
    def position_extrema(self) -> list[Any]:
        if self._extrema is None:
            t = np.linspace(0.0, self.duration, max(200, int(self.duration / 0.002)))
            q = np.array([self.at_time(float(x))[0] for x in t])
            self._extrema = [_Extremum(float(lo), float(hi)) for lo, hi in zip(q.min(0), q.max(0), strict=True)]  # fmt: skip
        return self._extrema


@dataclass(frozen=True)
class _Extremum:
    min: float
    max: float


@dataclass(frozen=True)
class SeamPlan:
    """The joint plan of a seam and the seam it follows (see :func:`plan_seam`).

    Attributes
    ----------
    plan : JointPlan
        Unscheduled; plan time ``sync_s`` is the meeting with the seam.
    cell : WeldCell
    seam : Seam
    sync_s : float
        Plan time at which the torch meets the seam start, s (the approach's duration).
    weld_s : float
        Seam time covered by the plan after ``sync_s``, s.
    start_m : ndarray (3,)
        Seam start in the base frame at the meeting instant, m.
    """

    plan: JointPlan
    cell: WeldCell
    seam: Seam
    sync_s: float
    weld_s: float
    start_m: FloatArray

    def target(self, t_since_sync_s: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Where the torch tip must be ``t_since_sync_s`` (n,) after the meeting, base frame.

        Returns
        -------
        point, tangent, normal : ndarray (n, 3)
            Seam point (m), the seam's unit tangent (direction of welding) and its
            horizontal unit normal (to the left of the tangent), base frame.
        """
        t = np.atleast_1d(np.asarray(t_since_sync_s, dtype=float))
        ux, uy, _ = self.cell.conveyor.direction
        frame_t = np.array([[ux, uy, 0.0], [-uy, ux, 0.0], [0.0, 0.0, 1.0]])  # part -> base, ᵀ
        p_part, tan_part = self.seam.point(self.seam.weld_speed_m_s * t)
        velocity = np.asarray(self.cell.conveyor.velocity_m_s)
        point = self.start_m + t[:, None] * velocity + p_part @ frame_t
        tangent = tan_part @ frame_t
        normal = np.zeros_like(tangent)
        normal[:, 0], normal[:, 1] = -tangent[:, 1], tangent[:, 0]
        return point, tangent, normal

    def torch_m(self, q_rad: ArrayLike) -> FloatArray:
        """Torch tip positions (n, 3), m, of joint configurations (n, 6)."""
        q = np.asarray(q_rad, dtype=float).reshape(-1, 6)
        return np.asarray(tool_pose(self.cell.spec, q, self.cell.tool_m)[:, :3, 3])

    def summary(self) -> dict[str, Any]:
        """JSON-safe description."""
        return {
            "cell": self.cell.to_dict(),
            "seam": self.seam.to_dict(),
            "sync_s": self.sync_s,
            "weld_s": self.weld_s,
            "start_m": self.start_m.tolist(),
        }


def _ruckig_to_state(
    spec: RobotSpec,
    limits: ExecutionLimits,
    q0: FloatArray,
    q1: FloatArray,
    qd1: FloatArray,
    qdd1: FloatArray,
) -> Any:
    """Time-optimal jerk-limited trajectory from rest at ``q0`` to the state (q1, qd1, qdd1)."""
    from ruckig import InputParameter, Result, Ruckig, Synchronization, Trajectory

    vmax, amax, jmax = limits.velocity(spec), limits.acceleration(spec), limits.jerk(spec)
    inp = InputParameter(6)
    inp.current_position = q0.tolist()
    inp.current_velocity = [0.0] * 6
    inp.current_acceleration = [0.0] * 6
    inp.target_position = q1.tolist()
    inp.target_velocity = qd1.tolist()
    inp.target_acceleration = np.clip(qdd1, -0.99 * amax, 0.99 * amax).tolist()
    inp.max_velocity = vmax.tolist()
    inp.max_acceleration = amax.tolist()
    inp.max_jerk = jmax.tolist()
    traj = Trajectory(6)
    for sync in (Synchronization.Phase, Synchronization.Time):
        inp.synchronization = sync
        try:
            result = Ruckig(6).calculate(inp, traj)
        except Exception as exc:  # ruckig.RuckigError: invalid input
            raise ConfigError(f"Ruckig cannot plan the approach to the seam: {exc}") from exc
        if result in (Result.Working, Result.Finished):
            return traj
    raise ConfigError(f"Ruckig cannot plan the approach to the seam (result {result})")


def _ruckig_velocity(
    spec: RobotSpec,
    limits: ExecutionLimits,
    q: FloatArray,
    qd: FloatArray,
    qdd: FloatArray,
    target_qd: FloatArray | None = None,
    *,
    what: str = "the stop after the seam",
) -> Any:
    """Jerk-limited change from the state (q, qd, qdd) to the constant speed ``target_qd``
    (default: rest), velocity interface, all joints finishing together."""
    from ruckig import ControlInterface, InputParameter, Result, Ruckig, Synchronization, Trajectory

    amax, jmax = limits.acceleration(spec), limits.jerk(spec)
    inp = InputParameter(6)
    inp.control_interface = ControlInterface.Velocity
    inp.synchronization = Synchronization.Time
    inp.current_position = q.tolist()
    inp.current_velocity = qd.tolist()
    inp.current_acceleration = np.clip(qdd, -0.99 * amax, 0.99 * amax).tolist()
    inp.target_velocity = [0.0] * 6 if target_qd is None else np.asarray(target_qd).tolist()
    inp.target_acceleration = [0.0] * 6
    inp.max_velocity = limits.velocity(spec).tolist()
    inp.max_acceleration = amax.tolist()
    inp.max_jerk = jmax.tolist()
    traj = Trajectory(6)
    result = Ruckig(6).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise ConfigError(f"Ruckig cannot plan {what} (result {result})")
    return traj


def plan_seam(
    cell: WeldCell,
    seam: Seam,
    *,
    weld_s: float = 1.0,
    limits: ExecutionLimits | None = None,
    approach_s: float = 0.1,
) -> SeamPlan:
    """Plan the approach to a moving seam, the weld along it and the stop after it.

    The seam's middle (``weld_s / 2`` after the meeting) passes the cell's work point; the
    torch meets the seam start at plan time ``sync_s`` (the Ruckig approach's duration)
    with the seam's joint speeds and accelerations, follows it for ``weld_s`` and stops.

    Parameters
    ----------
    cell : WeldCell
    seam : Seam
    weld_s : float
        Time on the seam, s (the cruise: settle and measurement window inside it).
    limits : ExecutionLimits, optional
        The executor's limits (default :class:`ExecutionLimits()`: acceleration cap 8
        rad/s², the calibration ramp).
    approach_s : float
        The approach starts where the seam's joint path would have been this long before
        the meeting (joint speeds ramp up over about twice this from rest), s.

    Raises
    ------
    ConfigError
        When the seam leaves the robot's reach, a joint limit or a joint speed limit, or
        Ruckig cannot plan the approach or the stop; nothing is sent.
    """
    from scipy.interpolate import CubicSpline

    if not (math.isfinite(weld_s) and weld_s > 0):
        raise ConfigError(f"weld_s={weld_s!r} must be a duration > 0 s")
    if not (math.isfinite(approach_s) and approach_s > 0):
        raise ConfigError(f"approach_s={approach_s!r} must be a duration > 0 s")
    spec = cell.spec
    lim = limits or ExecutionLimits()
    # Seam start at the meeting: the middle of the weld passes the work point.
    u = np.asarray(cell.conveyor.direction)
    left = np.array([-u[1], u[0], 0.0])
    frame = np.column_stack([u, left, [0.0, 0.0, 1.0]])
    mid = 0.5 * weld_s
    p_mid, _ = seam.point(seam.weld_speed_m_s * mid)
    start = np.asarray(cell.work_point_m) - cell.conveyor.velocity_m_s * mid - p_mid[0] @ frame.T
    draft = SeamPlan(JointPlan(None, *(np.zeros(6),) * 4), cell, seam, 0.0, weld_s, start)
    # IK on a grid from a little before the meeting to the end of the weld, outwards from
    # the work point (the seed is a configuration there) so the branch is the seed's.
    pad = 4 * IK_STEP_S
    t_grid = np.arange(-pad, weld_s + pad + 0.5 * IK_STEP_S, IK_STEP_S)
    points, _, _ = draft.target(t_grid)
    rot = np.asarray(cell.torch_rotation, dtype=float)
    q_grid = np.empty((len(t_grid), 6))
    k_mid = int(np.argmin(np.abs(t_grid - mid)))
    seed = np.asarray(cell.seed_q_rad, dtype=float)
    pose = np.eye(4)
    pose[:3, :3] = rot
    for order in (range(k_mid, len(t_grid)), range(k_mid, -1, -1)):
        q = seed
        for k in order:
            pose[:3, 3] = points[k]
            try:
                q = solve_ik(spec, pose, q, tool=cell.tool_m)
            except ConfigError as exc:
                raise ConfigError(
                    f"the seam leaves the reach of {spec.name} {t_grid[k]:.3f} s after the "
                    f"meeting (torch at {points[k].round(3).tolist()} m): {exc}"
                ) from exc
            q_grid[k] = q
    step = np.abs(np.diff(q_grid, axis=0)).max()
    if step > 0.05:
        raise ConfigError(
            f"the seam's inverse kinematics jumps by {step:.3f} rad between samples (a wrist "
            "flip or a singularity on the way); move the work point or the seam"
        )
    spline = CubicSpline(t_grid, q_grid, axis=0)
    q_s, qd_s, qdd_s = spline(0.0), spline(0.0, 1), spline(0.0, 2)
    vmax = lim.velocity(spec)
    speeds = np.abs(spline(t_grid, 1)).max(axis=0)
    if np.any(speeds > 0.9 * vmax):
        j = int(np.argmax(speeds / vmax))
        raise ConfigError(
            f"the seam needs joint {j + 1} at {speeds[j]:.3g} rad/s, above 90 % of its "
            f"limit {vmax[j]:.3g} rad/s; lower the belt speed or move the work point"
        )
    # Start from rest where the seam's joint path was approach_s earlier: every joint's
    # first motion is in the direction of its motion on the seam.
    q0 = q_s - qd_s * approach_s
    approach = _ruckig_to_state(spec, lim, q0, q_s, qd_s, qdd_s)
    q_e, qd_e, qdd_e = spline(weld_s), spline(weld_s, 1), spline(weld_s, 2)
    stop = _ruckig_velocity(spec, lim, q_e, qd_e, qdd_e)
    traj = _SeamTrajectory(approach, spline, 0.0, weld_s, stop)
    q_end = np.asarray(stop.at_time(float(stop.duration))[0])
    lo, hi = lim.position_range(spec)
    for j, ext in enumerate(traj.position_extrema):
        if ext.min < lo[j] or ext.max > hi[j]:
            raise ConfigError(
                f"the seam plan takes joint {j + 1} to [{ext.min:.4g}, {ext.max:.4g}] rad, "
                f"outside [{spec.q_min_rad[j]:.4g}, {spec.q_max_rad[j]:.4g}] rad; move the "
                "work point"
            )
    plan = JointPlan(traj, q0, np.zeros(6), q_end, np.zeros(6))
    return SeamPlan(plan, cell, seam, float(approach.duration), float(weld_s), start)
