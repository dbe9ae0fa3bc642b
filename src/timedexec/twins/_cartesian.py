"""Cartesian side of the UR twin's control script: the TCP pose and speed a UR reports, and
``moveL`` / ``speedL`` / ``servoL`` turned into joint commands once per controller cycle.

Poses are UR poses: ``[x, y, z, rx, ry, rz]``, position in m and orientation as a rotation
vector (axis times angle, rad, angle in [0, pi]) in the robot's base frame; the TCP is the
flange (the control script sets no TCP offset). The kinematics are the robot's DH chain from
:mod:`timedexec.robots` (the numbers come from its :class:`~timedexec.robots.RobotSpec`);
:class:`Kinematics` evaluates it for one configuration in plain floats, because the twin
needs a pose and a Jacobian every 2 ms and the batch functions' per-call overhead
(:func:`~timedexec.robots.tool_pose`, :func:`~timedexec.robots.tool_jacobian`: 0.15-0.25
ms each) would cost a fifth of a core; ``tests/test_ur_script_semantics.py`` checks both
against them.

How each motion maps onto the simulated controller (which takes joint commands only):

* :class:`LinearMove` (``moveL``): a trapezoidal profile of the path length (the TCP's
  straight line; a pure rotation uses the angle, with speed and acceleration read as rad/s
  and rad/s²), the orientation turned about one fixed axis in proportion. Each cycle the
  setpoint at the end of the coming cycle is converted to joints by one Newton step of the
  pose error from the previous setpoint's joints (the step is at most a few millimetres, so
  the error left is micrometres and does not accumulate: every step aims at the absolute
  pose); the joint speeds that carry the setpoint there within the cycle go to the
  controller as a ``SpeedJ`` (a per-cycle ``ServoJ`` would restart from rest every cycle,
  and the controller would watch each one for a motion onset), and once the profile ends a
  ``ServoJ`` to the goal's joints removes what the joints' speed loops lost on the way.
  The whole path is checked first (:meth:`LinearMove.check`): a target out of reach, a
  joint limit or a singularity on the way refuses the command before any motion.
* :class:`ToolSpeed` (``speedL``): the commanded tool speed ramps towards the target at the
  given acceleration (m/s², the same number in rad/s² for the rotation), and each cycle the
  joint speeds that produce it at the present configuration (damped least squares on the
  Jacobian, scaled down as a whole to the joint speed limits) go to the controller as a
  ``SpeedJ`` that holds.
* ``servoL`` (:func:`servo_target`): the target pose converted to joints by Newton steps
  from the previous servo target, fed to ``servoj``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec

#: Damping of the least-squares inverse of the Jacobian (m or rad): small against any step
#: the twin takes, large enough to keep the inverse bounded next to a singularity.
_DAMPING = 1e-4
#: A configuration whose Jacobian has a singular value below this (m/rad) counts as
#: singular: a Cartesian path through it is refused (a real UR stops there too).
_SINGULAR_SV = 1e-3
#: Largest pose error left after converting one path sample to joints (m, rad).
_PATH_TOLERANCE = 1e-5
#: Path samples checked before a moveL starts: one per this length (m) or angle (rad).
_CHECK_STEP_M = 0.02
_CHECK_STEP_RAD = 0.05
#: Most samples checked (the check runs on the controller clock: keep it under a cycle).
_CHECK_MAX_SAMPLES = 40
#: A joint turning more than this between two neighbouring path samples means the path
#: crosses a branch of the kinematics (a wrist flip): refused, rad.
_CHECK_MAX_JOINT_STEP_RAD = 0.35


def rotation_matrix(rotvec: ArrayLike) -> FloatArray:
    """Rotation matrix (3, 3) of a rotation vector (axis times angle, rad; Rodrigues)."""
    rx, ry, rz = (float(v) for v in np.asarray(rotvec, dtype=float).reshape(3))
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        return np.eye(3)
    kx, ky, kz = rx / angle, ry / angle, rz / angle
    c, s = math.cos(angle), math.sin(angle)
    v = 1.0 - c
    return np.array(
        [
            [c + kx * kx * v, kx * ky * v - kz * s, kx * kz * v + ky * s],
            [ky * kx * v + kz * s, c + ky * ky * v, ky * kz * v - kx * s],
            [kz * kx * v - ky * s, kz * ky * v + kx * s, c + kz * kz * v],
        ]
    )


def rotation_vector(r: FloatArray) -> FloatArray:
    """Rotation vector (3,) of a rotation matrix, angle in [0, pi] (UR's convention)."""
    r00, r01, r02 = float(r[0, 0]), float(r[0, 1]), float(r[0, 2])
    r10, r11, r12 = float(r[1, 0]), float(r[1, 1]), float(r[1, 2])
    r20, r21, r22 = float(r[2, 0]), float(r[2, 1]), float(r[2, 2])
    cos_a = 0.5 * (r00 + r11 + r22 - 1.0)
    s0, s1, s2 = r21 - r12, r02 - r20, r10 - r01  # 2 sin(angle) * axis
    sin_a = 0.5 * math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    # atan2 keeps the angle exact near 0 and pi, where acos and asin lose digits.
    angle = math.atan2(sin_a, cos_a)
    if sin_a < 1e-12 and cos_a > 0.0:
        return np.array([0.5 * s0, 0.5 * s1, 0.5 * s2])
    if sin_a > 1e-4 or cos_a > 0.0:
        f = angle / (2.0 * sin_a)
        return np.array([f * s0, f * s1, f * s2])
    # Near a half turn the skew part vanishes: the symmetric part is (1 - cos) k k^T, whose
    # column of the largest diagonal element is the axis; the skew part gives its sign.
    cos_a = max(-1.0, cos_a)
    d0, d1, d2 = r00 - cos_a, r11 - cos_a, r22 - cos_a
    if d0 >= d1 and d0 >= d2:
        k0, k1, k2 = d0, 0.5 * (r10 + r01), 0.5 * (r20 + r02)
    elif d1 >= d2:
        k0, k1, k2 = 0.5 * (r01 + r10), d1, 0.5 * (r21 + r12)
    else:
        k0, k1, k2 = 0.5 * (r02 + r20), 0.5 * (r12 + r21), d2
    f = angle / math.sqrt(k0 * k0 + k1 * k1 + k2 * k2)
    if s0 * k0 + s1 * k1 + s2 * k2 < 0.0:
        f = -f
    return np.array([f * k0, f * k1, f * k2])


def pose_matrix(pose: ArrayLike) -> FloatArray:
    """4 x 4 transform of a UR pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector rad)."""
    p = np.asarray(pose, dtype=float).reshape(6)
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(p[3:])
    out[:3, 3] = p[:3]
    return out


def pose_vector(transform: FloatArray) -> tuple[float, ...]:
    """UR pose ``(x, y, z, rx, ry, rz)`` of a 4 x 4 transform."""
    rv = rotation_vector(transform[:3, :3])
    t = transform[:3, 3]
    return (float(t[0]), float(t[1]), float(t[2]), float(rv[0]), float(rv[1]), float(rv[2]))


def _rotation_between(r_to: FloatArray, r_from: FloatArray) -> FloatArray:
    """Rotation vector ``e`` with ``r_to = Rot(e) @ r_from`` (base frame)."""
    return rotation_vector(r_to @ r_from.T)


class Kinematics:
    """Forward kinematics and geometric Jacobian of the flange for one configuration.

    The same DH chain as :mod:`timedexec.robots` (``A_i = Rz(theta_i) Tz(d_i) Tx(a_i)
    Rx(alpha_i)``, ``theta = joint_sign * q + dh_offset``) evaluated in plain floats.

    Parameters
    ----------
    spec : RobotSpec
        The robot (DH table, joint limits, joint speed limits).
    """

    def __init__(self, spec: RobotSpec) -> None:
        self.spec = spec
        self._dh = tuple(
            zip(
                (float(v) for v in spec.joint_sign),
                (float(v) for v in spec.dh_offset_rad),
                (math.cos(float(v)) for v in spec.dh_alpha_rad),
                (math.sin(float(v)) for v in spec.dh_alpha_rad),
                (float(v) for v in spec.dh_d_m),
                (float(v) for v in spec.dh_a_m),
                strict=True,
            )
        )
        self.q_min_rad = np.asarray(spec.q_min_rad, dtype=float)
        self.q_max_rad = np.asarray(spec.q_max_rad, dtype=float)
        self.qd_max_rad_s = np.asarray(spec.qd_max_rad_s, dtype=float)

    def _chain(
        self, q_rad: ArrayLike
    ) -> tuple[
        tuple[float, ...], list[tuple[float, float, float]], list[tuple[float, float, float]]
    ]:
        """The flange frame as 12 floats (x, y, z axes and origin, each 3), and per joint its
        axis (vendor direction) and a point on it, all in base coordinates."""
        x0, x1, x2 = 1.0, 0.0, 0.0
        y0, y1, y2 = 0.0, 1.0, 0.0
        z0, z1, z2 = 0.0, 0.0, 1.0
        o0, o1, o2 = 0.0, 0.0, 0.0
        axes: list[tuple[float, float, float]] = []
        origins: list[tuple[float, float, float]] = []
        q_list = np.asarray(q_rad, dtype=float).tolist()
        for qi, (sg, offset, ca, sa, d, a) in zip(q_list, self._dh, strict=True):
            axes.append((sg * z0, sg * z1, sg * z2))
            origins.append((o0, o1, o2))
            th = sg * qi + offset
            c, s = math.cos(th), math.sin(th)
            xn0, xn1, xn2 = c * x0 + s * y0, c * x1 + s * y1, c * x2 + s * y2
            r0, r1, r2 = c * y0 - s * x0, c * y1 - s * x1, c * y2 - s * x2
            o0, o1, o2 = o0 + d * z0 + a * xn0, o1 + d * z1 + a * xn1, o2 + d * z2 + a * xn2
            y0, y1, y2 = ca * r0 + sa * z0, ca * r1 + sa * z1, ca * r2 + sa * z2
            z0, z1, z2 = ca * z0 - sa * r0, ca * z1 - sa * r1, ca * z2 - sa * r2
            x0, x1, x2 = xn0, xn1, xn2
        frame = (x0, x1, x2, y0, y1, y2, z0, z1, z2, o0, o1, o2)
        return frame, axes, origins

    def pose_and_jacobian(self, q_rad: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Flange pose (4, 4) in the base frame and the geometric Jacobian (6, 6): rows vx,
        vy, vz (m/rad), wx, wy, wz (rad/rad); columns joints 1..6 (vendor angles)."""
        f, axes, origins = self._chain(q_rad)
        pose = np.array(
            [
                [f[0], f[3], f[6], f[9]],
                [f[1], f[4], f[7], f[10]],
                [f[2], f[5], f[8], f[11]],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        o0, o1, o2 = f[9], f[10], f[11]
        cols = []
        for (a0, a1, a2), (p0, p1, p2) in zip(axes, origins, strict=True):
            r0, r1, r2 = o0 - p0, o1 - p1, o2 - p2
            cols.append((a1 * r2 - a2 * r1, a2 * r0 - a0 * r2, a0 * r1 - a1 * r0, a0, a1, a2))
        return pose, np.array(cols).T

    def tcp(
        self, q_rad: ArrayLike, qd_rad_s: ArrayLike
    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """UR TCP pose ``(x, y, z, rx, ry, rz)`` and TCP speed ``(vx, vy, vz, wx, wy, wz)``
        (m/s, rad/s, base frame) of a configuration and its joint speeds."""
        f, axes, origins = self._chain(q_rad)
        o0, o1, o2 = f[9], f[10], f[11]
        v0 = v1 = v2 = w0 = w1 = w2 = 0.0
        for qd, (a0, a1, a2), (p0, p1, p2) in zip(
            np.asarray(qd_rad_s, dtype=float).tolist(), axes, origins, strict=True
        ):
            if qd == 0.0:
                continue
            r0, r1, r2 = o0 - p0, o1 - p1, o2 - p2
            v0 += qd * (a1 * r2 - a2 * r1)
            v1 += qd * (a2 * r0 - a0 * r2)
            v2 += qd * (a0 * r1 - a1 * r0)
            w0, w1, w2 = w0 + qd * a0, w1 + qd * a1, w2 + qd * a2
        rot = np.array([[f[0], f[3], f[6]], [f[1], f[4], f[7]], [f[2], f[5], f[8]]])
        rv = rotation_vector(rot).tolist()
        return (o0, o1, o2, rv[0], rv[1], rv[2]), (v0, v1, v2, w0, w1, w2)

    @staticmethod
    def solve(jac: FloatArray, twist: FloatArray) -> FloatArray:
        """Joint increments (6,) that move the flange by ``twist`` (6,): damped least
        squares, ``J^T (J J^T + lambda^2 I)^-1 twist``."""
        return np.asarray(jac.T @ np.linalg.solve(jac @ jac.T + _DAMPING**2 * np.eye(6), twist))

    def newton(
        self,
        target: FloatArray,
        q_seed: FloatArray,
        *,
        iterations: int = 1,
        tolerance: float = 0.0,
    ) -> tuple[FloatArray, float]:
        """Joints near ``q_seed`` that put the flange at ``target`` (4, 4): up to
        ``iterations`` Newton steps on the pose error, fewer once the error is below
        ``tolerance``. Returns the joints and, when it stopped early, their pose error;
        otherwise the error before the last step (m or rad)."""
        q = np.array(q_seed, dtype=float)
        err = math.inf
        e = np.empty(6)
        for _ in range(iterations):
            pose, jac = self.pose_and_jacobian(q)
            e[:3] = target[:3, 3] - pose[:3, 3]
            e[3:] = _rotation_between(target[:3, :3], pose[:3, :3])
            err = float(np.abs(e).max())
            if err <= tolerance:
                break
            q = q + self.solve(jac, e)
        return q, err

    def reach(self, target: FloatArray, q_seed: FloatArray, what: str) -> FloatArray:
        """Joints that put the flange at ``target`` from a nearby seed, or ConfigError.

        Raises
        ------
        ConfigError
            The pose is out of reach from the seed, beyond a joint limit, or singular.
        """
        q, err = self.newton(target, q_seed, iterations=10, tolerance=0.01 * _PATH_TOLERANCE)
        if not err < _PATH_TOLERANCE:
            raise ConfigError(
                f"{what}: the pose {pose_vector(target)} is out of reach of "
                f"{self.spec.name} from the present configuration (error "
                f"{err * 1e3:.2f} mm/mrad left)"
            )
        if np.any(q < self.q_min_rad) or np.any(q > self.q_max_rad):
            raise ConfigError(f"{what}: the pose needs a joint beyond its limits ({q.round(3)})")
        _, jac = self.pose_and_jacobian(q)
        if float(np.linalg.svd(jac, compute_uv=False)[-1]) < _SINGULAR_SV:
            raise ConfigError(f"{what}: the path meets a singular configuration at {q.round(3)}")
        return q


def _trapezoid(t: float, t_acc: float, t_cruise: float, v_peak: float) -> tuple[float, float]:
    """Distance and speed along a trapezoidal (or triangular) profile at time ``t``."""
    if t <= 0.0 or v_peak <= 0.0:
        return 0.0, 0.0
    a = v_peak / t_acc if t_acc > 0.0 else 0.0
    d_acc = 0.5 * v_peak * t_acc
    if t < t_acc:
        return 0.5 * a * t * t, a * t
    if t < t_acc + t_cruise:
        return d_acc + v_peak * (t - t_acc), v_peak
    td = min(t - t_acc - t_cruise, t_acc)
    return d_acc + v_peak * t_cruise + v_peak * td - 0.5 * a * td * td, v_peak - a * td


class LinearMove:
    """A ``moveL``: the flange along a straight line to ``goal``, trapezoidal in time.

    Parameters
    ----------
    kin : Kinematics
    q_start_rad : array_like, shape (6,)
        Joints at the start (the reference, where the previous motion left the arm).
    goal : array_like, shape (6,)
        UR pose to reach.
    speed_m_s, acceleration_m_s2 : float
        Tool speed and acceleration (a pure rotation: rad/s, rad/s²).
    start_s : float
        Controller time of the start, s.

    Raises
    ------
    ConfigError
        Bad speed or acceleration, or a path the arm cannot follow (:meth:`check`).
    """

    kind = "MoveL"

    def __init__(
        self,
        kin: Kinematics,
        q_start_rad: ArrayLike,
        goal: ArrayLike,
        speed_m_s: float,
        acceleration_m_s2: float,
        start_s: float,
    ) -> None:
        if not (math.isfinite(speed_m_s) and speed_m_s > 0):
            raise ConfigError(f"moveL: speed {speed_m_s!r} m/s must be > 0")
        if not (math.isfinite(acceleration_m_s2) and acceleration_m_s2 > 0):
            raise ConfigError(f"moveL: acceleration {acceleration_m_s2!r} m/s² must be > 0")
        goal_arr = np.asarray(goal, dtype=float)
        if goal_arr.shape != (6,) or not np.all(np.isfinite(goal_arr)):
            raise ConfigError(f"moveL: the target pose must be 6 finite numbers, got {goal!r}")
        self.kin = kin
        self.q = np.array(q_start_rad, dtype=float)
        start, _ = kin.pose_and_jacobian(self.q)
        self.p0 = start[:3, 3].copy()
        self.r0 = start[:3, :3].copy()
        self.goal = pose_matrix(goal_arr)
        self.dp = self.goal[:3, 3] - self.p0
        self.rot = _rotation_between(self.goal[:3, :3], self.r0)
        distance = float(np.linalg.norm(self.dp))
        angle = float(np.linalg.norm(self.rot))
        self.length = distance if distance > 1e-6 else angle
        v, a = float(speed_m_s), float(acceleration_m_s2)
        if self.length <= v * v / a:  # triangular profile
            t_acc = math.sqrt(self.length / a)
            self.profile = (t_acc, 0.0, a * t_acc)
        else:
            self.profile = (v / a, self.length / v - v / a, v)
        self.start_s = float(start_s)
        self.duration_s = 2.0 * self.profile[0] + self.profile[1]
        self.finished = False
        self._qd = np.zeros(6)

    def setpoint(self, t_s: float) -> FloatArray:
        """The flange pose (4, 4) the path prescribes at controller time ``t_s``."""
        s, _ = _trapezoid(t_s - self.start_s, *self.profile)
        f = min(1.0, s / self.length) if self.length > 0 else 1.0
        out = np.eye(4)
        out[:3, 3] = self.p0 + f * self.dp
        out[:3, :3] = rotation_matrix(f * self.rot) @ self.r0
        return out

    def check(self) -> None:
        """Refuse a path the arm cannot follow: every sample reachable by Newton steps from
        its neighbour, inside the joint limits, away from singularities, on one branch.

        Raises
        ------
        ConfigError
        """
        distance = float(np.linalg.norm(self.dp))
        angle = float(np.linalg.norm(self.rot))
        n = int(
            min(
                _CHECK_MAX_SAMPLES,
                max(2, math.ceil(distance / _CHECK_STEP_M + angle / _CHECK_STEP_RAD)),
            )
        )
        q = self.q
        for k in range(1, n + 1):
            f = k / n
            target = np.eye(4)
            target[:3, 3] = self.p0 + f * self.dp
            target[:3, :3] = rotation_matrix(f * self.rot) @ self.r0
            q_next = self.kin.reach(target, q, "moveL")
            if float(np.abs(q_next - q).max()) > _CHECK_MAX_JOINT_STEP_RAD:
                raise ConfigError(
                    "moveL: the straight line to the target crosses a branch of the arm's "
                    "kinematics (a joint would flip); use moveJ or an intermediate waypoint"
                )
            q = q_next

    def joint_speeds(self, boundary_s: float, period_s: float) -> tuple[FloatArray, float]:
        """Joint speeds (6,) that carry the path's joint setpoint from this boundary to the
        next one (one Newton step from the previous setpoint), and the joint acceleration
        (rad/s²) that reaches them within the cycle. Once the profile has ended the speeds
        are zero and :attr:`finished` is set; :attr:`q` is then the goal's joints."""
        end_s = self.start_s + self.duration_s
        if boundary_s >= end_s:
            self.finished = True
            self.q, _ = self.kin.newton(self.goal, self.q, iterations=3)
            qd = np.zeros(6)
        else:
            t_next = boundary_s + period_s
            target = self.goal if t_next >= end_s else self.setpoint(t_next)
            q_next, _ = self.kin.newton(target, self.q, iterations=1)
            qd = _snap((q_next - self.q) / period_s)
            self.q = q_next
        accel = float(np.abs(qd - self._qd).max()) / period_s
        self._qd = qd
        return qd, accel


def _snap(qd: FloatArray) -> FloatArray:
    """Joint speeds below 1e-9 rad/s set to exactly 0 (numerical noise of the inverse;
    the controller counts an exactly zero speed as "this joint stays still")."""
    return np.where(np.abs(qd) < 1e-9, 0.0, qd)


class ToolSpeed:
    """A ``speedL``: the tool speed ramped to ``target`` and mapped to joint speeds each
    cycle; it never expires (the script's speed thread re-issues it until stopped).

    Parameters
    ----------
    kin : Kinematics
    target : array_like, shape (6,)
        Tool speed ``(vx, vy, vz, wx, wy, wz)``, m/s and rad/s, base frame.
    acceleration_m_s2 : float
        Tool acceleration (the same number in rad/s² for the rotation).
    start_speed : array_like, shape (6,)
        The tool speed commanded when this command takes over.

    Raises
    ------
    ConfigError
        A target or acceleration that is not finite, or an acceleration <= 0.
    """

    kind = "SpeedL"

    def __init__(
        self, kin: Kinematics, target: ArrayLike, acceleration_m_s2: float, start_speed: ArrayLike
    ) -> None:
        tgt = np.asarray(target, dtype=float)
        if tgt.shape != (6,) or not np.all(np.isfinite(tgt)):
            raise ConfigError(f"speedL: the tool speed must be 6 finite numbers, got {target!r}")
        if not (math.isfinite(acceleration_m_s2) and acceleration_m_s2 > 0):
            raise ConfigError(f"speedL: acceleration {acceleration_m_s2!r} m/s² must be > 0")
        self.kin = kin
        self.target = tgt
        self.acceleration = float(acceleration_m_s2)
        self.speed = np.array(start_speed, dtype=float)
        self.qd = np.zeros(6)
        self.finished = False

    def joint_speeds(self, q_rad: ArrayLike, period_s: float) -> tuple[FloatArray, float]:
        """Joint speeds (6,) for the coming cycle at configuration ``q_rad`` and the joint
        acceleration (rad/s²) that reaches them within the cycle."""
        step = self.acceleration * period_s
        for part in (slice(0, 3), slice(3, 6)):
            diff = self.target[part] - self.speed[part]
            norm = float(np.linalg.norm(diff))
            self.speed[part] += diff if norm <= step else diff * (step / norm)
        _, jac = self.kin.pose_and_jacobian(q_rad)
        qd = _snap(self.kin.solve(jac, self.speed))
        # Scale the whole vector into the joint speed limits: the path stays straight, the
        # tool is slower there (a real UR slows down the same way near a singularity).
        over = float(np.max(np.abs(qd) / (0.99 * self.kin.qd_max_rad_s)))
        if over > 1.0:
            qd = qd / over
        accel = float(np.abs(qd - self.qd).max()) / period_s
        self.qd = qd
        return qd, accel


def servo_target(kin: Kinematics, pose: ArrayLike, q_seed: ArrayLike) -> FloatArray:
    """Joints (6,) for a ``servoL`` target pose, from the previous servo target.

    Raises
    ------
    ConfigError
        The pose is not 6 finite numbers, out of reach, beyond a joint limit or singular.
    """
    arr = np.asarray(pose, dtype=float)
    if arr.shape != (6,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"servoL: the target pose must be 6 finite numbers, got {pose!r}")
    return kin.reach(pose_matrix(arr), np.asarray(q_seed, dtype=float), "servoL")


def tcp_values(kin: Kinematics, packet: Any) -> dict[str, tuple[float, ...]]:
    """``actual_TCP_pose``, ``actual_TCP_speed``, ``target_TCP_pose`` and
    ``target_TCP_speed`` of a state package (physical and reference joint state)."""
    pose, speed = kin.tcp(packet.q_rad, packet.qd_rad_s)
    tpose, tspeed = kin.tcp(packet.q_target_rad, packet.qd_target_rad_s)
    return {
        "actual_TCP_pose": pose,
        "actual_TCP_speed": speed,
        "target_TCP_pose": tpose,
        "target_TCP_speed": tspeed,
    }
