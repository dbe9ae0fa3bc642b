"""Closed-form inverse kinematics of arms with a spherical wrist (the KUKA KR 5 family), on
this package's DH tables (``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, DH angle
``theta_i = sign_i q_i + offset_i``).

Applies to chains with ``d2 = d3 = 0`` (no lateral offset: the arm of joints 2-3 moves in
one plane), ``alpha2 = 0``, ``|sin alpha1| = |sin alpha3| = 1`` and a spherical wrist: axes 4,
5 and 6 meet (``a4 = a5 = d5 = 0``, ``alpha4 = -alpha5 = +-pi/2``, ``alpha6 = 0``). Pieper's
decoupling, derived here from that chain: with ``p`` the flange position and ``z6`` its
approach axis, the wrist centre is ``w = p - d6 z6`` (``= o4 = o5``), and

* ``w`` lies in the arm plane, ``(w - o1) . z1 = 0`` with ``z1 = Rz(theta1) (0, -sin alpha1,
  0)``: ``theta1 = atan2(w_y, w_x)`` or that + pi (reaching over the base);
* in frame 1 the arm is planar, ``w1 = Rz(theta2) [(a2, 0) + (a3 c3 + d4 s_a3 s3,
  a3 s3 - d4 s_a3 c3)]`` (``s_a3 = sin alpha3``): ``|w1|^2`` gives ``theta3 = gamma +- acos(k /
  L)`` (``L = hypot(a3, d4)``, ``gamma = atan2(d4 s_a3, a3)``), then ``theta2`` from the angle
  of ``w1``;
* ``R03^T R06 = Rz(theta4) Rx(alpha4) Rz(theta5) Rx(-alpha4) Rz(theta6) = Rz(theta4)
  Ry(b) Rz(theta6)`` with ``b = -sin(alpha4) theta5`` (a rotation about ``Rx(alpha4) e_z``):
  ``cos b`` is its (2, 2) entry, ``theta4`` and ``theta6`` follow from the last column and row.

Each choice (shoulder, elbow, wrist) is the seed's, every angle wrapped to the turn nearest
the seed's, as :func:`timedexec.robots._ur_ik.ur_closed_form` does for the UR family. Near a
singularity (wrist centre on the base axis, elbow stretched or folded, ``sin b ~ 0``) or out
of reach this returns None and :func:`timedexec.robots.solve_ik` iterates.
"""

from __future__ import annotations

import math

import numpy as np

from timedexec._types import FloatArray
from timedexec.robots._dynamics import _params
from timedexec.robots._spec import RobotSpec, spec_cache
from timedexec.robots._ur_ik import _SINGULAR, _acos_branch, _near, _pick

__all__ = ["wrist_closed_form"]


class _Geometry:
    """The constants of a spherical-wrist chain the closed form needs."""

    def __init__(self, d: FloatArray, a: FloatArray, ca: FloatArray, sa: FloatArray,
                 sign: FloatArray, offset: FloatArray) -> None:  # fmt: skip
        self.d1, self.a1, self.a2, self.a3 = float(d[0]), float(a[0]), float(a[1]), float(a[2])
        self.d4, self.d6 = float(d[3]), float(d[5])
        self.ca1, self.sa1 = float(ca[0]), float(sa[0])
        self.ca3, self.sa3 = float(ca[2]), float(sa[2])
        self.sa4 = float(sa[3])
        self.sign = [float(s) for s in sign]
        self.offset = [float(o) for o in offset]
        self.length = math.hypot(self.a3, self.d4)
        self.gamma = math.atan2(self.d4 * self.sa3, self.a3)


@spec_cache
def _wrist_geometry(spec: RobotSpec) -> _Geometry | None:
    """The chain's constants when ``spec``'s DH table has a planar arm and a spherical wrist
    (see the module docstring), else None."""
    p = _params(spec)
    d, a = np.asarray(p.d, float), np.asarray(p.a, float)
    ca, sa = np.asarray(p.ca, float), np.asarray(p.sa, float)
    sign = np.asarray(p.sign, float)
    fits = (
        np.all(np.abs(sign) == 1.0)
        and d[1] == 0.0
        and d[2] == 0.0
        and a[3] == 0.0
        and a[4] == 0.0
        and a[5] == 0.0
        and d[4] == 0.0
        and abs(sa[1]) < 1e-12
        and ca[1] > 0
        and abs(abs(sa[0]) - 1.0) < 1e-12
        and abs(abs(sa[2]) - 1.0) < 1e-12
        and abs(abs(sa[3]) - 1.0) < 1e-12
        and abs(sa[3] + sa[4]) < 1e-12
        and abs(sa[5]) < 1e-12
        and ca[5] > 0
        and a[1] != 0.0
    )
    if not fits:
        return None
    return _Geometry(d, a, ca, sa, sign, np.asarray(p.offset, float))


