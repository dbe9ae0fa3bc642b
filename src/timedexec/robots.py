"""Robot specs: the single source of truth for every number about a robot.

A :class:`RobotSpec` holds a robot's standard Denavit-Hartenberg kinematics, its inertial data
(link masses, centres of mass, link and rotor inertia), its joint limits and its controller
period. The functions below turn a spec and joint configurations into the quantities the
rest of timedexec needs: frames (:func:`forward_kinematics`), the torque each joint holds
against gravity (:func:`gravity_torque`, :func:`gravity_torque_coefficients`), the inertia
each joint accelerates (:func:`joint_inertia`) and what a gyro on the flange sees when one
joint moves (:func:`joint_axis_in_tool`).

Conventions
-----------
* Joint angles ``q`` are the **vendor's** angles, the numbers a user types on the teach
  pendant (UR: rad as shown by PolyScope; KUKA: A1..A6). The DH joint angle is
  ``theta = joint_sign * q + dh_offset_rad``; KUKA's A1, A4 and A6 turn the other way round
  from the DH z axes, hence ``joint_sign = -1`` there.
* The base frame (frame 0) has z up, against gravity. DH frame ``i`` sits at the distal end
  of link ``i``; frame 6 is the flange (tool) frame. Joint ``j`` (1-based) turns about the z
  axis of frame ``j - 1``.
* Batches: every function accepts one configuration, shape (6,), or ``N`` of them, shape
  (N, 6), and answers with the matching leading shape.
* SI units: m, kg, kg·m², rad, rad/s, rad/s², N·m, s.

Why not roboticstoolbox-python
------------------------------
Everything here is a few vectorised numpy expressions over (N, 6) batches: six DH updates
of the frame axes for the kinematics, and suffix sums over the links (composite bodies) for
gravity and inertia. roboticstoolbox-python would bring a heavy dependency tree
(spatialmath, swift, compiled extensions) for this, and its per-configuration methods run a
Python loop per row, far slower for the 33,500-configuration sweeps of a calibration plan;
here such a sweep takes tens of milliseconds (see ``tests/test_robots.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError

__all__ = [
    "N_JOINTS",
    "ROBOT_NAMES",
    "RobotSpec",
    "check_configuration",
    "forward_kinematics",
    "get_robot",
    "gravity_torque",
    "gravity_torque_coefficients",
    "joint_axis_in_tool",
    "joint_inertia",
]

FloatArray = NDArray[np.float64]

#: Number of joints of every robot described here.
N_JOINTS = 6

#: Names accepted by :func:`get_robot`.
ROBOT_NAMES: tuple[str, ...] = ("ur10", "ur10e", "kr5")

# Joint-limit checks accept values this far outside a limit (rad): limits given in degrees
# and converted to rad, or angles read back from a controller, differ in the last bits.
_LIMIT_TOLERANCE_RAD = 1e-9

# Tuple fields with one float per joint.
_JOINT_FIELDS = (
    "dh_a_m",
    "dh_d_m",
    "dh_alpha_rad",
    "dh_offset_rad",
    "joint_sign",
    "link_mass_kg",
    "rotor_inertia_kgm2",
    "torque_max_nm",
    "q_min_rad",
    "q_max_rad",
    "qd_max_rad_s",
    "qdd_max_rad_s2",
    "home_q_rad",
)
# Tuple fields with one 3-vector per link.
_VECTOR_FIELDS = ("link_com_m", "link_inertia_kgm2")


def _fmt(values: tuple[float, ...]) -> str:
    return ", ".join(f"{v:g}" for v in values)


@dataclass(frozen=True, kw_only=True)
class RobotSpec:
    """Kinematic, inertial, limit and timing data of one robot arm.

    Build one with :func:`get_robot`; derive variants with :meth:`with_period` or
    :func:`dataclasses.replace` (validated again). Every per-joint tuple has 6 entries,
    joint 1 first.

    Attributes
    ----------
    name : str
        Short name, ``"ur10"``, ``"ur10e"`` or ``"kr5"`` for the built-in robots.
    description : str
        Human-readable model and interface.
    vendor : str
        ``"universal_robots"`` or ``"kuka"`` (drivers choose their protocol by it).
    controller_period_s : float
        Controller cycle period, s; one of ``period_options_s``.
    period_options_s : tuple of float
        The cycle periods the controller interface offers, s.
    dh_a_m, dh_d_m : tuple of 6 float
        Standard DH link length ``a`` and offset ``d``, m.
    dh_alpha_rad : tuple of 6 float
        Standard DH link twist, rad.
    dh_offset_rad : tuple of 6 float
        DH angle at vendor angle zero: ``theta = joint_sign * q + dh_offset_rad``, rad.
    joint_sign : tuple of 6 float
        +1 where the vendor's positive direction turns about +z of DH frame ``j - 1``,
        -1 where it turns the other way.
    link_mass_kg : tuple of 6 float
        Mass of links 1..6, kg (link 6 without tool or payload).
    link_com_m : tuple of 6 (x, y, z)
        Centre of mass of link ``i`` in DH frame ``i``, m.
    link_inertia_kgm2 : tuple of 6 (Ixx, Iyy, Izz)
        Principal inertia of link ``i`` about its centre of mass, along the axes of DH frame
        ``i``, kg·m².
    rotor_inertia_kgm2 : tuple of 6 float
        Motor rotor plus gear inertia reflected to the joint side (``J_m * N²``), kg·m².
    torque_max_nm : tuple of 6 float
        Peak joint torque, N·m.
    q_min_rad, q_max_rad : tuple of 6 float
        Joint position limits, rad.
    qd_max_rad_s : tuple of 6 float
        Joint speed limits, rad/s.
    qdd_max_rad_s2 : tuple of 6 float
        Joint acceleration limits used for planning, rad/s².
    home_q_rad : tuple of 6 float
        A start pose inside the limits, rad.
    payload_kg : float
        Point mass at the flange origin (on the tool z axis), kg.
    sources : str
        Where the numbers come from and which are estimates.
    """

    name: str
    description: str
    vendor: str
    controller_period_s: float
    period_options_s: tuple[float, ...]
    dh_a_m: tuple[float, ...]
    dh_d_m: tuple[float, ...]
    dh_alpha_rad: tuple[float, ...]
    dh_offset_rad: tuple[float, ...]
    joint_sign: tuple[float, ...]
    link_mass_kg: tuple[float, ...]
    link_com_m: tuple[tuple[float, float, float], ...]
    link_inertia_kgm2: tuple[tuple[float, float, float], ...]
    rotor_inertia_kgm2: tuple[float, ...]
    torque_max_nm: tuple[float, ...]
    q_min_rad: tuple[float, ...]
    q_max_rad: tuple[float, ...]
    qd_max_rad_s: tuple[float, ...]
    qdd_max_rad_s2: tuple[float, ...]
    home_q_rad: tuple[float, ...]
    payload_kg: float = 0.0
    sources: str = ""

    def __post_init__(self) -> None:
        # Normalise sequences (lists from JSON, numpy arrays) to tuples of float so the spec
        # stays hashable and comparable, then validate once, here.
        for name in ("name", "description", "vendor", "sources"):
            if not isinstance(getattr(self, name), str):
                raise ConfigError(f"RobotSpec.{name} must be a str, got {getattr(self, name)!r}")
        if not self.name:
            raise ConfigError("RobotSpec.name must not be empty")
        if not self.vendor:
            raise ConfigError(f"robot {self.name!r}: vendor must not be empty")
        for name in _JOINT_FIELDS:
            object.__setattr__(self, name, self._float_tuple(name, getattr(self, name)))
        for name in _VECTOR_FIELDS:
            object.__setattr__(self, name, self._vector_tuple(name, getattr(self, name)))
        options = self._float_tuple("period_options_s", self.period_options_s, length=None)
        object.__setattr__(self, "period_options_s", options)
        for name in ("controller_period_s", "payload_kg"):
            value = getattr(self, name)
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise ConfigError(
                    f"robot {self.name!r}: {name} must be a number, got {value!r}"
                ) from None
            if not math.isfinite(number):
                raise ConfigError(f"robot {self.name!r}: {name} must be finite, got {value!r}")
            object.__setattr__(self, name, number)
        self._validate()

    def _float_tuple(
        self, name: str, value: Any, length: int | None = N_JOINTS
    ) -> tuple[float, ...]:
        try:
            out = tuple(float(v) for v in value)
        except (TypeError, ValueError):
            raise ConfigError(
                f"robot {self.name!r}: {name} must be a sequence of numbers, got {value!r}"
            ) from None
        if length is not None and len(out) != length:
            raise ConfigError(
                f"robot {self.name!r}: {name} needs {length} values (one per joint), got {len(out)}"
            )
        if not all(math.isfinite(v) for v in out):
            raise ConfigError(f"robot {self.name!r}: {name} must be finite, got ({_fmt(out)})")
        return out

    def _vector_tuple(self, name: str, value: Any) -> tuple[tuple[float, float, float], ...]:
        try:
            rows = [tuple(float(x) for x in row) for row in value]
        except (TypeError, ValueError):
            raise ConfigError(
                f"robot {self.name!r}: {name} must be 6 triples of numbers, got {value!r}"
            ) from None
        if len(rows) != N_JOINTS or any(len(r) != 3 for r in rows):
            raise ConfigError(
                f"robot {self.name!r}: {name} must be 6 triples (x, y, z), one per link, "
                f"got {value!r}"
            )
        if not all(math.isfinite(x) for r in rows for x in r):
            raise ConfigError(f"robot {self.name!r}: {name} must be finite, got {value!r}")
        return tuple((r[0], r[1], r[2]) for r in rows)

    def _validate(self) -> None:
        who = f"robot {self.name!r}"
        if not self.period_options_s or min(self.period_options_s) <= 0.0:
            raise ConfigError(
                f"{who}: period_options_s must list positive periods in s, "
                f"got ({_fmt(self.period_options_s)})"
            )
        if not any(math.isclose(self.controller_period_s, p) for p in self.period_options_s):
            raise ConfigError(
                f"{who}: controller_period_s {self.controller_period_s:g} s is not one of "
                f"the period options ({_fmt(self.period_options_s)}) s"
            )
        if any(s not in (1.0, -1.0) for s in self.joint_sign):
            raise ConfigError(
                f"{who}: joint_sign must be +1 or -1 per joint, got ({_fmt(self.joint_sign)})"
            )
        nonnegative = ("link_mass_kg", "rotor_inertia_kgm2")
        for name in nonnegative:
            values = getattr(self, name)
            if min(values) < 0.0:
                raise ConfigError(f"{who}: {name} must be >= 0, got ({_fmt(values)})")
        if min(min(r) for r in self.link_inertia_kgm2) < 0.0:
            raise ConfigError(
                f"{who}: link_inertia_kgm2 must be >= 0, got {self.link_inertia_kgm2}"
            )
        for name in ("torque_max_nm", "qd_max_rad_s", "qdd_max_rad_s2"):
            values = getattr(self, name)
            if min(values) <= 0.0:
                raise ConfigError(f"{who}: {name} must be > 0, got ({_fmt(values)})")
        if self.payload_kg < 0.0:
            raise ConfigError(f"{who}: payload_kg must be >= 0, got {self.payload_kg:g}")
        for j, (lo, hi) in enumerate(zip(self.q_min_rad, self.q_max_rad, strict=True), 1):
            if not lo < hi:
                raise ConfigError(
                    f"{who}: joint {j} limits need q_min_rad < q_max_rad, got {lo:g} >= {hi:g}"
                )
        try:
            check_configuration(self, self.home_q_rad)
        except ConfigError as exc:
            raise ConfigError(f"{who}: home_q_rad is outside the joint limits: {exc}") from None

    def with_period(self, period_s: float) -> RobotSpec:
        """Return a copy running at another controller period.

        Parameters
        ----------
        period_s : float
            New controller cycle period, s; must be one of ``period_options_s``.

        Raises
        ------
        ConfigError
            If the controller does not offer ``period_s``; the message lists the options.
        """
        for option in self.period_options_s:
            if math.isclose(float(period_s), option, rel_tol=1e-9, abs_tol=1e-12):
                return dataclasses.replace(self, controller_period_s=option)
        raise ConfigError(
            f"robot {self.name!r} cannot run at a controller period of {period_s!r} s; "
            f"choose one of {', '.join(f'{p:g}' for p in self.period_options_s)} s"
        )

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-safe dict (tuples become lists) that :meth:`from_dict` reads back."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name in _VECTOR_FIELDS:
                value = [list(row) for row in value]
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RobotSpec:
        """Build a spec from :meth:`to_dict` output (for example after a JSON round trip).

        Raises
        ------
        ConfigError
            On unknown or missing keys, or values that fail validation.
        """
        if not isinstance(d, Mapping):
            raise ConfigError(f"RobotSpec.from_dict needs a mapping, got {type(d).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - set(fields))
        if unknown:
            raise ConfigError(f"unknown RobotSpec keys {unknown}; expected only {sorted(fields)}")
        required = [
            name for name, f in fields.items() if f.default is dataclasses.MISSING and name not in d
        ]
        if required:
            raise ConfigError(f"RobotSpec dict is missing keys {required}")
        return cls(**dict(d))


def get_robot(name: str, *, period_s: float | None = None) -> RobotSpec:
    """Return the built-in spec of a robot.

    Parameters
    ----------
    name : str
        One of :data:`ROBOT_NAMES` (``"ur10"``, ``"ur10e"``, ``"kr5"``); case-insensitive.
    period_s : float, optional
        Controller period, s; default: the robot's default period (see
        :meth:`RobotSpec.with_period`).

    Raises
    ------
    ConfigError
        For an unknown name or a period the controller does not offer.
    """
    key = name.strip().lower() if isinstance(name, str) else name
    spec = _BUILTIN.get(key) if isinstance(key, str) else None
    if spec is None:
        raise ConfigError(f"unknown robot {name!r}; choose one of {', '.join(ROBOT_NAMES)}")
    return spec if period_s is None else spec.with_period(period_s)


# --------------------------------------------------------------------------------------
# Input normalisation
# --------------------------------------------------------------------------------------


def _as_configurations(q: ArrayLike) -> tuple[FloatArray, bool]:
    """Return ``q`` as a finite float64 (N, 6) array and whether the input was one row."""
    try:
        arr = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(
            f"a configuration must be numbers, shape (6,) or (N, 6), got {q!r:.80}"
        ) from None
    if arr.ndim == 1:
        if arr.shape[0] != N_JOINTS:
            raise ConfigError(
                f"incorrect configuration length: expected {N_JOINTS}, got {arr.shape[0]}"
            )
        single = True
        arr = arr[None, :]
    elif arr.ndim == 2:
        if arr.shape[1] != N_JOINTS:
            raise ConfigError(
                f"incorrect configuration length: expected {N_JOINTS}, got {arr.shape[1]} "
                f"(array of shape {arr.shape}; pass one row of 6 joint angles per configuration)"
            )
        single = False
    else:
        raise ConfigError(
            f"incorrect configuration shape: expected (6,) or (N, 6), got {arr.shape}"
        )
    finite = np.isfinite(arr)
    if not finite.all():
        row, col = (int(i) for i in np.argwhere(~finite)[0])
        where = "" if single else f"row {row}, "
        raise ConfigError(
            f"configuration {where}joint {col + 1} is {arr[row, col]}; joint angles must be "
            f"finite numbers in rad"
        )
    return arr, single


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


@functools.lru_cache(maxsize=64)
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


def _chain(p: _Params, q: FloatArray) -> _Chain:
    """Frames 0..6 for (N, 6) vendor angles.

    Standard DH, ``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, applied to the columns
    of the rotation: ``Rz`` mixes x and y, ``Rx`` then mixes the new y with z.
    """
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
    return _Chain(x, y, z, o)


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


def check_configuration(spec: RobotSpec, q: ArrayLike) -> FloatArray:
    """Validate joint configurations against shape, finiteness and the joint limits.

    Parameters
    ----------
    spec : RobotSpec
        The robot.
    q : array_like, shape (6,) or (N, 6)
        Vendor joint angles, rad.

    Returns
    -------
    ndarray, same shape as ``q``
        ``q`` as float64.

    Raises
    ------
    ConfigError
        On a wrong shape ("incorrect configuration length: expected 6, got 5"), NaN or
        infinity, or an angle outside ``[q_min_rad, q_max_rad]`` (beyond a 1e-9 rad round-off
        tolerance). The message names the row (for 2-D input, 0-based), the 1-based joint,
        the value in rad and degrees and the allowed range.
    """
    arr, single = _as_configurations(q)
    lo = np.asarray(spec.q_min_rad) - _LIMIT_TOLERANCE_RAD
    hi = np.asarray(spec.q_max_rad) + _LIMIT_TOLERANCE_RAD
    bad = (arr < lo) | (arr > hi)
    if bad.any():
        rows, cols = np.nonzero(bad)
        row, col = int(rows[0]), int(cols[0])
        value = float(arr[row, col])
        qmin, qmax = spec.q_min_rad[col], spec.q_max_rad[col]
        where = "" if single else f"row {row}: "
        more = int(bad.sum()) - 1
        extra = f" ({more} more values are out of range)" if more else ""
        raise ConfigError(
            f"{spec.name} configuration {where}joint {col + 1} = {value:.6g} rad "
            f"({math.degrees(value):.2f}°) is outside the allowed range "
            f"[{qmin:.6g}, {qmax:.6g}] rad ([{math.degrees(qmin):.2f}, "
            f"{math.degrees(qmax):.2f}]°){extra}; move the joint inside its limits"
        )
    return arr[0] if single else arr


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


# --------------------------------------------------------------------------------------
# Built-in robots
# --------------------------------------------------------------------------------------


def _cylinder(
    mass_kg: float, radius_m: float, length_m: float, axis: int
) -> tuple[float, float, float]:
    """Principal inertia (Ixx, Iyy, Izz) of a solid cylinder along ``axis`` (0=x, 1=y, 2=z)."""
    along = 0.5 * mass_kg * radius_m**2
    across = mass_kg * (3.0 * radius_m**2 + length_m**2) / 12.0
    out = [across, across, across]
    out[axis] = along
    return (out[0], out[1], out[2])


_DEG = math.pi / 180.0
_PI = math.pi
_HALF_PI = math.pi / 2.0

# UR joints: harmonic drives, ratio about 101 in every joint. Rotor inertias are not
# published; J_m is estimated from the frameless-motor size of each joint (size 4 base and
# shoulder, size 3 elbow, size 2 wrists): J_m about 1.2e-4, 4.4e-5, 1.0e-5 kg·m².
_UR_ROTOR_KGM2 = (1.2, 1.2, 0.45, 0.10, 0.10, 0.10)
_UR_LIMIT_RAD = 2.0 * math.pi
_UR_SOURCES_COMMON = (
    "DH parameters, link masses and centres of mass: Universal Robots, 'DH parameters for "
    "calculations of kinematics and dynamics' (universal-robots.com support article). "
    "Joint limits (±360°) and speeds (120°/s base and shoulder, 180°/s the others) from "
    "the UR data sheet. ESTIMATES: link inertias (solid cylinders along each link or "
    "joint housing, radii from the housing sizes); rotor inertias (J_m·N² with harmonic "
    "drive ratio N = 101 and J_m from the motor size); acceleration limits (working "
    "values, not published: 10 rad/s² base/shoulder, 12 elbow, 15 wrists)."
)

_UR10 = RobotSpec(
    name="ur10",
    description="Universal Robots UR10 (CB3), RTDE at 125 Hz",
    vendor="universal_robots",
    controller_period_s=0.008,
    period_options_s=(0.008,),
    dh_a_m=(0.0, -0.612, -0.5723, 0.0, 0.0, 0.0),
    dh_d_m=(0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922),
    dh_alpha_rad=(_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0),
    dh_offset_rad=(0.0,) * 6,
    joint_sign=(1.0,) * 6,
    link_mass_kg=(7.1, 12.7, 4.27, 2.0, 2.0, 0.365),
    link_com_m=(
        (0.021, 0.0, 0.027),
        (0.38, 0.0, 0.158),
        (0.24, 0.0, 0.068),
        (0.0, 0.007, 0.018),
        (0.0, 0.007, 0.018),
        (0.0, 0.0, -0.026),
    ),
    link_inertia_kgm2=(
        _cylinder(7.1, 0.075, 0.18, 2),  # shoulder housing, along the joint-2 axis
        _cylinder(12.7, 0.06, 0.612, 0),  # upper arm tube, along x2
        _cylinder(4.27, 0.045, 0.5723, 0),  # forearm tube, along x3
        _cylinder(2.0, 0.05, 0.12, 2),  # wrist housings, along their joint axes
        _cylinder(2.0, 0.05, 0.12, 2),
        _cylinder(0.365, 0.045, 0.03, 2),  # flange disc
    ),
    rotor_inertia_kgm2=_UR_ROTOR_KGM2,
    torque_max_nm=(330.0, 330.0, 150.0, 54.0, 54.0, 54.0),
    q_min_rad=(-_UR_LIMIT_RAD,) * 6,
    q_max_rad=(_UR_LIMIT_RAD,) * 6,
    qd_max_rad_s=(120 * _DEG, 120 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG),
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -_HALF_PI, _HALF_PI, -_HALF_PI, -_HALF_PI, 0.0),
    sources=(
        "UR10 (CB3). "
        + _UR_SOURCES_COMMON
        + " Peak torques (330, 330, 150, 54, 54, 54) N·m from UR's joint sizes. "
        "Controller: 8 ms (RTDE at 125 Hz). Rated payload 10 kg (not included by default)."
    ),
)

_UR10E = RobotSpec(
    name="ur10e",
    description="Universal Robots UR10e (e-Series), RTDE at 500 Hz",
    vendor="universal_robots",
    controller_period_s=0.002,
    period_options_s=(0.002,),
    dh_a_m=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
    dh_d_m=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
    dh_alpha_rad=(_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0),
    dh_offset_rad=(0.0,) * 6,
    joint_sign=(1.0,) * 6,
    link_mass_kg=(7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
    link_com_m=(
        (0.021, 0.0, 0.027),
        (0.38, 0.0, 0.158),
        (0.24, 0.0, 0.068),
        (0.0, 0.007, 0.018),
        (0.0, 0.007, 0.018),
        (0.0, 0.0, -0.026),
    ),
    link_inertia_kgm2=(
        _cylinder(7.369, 0.075, 0.18, 2),
        _cylinder(13.051, 0.06, 0.6127, 0),
        _cylinder(3.989, 0.045, 0.57155, 0),
        _cylinder(2.1, 0.05, 0.12, 2),
        _cylinder(1.98, 0.05, 0.12, 2),
        _cylinder(0.615, 0.045, 0.04, 2),
    ),
    rotor_inertia_kgm2=_UR_ROTOR_KGM2,
    torque_max_nm=(330.0, 330.0, 150.0, 56.0, 56.0, 56.0),
    q_min_rad=(-_UR_LIMIT_RAD,) * 6,
    q_max_rad=(_UR_LIMIT_RAD,) * 6,
    qd_max_rad_s=(120 * _DEG, 120 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG),
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -_HALF_PI, _HALF_PI, -_HALF_PI, -_HALF_PI, 0.0),
    sources=(
        "UR10e (e-Series). "
        + _UR_SOURCES_COMMON
        + " Peak torques (330, 330, 150, 56, 56, 56) N·m from UR's e-Series joint sizes. "
        "Controller: 2 ms (RTDE at 500 Hz). Rated payload 12.5 kg (not included by default)."
    ),
)

# KUKA KR 5 sixx R850. DH frames chosen so that the vendor angles A1..A6 are the inputs:
# frame 0 z up; A1 turns about -z (joint_sign -1); A2 and A3 about the DH z axes; A3's
# offset -90° puts x3 along the 90 mm elbow offset; A4 and A6 turn about -z (joint_sign
# -1); the offset of 180° on A6 makes frame 6 the ROS-Industrial tool0 frame (z out of the
# flange, x down at A1..A6 = 0). At (0, -90, 90, 0, 0, 0)° the upper arm is vertical, the
# forearm horizontal and the flange points forward along base +x at (0.560, 0, 0.790) m.
_KR5_MASS_KG = (7.0, 6.5, 4.5, 2.5, 1.2, 0.3)  # + about 7 kg fixed base = 29 kg
_KR5 = RobotSpec(
    name="kr5",
    description="KUKA KR 5 sixx R850, RSI at 12 ms (IPO) or 4 ms (IPO_FAST)",
    vendor="kuka",
    controller_period_s=0.012,
    period_options_s=(0.012, 0.004),
    dh_a_m=(0.075, 0.365, 0.090, 0.0, 0.0, 0.0),
    dh_d_m=(0.335, 0.0, 0.0, 0.405, 0.0, 0.080),
    dh_alpha_rad=(-_HALF_PI, 0.0, -_HALF_PI, _HALF_PI, -_HALF_PI, 0.0),
    dh_offset_rad=(0.0, 0.0, -_HALF_PI, 0.0, 0.0, _PI),
    joint_sign=(-1.0, 1.0, 1.0, -1.0, 1.0, -1.0),
    link_mass_kg=_KR5_MASS_KG,
    link_com_m=(
        (-0.04, 0.10, 0.0),  # rotating column, below and behind the A2 axis
        (-0.18, 0.0, 0.0),  # rocker: halfway between A2 and A3
        (-0.04, 0.0, -0.03),  # arm housing with wrist motors, near the elbow
        (0.0, -0.19, 0.0),  # forearm, behind the wrist centre
        (0.0, 0.0, 0.01),  # wrist
        (0.0, 0.0, -0.01),  # flange
    ),
    link_inertia_kgm2=(
        _cylinder(7.0, 0.10, 0.20, 1),  # column, vertical (y1 points down)
        _cylinder(6.5, 0.06, 0.365, 0),  # rocker along x2
        _cylinder(4.5, 0.07, 0.20, 2),  # arm housing along the forearm axis z3
        _cylinder(2.5, 0.04, 0.30, 1),  # forearm along y4
        _cylinder(1.2, 0.04, 0.10, 2),
        _cylinder(0.3, 0.03, 0.02, 2),
    ),
    rotor_inertia_kgm2=(0.9, 0.9, 0.4, 0.06, 0.06, 0.03),
    torque_max_nm=(160.0, 220.0, 110.0, 30.0, 30.0, 20.0),
    q_min_rad=(-170 * _DEG, -190 * _DEG, -119 * _DEG, -190 * _DEG, -120 * _DEG, -358 * _DEG),
    q_max_rad=(170 * _DEG, 45 * _DEG, 165 * _DEG, 190 * _DEG, 120 * _DEG, 358 * _DEG),
    qd_max_rad_s=tuple(v * _DEG for v in (375.0, 300.0, 375.0, 410.0, 410.0, 660.0)),
    qdd_max_rad_s2=(18.0, 15.0, 18.0, 28.0, 28.0, 45.0),
    home_q_rad=(0.0, -_HALF_PI, _HALF_PI, 0.0, 0.0, 0.0),
    sources=(
        "KUKA KR 5 sixx R850 (the paper's 'KR 5 sixx'; the R850 variant is chosen). "
        "Dimensions (a1 = 75, d1 = 335, a2 = 365, a3 = 90, d4 = 405, d6 = 80 mm), axis "
        "ranges (A1 ±170°, A2 -190°..+45°, A3 -119°..+165°, A4 ±190°, A5 ±120°, A6 ±358°) "
        "and axis speeds (375, 300, 375, 410, 410, 660 °/s) from the KUKA data sheet; joint "
        "directions as in ROS-Industrial kuka_experimental (A1, A4, A6 turn about -z). "
        "ESTIMATES (KUKA does not publish them): link masses (7.0, 6.5, 4.5, 2.5, 1.2, "
        "0.3) kg, chosen so that with a fixed base of about 7 kg the total is the data "
        "sheet's 29 kg; centres of mass from the link geometry; link inertias as solid "
        "cylinders; rotor inertias (J_m·N² for AC servos of about 3e-5..1e-4 kg·m² behind "
        "gears of ratio 100..160); peak torques (160, 220, 110, 30, 30, 20) N·m, sized to "
        "exceed the gravity torque at the rated 5 kg payload; acceleration limits (about "
        "0.3 s to full speed on A1..A3, 0.25 s on the wrist). RSI: 12 ms (#IPO) default, "
        "4 ms (#IPO_FAST) option. Rated payload 5 kg (not included by default)."
    ),
)

_BUILTIN: dict[str, RobotSpec] = {"ur10": _UR10, "ur10e": _UR10E, "kr5": _KR5}
