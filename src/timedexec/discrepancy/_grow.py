"""Growing the model by structure: the term families of the current model, the search
in two stages, the proposals it yields, and adding an effect (the simulator's form, its
measured shape, or the shape alone), confirmed by the drop of the gap.

The model of the actuation condition means is the calibrated simulator plus, per named
effect whose simulator form does not reproduce the measured dependence, that dependence's
*measured shape*: the columns of its term family (frozen when attached), refitted with the
actuation constants to what the simulator leaves (:func:`with_shapes`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._candidates import (
    CandidateScore,
    compare_models,
    initial_effect,
    n_new_params,
)
from timedexec.discrepancy._conditions import NoiseFloor
from timedexec.discrepancy._explain import describe_parameters, gaps_ms, observed_effect
from timedexec.discrepancy._model import (
    FittedModel,
    SimModel,
    actuation_columns,
    calibrate,
    default_effect,
    get_values,
)
from timedexec.discrepancy._result import DiscrepancyStep
from timedexec.discrepancy._select import Selection, forward_select, score_unit
from timedexec.discrepancy._terms import (
    TermFamily,
    actuation_families,
    response_families,
    term_inputs,
)
from timedexec.effects import TermInputs, Variable, effect_type
from timedexec.robots import joint_inertia

__all__ = [
    "Proposal",
    "TermContext",
    "add_effect",
    "find_proposals",
    "search",
    "shape_summary",
    "with_shapes",
]


class TermContext:
    """The variables the term families are built from, and every family's generic columns
    (no simulator signature): the measured *shapes* of named effects use those."""

    def __init__(self, model: SimModel, gravity_torque_nm: FloatArray) -> None:
        cond = model.cond
        spec = model.spec
        home = np.asarray(spec.home_q_rad, dtype=float)[None, :]
        self.model = model
        self.tau = gravity_torque_nm
        self.nominal_inertia = joint_inertia(spec, home)[0][cond.joint - 1]
        self.generic = actuation_families(
            cond,
            gravity_torque_nm=gravity_torque_nm,
            inertia_kgm2=model.true_inertia_kgm2,
            nominal_inertia_kgm2=self.nominal_inertia,
            present=(),
            outside=False,
        )
        self.families: dict[str, TermFamily] = {}
        #: The columns of every shape in the model, frozen when it was attached.
        self.frozen: dict[str, TermFamily] = {}
        #: The conditions as the effects' explanations take them.
        self.inputs: TermInputs = term_inputs(
            cond,
            gravity_torque_nm=gravity_torque_nm,
            inertia_kgm2=model.true_inertia_kgm2,
            nominal_inertia_kgm2=self.nominal_inertia,
            period_s=model.period_s,
        )

    def freeze(self, key: str) -> str:
        """Fix the columns of generic family ``key`` as they are now (a change point is
        chosen on the residuals of the moment); returns the key."""
        self.frozen[key] = self.generic[key]
        return key

    def build(
        self, fitted: FittedModel, signatures: dict[str, FloatArray], resid_ms: FloatArray
    ) -> dict[str, dict[str, TermFamily]]:
        """The candidate families of both delays for the current model (``resid_ms``: its
        actuation residuals, for the change points); the generic families too."""
        cond = self.model.cond
        self.generic = actuation_families(
            cond,
            gravity_torque_nm=self.tau,
            inertia_kgm2=self.model.true_inertia_kgm2,
            nominal_inertia_kgm2=self.nominal_inertia,
            present=(),
            outside=False,
            resid_ms=resid_ms,
        )
        # Families of effects the model has stay candidates: a shape of theirs the
        # simulator's form does not reproduce refines them (never a new name). The
        # closed-form effects are exact: their families would only repeat the model's
        # constants.
        exact = [e for e in fitted.effects if e.closed_form is not None]
        present_a = tuple(e.name for e in exact if e.acts_on == "actuation_delay")
        present_r = tuple(e.name for e in exact if e.acts_on == "response_delay")
        fam_a = actuation_families(
            cond,
            gravity_torque_nm=self.tau,
            inertia_kgm2=self.model.true_inertia_kgm2,
            nominal_inertia_kgm2=self.nominal_inertia,
            present=present_a,
            signatures=signatures,
            resid_ms=resid_ms,
        )
        fam_r = response_families(
            cond, gravity_torque_nm=self.tau, present=present_r, period_s=self.model.period_s
        )
        self.families = {**fam_a, **fam_r}
        return {"actuation_delay": fam_a, "response_delay": fam_r}


def model_constants(model: SimModel, fitted: FittedModel) -> FloatArray:
    """The actuation constants of a model (one, or one per joint with per-joint levels)
    and its data-driven terms' bases (:func:`timedexec.discrepancy._model.actuation_columns`)."""
    return actuation_columns(model, fitted.effects)