def wrist_closed_form(spec: RobotSpec, flange: FloatArray, seed: FloatArray) -> FloatArray | None:
    """Joint angles (6,) that put the flange at ``flange`` (4 x 4, base frame) on the seed's
    branch, or None (not a spherical-wrist chain, a singular branch, out of reach)."""
    geo = _wrist_geometry(spec)
    if geo is None:
        return None
    sg, off = geo.sign, geo.offset
    th_seed = [sg[i] * float(seed[i]) + off[i] for i in range(6)]
    m = flange.tolist()
    ax, ay, az = m[0][2], m[1][2], m[2][2]
    wx, wy, wz = m[0][3] - geo.d6 * ax, m[1][3] - geo.d6 * ay, m[2][3] - geo.d6 * az
    # Shoulder: the wrist centre's azimuth (or the opposite one, reaching over the base).
    if math.hypot(wx, wy) < 1e3 * _SINGULAR:
        return None
    phi = math.atan2(wy, wx)
    t1 = _pick((phi, phi + math.pi), th_seed[0])
    c1, s1 = math.cos(t1), math.sin(t1)
    # Frame 1: origin (a1 c1, a1 s1, d1); axes x1 = (c1, s1, 0), y1 = Rz(t1) (0, ca1, sa1).
    rx, ry, rz = wx - geo.a1 * c1, wy - geo.a1 * s1, wz - geo.d1
    u = rx * c1 + ry * s1
    v = (-rx * s1 + ry * c1) * geo.ca1 + rz * geo.sa1
    # Elbow: |w1|^2 = a2^2 + L^2 + 2 a2 L cos(t3 - gamma).
    k = (u * u + v * v - geo.a2**2 - geo.length**2) / (2.0 * geo.a2 * geo.length)
    elbow = _acos_branch(k, th_seed[2] - geo.gamma)
    if elbow is None:
        return None
    t3 = elbow[0] + geo.gamma
    c3, s3 = math.cos(t3), math.sin(t3)
    ex = geo.a2 + geo.a3 * c3 + geo.d4 * geo.sa3 * s3
    ey = geo.a3 * s3 - geo.d4 * geo.sa3 * c3
    t2 = _near(math.atan2(v, u) - math.atan2(ey, ex), th_seed[1])
    # R03 = Rz(t1) Rx(alpha1) Rz(t2 + t3) Rx(alpha3) = A B (plain floats: a few µs where
    # numpy's 3 x 3 products cost tens); W = R03^T R06 = Rz(t4) Ry(b) Rz(t6), of which the
    # last column and row are needed: W[i][j] = (column i of R03) . (column j of R06).
    c23, s23 = math.cos(t2 + t3), math.sin(t2 + t3)
    ca1, sa1, ca3, sa3 = geo.ca1, geo.sa1, geo.ca3, geo.sa3
    a_rows = ((c1, -s1 * ca1, s1 * sa1), (s1, c1 * ca1, -c1 * sa1), (0.0, sa1, ca1))
    b_cols = ((c23, s23, 0.0), (-s23 * ca3, c23 * ca3, sa3), (s23 * sa3, -c23 * sa3, ca3))
    r03 = [[r[0] * c[0] + r[1] * c[1] + r[2] * c[2] for c in b_cols] for r in a_rows]
    col = [[m[k][j] for k in range(3)] for j in range(3)]  # columns of R06

    def w(i: int, j: int) -> float:
        return r03[0][i] * col[j][0] + r03[1][i] * col[j][1] + r03[2][i] * col[j][2]

    b_seed = -geo.sa4 * th_seed[4]
    wrist = _acos_branch(max(-1.0, min(1.0, w(2, 2))), b_seed)
    if wrist is None:
        return None
    b, sb = wrist
    t4 = _near(math.atan2(w(1, 2) / sb, w(0, 2) / sb), th_seed[3])
    t6 = _near(math.atan2(w(2, 1) / sb, -w(2, 0) / sb), th_seed[5])
    theta = (t1, t2, t3, t4, -geo.sa4 * b, t6)
    return np.array([_near((theta[i] - off[i]) * sg[i], float(seed[i])) for i in range(6)])
