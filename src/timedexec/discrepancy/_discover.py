"""Discovery in the workflow: the acceptance test a vocabulary name must pass, and the
terms outside the vocabulary added to the model.

**A vocabulary effect is accepted only where it fits.** An effect outside the vocabulary
often correlates over the sweep with one inside it (a dependence on an angle of the arm
with the gravity load that angle sets, a term on one direction with a direction
asymmetry, a term on one joint with that joint's constant): the vocabulary's family then
passes its test and the name is pinned on the wrong cause, leaving a residual 1.5-5x the
floor. Before a name is given (or a shape attached to an effect the model has), the
library of data-driven terms (:mod:`timedexec.discrepancy._library`) is searched on the
same residuals, with the same nuisance columns; the vocabulary's columns V and the terms
found D are then tested against each other: V is *explained away* when it adds nothing
significant beyond D (F test at ``alpha``) while D adds significantly beyond V. The name is
then not given (it is listed under ``rejected_candidates`` with that test) and the
structure is left to discovery. When both add something, or neither (they explain the same
thing), the name stands: the vocabulary is preferred where it explains as well.

**Discovery** (:func:`add_discovered`): when the vocabulary has nothing more to name, the
library is searched on what the model leaves; the terms found (merged across joints where
one shape serves several) become data terms registered at run time
(:func:`timedexec.effects.register_term`), the model is recalibrated with them (their
coefficients fitted with the constants, the simulated effects' parameters re-fitted with
the terms projected out), the drop of the gap must be significant, and the final model is
run through the batch simulator with the terms as effects to show the same gap.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._candidates import compare_models
from timedexec.discrepancy._conditions import NoiseFloor
from timedexec.discrepancy._explain import gaps_ms
from timedexec.discrepancy._grow import (
    TermContext,
    free_parameters,
    model_columns,
    shape_columns,
    with_shapes,
)
from timedexec.discrepancy._library import (
    FIXED_SHAPE,
    Candidate,
    Found,
    Library,
    discover,
    merge_terms,
    nested_test,
    register_found,
    term_uncertainty,
)
from timedexec.discrepancy._model import (
    FittedModel,
    SimModel,
    actuation_columns,
    calibrate,
    closed_form_shift_s,
)
from timedexec.discrepancy._result import DiscoveredTerm, DiscrepancyStep
from timedexec.effects import DataTerm, EffectSet

__all__ = ["add_discovered", "nuisance_columns", "vocabulary_check", "withdraw_names"]

_A = "actuation_delay"


def nuisance_columns(
    model: SimModel, fitted: FittedModel, shapes: dict[str, list[str]], terms: TermContext
) -> FloatArray:
    """What the model can still move on the actuation delay (ms units): its constants, data
    terms and measured shapes, and the sensitivities of its calibrated parameters that are
    not at a bound (as the naming stage of the structure search lets them move)."""
    cols = model_columns(model, fitted, shapes, terms)
    if fitted.jac.shape[1]:
        free = free_parameters(fitted)
        if free.any():
            cols = np.column_stack([cols, fitted.jac[:, free] * 1e3])
    return cols


def _pure(noise: NoiseFloor) -> float:
    return float(np.mean(noise.mean_var_s2[_A])) * 1e6


def vocabulary_check(
    lib: Library,
    model: SimModel,
    fitted: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    noise: NoiseFloor,
    vocab_columns: FloatArray,
    *,
    alpha: float,
    min_share: float,
) -> dict[str, Any] | None:
    """The acceptance test of a vocabulary effect proposed with the columns
    ``vocab_columns`` (module docstring). Returns None when no data-driven term is
    significant on these residuals (nothing to compare with), else the test:
    ``terms`` (the terms found), ``vocabulary_beyond_terms`` and ``terms_beyond_vocabulary``
    (F, df, p) and ``explained_away``."""
    b = fitted.resid_s[_A] * 1e3
    base = nuisance_columns(model, fitted, shapes, terms)
    pure, df = _pure(noise), noise.df
    found = discover(lib, b, base, pure_ms2=pure, pure_df=df, alpha=alpha, min_share=min_share)
    if not found:
        return None
    d_cols = np.column_stack([f.columns for f in found])
    v_given_d = nested_test(
        b, np.column_stack([base, d_cols]), vocab_columns, pure_ms2=pure, pure_df=df
    )
    d_given_v = nested_test(
        b, np.column_stack([base, vocab_columns]), d_cols, pure_ms2=pure, pure_df=df
    )
    away = v_given_d["p_value"] >= alpha and d_given_v["p_value"] < alpha
    return {
        "terms": [f.candidate.label for f in found],
        "vocabulary_beyond_terms": v_given_d,
        "terms_beyond_vocabulary": d_given_v,
        "explained_away": bool(away),
    }


# ---------------------------------------------------------------------------- in words
_SHAPE_NAMES = {
    "linear": ("reference",),
    "hinge_up": ("knot",),
    "hinge_down": ("knot",),
    "harmonic": ("order",),
    "bump": ("centre", "width"),
    "bump2": ("centre", "width", "centre", "width"),
    "product": ("reference", "reference"),
}


def _unit(name: str) -> str:
    return "rad" if name.startswith("q") else "N·m"


def _parameters(term: DataTerm, unc: dict[str, Any]) -> dict[str, Any]:
    """The term's coefficients, shape and size per joint, each with its standard error."""
    k = term.n_columns // len(term.joints)
    coef_ms = np.asarray(term.coef_s) * 1e3
    se = np.asarray(unc.get("coefficient_se_ms", [math.nan] * len(coef_ms)))
    cov = np.asarray(unc.get("coefficient_cov_ms2", np.full((len(coef_ms),) * 2, math.nan)))
    x_unit = (
        "·".join(_unit(i) for i in term.inputs) if term.form == "product" else _unit(term.inputs[0])
    )
    coefficients: dict[str, Any] = {}
    sizes: dict[str, Any] = {}
    for i, j in enumerate(term.joints):
        c = coef_ms[i * k : (i + 1) * k]
        s = se[i * k : (i + 1) * k]
        coefficients[f"joint {j}"] = [
            {"value": float(v), "se": float(e)} for v, e in zip(c, s, strict=True)
        ]
        if term.form == "harmonic":
            amp = float(np.hypot(c[0], c[1]))
            block = cov[i * k : (i + 1) * k, i * k : (i + 1) * k]
            var = (c @ block @ c) / amp**2 if amp > 0 else math.nan
            sizes[str(j)] = {
                "kind": "amplitude",
                "value": amp,
                "se": float(math.sqrt(max(var, 0.0))),
                "unit": "ms",
                "phase_rad": float(math.atan2(c[1], c[0])),
            }
        elif term.form.startswith("bump"):
            sizes[str(j)] = {"kind": "peak", "value": float(c[0]), "se": float(s[0]), "unit": "ms"}
        else:
            sizes[str(j)] = {
                "kind": "slope",
                "value": float(c[0]),
                "se": float(s[0]),
                "unit": f"ms/{x_unit}",
            }
    names = _SHAPE_NAMES[term.form]
    shape_se = list(unc.get("shape_se", []))
    shape = []
    for i, (name, v) in enumerate(zip(names, term.shape, strict=True)):
        inp = {"bump2": term.inputs[min(i // 2, len(term.inputs) - 1)]}.get(
            term.form, term.inputs[min(i, len(term.inputs) - 1)]
        )
        fitted = term.form not in FIXED_SHAPE
        shape.append(
            {
                "name": f"{name} of {inp}" if name != "order" else "order",
                "value": float(v),
                "se": float(shape_se[i]) if fitted and i < len(shape_se) else None,
                "unit": _unit(inp) if name != "order" else "",
                "fitted": fitted,
            }
        )
    return {"coefficients_ms": coefficients, "shape": shape, "size_per_joint": sizes}


def _pm(v: float, e: float | None, fmt: str = ".2f") -> str:
    if e is None or not math.isfinite(e):
        return format(v, fmt)
    return f"{format(v, fmt)} ± {format(e, fmt)}"


def _words(term: DataTerm, params: dict[str, Any]) -> str:
    """The term in words: joint, form, input, size with its standard error, direction."""
    x = term.inputs[0]
    u = _unit(x)
    shape = params["shape"]
    sizes = params["size_per_joint"]

    def size_text(j: int) -> str:
        z = sizes[str(j)]
        v, e = z["value"], z["se"]
        if z["kind"] == "slope" and term.form == "product":
            x2, r1, r2 = term.inputs[1], shape[0]["value"], shape[1]["value"]
            verb = "rises" if v >= 0 else "falls"
            return (
                f"{verb} {_pm(abs(v), e)} ms per {u}·{_unit(x2)} of ({x} - {r1:.2f})·"
                f"({x2} - {r2:.2f}) (with both angles at once, a saddle)"
            )
        if z["kind"] == "slope":
            verb = "rises" if v >= 0 else "falls"
            return f"{verb} {_pm(abs(v), e)} ms per {u} of {x}"
        if z["kind"] == "amplitude":
            return f"varies by {_pm(v, e)} ms (amplitude)"
        return f"is {_pm(abs(v), e)} ms {'longer' if v >= 0 else 'shorter'}"

    if term.form in ("linear", "product"):
        where = ""
    elif term.form == "hinge_up":
        where = f" beyond {x} = {_pm(shape[0]['value'], shape[0]['se'])} {u} (zero below)"
    elif term.form == "hinge_down":
        where = f" as {x} falls below {_pm(shape[0]['value'], shape[0]['se'])} {u} (zero above)"
    elif term.form == "harmonic":
        n = int(term.shape[0])
        where = f" periodically with {x}, {n} period{'s' if n > 1 else ''} per turn"
    elif term.form == "bump":
        c, w = shape
        where = (
            f" near {x} = {_pm(c['value'], c['se'])} {u} (a bump of width "
            f"{_pm(w['value'], w['se'])} {u})"
        )
    else:
        c1, w1, c2, w2 = shape
        x2 = term.inputs[1]
        where = (
            f" near ({x}, {x2}) = ({_pm(c1['value'], c1['se'])}, "
            f"{_pm(c2['value'], c2['se'])}) {u} (a local bump of widths "
            f"{_pm(w1['value'], w1['se'])} and {_pm(w2['value'], w2['se'])} {u})"
        )
    side = {0: "", 1: ", on the positive direction only", -1: ", on the negative direction only"}
    if len(term.joints) == 1:
        j = term.joints[0]
        return f"joint {j}'s actuation delay {size_text(j)}{where}{side[term.direction]}"
    per = "; ".join(f"joint {j} {size_text(j)}" for j in term.joints)
    joints = ", ".join(map(str, term.joints))
    return f"joints {joints} share one term{where}{side[term.direction]}: {per}"


# ---------------------------------------------------------------------------- adding
def _linear_rest(
    model: SimModel,
    fitted: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    without: str,
) -> FloatArray:
    """The model's linear actuation columns without the data term ``without`` (constants,
    the other terms, the measured shapes)."""
    others = EffectSet(tuple(e for e in fitted.effects if e.name != without))
    cols = [actuation_columns(model, others), *(c for _, c in shape_columns(shapes, terms))]
    return np.column_stack(cols)


def add_discovered(
    lib: Library,
    model: SimModel,
    fitted: FittedModel,
    current: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    noise: NoiseFloor,
    *,
    alpha: float,
    min_share: float,
    say: Callable[[str], None],
) -> tuple[FittedModel, FittedModel, list[DiscoveredTerm], dict[str, Any] | None] | None:
    """Search the library on what the model leaves, add the terms found, recalibrate and
    confirm (module docstring).

    Returns None when no term is significant; else the recalibrated model (without and
    with the measured shapes), the discovered terms, and None — or, when the drop of the
    gap is not significant, the unchanged models, no term and the rejection.
    """
    b = fitted.resid_s[_A] * 1e3
    base = nuisance_columns(model, fitted, shapes, terms)
    pure, df = _pure(noise), noise.df
    found = discover(lib, b, base, pure_ms2=pure, pure_df=df, alpha=alpha, min_share=min_share)
    if not found:
        return None
    merged = merge_terms(lib, found, b, base)
    new_terms = [register_found(c) for c, _ in merged]
    say(
        "outside the vocabulary: "
        + "; ".join(c.label for c, _ in merged)
        + " — recalibrating with them"
    )
    effects = fitted.effects
    for t in new_terms:
        effects = effects.with_effect(t)
    new_fitted = calibrate(model, effects)
    new_current = with_shapes(model, new_fitted, shapes, terms)
    n_new = sum(t.n_columns + (0 if t.form in FIXED_SHAPE else len(t.shape)) for t in new_terms)
    check = compare_models(current, new_current, noise, _A, n_new, alpha)
    if not check["confirmed"]:
        say("the discovered terms do not close the gap significantly: not added")
        rejected = {
            "terms": [c.label for c, _ in merged],
            "confirmation": check,
            "rejected_because": "the recalibrated model is not significantly closer",
        }
        return fitted, current, [], rejected
    # The re-run: every effect, the discovered terms included, through the batch simulator.
    sim_all = model.simulate(new_fitted.effects, closed_form=True)
    shape_part = new_current.pred_s[_A] - new_fitted.pred_s[_A]
    resim_pred = {
        _A: sim_all[_A] + new_fitted.act_offset_s + shape_part,
        "response_delay": sim_all["response_delay"] + new_fitted.resp_offset_s,
    }
    resim_gap = {
        d: float(np.sqrt(np.mean((model.cond.mean_s[d] - resim_pred[d]) ** 2)) * 1e3)
        for d in DELAY_COLUMNS
    }
    agree_ms = float(np.max(np.abs(resim_pred[_A] - new_current.pred_s[_A])) * 1e3)
    g0, g1 = gaps_ms(current), gaps_ms(new_current)
    floor = noise.floor_s[_A] * 1e3
    excess0 = max(g0[_A] ** 2 - floor**2, 1e-12)
    share = float(np.clip((g0[_A] ** 2 - g1[_A] ** 2) / excess0, 0.0, 1.0))
    r_final = new_current.resid_s[_A]
    free_jac = (
        new_fitted.jac[:, free_parameters(new_fitted)] * 1e3
        if new_fitted.jac.shape[1]
        else np.zeros((len(r_final), 0))
    )
    out: list[DiscoveredTerm] = []
    for (cand, members), t in zip(merged, new_terms, strict=True):
        fitted_t = new_fitted.effects.get(t.name)
        assert isinstance(fitted_t, DataTerm)
        contrib = closed_form_shift_s(fitted_t, model)
        rest = _linear_rest(model, new_fitted, shapes, terms, t.name)
        q, _ = np.linalg.qr(rest)
        r_without = r_final + contrib
        r_without = r_without - q @ (q.T @ r_without)
        closed = float(np.sqrt(np.mean(r_without**2)) - np.sqrt(np.mean(r_final**2))) * 1e3
        unc = term_uncertainty(
            lib,
            Candidate(
                fitted_t.joints, fitted_t.inputs, fitted_t.form, fitted_t.shape, fitted_t.direction
            ),
            (r_final + contrib) * 1e3,
            np.column_stack([rest, free_jac]),
            pure_ms2=pure,
        )
        params = _parameters(fitted_t, unc)
        text = (
            f"{_words(fitted_t, params)}; closes {closed:.2f} ms of the actuation gap "
            f"({g0[_A]:.2f} -> {g1[_A]:.2f} ms with the terms of this step, noise floor "
            f"{floor:.2f} ms)"
        )
        evidence: dict[str, Any] = {
            **_merged_evidence(cand, members),
            "confirmation": check,
            "resimulated_max_difference_ms": agree_ms,
        }
        mask = np.isin(model.cond.joint, cand.joints)
        if cand.direction:
            mask &= np.sign(model.cond.direction) == cand.direction
        out.append(
            DiscoveredTerm(
                effect=fitted_t,
                description=text,
                parameters=params,
                gap_closed_ms=closed,
                gap_before_ms=g0,
                gap_after_ms=g1,
                gap_after_resimulated_ms=resim_gap,
                share_of_excess_explained=share,
                evidence=evidence,
                resid_before_s=r_final + contrib,
                resid_after_s=r_final.copy(),
                input_values={n: lib.inputs[n] for n in cand.inputs},
                mask=mask,
            )
        )
        say(f"discovered: {text}")
    return new_fitted, new_current, out, None


def _merged_evidence(cand: Candidate, members: list[Found]) -> dict[str, Any]:
    """The selection evidence of a term (of each joint's part when merged)."""
    if len(members) == 1:
        return members[0].evidence()
    return {
        "method": "discovery",
        "merged": f"one shape for joints {', '.join(map(str, cand.joints))}",
        "parts": [m.evidence() for m in members],
    }


def withdraw_names(
    model: SimModel,
    fitted: FittedModel,
    current: FittedModel,
    shapes: dict[str, list[str]],
    terms: TermContext,
    noise: NoiseFloor,
    steps: list[DiscrepancyStep],
    alpha: float,
    say: Callable[[str], None],
) -> tuple[FittedModel, FittedModel, dict[str, list[str]], list[dict[str, Any]]]:
    """Each vocabulary effect named on the actuation delay (``steps``) must still be
    significant beside the discovered terms: the model is recalibrated without it (the
    terms and the other effects kept); when the full model is not significantly closer
    (extra-sum-of-squares F test at ``alpha``) the name is withdrawn — it was named before
    the term that explains its residuals better was found (a one-direction term on two
    joints first named ``direction`` and ``joint_offset``, say).

    Returns the model (without and with the measured shapes) and the shapes after the
    withdrawals, and the withdrawn names' entries for the rejected candidates."""
    withdrawn: list[dict[str, Any]] = []
    for st in steps:
        if st.acts_on != _A:
            continue
        effects = EffectSet(tuple(e for e in fitted.effects if e.name != st.effect))
        fewer = {k: v for k, v in shapes.items() if k != st.effect}
        fitted_w = calibrate(model, effects)
        current_w = with_shapes(model, fitted_w, fewer, terms)
        n_new = max(current.n_fitted[_A] - current_w.n_fitted[_A], 1)
        check = compare_models(current_w, current, noise, _A, n_new, alpha)
        if check["confirmed"]:
            continue
        say(
            f"{st.effect} withdrawn: not significant beside the discovered terms (p = {check['p_value']:.2g})"
        )
        withdrawn.append(
            {
                **st.evidence,
                "effect": st.effect,
                "recheck": check,
                "rejected_because": "not significant beside the discovered terms "
                "(named before them; step_recheck)",
            }
        )
        fitted, current, shapes = fitted_w, current_w, fewer
    return fitted, current, shapes, withdrawn
