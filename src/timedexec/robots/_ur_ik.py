"""Closed-form inverse kinematics of the Universal Robots arm family, on this package's DH
tables (``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``; UR: ``alpha = (pi/2, 0, 0, pi/2,
-pi/2, 0)``, ``a = (0, a2, a3, 0, 0, 0)``, vendor angles equal DH angles).

Derived here from that chain (the geometry of Hawkins' "Analytic inverse kinematics for the
Universal Robots UR-5/UR-10 arms", 2013): with ``p`` the flange position, ``z1 = (sin q1,
-cos q1, 0)`` the axis of joints 2-4 and ``p5 = p - d6 z6`` the wrist centre,

* ``(p5 - d1 e_z) . z1 = d4`` gives ``q1 = phi + asin(d4 / r)`` or ``phi + pi - asin(d4 / r)``
  (``p5 = r (cos phi, sin phi)`` in the base plane);
* ``p . z1 = d4 + d6 cos q5`` gives ``q5 = +-acos(...)``;
* the third row of ``R01^T R06 = Rz(q234) Rx(pi/2) Rz(q5) Rx(-pi/2) Rz(q6)`` gives ``q6``;
* the planar arm of joints 2-4 gives ``q3 = +-acos(...)``, ``q2`` and ``q4``.

Each choice (shoulder, wrist, elbow) is taken from the seed, so a path sampled finely stays
on the seed's branch exactly as the damped Newton iteration it replaces does; every angle
is wrapped to the turn nearest the seed's. Near a singularity (wrist: ``sin q5 ~ 0``;
shoulder: ``r ~ d4``; elbow stretched) or outside the reach this returns None and
:func:`timedexec.robots.solve_ik` iterates instead. One solve costs a few tens of µs in
plain floats (the iteration: 0.2-0.5 ms, three forward kinematics with Jacobians).
"""

from __future__ import annotations

import math

import numpy as np

from timedexec._types import FloatArray
from timedexec.robots._dynamics import _params
from timedexec.robots._spec import RobotSpec, spec_cache

__all__ = ["ur_closed_form"]


_UR_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
#: Below this |sin q5| (wrist), |1 - (d4 / r)^2| (shoulder) or |sin q3| (elbow) the branch is
#: ill-conditioned: the iteration takes over.
_SINGULAR = 1e-6


@spec_cache
def _ur_geometry(spec: RobotSpec) -> tuple[float, float, float, float, float, float] | None:
    """``(d1, a2, a3, d4, d5, d6)`` when ``spec``'s DH table has the UR structure, else None."""
    p = _params(spec)
    sign, offset = np.asarray(p.sign, float), np.asarray(p.offset, float)
    ca, sa = np.asarray(p.ca, float), np.asarray(p.sa, float)
    d, a = np.asarray(p.d, float), np.asarray(p.a, float)
    ur = (
        np.all(sign == 1.0)
        and np.all(offset == 0.0)
        and np.allclose(ca, np.cos(_UR_ALPHA), atol=1e-12)
        and np.allclose(sa, np.sin(_UR_ALPHA), atol=1e-12)
        and a[0] == 0.0
        and np.all(a[3:] == 0.0)
        and np.all(d[1:3] == 0.0)
        and a[1] != 0.0
        and a[2] != 0.0
        and d[5] != 0.0
    )
    if not ur:
        return None
    return float(d[0]), float(a[1]), float(a[2]), float(d[3]), float(d[4]), float(d[5])


def _near(angle: float, seed: float) -> float:
    """``angle`` plus the whole turns that bring it nearest ``seed``."""
    return angle + 2.0 * math.pi * round((seed - angle) / (2.0 * math.pi))


def _pick(candidates: tuple[float, float], seed: float) -> float:
    a, b = (_near(c, seed) for c in candidates)
    return a if abs(a - seed) <= abs(b - seed) else b


