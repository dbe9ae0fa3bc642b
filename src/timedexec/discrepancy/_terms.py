"""Structural terms: the shapes a disagreement between simulation and measurement can take.

A *term family* is a small set of columns over the conditions — a free function of one
variable, or of two (an *interaction*) — that the residuals of the condition means may
follow. Each family carries the name of the effect of the vocabulary it stands for, or
None when no effect of the vocabulary has that shape (it is then reported as
unexplained, where it sits):

===========================  =========================================  ========================
family                       columns (per joint where it says so)       effect
===========================  =========================================  ========================
``joint``                    joint indicators (one joint the reference)  ``joint_offset``
``direction``                d                                           ``direction``
``direction_x_joint``        d, per joint                                ``direction``
``load``                     u, u², sqrt(u) per joint, u = |τ_g|/max     ``gravity_load``
``direction_x_load``         v, v·|v|, sign(v)·sqrt|v| per joint,        ``gravity_direction``
                             v = d·τ_g/max
``inertia``                  w, w² per joint, w = log(I / I_home)        ``inertia``
``time``                     1 - s, hinges (c - s)+ at c = 1/4, 1/2,     ``thermal_drift``
                             3/4, e^(-s/0.05), a step [s < c*] at the
                             best change point; s = sweep time 0..1
``time_x_joint``             1 - s, (1/2 - s)+, e^(-s/0.1), [s < c*]     ``thermal_drift``
                             per joint
``response_cycle``           a constant on the response delay            ``response_extra_cycle``
``EFFECT:simulator``         the simulator's signature of EFFECT alone   EFFECT
``qK``, ``qK@jointJ``        sin, cos of q_K and 2 q_K (all joints, or   outside
                             one joint)
``response_joint`` ...       joint, direction, load, time, angles on     outside
                             the response delay (centred)
===========================  =========================================  ========================

Where a simulated effect is a candidate, its simulator signature (how switching it on
changes every condition, :func:`timedexec.discrepancy._candidates.signature`) is one more
column of its family: the simulator's own form is always among the shapes tried.

Anchors: a load family vanishes at zero load, an inertia family at the nominal (home
pose) inertia, a time family at the end of the sweep (warm). Together with the
per-joint gains this makes a per-joint level part of the effect that causes it, so a
joint that only drifts (or only carries load) is not also named ``joint_offset``.

**Hierarchy.** An interaction lists its main effects as ``parents``
(``direction_x_load``: ``load`` and ``direction_x_joint``; ``direction_x_joint``:
``direction`` and ``joint``; ``time_x_joint``: ``time`` and ``joint``). The selection
(:mod:`timedexec.discrepancy._select`) scores an interaction together with its missing
parents, then keeps each part only if it explains something the others do not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from timedexec.discrepancy._conditions import Conditions

__all__ = [
    "EFFECT_FAMILY",
    "TermFamily",
    "actuation_families",
    "change_point",
    "response_families",
    "sweep_fraction",
]

FloatArray = NDArray[np.float64]

#: Smallest spread of a variable over a joint's conditions for a family to use it.
_MIN_SPREAD = 1e-6

#: Degrees of freedom charged for choosing a change point on the residuals (a search over
#: 37 positions: the likelihood-ratio statistic of an unknown change point exceeds a
#: one-column chi-square by about as much as two more columns would).
CHANGE_POINT_DF = 2

#: The generic family of each simulated effect: what its measured shape is made of.
EFFECT_FAMILY: dict[str, str] = {
    "gravity_load": "load",
    "gravity_direction": "direction_x_load",
    "direction": "direction_x_joint",
    "inertia": "inertia",
    "thermal_drift": "time",
}
_EFFECT_VARIABLE = {
    "gravity_load": "gravity_torque",
    "gravity_direction": "direction_x_gravity",
    "direction": "direction",
    "inertia": "inertia",
    "thermal_drift": "time",
}
#: Effects whose simulator signature is also a family of its own.
SIGNATURE_EFFECTS = tuple(EFFECT_FAMILY)


@dataclass(frozen=True, eq=False)
class TermFamily:
    """A set of columns over the conditions that the residuals may follow.

    Attributes
    ----------
    key : str
        Identifier (``load``, ``direction_x_joint``, ``q5@joint2``, ...).
    label : str
        The shape in words, for reports.
    effect : str or None
        The effect of the vocabulary with this shape, None outside the vocabulary.
    delay : str
        The delay it acts on.
    columns : ndarray (m, k)
        The columns, each scaled to unit RMS.
    parents : tuple of str
        Keys of its main effects (for an interaction).
    variable : str or None
        The condition variable it follows (a key of ``condition_variables``), for reports.
    joints : tuple of int
        Joints whose conditions it can change.
    extra_df : int
        Degrees of freedom beyond its columns: a column chosen by a search on the same
        residuals (a change point) fits noise better than a fixed one.
    """

    key: str
    label: str
    effect: str | None
    delay: str
    columns: FloatArray
    parents: tuple[str, ...] = ()
    variable: str | None = None
    joints: tuple[int, ...] = ()
    extra_df: int = 0

    @property
    def width(self) -> int:
        """Number of columns."""
        return int(self.columns.shape[1])


def _stack(cols: list[FloatArray], m: int) -> FloatArray:
    """Columns with a non-zero spread, each scaled to unit RMS, as an (m, k) array."""
    keep = []
    for c in cols:
        rms = float(np.sqrt(np.mean(c**2)))
        if rms > 1e-12 and np.ptp(c) > 1e-12:
            keep.append(c / rms)
    return np.column_stack(keep) if keep else np.zeros((m, 0))


def _despiked(x: FloatArray) -> FloatArray:
    """A simulator signature without its spikes: a condition where the candidate pushes a
    joint past its torque limit (it no longer breaks away inside the simulated window)
    changes by up to the window's length; such a column describes one condition, not a
    shape. Values beyond 5 x the 90th percentile of |x| are clipped to it."""
    top = float(np.quantile(np.abs(x), 0.9)) if len(x) else 0.0
    if top <= 0:
        return x
    out: FloatArray = np.clip(x, -5.0 * top, 5.0 * top)
    return out


def _per_joint(
    cond: Conditions, x: FloatArray, funcs: list[str], *, min_spread: float = _MIN_SPREAD
) -> tuple[list[FloatArray], tuple[int, ...]]:
    """``f(x)`` on each joint's conditions (zero elsewhere) for each named function."""
    cols: list[FloatArray] = []
    joints: list[int] = []
    for j in cond.joints:
        mk = cond.joint == j
        if np.ptp(x[mk]) <= min_spread:
            continue
        joints.append(j)
        xj = x[mk]
        for f in funcs:
            if f == "x":
                y = xj
            elif f == "x2":
                y = xj**2
            elif f == "sqrt":
                y = np.sqrt(np.abs(xj))
            elif f == "x|x|":
                y = xj * np.abs(xj)
            elif f == "sign_sqrt":
                y = np.sign(xj) * np.sqrt(np.abs(xj))
            elif f == "1-s":
                y = 1.0 - xj
            elif f == "hinge_half":
                y = np.maximum(0.5 - xj, 0.0)
            elif f == "fast":
                y = np.exp(-xj / 0.1)
            else:  # pragma: no cover - internal table
                raise KeyError(f)
            col = np.zeros(len(cond))
            col[mk] = y
            cols.append(col)
    return cols, tuple(joints)