def shape_columns(shapes: dict[str, list[str]], terms: TermContext) -> list[tuple[str, FloatArray]]:
    """(effect, frozen columns) of every shape in the model."""
    return [(name, terms.frozen[key].columns) for name, keys in shapes.items() for key in keys]


def model_columns(
    model: SimModel, fitted: FittedModel, shapes: dict[str, list[str]], terms: TermContext
) -> FloatArray:
    """The linear part of the actuation model: its constants and the named effects'
    shapes. The sensitivities of the simulator's parameters are not part of the model:
    the calibration has already moved the parameters as far as the simulator allows, and
    a linearisation (finite differences on a 0.25 ms physics grid, near torque
    saturation) promises more than the simulator can deliver. Only the naming stage of
    :func:`search` lets them move (a missing effect's entry may un-bend them)."""
    cols = [model_constants(model, fitted), *(c for _, c in shape_columns(shapes, terms))]
    return np.column_stack(cols)


def with_shapes(
    model: SimModel, fitted: FittedModel, shapes: dict[str, list[str]], terms: TermContext
) -> FittedModel:
    """The calibrated simulator plus the measured shapes of named effects: the shapes'
    columns and the actuation constants refitted by least squares to what the simulator
    leaves. Returns ``fitted`` itself when there is no shape."""
    blocks = shape_columns(shapes, terms)
    if not blocks:
        return fitted
    a_delay = "actuation_delay"
    consts = model_constants(model, fitted)
    a = np.column_stack([consts, *(c for _, c in blocks)])
    b = fitted.resid_s[a_delay]
    coef, *_ = np.linalg.lstsq(a, b, rcond=1e-8)
    col = consts.shape[1]
    contrib: dict[str, FloatArray] = {}
    for name, c in blocks:
        part = c @ coef[col : col + c.shape[1]]
        contrib[name] = contrib.get(name, np.zeros(len(b))) + part
        col += c.shape[1]
    pred = dict(fitted.pred_s)
    pred[a_delay] = pred[a_delay] + a @ coef
    resid = {d: model.cond.mean_s[d] - pred[d] for d in DELAY_COLUMNS}
    n_fitted = dict(fitted.n_fitted)
    n_fitted[a_delay] += int(np.linalg.matrix_rank(a)) - int(np.linalg.matrix_rank(consts))
    info = {
        **fitted.info,
        "shape_s": contrib,
        "shape_families": {k: list(v) for k, v in shapes.items()},
    }
    return dataclasses.replace(fitted, pred_s=pred, resid_s=resid, n_fitted=n_fitted, info=info)


def free_parameters(fitted: FittedModel) -> NDArray[np.bool_]:
    """Which calibrated parameters can still move both ways: a parameter at a bound of its
    calibration range (within 1 % of the range) cannot follow its sensitivity past it."""
    if not fitted.params:
        return np.zeros(0, dtype=bool)
    x = get_values(fitted.effects, fitted.params)
    lo = np.array([p.lower for p in fitted.params])
    hi = np.array([p.upper for p in fitted.params])
    margin = 0.01 * (hi - lo)
    out: NDArray[np.bool_] = (x > lo + margin) & (x < hi - margin)
    return out


def shape_summary(
    fitted: FittedModel, shapes: dict[str, list[str]], terms: TermContext
) -> dict[str, Any]:
    """The measured shapes in the final model: per effect, its families and the RMS of
    what they add beyond the simulator's form (ms)."""
    contrib = fitted.info.get("shape_s", {})
    out: dict[str, Any] = {}
    for name, keys in shapes.items():
        c = contrib.get(name)
        out[name] = {
            "families": [terms.frozen[k].label for k in keys],
            "rms_ms": float(np.sqrt(np.mean((c - c.mean()) ** 2)) * 1e3) if c is not None else 0.0,
        }
    return out


