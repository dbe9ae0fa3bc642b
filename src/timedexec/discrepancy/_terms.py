"""Structural terms: the shapes a disagreement between simulation and measurement can take.

A *term family* is a small set of columns over the conditions — a free function of one
variable, or of two (an *interaction*) — that the residuals of the condition means may
follow. Each family carries the name of the effect of the vocabulary it stands for, or
None when no effect of the vocabulary has that shape (it is then reported as
unexplained, where it sits). The families of an effect are declared by its class
(``Effect.term_families``, :mod:`timedexec.effects`); this module adds each simulated
effect's signature and the shapes outside the vocabulary. The built-in vocabulary's:

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
column of the families it marks (``TermSpec.signature``): the simulator's own form is
always among the shapes tried.

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

from timedexec._columns import normalised_per_joint, stack_columns, sweep_fraction
from timedexec._types import FloatArray
from timedexec.discrepancy._conditions import Conditions
from timedexec.effects import EFFECTS, TermInputs, TermSpec, effect_type

__all__ = ["TermFamily", "actuation_families", "response_families", "term_inputs"]


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
    positive : bool
        Its effect only lengthens the delay: the family passes only when the residuals'
        mean is positive.
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
    positive: bool = False

    @property
    def width(self) -> int:
        """Number of columns."""
        return int(self.columns.shape[1])


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


def _harmonics(x: FloatArray) -> list[FloatArray]:
    return [np.sin(x), np.cos(x), np.sin(2 * x), np.cos(2 * x)]


def term_inputs(
    cond: Conditions,
    *,
    gravity_torque_nm: FloatArray,
    inertia_kgm2: FloatArray,
    nominal_inertia_kgm2: FloatArray,
    resid_ms: FloatArray | None = None,
    period_s: float = float("nan"),
) -> TermInputs:
    """The conditions as the effects' term families and explanations take them."""
    return TermInputs(
        joint=cond.joint,
        direction=cond.direction.astype(float),
        joints=cond.joints,
        q_rad=cond.q_rad,
        t_start_s=cond.t_start_s,
        gravity_torque_nm=gravity_torque_nm,
        inertia_kgm2=inertia_kgm2,
        nominal_inertia_kgm2=nominal_inertia_kgm2,
        resid_ms=resid_ms,
        period_s=period_s,
        mean_s=cond.mean_s,
    )


def _effect_families(
    x: TermInputs,
    delay: str,
    present: tuple[str, ...],
    signatures: dict[str, FloatArray],
) -> dict[str, TermFamily]:
    """The families every registered effect of ``delay`` not in ``present`` declares, in
    the vocabulary's order, each marked one with its simulator signature appended."""
    m = len(x)
    fams: dict[str, TermFamily] = {}
    for name in EFFECTS.vocabulary:
        cls = EFFECTS[name]
        if cls.acts_on != delay or name in present:
            continue
        for spec in cls.term_families(x):
            arr = spec.columns
            if spec.signature and name in signatures:
                sig = signatures[name]
                extra = stack_columns([_despiked(sig[:, k]) for k in range(sig.shape[1])], m)
                arr = np.column_stack([arr, extra])
            if arr.shape[1]:
                fams[spec.key] = _family(spec, arr, name, delay, x.joints)
    return fams


def _family(
    spec: TermSpec, columns: FloatArray, effect: str, delay: str, joints: tuple[int, ...]
) -> TermFamily:
    return TermFamily(
        spec.key,
        spec.label,
        effect,
        delay,
        columns,
        spec.parents,
        spec.variable,
        spec.joints or joints,
        spec.extra_df,
        spec.positive,
    )


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
        point that fits them best (:func:`timedexec._columns.change_point`; overall, and
        per joint).
    """
    m = len(cond)
    sig = signatures or {}
    a = "actuation_delay"
    x = term_inputs(
        cond,
        gravity_torque_nm=gravity_torque_nm,
        inertia_kgm2=inertia_kgm2,
        nominal_inertia_kgm2=nominal_inertia_kgm2,
        resid_ms=resid_ms,
    )
    fams = _effect_families(x, a, present, sig)
    # The simulator's own form of each candidate alone: few columns, so a small effect of
    # exactly that form is found with the power a generic family of many columns lacks.
    for effect, s in sig.items():
        cls = effect_type(effect)
        if cls.closed_form is not None or effect in present:
            continue
        arr = stack_columns([_despiked(s[:, k]) for k in range(s.shape[1])], m)
        if arr.shape[1]:
            key = f"{effect}:simulator"
            fams[key] = TermFamily(
                key,
                f"the simulator's form of {effect}",
                effect,
                a,
                arr,
                (),
                cls.variable_key,
                cond.joints,
            )
    if outside:
        masks = x.masks
        for k in range(6):
            q = cond.q_rad[:, k]
            if np.ptp(q) < 0.1:
                continue
            fams[f"q{k + 1}"] = TermFamily(
                f"q{k + 1}",
                f"joint angle q{k + 1} (all joints)",
                None,
                a,
                stack_columns(_harmonics(q), m),
                (),
                f"q{k + 1}",
                cond.joints,
            )
            for j, mk in zip(cond.joints, masks, strict=True):
                cols = [h * mk for h in _harmonics(q)]
                arr = stack_columns(cols, m)
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
    what the bound leaves are the families of the effects on the response delay (whole
    extra periods, ``response_cycle`` of ``response_extra_cycle``). Every other shape of the
    response delay is outside the vocabulary; those families are centred so that they never
    take the constant.
    """
    m = len(cond)
    r = "response_delay"
    x = term_inputs(
        cond,
        gravity_torque_nm=gravity_torque_nm,
        inertia_kgm2=np.full(m, np.nan),
        nominal_inertia_kgm2=np.full(m, np.nan),
        period_s=period_s,
    )
    fams = _effect_families(x, r, present, {})
    if not outside:
        return fams
    masks = x.masks
    d = x.direction
    s = sweep_fraction(cond.t_start_s)
    u = np.abs(normalised_per_joint(cond.joint, cond.joints, gravity_torque_nm))
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
        arr = stack_columns(_centred(cols), m)
        if arr.shape[1]:
            fams[key] = TermFamily(key, label, None, r, arr, (), var, cond.joints)
    return fams
