"""Data-driven terms: effects outside the vocabulary, as the discrepancy workflow found them.

A :class:`DataTerm` is a closed-form effect on the actuation delay: the drive of each
joint it acts on applies the setpoint ``Σ coef · basis(pose)`` later, where the basis is a
fixed function of one or two *inputs* (a joint angle ``qK`` in rad, or the gravity torque
``tauK`` of joint K at the start pose in N·m, from :func:`timedexec.robots.gravity_torque`)
of one of a few forms, per joint, gated on one direction or on both:

============  ==========================================  ================================
form          basis (x, x1, x2: the inputs)               shape parameters
============  ==========================================  ================================
``linear``    x - x0                                      reference x0 (not fitted)
``hinge_up``  max(x - k, 0)                               knot k
``hinge_down``  max(k - x, 0)                             knot k
``harmonic``  sin(n x), cos(n x)                          order n
``bump``      exp(-(x - c)² / 2w²)                        centre c, width w
``bump2``     exp(-((x1 - c1)²/w1² + (x2 - c2)²/w2²)/2)   c1, w1, c2, w2
``product``   (x1 - r1)(x2 - r2)                          references r1, r2 (not fitted)
============  ==========================================  ================================

Because the term is a dead time of the drive (:meth:`Effect.drive_delay_s`), the batch
simulator applies it exactly (the onset moves by the term, to the physics grid), and the
discrepancy workflow fits its coefficients in closed form beside the model's constants
(``closed_form = "term"``). The stepped controller (twins, ``sim://``) asks for a drive's
dead time once per joint at its start pose, before any command: it applies a pose-dependent
term at that pose and a one-direction term at half its size (the direction is not known
there); only the batch simulator, which the discrepancy workflow uses, is exact for both.

Each discovered term is its own class, registered at run time under a name of its own
(:func:`register_term`): it is simulated from then on like any effect
(``EffectSet((*effects, term))``). Data-driven classes are not part of the vocabulary
(:attr:`Effect.data_driven`): the workflow never proposes them as names.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import re
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._types import FloatArray
from timedexec.effects._base import ClosedForm, Effect, Pose
from timedexec.effects._registry import EFFECTS
from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec, gravity_torque

__all__ = [
    "TERM_FORMS",
    "DataTerm",
    "input_values",
    "register_term",
    "term_columns",
]

#: The forms of a data-driven term: number of inputs, of columns, of shape parameters.
TERM_FORMS: dict[str, tuple[int, int, int]] = {
    "linear": (1, 1, 1),
    "hinge_up": (1, 1, 1),
    "hinge_down": (1, 1, 1),
    "harmonic": (1, 2, 1),
    "bump": (1, 1, 2),
    "bump2": (2, 1, 4),
    "product": (2, 1, 2),
}
_INPUT = re.compile(r"^(q|tau)([1-6])$")
_GATES = {0: "both directions", 1: "positive direction only", -1: "negative direction only"}


def input_values(spec: RobotSpec, q_rad: FloatArray, name: str) -> FloatArray:
    """The input ``name`` at the start configurations ``q_rad`` (n, 6): ``qK`` (rad) or
    ``tauK``, the gravity torque joint K holds there (N·m)."""
    m = _INPUT.match(name)
    if m is None:
        raise ConfigError(f"term input {name!r}: give q1..q6 (rad) or tau1..tau6 (N·m)")
    k = int(m.group(2)) - 1
    if m.group(1) == "q":
        out: FloatArray = np.asarray(q_rad, dtype=float)[:, k]
        return out
    torque: FloatArray = gravity_torque(spec, np.asarray(q_rad, dtype=float))[:, k]
    return torque


def term_columns(form: str, x: FloatArray, shape: tuple[float, ...]) -> FloatArray:
    """The basis of ``form`` at inputs ``x`` (n, inputs) with shape parameters ``shape``:
    (n, columns)."""
    if form == "linear":
        return x[:, :1] - shape[0]
    if form == "hinge_up":
        return np.maximum(x[:, :1] - shape[0], 0.0)
    if form == "hinge_down":
        return np.maximum(shape[0] - x[:, :1], 0.0)
    if form == "harmonic":
        n = shape[0]
        return np.column_stack([np.sin(n * x[:, 0]), np.cos(n * x[:, 0])])
    if form == "bump":
        c, w = shape
        return np.exp(-0.5 * ((x[:, :1] - c) / w) ** 2)
    if form == "product":
        return ((x[:, 0] - shape[0]) * (x[:, 1] - shape[1]))[:, None]
    if form == "bump2":
        c1, w1, c2, w2 = shape
        z = ((x[:, 0] - c1) / w1) ** 2 + ((x[:, 1] - c2) / w2) ** 2
        return np.exp(-0.5 * z)[:, None]
    raise ConfigError(f"term form {form!r}: one of {', '.join(TERM_FORMS)}")


def _unit(name: str) -> str:
    return "rad" if name.startswith("q") else "N·m"


@dataclass(frozen=True, kw_only=True)
class DataTerm(Effect):
    """A term outside the vocabulary: the actuation delay of ``joints`` changes by
    ``coef · basis(inputs)`` (module docstring), on one direction or both.

    Parameters
    ----------
    joints : tuple of int
        The joints whose drive it delays, 1-based, distinct.
    inputs : tuple of str
        ``qK`` (rad) or ``tauK`` (N·m); two for ``bump2``, else one.
    form : str
        One of :data:`TERM_FORMS`.
    shape : tuple of float
        The form's shape parameters (knot, order, centre and width; in the inputs' units).
    direction : int
        0 both directions, +1 or -1 that direction only.
    coef_s : tuple of float
        Coefficients, s per unit of the basis: for each joint of ``joints`` in turn, one
        per column of the form (empty: zeros).
    """

    data_driven: ClassVar[bool] = True
    closed_form: ClassVar[ClosedForm | None] = "term"
    acts_on: ClassVar[str] = "actuation_delay"
    meaning: ClassVar[str] = "a term outside the vocabulary, found in the data"
    variable: ClassVar[str] = "its inputs"
    variable_key: ClassVar[str] = "joint"
    joints: tuple[int, ...] = (1,)
    inputs: tuple[str, ...] = ("q1",)
    form: str = "linear"
    shape: tuple[float, ...] = ()
    direction: int = 0
    coef_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        owner = f"data term {self.name or '(unnamed)'}"
        joints = tuple(int(j) for j in self.joints)
        if not joints or len(set(joints)) != len(joints) or any(not 1 <= j <= 6 for j in joints):
            raise ConfigError(f"{owner}: joints {self.joints!r} must be distinct joints 1..6")
        if self.form not in TERM_FORMS:
            raise ConfigError(f"{owner}: form {self.form!r} is not one of {', '.join(TERM_FORMS)}")
        n_in, n_cols, n_shape = TERM_FORMS[self.form]
        inputs = tuple(str(i) for i in self.inputs)
        if len(inputs) != n_in or any(_INPUT.match(i) is None for i in inputs):
            raise ConfigError(
                f"{owner}: inputs {self.inputs!r}: form {self.form} takes {n_in} of q1..q6, "
                "tau1..tau6"
            )
        shape = tuple(float(v) for v in self.shape)
        if len(shape) != n_shape or not all(math.isfinite(v) for v in shape):
            raise ConfigError(
                f"{owner}: shape {self.shape!r}: form {self.form} takes {n_shape} finite numbers"
            )
        if self.form.startswith("bump") and any(w <= 0 for w in shape[1::2]):
            raise ConfigError(f"{owner}: widths in shape {shape} must be > 0")
        if self.direction not in _GATES:
            raise ConfigError(f"{owner}: direction={self.direction!r} must be 0, 1 or -1")
        coef = tuple(float(c) for c in self.coef_s) or (0.0,) * (len(joints) * n_cols)
        if len(coef) != len(joints) * n_cols or not all(math.isfinite(c) for c in coef):
            raise ConfigError(
                f"{owner}: coef_s needs {len(joints) * n_cols} finite values ({n_cols} per "
                f"joint of {joints}), got {self.coef_s!r}"
            )
        for name, value in (("joints", joints), ("inputs", inputs), ("shape", shape)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "coef_s", coef)
        object.__setattr__(self, "direction", int(self.direction))

    @property
    def n_columns(self) -> int:
        """Columns of its basis: one per joint and column of the form."""
        return len(self.joints) * TERM_FORMS[self.form][1]

    def basis(self, pose: Pose) -> FloatArray:
        """The basis at ``pose``, (n, :attr:`n_columns`): the form's columns on each joint's
        elements (zero elsewhere), gated on the direction (at half weight where the
        direction is unknown)."""
        x = np.column_stack([input_values(pose.spec, pose.q_start_rad, i) for i in self.inputs])
        cols = term_columns(self.form, x, self.shape)
        gate = np.ones(len(pose.joint))
        if self.direction != 0:
            if pose.direction is None:
                gate = gate * 0.5
            else:
                gate = (np.sign(pose.direction) == self.direction).astype(float)
        out = [
            cols[:, c] * gate * (pose.joint == j) for j in self.joints for c in range(cols.shape[1])
        ]
        return np.column_stack(out)

    def drive_delay_s(self, pose: Pose) -> FloatArray:
        out: FloatArray = self.basis(pose) @ np.asarray(self.coef_s)
        return out

    def with_coefficients(self, coef_s: FloatArray) -> DataTerm:
        """A copy with the coefficients ``coef_s`` (s per unit of the basis)."""
        return dataclasses.replace(self, coef_s=tuple(float(c) for c in coef_s))

    @classmethod
    def fit_closed_form(
        cls, y_s: FloatArray, pose: Pose, period_s: float, bounds_s: tuple[float, float]
    ) -> tuple[Effect, float]:
        raise NotImplementedError(
            "a data term is fitted with the model's constants (discrepancy's calibration)"
        )

    @classmethod
    def n_parameters(cls, n_joints: int) -> int:
        return 0  # counted per instance (n_columns)

    # -- in words --------------------------------------------------------------------------
    def sizes(self) -> dict[int, dict[str, float]]:
        """Per joint, the term's size in its form's natural unit: ``slope`` (ms per rad or
        per N·m) for linear and hinge forms, ``amplitude`` (ms) and ``phase`` (rad) for a
        harmonic, ``peak`` (ms) for a bump."""
        k = TERM_FORMS[self.form][1]
        out: dict[int, dict[str, float]] = {}
        for i, j in enumerate(self.joints):
            c = np.asarray(self.coef_s[i * k : (i + 1) * k]) * 1e3
            if self.form == "harmonic":
                out[j] = {
                    "amplitude": float(np.hypot(c[0], c[1])),
                    "phase": float(math.atan2(c[1], c[0])),
                }
            elif self.form.startswith("bump"):
                out[j] = {"peak": float(c[0])}
            else:
                out[j] = {"slope": float(c[0])}
        return out

    def basis_text(self) -> str:
        """The basis as a formula, e.g. ``max(q5 - 0.40 rad, 0)``."""
        s = self.shape
        x = self.inputs[0]
        u = _unit(x)

        def minus(name: str, v: float, unit: str = "") -> str:
            unit = f" {unit}" if unit else ""
            return f"{name} {'-' if v >= 0 else '+'} {abs(v):.2f}{unit}"

        if self.form == "linear":
            return f"({minus(x, s[0], u)})"
        if self.form == "hinge_up":
            return f"max({minus(x, s[0], u)}, 0)"
        if self.form == "hinge_down":
            return f"max({s[0]:.2f} {u} - {x}, 0)"
        if self.form == "harmonic":
            n = f"{s[0]:g} " if s[0] != 1 else ""
            return f"sin({n}{x} + φ)"
        if self.form == "bump":
            return f"exp(-({minus(x, s[0], u)})² / (2·({s[1]:.2f} {u})²))"
        x2 = self.inputs[1]
        if self.form == "product":
            return f"({minus(x, s[0], u)})·({minus(x2, s[1], _unit(x2))})"
        return f"exp(-(({minus(x, s[0])})²/{s[1]:.2f}² + ({minus(x2, s[2])})²/{s[3]:.2f}²)/2), {u}"

    def formula(self) -> str:
        """The term as a formula in ms, one part per joint, e.g. ``joint 3: +2.80 ms/rad ·
        max(q5 - 0.40 rad, 0), positive direction only``."""
        sizes = self.sizes()
        parts = []
        for j in self.joints:
            z = sizes[j]
            if self.form == "harmonic":
                n = f"{self.shape[0]:g} " if self.shape[0] != 1 else ""
                text = f"{z['amplitude']:.2f} ms · sin({n}{self.inputs[0]} {z['phase']:+.2f})"
            elif self.form.startswith("bump"):
                text = f"{z['peak']:+.2f} ms · {self.basis_text()}"
            else:
                per = "·".join(_unit(i) for i in self.inputs)
                text = f"{z['slope']:+.3g} ms/{per} · {self.basis_text()}"
            parts.append(f"joint {j}: {text}")
        gate = "" if self.direction == 0 else f" ({_GATES[self.direction]})"
        return "actuation delay += " + "; ".join(parts) + gate

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "formula": self.formula(),
            "joints": list(self.joints),
            "inputs": list(self.inputs),
            "form": self.form,
            "shape": list(self.shape),
            "direction": _GATES[self.direction],
            "size_per_joint": {str(j): v for j, v in self.sizes().items()},
        }


def _default_name(term: DataTerm) -> str:
    joints = "".join(str(j) for j in term.joints)
    side = {0: "", 1: "_pos", -1: "_neg"}[term.direction]
    key = repr((term.joints, term.inputs, term.form, term.shape, term.direction)).encode()
    digest = hashlib.sha256(key).hexdigest()[:6]
    return f"term_j{joints}_{'_'.join(term.inputs)}_{term.form}{side}_{digest}"


def register_term(
    *,
    joints: tuple[int, ...],
    inputs: tuple[str, ...],
    form: str,
    shape: tuple[float, ...] = (),
    direction: int = 0,
    coef_s: tuple[float, ...] = (),
    name: str | None = None,
) -> DataTerm:
    """Build a data term and register its class at run time (a class per term, so that a
    model holds several); returns the term, an instance of the registered class.

    The name defaults to one made of the joints, inputs, form and a digest of the shape
    (``term_j3_q5_hinge_up_pos_1a2b3c``); an existing data-term class of that name is
    reused. The batch simulator applies the term from then on; the discrepancy workflow
    never proposes it as a vocabulary name.

    Raises
    ------
    ConfigError
        Invalid fields, or ``name`` belongs to an effect that is not a data term.
    """
    term = DataTerm(
        joints=joints, inputs=inputs, form=form, shape=shape, direction=direction, coef_s=coef_s
    )
    key = name or _default_name(term)
    old = EFFECTS.get(key)
    if old is not None and not issubclass(old, DataTerm):
        raise ConfigError(f"effect name {key!r} is taken by {old.__qualname__}, not a data term")
    cls = old
    if cls is None:
        cls = type(f"DataTerm_{key}", (DataTerm,), {"name": key, "__module__": __name__})
        EFFECTS.register(cls)
    fields = {f.name: getattr(term, f.name) for f in dataclasses.fields(term)}
    out: DataTerm = cls(**fields)
    return out
