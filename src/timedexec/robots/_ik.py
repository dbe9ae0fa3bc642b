"""Tool-point kinematics: the pose of a tool on the flange, its Jacobian, inverse kinematics.

A tool (a welding torch, a gripper) is a fixed transform from the flange frame (DH frame 6)
to its tool centre point (TCP). :func:`tool_pose` is the TCP's pose in the base frame,
:func:`tool_jacobian` the geometric Jacobian at the TCP (6 x 6: linear rows first, then
angular; columns per vendor joint angle), :func:`solve_ik` the joint angles that put the TCP
at a pose.

Why a numerical IK on the DH chain
----------------------------------
The chain and its frames are already here (:mod:`timedexec.robots._dynamics`), so the
Jacobian is one cross product per joint. A tracking task solves the IK once per sample of a
smooth path, each time from the previous solution: damped least squares (Levenberg-Marquardt
on the pose error, Wampler's damping) converges in one to three iterations from there, keeps
the branch (elbow, wrist) of the seed, and works for every robot in the catalog without a
per-robot closed form. ``ikpy`` (the maintained pure-Python IK) builds chains from URDF and
runs a generic SciPy optimiser per solve (milliseconds), without the warm-started branch
keeping; closed-form solvers (``ur_kinematics``, IKFast) exist per robot family only and
need their own conventions checked against these DH tables. ``tests/test_welding.py`` checks
the round trip to 1e-9 m and the speed (``benchmarks/bench_welding.py``: ~0.1 ms per
warm-started solve). For the UR family the closed form is derived on these DH tables
(:mod:`timedexec.robots._ur_ik`, checked against the chain's forward kinematics) and used
first: exact and about 20x cheaper, which a 500 Hz online tracking cycle needs. Arms with
a spherical wrist and a planar arm (the KR 5) have their own closed form, Pieper's
decoupling on the same tables (:mod:`timedexec.robots._wrist_ik`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.robots._dynamics import _chain, _params
from timedexec.robots._spec import RobotSpec, _as_configurations, check_configuration
from timedexec.robots._ur_ik import ur_closed_form
from timedexec.robots._wrist_ik import wrist_closed_form

__all__ = ["rotation_error", "solve_ik", "tool_jacobian", "tool_pose"]


def _tool(tool: ArrayLike | None) -> FloatArray:
    """``tool`` as a 4 x 4 homogeneous transform (None: the flange itself)."""
    if tool is None:
        return np.eye(4)
    t = np.asarray(tool, dtype=float)
    if t.shape == (3,):
        out = np.eye(4)
        out[:3, 3] = t
        return out
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ConfigError(
            f"tool must be a TCP offset (3,) in the flange frame, m, or a finite 4 x 4 "
            f"transform, got shape {t.shape}"
        )
    return t


def tool_pose(spec: RobotSpec, q: ArrayLike, tool: ArrayLike | None = None) -> FloatArray:
    """Pose of the tool centre point in the base frame.

    Parameters
    ----------
    spec : RobotSpec
        The robot.
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad.
    tool : array_like, optional
        The TCP in the flange frame: an offset (3,), m, or a 4 x 4 transform. Default: the
        flange origin and axes.

    Returns
    -------
    ndarray, shape (4, 4) or (N, 4, 4)
        Homogeneous transforms, translations in m.
    """
    arr, single = _as_configurations(q)
    ch = _chain(_params(spec), arr)
    flange = np.zeros((arr.shape[0], 4, 4))
    flange[:, :3, 0] = ch.x[-1].T
    flange[:, :3, 1] = ch.y[-1].T
    flange[:, :3, 2] = ch.z[-1].T
    flange[:, :3, 3] = ch.o[-1].T
    flange[:, 3, 3] = 1.0
    out = flange @ _tool(tool)
    return out[0] if single else out


def tool_jacobian(spec: RobotSpec, q: ArrayLike, tool: ArrayLike | None = None) -> FloatArray:
    """Geometric Jacobian of the tool centre point in the base frame.

    ``[v; w] = J @ qd``: ``v`` the TCP's linear velocity (m/s), ``w`` the tool's angular
    velocity (rad/s), both in base coordinates, for vendor joint speeds ``qd`` (rad/s).

    Parameters
    ----------
    spec : RobotSpec
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad.
    tool : array_like, optional
        See :func:`tool_pose`.

    Returns
    -------
    ndarray, shape (6, 6) or (N, 6, 6)
        Rows: vx, vy, vz (m/rad), wx, wy, wz (rad/rad); columns: joints 1..6.
    """
    arr, single = _as_configurations(q)
    p = _params(spec)
    ch = _chain(p, arr)
    tcp = _tool(tool)
    # TCP position: flange origin + R_flange @ tool offset, (3, N).
    off = tcp[:3, 3]
    point = ch.o[-1] + ch.x[-1] * off[0] + ch.y[-1] * off[1] + ch.z[-1] * off[2]
    z = ch.z[:-1] * p.sign[:, None, None]  # (6, 3, N): axis of joint j, vendor direction
    r = point[None] - ch.o[:-1]  # (6, 3, N)
    lin = np.cross(z, r, axis=1)  # (6, 3, N)
    jac = np.concatenate([lin, z], axis=1).transpose(2, 1, 0)  # (N, 6, 6)
    return jac[0] if single else jac


@functools.lru_cache(maxsize=64)
def _dh_lists(spec: RobotSpec) -> tuple[tuple[float, ...], ...]:
    """The DH table as plain float tuples (sign, offset, cos alpha, sin alpha, d, a)."""
    p = _params(spec)
    return tuple(tuple(float(v) for v in arr) for arr in (p.sign, p.offset, p.ca, p.sa, p.d, p.a))


def _frames_one(spec: RobotSpec, q: FloatArray, tcp: FloatArray) -> tuple[FloatArray, FloatArray]:
    """One configuration, in plain floats (the batch code's per-call overhead dominates
    for a single row): the TCP pose (4, 4) and the geometric Jacobian (6, 6).

    Same chain as ``_dynamics._chain``: ``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``.
    """
    sign, offset, cal, sal, dl, al = _dh_lists(spec)
    x0, x1, x2 = 1.0, 0.0, 0.0
    y0, y1, y2 = 0.0, 1.0, 0.0
    z0, z1, z2 = 0.0, 0.0, 1.0
    o0, o1, o2 = 0.0, 0.0, 0.0
    axes = np.empty((6, 3))
    origins = np.empty((6, 3))
    for i in range(6):
        sg = sign[i]
        axes[i] = (sg * z0, sg * z1, sg * z2)
        origins[i] = (o0, o1, o2)
        th = sg * float(q[i]) + offset[i]
        c, s = math.cos(th), math.sin(th)
        xn0, xn1, xn2 = c * x0 + s * y0, c * x1 + s * y1, c * x2 + s * y2
        r0, r1, r2 = c * y0 - s * x0, c * y1 - s * x1, c * y2 - s * x2
        d, a = dl[i], al[i]
        # Along the previous z axis by d, then along the new x axis by a.
        o0, o1, o2 = o0 + d * z0 + a * xn0, o1 + d * z1 + a * xn1, o2 + d * z2 + a * xn2
        ca, sa = cal[i], sal[i]
        y0, y1, y2 = ca * r0 + sa * z0, ca * r1 + sa * z1, ca * r2 + sa * z2
        z0, z1, z2 = ca * z0 - sa * r0, ca * z1 - sa * r1, ca * z2 - sa * r2
        x0, x1, x2 = xn0, xn1, xn2
    flange = np.array([[x0, y0, z0, o0], [x1, y1, z1, o1], [x2, y2, z2, o2], [0.0, 0.0, 0.0, 1.0]])
    pose = flange @ tcp
    r = pose[:3, 3] - origins  # (6, 3)
    jac = np.empty((6, 6))
    jac[0] = axes[:, 1] * r[:, 2] - axes[:, 2] * r[:, 1]
    jac[1] = axes[:, 2] * r[:, 0] - axes[:, 0] * r[:, 2]
    jac[2] = axes[:, 0] * r[:, 1] - axes[:, 1] * r[:, 0]
    jac[3:] = axes.T
    return pose, jac


def rotation_error(r_target: FloatArray, r_actual: FloatArray) -> FloatArray:
    """Rotation vector (3,), rad, that turns ``r_actual`` into ``r_target`` (base frame).

    ``R_target = Rot(e) @ R_actual``; robust near a half turn (via SciPy's rotation).
    """
    from scipy.spatial.transform import Rotation

    m = r_target @ r_actual.T
    # Fast path for small errors (the IK's case): the skew part is sin(angle) * axis.
    skew = 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    s = float(np.linalg.norm(skew))
    if s < 0.5 and m[0, 0] + m[1, 1] + m[2, 2] > 1.0:  # angle < 30 degrees
        return skew * (math.asin(s) / s) if s > 1e-12 else skew
    return np.asarray(Rotation.from_matrix(m).as_rotvec())


def solve_ik(
    spec: RobotSpec,
    target: ArrayLike,
    q_seed: ArrayLike,
    *,
    tool: ArrayLike | None = None,
    tol_m: float = 1e-9,
    tol_rad: float = 1e-9,
    max_iterations: int = 100,
    damping: float = 1e-3,
    position_only: bool = False,
    closed_form: bool = True,
) -> FloatArray:
    """Joint angles that put the tool centre point at ``target``, near ``q_seed``.

    UR arms and arms with a spherical wrist (the KR 5): the closed form, each branch
    (shoulder, elbow, wrist) the seed's (:mod:`timedexec.robots._ur_ik`,
    :mod:`timedexec.robots._wrist_ik`). Otherwise, and near a singularity:
    damped least squares (Levenberg-Marquardt) on the pose error, from the seed: each step
    solves ``(J Jᵀ + λ² I) y = e``, ``Δq = Jᵀ y`` with the damping ``λ`` raised while a
    step does not reduce the error (Wampler 1986; Nakamura and Hanafusa's damped inverse
    near singularities). The solution stays on the seed's branch (elbow up/down, wrist
    flip): seed with the previous sample when following a path.

    Parameters
    ----------
    spec : RobotSpec
    target : array_like, shape (4, 4) or (3,)
        Target pose of the TCP in the base frame (m); a point (3,) fixes the position only.
    q_seed : array_like, shape (6,)
        Start of the iteration, rad (inside the joint limits).
    tool : array_like, optional
        See :func:`tool_pose`.
    tol_m, tol_rad : float
        Convergence: position error below ``tol_m`` (m) and orientation error below
        ``tol_rad`` (rad).
    max_iterations : int
        Iterations before giving up.
    damping : float
        Initial damping ``λ`` (m or rad); grows tenfold after a rejected step.
    position_only : bool
        Solve the position only (the orientation is free); implied by a (3,) target.
    closed_form : bool
        Use a closed form where one applies (default); False always iterates.

    Returns
    -------
    ndarray, shape (6,)
        Vendor joint angles, rad, inside the joint limits.

    Raises
    ------
    ConfigError
        When the pose is out of reach from this seed or the solution leaves the joint
        limits; the message gives the remaining error.
    """
    try:
        seed = np.asarray(q_seed, dtype=float)
    except (TypeError, ValueError):
        seed = np.empty(0)  # check_configuration names what is wrong with it
    if seed.shape == (6,) and all(
        lo <= v <= hi
        for v, lo, hi in zip(seed.tolist(), spec.q_min_rad, spec.q_max_rad, strict=True)
    ):
        q = seed.copy()  # the common case, checked in plain floats (a NaN fails the test)
    else:
        q = check_configuration(spec, q_seed).astype(float).copy()  # raises, naming it
    tgt = np.asarray(target, dtype=float)
    if tgt.shape == (3,):
        position_only = True
        pose = np.eye(4)
        pose[:3, 3] = tgt
    elif tgt.shape == (4, 4) and math.isfinite(float(tgt.sum())):  # a NaN or inf sums so
        pose = tgt
    else:
        raise ConfigError(
            f"target must be a 4 x 4 pose or a point (3,), m, finite; got shape {tgt.shape}"
        )
    tcp = _tool(tool)
    if closed_form and not position_only:
        # UR and spherical-wrist arms: the closed form on the seed's branch (exact, tens of
        # µs); None near a singularity or for another arm, and a solution beyond a limit:
        # iterate.
        # flange = pose @ tcp⁻¹ in plain floats (3 x 3 numpy products cost µs each)
        m, t = pose.tolist(), tcp.tolist()
        rot = [[sum(m[i][k] * t[j][k] for k in range(3)) for j in range(3)] for i in range(3)]
        flange = np.array(
            [[*rot[i], m[i][3] - sum(rot[i][k] * t[k][3] for k in range(3))] for i in range(3)]
            + [[0.0, 0.0, 0.0, 1.0]]
        )
        closed = ur_closed_form(spec, flange, q)
        if closed is None:
            closed = wrist_closed_form(spec, flange, q)
        if closed is not None and all(
            lo <= v <= hi
            for v, lo, hi in zip(closed.tolist(), spec.q_min_rad, spec.q_max_rad, strict=True)
        ):
            return closed
    lo, hi = np.asarray(spec.q_min_rad), np.asarray(spec.q_max_rad)
    rows = slice(0, 3) if position_only else slice(0, 6)
    eye = np.eye(3 if position_only else 6)

    def error(qq: FloatArray) -> tuple[FloatArray, FloatArray]:
        cur, jac = _frames_one(spec, qq, tcp)
        e = np.empty(6)
        e[:3] = pose[:3, 3] - cur[:3, 3]
        e[3:] = 0.0 if position_only else rotation_error(pose[:3, :3], cur[:3, :3])
        return e, jac

    e, jac = error(q)
    cost = float(e[rows] @ e[rows])
    lam = float(damping)
    for _ in range(int(max_iterations)):
        if math.sqrt(e[0] ** 2 + e[1] ** 2 + e[2] ** 2) < tol_m and (
            math.sqrt(e[3] ** 2 + e[4] ** 2 + e[5] ** 2) < tol_rad
        ):
            break
        jr = jac[rows]
        step = jr.T @ np.linalg.solve(jr @ jr.T + (lam * lam) * eye, e[rows])
        q_new = np.minimum(np.maximum(q + step, lo), hi)
        e_new, jac_new = error(q_new)
        cost_new = float(e_new[rows] @ e_new[rows])
        if cost_new < cost:
            q, e, jac, cost = q_new, e_new, jac_new, cost_new
            lam = max(lam * 0.1, 1e-9)
        else:
            lam *= 10.0
            if lam > 1e3:
                break
    pos_err = float(np.linalg.norm(e[:3]))
    rot_err = float(np.linalg.norm(e[3:]))
    # Accept what Newton's method cannot improve in the last bits (1000 x the tolerance).
    if pos_err > 1e3 * tol_m or rot_err > 1e3 * tol_rad:
        raise ConfigError(
            f"{spec.name}: no joint configuration near the seed puts the tool at "
            f"{pose[:3, 3].round(4).tolist()} m (closest {pos_err * 1e3:.2f} mm and "
            f"{math.degrees(rot_err):.2f}° away); the pose is out of reach or beyond a joint "
            "limit from this seed: move the target closer or seed from a nearer configuration"
        )
    return q