def search(
    model: SimModel,
    fitted: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    scores: list[CandidateScore],
    noise: NoiseFloor,
    alpha: float,
    min_share: float,
    stage: str,
) -> dict[str, Selection]:
    """Search the residuals of both delays over the term families of one stage.

    ``"name"``: the families of effects the model lacks and those outside the vocabulary,
    with the sensitivities of the model's own parameters free (when a missing effect
    enters, the calibration may un-bend the present effects that mimicked it: a candidate
    is credited only with what they cannot do). ``"refine"``: the families of effects the
    model has, on what the calibrated model actually leaves (a shape of theirs the
    simulator's form does not reproduce), and those outside the vocabulary.
    """
    sigs = {
        s.name: s.signature
        for s in scores
        if effect_type(s.name).closed_form is None
        and s.signature.size
        and s.acts_on == "actuation_delay"
    }
    resid = with_shapes(model, fitted, shapes, terms).resid_s["actuation_delay"] * 1e3
    families = terms.build(fitted, sigs, resid)
    # A family already in the model as a shape adds nothing but rank-deficient columns.
    in_model = {k for keys in shapes.values() for k in keys}
    have = set(fitted.effects.names) | set(shapes)

    def wanted(f: TermFamily) -> bool:
        if f.key in in_model:
            return False
        if f.effect is None:
            return True
        return (f.effect in have) == (stage == "refine")

    families = {d: {k: f for k, f in fams.items() if wanted(f)} for d, fams in families.items()}
    out: dict[str, Selection] = {}
    for delay in DELAY_COLUMNS:
        if delay == "actuation_delay":
            nuisance = model_columns(model, fitted, shapes, terms)
            if stage == "name" and fitted.jac.shape[1]:
                free = free_parameters(fitted)
                if free.any():
                    nuisance = np.column_stack([nuisance, fitted.jac[:, free] * 1e3])
        else:
            nuisance = np.zeros((len(model.cond), 0))
        out[delay] = forward_select(
            fitted.resid_s[delay] * 1e3,
            nuisance,
            families[delay],
            pure_ms2=float(np.mean(noise.mean_var_s2[delay])) * 1e6,
            pure_df=noise.df,
            alpha=alpha,
            min_share=min_share,
        )
    return out


@dataclass(eq=False)
class Proposal:
    """An effect the search proposes to add (or a further shape of a named one)."""

    effect: str
    family: str | None
    evidence: dict[str, Any]
    refit: FittedModel | None
    delay: str


def find_proposals(
    selections: dict[str, Selection],
    families: dict[str, TermFamily],
    excluded: list[str],
) -> list[Proposal]:
    """The vocabulary families the searches kept, in the order they were accepted (the
    two delays merged by the share of the excess their unit explained)."""
    ranked: list[tuple[int, float, Proposal]] = []
    for delay, sel in selections.items():
        for pos, unit in enumerate(sel.accepted):
            for key in unit.kept:
                fam = families[key]
                if fam.effect is None or fam.effect in excluded:
                    continue
                ev = {
                    **unit.to_dict(),
                    "effect": fam.effect,
                    "family": key,
                    "family_label": fam.label,
                }
                ranked.append((pos, -unit.excess_share, Proposal(fam.effect, key, ev, None, delay)))
    ranked.sort(key=lambda r: (r[0], r[1]))
    return [r[2] for r in ranked]


def shape_test(
    model: SimModel,
    fitted: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    family: str,
    noise: NoiseFloor,
    alpha: float,
) -> dict[str, Any]:
    """Does the measured dependence go beyond the simulator's form of the effect? The
    family's generic columns on what the calibrated simulator leaves (the constants and
    the other shapes free): F test at ``alpha`` and a held-out gain of at least one
    standard error."""
    delay = "actuation_delay"
    a0 = model_columns(model, fitted, shapes, terms)
    unit = score_unit(
        fitted.resid_s[delay] * 1e3,
        a0,
        terms.generic[family],
        pure_ms2=float(np.mean(noise.mean_var_s2[delay])) * 1e6,
        pure_df=noise.df,
    )
    needed = bool(unit.p_value < alpha and unit.z >= 1.0 and unit.cv_mse_ms2 < unit.cv_mse_null_ms2)
    return {**unit.to_dict(), "needed": needed}