def _normalised(cond: Conditions, x: FloatArray) -> FloatArray:
    """``x / max |x|`` over each joint's conditions (0 where a joint's x is all 0)."""
    out = np.zeros(len(cond))
    for j in cond.joints:
        mk = cond.joint == j
        top = float(np.max(np.abs(x[mk]))) if mk.any() else 0.0
        if top > 0:
            out[mk] = x[mk] / top
    return out


def sweep_fraction(cond: Conditions) -> FloatArray:
    """Mean sweep time of each condition as a fraction of the sweep, 0..1."""
    t = cond.t_start_s
    span = float(np.ptp(t)) if len(t) else 0.0
    out: FloatArray = (t - t.min()) / span if span > 0 else np.zeros(len(t))
    return out


def _time_basis(s: FloatArray) -> list[FloatArray]:
    """Functions of the sweep fraction that vanish at its end: a linear spline with knots
    at 1/4, 1/2, 3/4 and a fast early decay."""
    return [
        1.0 - s,
        np.maximum(0.75 - s, 0.0),
        np.maximum(0.5 - s, 0.0),
        np.maximum(0.25 - s, 0.0),
        np.exp(-s / 0.05),
    ]


def change_point(
    s: FloatArray, r: FloatArray, mask: NDArray[np.bool_] | None = None
) -> float | None:
    """The sweep fraction at which a step best explains ``r`` over the conditions of
    ``mask`` (least squares of ``r`` on a constant, a slope and ``[s < c]``, ``c`` on a grid
    of 37 quantiles of ``s`` between 5 % and 95 %). None when there are too few conditions.

    A warm-up that ends abruptly (a mode switch, grease reaching its temperature) is a
    step; a linear spline with fixed knots smears it over a knot interval and leaves a
    misfit the size of the step near it.
    """
    x = s if mask is None else s[mask]
    y = r if mask is None else r[mask]
    if len(x) < 12 or np.ptp(x) <= 0:
        return None
    grid = np.unique(np.quantile(x, np.linspace(0.05, 0.95, 37)))
    best: tuple[float, float] | None = None
    for c in grid:
        a = np.column_stack([np.ones(len(x)), x, (x < c).astype(float)])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        ss = float(np.sum((y - a @ coef) ** 2))
        if best is None or ss < best[0]:
            best = (ss, float(c))
    return None if best is None else best[1]