def _acos_branch(cosine: float, seed: float) -> tuple[float, float] | None:
    """The angle with this cosine on the seed's side (+ or -), and its sine; None out of
    range or where the two sides meet (sine below :data:`_SINGULAR`)."""
    if abs(cosine) > 1.0:
        return None
    a = math.acos(cosine)
    q = _pick((a, -a), seed)
    sine = math.sin(q)
    return None if abs(sine) < _SINGULAR else (q, sine)


def ur_closed_form(spec: RobotSpec, flange: FloatArray, seed: FloatArray) -> FloatArray | None:
    """Joint angles (6,) that put the flange at ``flange`` (4 x 4, base frame) on the seed's
    branch, or None (not a UR chain, a singular branch, out of reach)."""
    geo = _ur_geometry(spec)
    if geo is None:
        return None
    d1, a2, a3, d4, d5, d6 = geo
    m = flange.tolist()
    nx, ny, nz = m[0][0], m[1][0], m[2][0]
    ox, oy, oz = m[0][1], m[1][1], m[2][1]
    ax, ay, az = m[0][2], m[1][2], m[2][2]
    px, py, pz = m[0][3], m[1][3], m[2][3]
    s = [float(v) for v in seed]
    # Shoulder (q1): the wrist centre's distance from joint 2's plane is d4.
    p5x, p5y = px - d6 * ax, py - d6 * ay
    r = math.hypot(p5x, p5y)
    if r <= abs(d4) or 1.0 - (d4 / r) ** 2 < _SINGULAR:
        return None
    phi, beta = math.atan2(p5y, p5x), math.asin(d4 / r)
    q1 = _pick((phi + beta, phi + math.pi - beta), s[0])
    s1, c1 = math.sin(q1), math.cos(q1)
    # Wrist 2 (q5): the flange's height along z1 is d4 + d6 cos q5.
    c5 = (px * s1 - py * c1 - d4) / d6
    wrist = _acos_branch(c5, s[4])
    if wrist is None:
        return None
    q5, s5 = wrist
    # Wrist 3 (q6): z1^T R06 = e_z^T Rx(pi/2) R46 = row 1 of R46 = (s5 c6, -s5 s6, c5), with
    # R46 = Rz(q5) Rx(-pi/2) Rz(q6) = [[c5 c6, -c5 s6, -s5], [s5 c6, -s5 s6, c5], [-s6, -c6, 0]].
    t0 = s1 * nx - c1 * ny
    t1 = s1 * ox - c1 * oy
    q6 = _near(math.atan2(-t1 / s5, t0 / s5), s[5])
    s6, c6 = math.sin(q6), math.cos(q6)
    # Frame 4 (base): x4 = R06 (row 0 of R46), z4 = R06 (row 2 of R46); o4 = p5 - d5 z4.
    x4 = (
        (nx * c6 - ox * s6) * c5 - ax * s5,
        (ny * c6 - oy * s6) * c5 - ay * s5,
        (nz * c6 - oz * s6) * c5 - az * s5,
    )
    z4 = (-nx * s6 - ox * c6, -ny * s6 - oy * c6, -nz * s6 - oz * c6)
    o4 = (p5x - d5 * z4[0], p5y - d5 * z4[1], pz - d6 * az - d5 * z4[2])
    # Frame 1: origin (0, 0, d1), x1 = (c1, s1, 0), y1 = (0, 0, 1) (Rz(q1) Rx(pi/2)).
    x = o4[0] * c1 + o4[1] * s1
    y = o4[2] - d1
    c3 = (x * x + y * y - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
    elbow = _acos_branch(c3, s[2])
    if elbow is None:
        return None
    q3, s3 = elbow
    q2 = _near(math.atan2(y, x) - math.atan2(a3 * s3, a2 + a3 * c3), s[1])
    # x4 in frame 1 is (cos q234, sin q234, 0).
    q234 = math.atan2(x4[2], x4[0] * c1 + x4[1] * s1)
    q4 = _near(q234 - q2 - q3, s[3])
    return np.array([q1, q2, q3, q4, q5, q6])