def calibrate_with(
    name: str, score: CandidateScore | None, model: SimModel, fitted: FittedModel
) -> FittedModel:
    """Calibrate the model with ``name`` added, from the better of several starts.

    Starts: the magnitude the signature amplitude suggests, the vocabulary's, weaker
    versions of the first, and each of these with the present simulated effects reset to
    the vocabulary's magnitudes (a calibration without the missing effect may have bent
    them far to mimic it). A linearised amplitude, or a bent parameter, can put the
    start where a joint no longer breaks away inside the window: the simulator's
    sensitivities vanish there and the solver cannot recover. The start with the smallest
    gap is calibrated (and the next one too when the result fits worse than the model
    without the effect).
    """
    base = default_effect(name, model)
    if score is not None and score.coef.size and np.any(np.abs(score.coef) > 1e-9):
        first = initial_effect(score, model)
    else:
        first = base
    if not first.simulated:
        return calibrate(model, fitted.effects.with_effect(first))
    news = [first, base, first.scaled(0.5), first.scaled(0.25)]
    reset = fitted.effects
    for e in fitted.effects:
        if e.simulated:
            reset = reset.with_effect(default_effect(e.name, model))
    starts = [fitted.effects.with_effect(e) for e in news]
    starts += [reset.with_effect(e) for e in news[:2]]
    delay = "actuation_delay"
    gaps = [calibrate(model, eff, fit_simulated=False).gap_s(delay) for eff in starts]
    order = np.argsort(gaps)
    best = calibrate(model, starts[int(order[0])])
    if best.gap_s(delay) > fitted.gap_s(delay):
        # Worse than without the effect: the solver is stuck; try the next start too.
        second = calibrate(model, starts[int(order[1])])
        best = min((best, second), key=lambda f: f.gap_s(delay))
    return best