def _harmonics(x: FloatArray) -> list[FloatArray]:
    return [np.sin(x), np.cos(x), np.sin(2 * x), np.cos(2 * x)]


def actuation_families(
    cond: Conditions,
    *,
    gravity_torque_nm: FloatArray,
    inertia_kgm2: FloatArray,
    nominal_inertia_kgm2: FloatArray,
    present: tuple[str, ...],
    signatures: dict[str, FloatArray] | None = None,
    outside: bool = True,
    resid_ms: FloatArray | None = None,
) -> dict[str, TermFamily]:
    """The term families of the actuation delay.

    Parameters
    ----------
    cond : Conditions
    gravity_torque_nm : ndarray (m,)
        Holding torque of the actuated joint at the start pose, N·m.
    inertia_kgm2, nominal_inertia_kgm2 : ndarray (m,)
        True reflected inertia of the actuated joint and the nominal one (home pose), kg·m².
    present : tuple of str
        Effects the model already has: their families are not candidates (a present
        ``joint_offset`` also makes the per-joint levels part of the model).
    signatures : dict name -> ndarray (m, k), optional
        The simulator's signature columns of candidate effects, added to their families.
    outside : bool
        Include the families outside the vocabulary (joint angles).
    resid_ms : ndarray (m,), optional
        The current residuals: the time families then also hold a step at the change
        point that fits them best (:func:`change_point`; overall, and per joint).
    """
    m = len(cond)
    d = cond.direction.astype(float)
    sig = signatures or {}
    fams: dict[str, TermFamily] = {}
    a = "actuation_delay"

    def add(
        key: str,
        label: str,
        effect: str | None,
        cols: list[FloatArray],
        *,
        parents: tuple[str, ...] = (),
        variable: str | None = None,
        joints: tuple[int, ...] = (),
        extra_df: int = 0,
    ) -> None:
        if effect is not None and effect in sig:
            s = sig[effect]
            cols = [*cols, *(_despiked(s[:, k]) for k in range(s.shape[1]))]
        arr = _stack(cols, m)
        if arr.shape[1]:
            fams[key] = TermFamily(
                key, label, effect, a, arr, parents, variable, joints or cond.joints, extra_df
            )

    masks = [(cond.joint == j).astype(float) for j in cond.joints]
    if "joint_offset" not in present and len(masks) > 1:
        fams["joint"] = TermFamily(
            "joint",
            "a constant per joint",
            "joint_offset",
            a,
            _stack(masks[1:], m),
            (),
            "joint",
            cond.joints,
        )
    if "direction" not in present:
        fams["direction"] = TermFamily(
            "direction",
            "direction (all joints alike)",
            "direction",
            a,
            _stack([d], m),
            (),
            "direction",
            cond.joints,
        )
        add(
            "direction_x_joint",
            "direction, per joint",
            "direction",
            [d * mk for mk in masks],
            parents=("direction", "joint"),
            variable="direction",
        )
    u = np.abs(_normalised(cond, gravity_torque_nm))
    if "gravity_load" not in present:
        cols, joints = _per_joint(cond, u, ["x", "x2", "sqrt"])
        add(
            "load",
            "|gravity torque|, per joint (vanishes at zero load)",
            "gravity_load",
            cols,
            variable="gravity_torque",
            joints=joints,
        )
    if "gravity_direction" not in present:
        v = d * _normalised(cond, gravity_torque_nm)
        cols, joints = _per_joint(cond, v, ["x", "x|x|", "sign_sqrt"])
        add(
            "direction_x_load",
            "direction x gravity torque, per joint",
            "gravity_direction",
            cols,
            parents=("load", "direction_x_joint"),
            variable="direction_x_gravity",
            joints=joints,
        )
    if "inertia" not in present:
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.log(np.maximum(inertia_kgm2, 1e-12) / np.maximum(nominal_inertia_kgm2, 1e-12))
        cols, joints = _per_joint(cond, w, ["x", "x2"], min_spread=0.02)
        add(
            "inertia",
            "log(reflected inertia / nominal), per joint",
            "inertia",
            cols,
            variable="inertia",
            joints=joints,
        )
    if "thermal_drift" not in present:
        s = sweep_fraction(cond)
        basis = _time_basis(s)
        cols, joints = _per_joint(cond, s, ["1-s", "hinge_half", "fast"])
        # One change point for the robot (a warm-up that ends, a mode that switches, ends
        # for every joint at once), chosen on the residuals of all joints; its search costs
        # degrees of freedom the F test counts (CHANGE_POINT_DF).
        c = change_point(s, resid_ms) if resid_ms is not None else None
        extra = 0
        if c is not None:
            basis.append((s < c).astype(float))
            cols += [((s < c) & (cond.joint == j)).astype(float) for j in joints]
            extra = CHANGE_POINT_DF
        add(
            "time",
            "time since the sweep started (vanishes at its end)",
            "thermal_drift",
            basis,
            variable="time",
            extra_df=extra,
        )
        add(
            "time_x_joint",
            "time since the sweep started, per joint",
            "thermal_drift",
            cols,
            parents=("time", "joint"),
            variable="time",
            joints=joints,
            extra_df=extra,
        )
    # The simulator's own form of each candidate alone: few columns, so a small effect of
    # exactly that form is found with the power a generic family of many columns lacks.
    for effect, s in sig.items():
        if effect not in SIGNATURE_EFFECTS or effect in present:
            continue
        arr = _stack([_despiked(s[:, k]) for k in range(s.shape[1])], m)
        if arr.shape[1]:
            key = f"{effect}:simulator"
            fams[key] = TermFamily(
                key,
                f"the simulator's form of {effect}",
                effect,
                a,
                arr,
                (),
                _EFFECT_VARIABLE[effect],
                cond.joints,
            )
    if outside:
        for k in range(6):
            q = cond.q_rad[:, k]
            if np.ptp(q) < 0.1:
                continue
            fams[f"q{k + 1}"] = TermFamily(
                f"q{k + 1}",
                f"joint angle q{k + 1} (all joints)",
                None,
                a,
                _stack(_harmonics(q), m),
                (),
                f"q{k + 1}",
                cond.joints,
            )
            for j, mk in zip(cond.joints, masks, strict=True):
                cols = [h * mk for h in _harmonics(q)]
                arr = _stack(cols, m)
                if arr.shape[1]:
                    fams[f"q{k + 1}@joint{j}"] = TermFamily(
                        f"q{k + 1}@joint{j}",
                        f"joint angle q{k + 1} on joint {j}",
                        None,
                        a,
                        arr,
                        (),
                        f"q{k + 1}",
                        (j,),
                    )
    return fams


