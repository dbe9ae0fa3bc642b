"""Kinematics and rigid-body quantities of a :class:`~timedexec.robots.RobotSpec`.

Plain functions on (6,) or (N, 6) arrays of joint angles: frames
(:func:`forward_kinematics`), the torque each joint holds against gravity
(:func:`gravity_torque`, :func:`gravity_torque_coefficients`), the inertia each joint
accelerates (:func:`joint_inertia`) and what a gyro on the flange sees when one joint moves
(:func:`joint_axis_in_tool`). Conventions: see :mod:`timedexec.robots`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.robots._spec import N_JOINTS, RobotSpec, _as_configurations, spec_cache

__all__ = [
    "forward_kinematics",
    "gravity_torque",
    "gravity_torque_coefficients",
    "joint_axis_in_tool",
    "joint_inertia",
]


# --------------------------------------------------------------------------------------
# Input normalisation
# --------------------------------------------------------------------------------------


def _as_joints(joint: int | ArrayLike, n: int) -> tuple[NDArray[np.intp], bool]:
    """Return 0-based joint indices of shape (n,) (or (k,) to broadcast a single row).

    The second value tells whether ``joint`` was a scalar.
    """
    arr = np.asarray(joint)
    if arr.dtype == np.bool_ or not (
        np.issubdtype(arr.dtype, np.integer)
        or (np.issubdtype(arr.dtype, np.floating) and np.all(np.mod(arr, 1) == 0))
    ):
        raise ConfigError(f"joint must be an integer 1..{N_JOINTS} (1-based), got {joint!r}")
    if arr.ndim > 1:
        raise ConfigError(f"joint must be a scalar or shape (N,), got shape {arr.shape}")
    bad = (arr < 1) | (arr > N_JOINTS)
    if np.any(bad):
        value = arr.flat[int(np.argmax(bad.ravel()))]
        raise ConfigError(f"joint {value} is out of range: joints are numbered 1 to {N_JOINTS}")
    idx = arr.astype(np.intp) - 1
    if arr.ndim == 0:
        return np.full(n, int(idx), dtype=np.intp), True
    if idx.shape[0] != n and n != 1:
        raise ConfigError(
            f"joint has {idx.shape[0]} entries but q has {n} rows; give one joint per row "
            f"or a single joint for all rows"
        )
    return idx, False


# --------------------------------------------------------------------------------------
# Cached numpy views of a spec
# --------------------------------------------------------------------------------------


class _Params(NamedTuple):
    a: FloatArray  # (6,)
    d: FloatArray
    ca: FloatArray  # cos alpha
    sa: FloatArray  # sin alpha
    offset: FloatArray
    sign: FloatArray
    mass: FloatArray  # (6,) links
    com: FloatArray  # (6, 3) in own frame
    inertia: FloatArray  # (6, 3) principal, own frame axes
    rotor: FloatArray  # (6,)
    payload: float
    suffix_mass: FloatArray  # (6,) mass of links j..6 plus payload, for joint j


@spec_cache
def _params(spec: RobotSpec) -> _Params:
    alpha = np.asarray(spec.dh_alpha_rad)
    mass = np.asarray(spec.link_mass_kg)
    suffix = np.cumsum(mass[::-1])[::-1] + spec.payload_kg
    return _Params(
        a=np.asarray(spec.dh_a_m),
        d=np.asarray(spec.dh_d_m),
        ca=np.cos(alpha),
        sa=np.sin(alpha),
        offset=np.asarray(spec.dh_offset_rad),
        sign=np.asarray(spec.joint_sign),
        mass=mass,
        com=np.asarray(spec.link_com_m),
        inertia=np.asarray(spec.link_inertia_kgm2),
        rotor=np.asarray(spec.rotor_inertia_kgm2),
        payload=spec.payload_kg,
        suffix_mass=suffix,
    )


class _Chain(NamedTuple):
    """Frames 0..6 in base coordinates, component-major: each array is (7, 3, N).

    ``x[i, :, n]`` is the x axis of frame ``i`` for configuration ``n``; ``o`` holds the
    origins. Keeping the batch axis last and contiguous makes every update below a
    contiguous element-wise operation, much faster than batched 4×4 products.
    """

    x: FloatArray
    y: FloatArray
    z: FloatArray
    o: FloatArray


#: Largest batch whose chain is remembered (see :func:`_chain`).
_CHAIN_MEMO_ROWS = 8
#: The last small batch's chain: (robot parameters, configurations' shape and dtype, their
#: bytes, chain).
_chain_memo: tuple[_Params, tuple[object, ...], bytes, _Chain] | None = None


def _chain(p: _Params, q: FloatArray) -> _Chain:
    """Frames 0..6 for (N, 6) vendor angles.

    Standard DH, ``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, applied to the columns
    of the rotation: ``Rz`` mixes x and y, ``Rx`` then mixes the new y with z.

    The chain of the last small batch (at most ``_CHAIN_MEMO_ROWS`` rows) is remembered,
    read-only: a stepped controller refreshing its pose-dependent parameters asks for the
    gravity coefficients, the inertia and the joint axes of one pose in a row, and the
    chain's ~60 small array operations were a fifth of the UR twin's clock thread.
    """
    global _chain_memo
    small = q.shape[0] <= _CHAIN_MEMO_ROWS
    if small:
        layout, key = (q.shape, q.dtype.str), q.tobytes()
        memo = _chain_memo
        if memo is not None and memo[0] is p and memo[1] == layout and memo[2] == key:
            return memo[3]
    n = q.shape[0]
    theta = (q * p.sign + p.offset).T  # (6, N)
    ct, st = np.cos(theta), np.sin(theta)
    x = np.zeros((N_JOINTS + 1, 3, n))
    y = np.zeros_like(x)
    z = np.zeros_like(x)
    o = np.zeros_like(x)
    x[0, 0], y[0, 1], z[0, 2] = 1.0, 1.0, 1.0
    for i in range(N_JOINTS):  # over the 6 links of the chain, never over rows
        c, s = ct[i], st[i]
        xi, yi, zi = x[i], y[i], z[i]
        x_new = c * xi + s * yi
        y_rot = c * yi - s * xi
        x[i + 1] = x_new
        y[i + 1] = p.ca[i] * y_rot + p.sa[i] * zi
        z[i + 1] = p.ca[i] * zi - p.sa[i] * y_rot
        o[i + 1] = o[i] + p.d[i] * zi + p.a[i] * x_new
    chain = _Chain(x, y, z, o)
    if small:
        for a in chain:
            a.setflags(write=False)
        _chain_memo = (p, layout, key, chain)
    return chain


def _outer(a: FloatArray, b: FloatArray) -> FloatArray:
    """Outer products: (..., 3, N), (..., 3, N) -> (..., 3, 3, N)."""
    return a[..., :, None, :] * b[..., None, :, :]


def _quadratic(m: FloatArray, v: FloatArray) -> FloatArray:
    """vᵀ M v: (..., 3, 3, N), (..., 3, N) -> (..., N)."""
    out: FloatArray = (m * _outer(v, v)).sum(axis=(-3, -2))
    return out


def _suffix_sum(a: FloatArray) -> FloatArray:
    """Sum over links j..6 along axis 0 (index j-1 then holds links j..6)."""
    return np.cumsum(a[::-1], axis=0)[::-1]


def _link_coms(p: _Params, ch: _Chain) -> FloatArray:
    """Centres of mass of links 1..6 in base coordinates, (6, 3, N)."""
    c = p.com[:, :, None, None]  # (6, 3, 1, 1)
    return ch.o[1:] + ch.x[1:] * c[:, 0] + ch.y[1:] * c[:, 1] + ch.z[1:] * c[:, 2]


def _gravity_moments(p: _Params, ch: _Chain) -> FloatArray:
    """First mass moment of links j..6 (+ payload) about the origin of frame j-1, (6, 3, N).

    ``r_j = sum_{i >= j} m_i (c_i - o_{j-1})`` in base coordinates, kg·m.
    """
    weighted = _link_coms(p, ch) * p.mass[:, None, None]
    weighted[-1] += p.payload * ch.o[-1]  # payload: point mass at the flange origin
    return _suffix_sum(weighted) - p.suffix_mass[:, None, None] * ch.o[:-1]


def _select(a: FloatArray, idx: NDArray[np.intp]) -> FloatArray:
    """Pick entry ``idx[n]`` of axis 0 for each configuration n: (6, 3, N) -> (N, 3)."""
    return a[idx, :, np.arange(idx.shape[0])]


# --------------------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------------------


def forward_kinematics(spec: RobotSpec, q: ArrayLike) -> FloatArray:
    """Homogeneous transforms of the base frame and DH frames 1..6 in the base frame.

    Parameters
    ----------
    spec : RobotSpec
        The robot.
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad. Limits are not checked (see :func:`check_configuration`).

    Returns
    -------
    ndarray, shape (N, 7, 4, 4) or (7, 4, 4)
        ``T[..., 0, :, :]`` is the identity (base frame); ``T[..., i, :, :]`` is DH frame
        ``i``, at the distal end of link ``i``; index 6 is the flange. Translations in m.
    """
    arr, single = _as_configurations(q)
    ch = _chain(_params(spec), arr)
    frames = np.zeros((arr.shape[0], N_JOINTS + 1, 4, 4))
    frames[..., :3, :3] = np.stack((ch.x, ch.y, ch.z), axis=2).transpose(3, 0, 1, 2)
    frames[..., :3, 3] = ch.o.transpose(2, 0, 1)
    frames[..., 3, 3] = 1.0
    return frames[0] if single else frames


def gravity_torque(spec: RobotSpec, q: ArrayLike, *, g_m_s2: float = 9.81) -> FloatArray:
    """Torque each joint must supply to hold the configuration against gravity.

    ``tau_j = dV/dq_j`` with ``V`` the potential energy of links and payload, so the sign
    follows the vendor's joint direction: positive means the motor pushes in the positive
    joint direction.

    Parameters
    ----------
    spec : RobotSpec
        The robot (its ``payload_kg`` is included).
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad.
    g_m_s2 : float
        Gravitational acceleration, m/s², along -z of the base frame.

    Returns
    -------
    ndarray, shape (N, 6) or (6,)
        Holding torque per joint, N·m. Joint 1 of a floor-mounted arm is always 0.
    """
    arr, single = _as_configurations(q)
    p = _params(spec)
    ch = _chain(p, arr)
    r = _gravity_moments(p, ch)  # (6, 3, N)
    z = ch.z[:-1]  # (6, 3, N) axis of joint j
    # dV/dtheta_j = g e_z · (z_{j-1} × r_j); dV/dq_j = joint_sign_j · dV/dtheta_j.
    tau = (g_m_s2 * p.sign[:, None]) * (z[:, 0] * r[:, 1] - z[:, 1] * r[:, 0])
    return tau[:, 0] if single else np.ascontiguousarray(tau.T)


def gravity_torque_coefficients(
    spec: RobotSpec, q: ArrayLike, joint: int | ArrayLike, *, g_m_s2: float = 9.81
) -> tuple[FloatArray, FloatArray]:
    """Holding torque of one joint as a function of its own angle, ``A cos x + B sin x``.

    With every other joint fixed at ``q``, the gravity torque of ``joint`` at vendor angle
    ``x`` is exactly ``A * cos(x) + B * sin(x)``: the distal links' mass moment turns
    rigidly with the joint about a fixed axis.

    Parameters
    ----------
    spec : RobotSpec
        The robot (payload included).
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad; the entry of ``joint`` itself is irrelevant.
    joint : int or array_like of int, shape (N,)
        1-based joint, one for all rows or one per row.
    g_m_s2 : float
        Gravitational acceleration, m/s².

    Returns
    -------
    A, B : ndarray, shape (N,) (shape () for a single configuration and a scalar joint)
        Coefficients, N·m.
    """
    arr, single = _as_configurations(q)
    idx, scalar_joint = _as_joints(joint, arr.shape[0])
    if arr.shape[0] != idx.shape[0]:  # one configuration, one joint per output row
        arr = np.broadcast_to(arr, (idx.shape[0], N_JOINTS))
    p = _params(spec)
    ch = _chain(p, arr)
    r = _select(_gravity_moments(p, ch), idx)  # (N, 3), base coordinates
    # Express r and "up" (base e_z) in frame j-1, about whose z axis joint j turns.
    xj, yj = _select(ch.x, idx), _select(ch.y, idx)
    rx, ry = (xj * r).sum(axis=1), (yj * r).sum(axis=1)
    kx, ky = xj[:, 2], yj[:, 2]
    sign, off = p.sign[idx], p.offset[idx]
    theta = sign * arr[np.arange(idx.shape[0]), idx] + off
    c, s = np.cos(theta), np.sin(theta)
    # Undo the joint's own rotation, r = Rz(theta) u; u stays fixed while the joint turns.
    ux = c * rx + s * ry
    uy = c * ry - s * rx
    # tau = sign·g·(k_y r_x - k_x r_y) = P cos(theta) + Q sin(theta) ...
    big_p = g_m_s2 * sign * (ky * ux - kx * uy)
    big_q = -g_m_s2 * sign * (kx * ux + ky * uy)
    # ... and with theta = sign·x + offset: A cos(x) + B sin(x).
    co, so = np.cos(off), np.sin(off)
    coef_a = big_p * co + big_q * so
    coef_b = sign * (big_q * co - big_p * so)
    if single and scalar_joint:
        return coef_a[0], coef_b[0]
    return coef_a, coef_b


def joint_inertia(spec: RobotSpec, q: ArrayLike) -> FloatArray:
    """Diagonal of the joint-space mass matrix: the inertia each joint accelerates alone.

    ``M_jj = sum_{i >= j} (m_i |z_{j-1} x (c_i - o_{j-1})|² + z_{j-1}ᵀ R_i I_i R_iᵀ z_{j-1})
    + rotor_j``: the composite rigid body of links j..6 (and the payload point mass) about
    the axis of joint j, plus the reflected rotor inertia.

    Parameters
    ----------
    spec : RobotSpec
        The robot.
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad.

    Returns
    -------
    ndarray, shape (N, 6) or (6,)
        Inertia about each joint axis, kg·m².
    """
    arr, single = _as_configurations(q)
    p = _params(spec)
    ch = _chain(p, arr)
    com = _link_coms(p, ch)  # (6, 3, N)
    flange = ch.o[-1]
    # Per link, in base coordinates: first moment m c, second moment m c cᵀ and the link's
    # own inertia about its COM, R diag(I) Rᵀ = sum_k I_k e_k e_kᵀ over the frame's axes.
    first = com * p.mass[:, None, None]
    second = _outer(first, com)
    first[-1] += p.payload * flange
    second[-1] += p.payload * _outer(flange, flange)
    inertia = p.inertia[:, :, None, None, None]  # (6, 3, 1, 1, 1)
    own = (
        inertia[:, 0] * _outer(ch.x[1:], ch.x[1:])
        + inertia[:, 1] * _outer(ch.y[1:], ch.y[1:])
        + inertia[:, 2] * _outer(ch.z[1:], ch.z[1:])
    )
    # Suffix sums: index j-1 holds the composite body of links j..6 (and the payload).
    first, second, own = _suffix_sum(first), _suffix_sum(second), _suffix_sum(own)
    o = ch.o[:-1]  # (6, 3, N) origin of frame j-1, a point on the axis of joint j
    z = ch.z[:-1]  # (6, 3, N) unit axis of joint j
    # sum m (c - o)(c - o)ᵀ = S2 - o S1ᵀ - S1 oᵀ + M o oᵀ  (S1 = sum m c, S2 = sum m c cᵀ)
    mass = p.suffix_mass[:, None, None, None]
    about_o = second - _outer(o, first) - _outer(first, o) + mass * _outer(o, o)
    # sum m |z × d|² = sum m (|d|² - (z·d)²) = trace(about_o) - zᵀ about_o z
    trace = about_o[:, 0, 0] + about_o[:, 1, 1] + about_o[:, 2, 2]
    total = trace - _quadratic(about_o, z) + _quadratic(own, z) + p.rotor[:, None]
    return total[:, 0] if single else np.ascontiguousarray(total.T)


def joint_axis_in_tool(spec: RobotSpec, q: ArrayLike, joint: int | ArrayLike) -> FloatArray:
    """Rotation axis of a joint (positive vendor direction) in the flange frame.

    A gyro fixed to the flange measures ``joint_axis_in_tool(spec, q, j) * qd_j`` (rad/s,
    flange axes) when joint ``j`` alone turns at ``qd_j``.

    Parameters
    ----------
    spec : RobotSpec
        The robot.
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad.
    joint : int or array_like of int, shape (N,)
        1-based joint, one for all rows or one per row.

    Returns
    -------
    ndarray, shape (N, 3) (shape (3,) for a single configuration and a scalar joint)
        Unit vectors in frame 6 coordinates.
    """
    arr, single = _as_configurations(q)
    idx, scalar_joint = _as_joints(joint, arr.shape[0])
    if arr.shape[0] != idx.shape[0]:  # one configuration, one joint per output row
        arr = np.broadcast_to(arr, (idx.shape[0], N_JOINTS))
    p = _params(spec)
    ch = _chain(p, arr)
    axis = _select(ch.z, idx) * p.sign[idx][:, None]  # (N, 3), base coordinates
    # Flange coordinates, R_6ᵀ axis: dot products with the flange frame's axes.
    tool = np.stack(
        [
            (ch.x[-1].T * axis).sum(axis=1),
            (ch.y[-1].T * axis).sum(axis=1),
            (ch.z[-1].T * axis).sum(axis=1),
        ],
        axis=1,
    )
    return tool[0] if single and scalar_joint else tool
