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
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.errors import ConfigError

__all__ = ["N_JOINTS", "RobotSpec", "check_configuration"]

_T = TypeVar("_T")


def spec_cache(fn: Callable[[RobotSpec], _T]) -> Callable[[RobotSpec], _T]:
    """Memoize ``fn(spec)``: the last spec by identity, others through an LRU cache.

    A frozen dataclass hashes all its fields on every call (~4 µs for a RobotSpec's
    tuples); a control loop asks for the same spec's constants every cycle, so the last
    one is matched by ``is`` first (one tuple swapped whole: safe across threads).
    """
    cached = functools.lru_cache(maxsize=64)(fn)
    box: list[tuple[Any, Any]] = [(None, None)]

    @functools.wraps(fn)
    def wrapper(spec: RobotSpec) -> _T:
        last_spec, last_out = box[0]
        if spec is last_spec:
            return last_out  # type: ignore[no-any-return]
        out = cached(spec)
        box[0] = (spec, out)
        return out

    return wrapper


#: Number of joints of every robot described here.
N_JOINTS = 6

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
        Short name; the built-in robots' are :data:`~timedexec.robots.ROBOT_NAMES`.
    description : str
        Human-readable model and interface.
    vendor : str
        ``"universal_robots"`` or ``"kuka"`` (the interface it speaks: its catalog entry's
        ``twin.interface``).
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