def _centred(cols: list[FloatArray]) -> list[FloatArray]:
    return [c - c.mean() for c in cols]


def response_families(
    cond: Conditions,
    *,
    gravity_torque_nm: FloatArray,
    present: tuple[str, ...],
    period_s: float,
    outside: bool = True,
) -> dict[str, TermFamily]:
    """The term families of the response delay.

    The response model has one free constant, bounded to the base timing's packing phase;
    what the bound leaves is the ``response_cycle`` family (a constant: whole extra
    periods, ``response_extra_cycle``). Every other shape of the response delay is outside
    the vocabulary; those families are centred so that they never take the constant.
    """
    m = len(cond)
    r = "response_delay"
    fams: dict[str, TermFamily] = {}
    if "response_extra_cycle" not in present:
        fams["response_cycle"] = TermFamily(
            "response_cycle",
            f"a constant on the response delay (whole {period_s * 1e3:.0f} ms periods)",
            "response_extra_cycle",
            r,
            np.ones((m, 1)),
            (),
            None,
            cond.joints,
        )
    if not outside:
        return fams
    masks = [(cond.joint == j).astype(float) for j in cond.joints]
    d = cond.direction.astype(float)
    s = sweep_fraction(cond)
    u = np.abs(_normalised(cond, gravity_torque_nm))
    shapes: list[tuple[str, str, list[FloatArray], str | None]] = [
        ("response_joint", "response delay per joint", masks[1:], "joint"),
        ("response_direction", "response delay by direction", [d], "direction"),
        (
            "response_time",
            "response delay over the sweep",
            [s, s**2, np.maximum(s - 0.5, 0.0)],
            "time",
        ),
        ("response_load", "response delay with |gravity torque|", [u, u**2], "gravity_torque"),
    ]
    for k in range(6):
        q = cond.q_rad[:, k]
        if np.ptp(q) >= 0.1:
            shapes.append(
                (f"response_q{k + 1}", f"response delay with q{k + 1}", _harmonics(q), f"q{k + 1}")
            )
    for key, label, cols, var in shapes:
        arr = _stack(_centred(cols), m)
        if arr.shape[1]:
            fams[key] = TermFamily(key, label, None, r, arr, (), var, cond.joints)
    return fams