def add_effect(
    prop: Proposal,
    model: SimModel,
    fitted: FittedModel,
    current: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    scores: list[CandidateScore],
    noise: NoiseFloor,
    variables: dict[str, Variable],
    alpha: float,
    say: Callable[[str], None],
) -> tuple[DiscrepancyStep, FittedModel, FittedModel, dict[str, list[str]]] | None:
    """Add the proposed effect and confirm that the gap fell significantly (None when it
    did not).

    The simulator is calibrated with the effect; when the simulator's form leaves
    structure along the effect's family, the family's columns are attached as the
    effect's *measured shape*. When the simulator's form cannot be made to fit at all (its
    ``inertia`` has no magnitude that is "off": a small inertia effect is out of its
    reach), the effect enters by its measured shape alone and the step says so.
    """
    name = prop.effect
    say(
        f"candidate {name} ({prop.family or 'recalibrated'}): explains "
        f"{100 * prop.evidence.get('cv_share_of_excess_explained', 0.0):.0f} % of the excess "
        f"(held out), p = {prop.evidence.get('p_value', float('nan')):.2g}; recalibrating"
    )
    if prop.refit is not None:
        new = prop.refit
    else:
        sc = next((s for s in scores if s.name == name), None)
        new = calibrate_with(name, sc, model, fitted)
    new_shapes = {k: list(v) for k, v in shapes.items()}
    shape_info: dict[str, Any] | None = None
    width = 0
    # The family the effect's measured shape is made of: the one that named it, or (named
    # by the simulator's form alone, or by recalibration) the effect's generic family.
    cls = effect_type(name)
    shape_key = prop.family if prop.family in terms.generic else cls.shape_family
    if cls.closed_form is None and shape_key in terms.generic:
        assert shape_key is not None
        test = shape_test(model, new, new_shapes, terms, shape_key, noise, alpha)
        if test["needed"]:
            new_shapes[name] = [terms.freeze(shape_key)]
            width = terms.generic[shape_key].width
            shape_info = {"families": [shape_key], "test": test, "simulator_form": True}
    new_current = with_shapes(model, new, new_shapes, terms)
    delay = prop.delay
    n_new = n_new_params(name, model) + width
    sim_form_fits = True
    if shape_info is not None:
        assert shape_key is not None
        # The same shape without the simulator's form of the effect. With the shape
        # attached, the simulator's form can only add freedom: if the model fits worse
        # with it than without, the form itself is wrong for these data.
        only = {k: list(v) for k, v in shapes.items()}
        only[name] = [terms.freeze(shape_key)]
        by_shape = with_shapes(model, fitted, only, terms)
        ss_sim = float(np.sum(new_current.resid_s[delay] ** 2))
        ss_shape = float(np.sum(by_shape.resid_s[delay] ** 2))
        if ss_shape < ss_sim:
            sim_form_fits = False
            say(
                f"{name}: the simulator's form does not fit (gap "
                f"{new.gap_s(delay) * 1e3:.2f} ms at its best); added by its measured shape"
            )
            best_sim = new
            new, new_current, new_shapes = fitted, by_shape, only
            width = terms.generic[shape_key].width
            n_new = width
            shape_info = {
                "families": [shape_key],
                "simulator_form": False,
                "simulator_form_gap_ms": gaps_ms(best_sim),
                "simulator_form_parameters": best_sim.parameters()["effects"],
            }
    check = compare_models(current, new_current, noise, delay, n_new, alpha)
    if not check["confirmed"]:
        say(f"{name} rejected: the recalibrated model is not significantly closer")
        prop.evidence["confirmation"] = check
        return None
    if shape_info is None or not sim_form_fits:
        sim_form = new_current if sim_form_fits else with_shapes(model, best_sim, shapes, terms)
    else:
        sim_form = with_shapes(model, new, shapes, terms)
    g0, g1 = current.gap_s(delay), new_current.gap_s(delay)
    floor = noise.floor_s[delay]
    excess0 = max(g0**2 - floor**2, 1e-30)
    share = float(np.clip((g0**2 - g1**2) / excess0, 0.0, 1.0))
    shape_s = new_current.info.get("shape_s", {}).get(name)
    extra_ms = None if shape_s is None else shape_s * 1e3
    observed, sentence, contrib_ms = observed_effect(
        name, model, new, variables, terms.inputs, extra_ms
    )
    size = float(np.sqrt(np.mean((contrib_ms - contrib_ms.mean()) ** 2)))
    explanation = (
        f"{sentence}; explains {100 * share:.0f} % of the {delay.replace('_', ' ')} gap "
        f"above the noise floor ({g0 * 1e3:.2f} -> {g1 * 1e3:.2f} ms, noise floor "
        f"{floor * 1e3:.2f} ms)"
    )
    if shape_info is not None:
        assert extra_ms is not None
        fam = terms.frozen[shape_info["families"][0]]
        shape_info["rms_ms"] = float(np.sqrt(np.mean((extra_ms - extra_ms.mean()) ** 2)))
        if sim_form_fits:
            explanation += (
                f"; the simulator's form of it alone leaves {sim_form.gap_s(delay) * 1e3:.2f} "
                f"ms: the measured dependence on the {fam.label} has a shape of its own "
                f"({shape_info['rms_ms']:.2f} ms RMS beyond the simulator's form)"
            )
        else:
            explanation += (
                f"; the simulator's form of it does not fit (at its best it leaves "
                f"{sim_form.gap_s(delay) * 1e3:.2f} ms), so it enters by its measured "
                f"dependence on the {fam.label} alone"
            )
    if sim_form_fits:
        eff = new.effects.get(name)
        assert eff is not None
        parameters = describe_parameters(eff, model)
    else:
        eff = best_sim.effects.get(name)
        assert eff is not None
        parameters = {
            "simulator_form": "does not fit; the effect is modelled by its measured shape",
            "best_simulator_form": describe_parameters(eff, model),
        }
    step = DiscrepancyStep(
        effect=name,
        acts_on=delay,
        explanation=explanation,
        evidence={**prop.evidence, "confirmation": check},
        parameters=parameters,
        observed=observed,
        gap_before_ms=gaps_ms(current),
        gap_after_ms=gaps_ms(new_current),
        share_of_excess_explained=share,
        resid_before_s=current.resid_s[delay].copy(),
        resid_after_s=new_current.resid_s[delay].copy(),
        size_ms=size,
        family=terms.families[prop.family].label if prop.family in terms.families else None,
        gap_after_simulator_form_ms=gaps_ms(sim_form),
        shape=shape_info,
    )
    return step, new, new_current, new_shapes
