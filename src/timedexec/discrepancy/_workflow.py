"""The discrepancy workflow: locate -> name -> add -> shrink.

:func:`analyse_discrepancy` reads the measured delays, groups them into conditions with
their noise floor, and runs the steps, each a function of its own:

1. :func:`step_locate`: simulate the measured conditions with the start effect set and
   calibrate its parameters (``_model.calibrate``); locate the disagreement per joint,
   direction, configuration variable and time against the noise floor of the replicates
   (``_locate``); a lack-of-fit F test says whether anything is missing at all.
2. :func:`step_name`: search the residuals for structure (``_select.forward_select`` over
   the term families of ``_terms``): main effects, interactions (direction x load,
   direction x joint, time x joint), each effect's simulator signature, and shapes outside
   the vocabulary (joint angles; response per joint, time, load), under a hierarchy rule
   and a parsimony test, stopped by a held-out criterion. Two stages: first the families
   of effects the model lacks, with the model's own parameter sensitivities free (the
   present effects may un-bend when the missing one enters); if none of those passes, the
   families of the effects it has, on what the calibrated model really leaves (a shape of
   theirs the simulator's form does not reproduce refines them; no new name). When
   nothing passes although the model does not fit, every simulated candidate is tried by
   recalibrating the whole model with it (the refit screen).
3. :func:`step_add`: add the first effect the search kept: recalibrate the simulator with
   it (from several starts); when its simulator form leaves structure along its family,
   attach the family as its *measured shape*; when the simulator's form cannot fit at
   all, the effect enters by its measured shape alone. Confirm that the gap fell
   significantly (else the effect is rejected). Steps 2 and 3 repeat until nothing of the
   vocabulary passes — a held-out criterion, not a count.
4. :func:`step_recheck` (after discovery): a vocabulary effect named before a discovered
   term that explains its residuals better is withdrawn when it is no longer significant
   beside the terms.
5. :func:`step_shrink`: the gap after, and what remains, reported as unexplained with
   where it sits — never forced onto a name; the order of the repeats within each
   condition is tested on its own (a first-repeat or settling effect no model of
   condition means can show).

Every effect the steps consider comes from the registry (:data:`timedexec.effects.EFFECTS`).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS, DelayTable
from timedexec.discrepancy._candidates import (
    CandidateScore,
    refit_candidates,
    score_candidates,
)
from timedexec.discrepancy._conditions import (
    Conditions,
    NoiseFloor,
    group_conditions,
    replicate_noise,
)
from timedexec.discrepancy._discover import add_discovered, vocabulary_check, withdraw_names
from timedexec.discrepancy._explain import gaps_ms
from timedexec.discrepancy._grow import (
    Proposal,
    TermContext,
    add_effect,
    find_proposals,
    search,
    shape_summary,
    with_shapes,
)
from timedexec.discrepancy._library import Library
from timedexec.discrepancy._locate import (
    condition_variables,
    locate,
    sequence_entries,
    unexplained_entries,
    variable_fit,
)
from timedexec.discrepancy._model import FittedModel, SimModel, calibrate
from timedexec.discrepancy._result import DiscoveredTerm, DiscrepancyResult, DiscrepancyStep
from timedexec.discrepancy._select import Selection, UnitScore
from timedexec.effects import EFFECTS, EffectSet, Variable, parse_effects
from timedexec.errors import ConfigError, RecordingError
from timedexec.robots import RobotSpec, get_robot
from timedexec.sim import simulate_delays

__all__ = [
    "DiscrepancyResult",
    "DiscrepancyStep",
    "Search",
    "analyse_discrepancy",
    "load_measured",
    "step_add",
    "step_discover",
    "step_locate",
    "step_name",
    "step_recheck",
    "step_shrink",
]

#: Most rounds of discovery (each followed by a new search of the vocabulary).
MAX_DISCOVERY_ROUNDS = 3


def load_measured(path: str | os.PathLike[str], *, progress: bool = False) -> DelayTable:
    """Read MEASURED: a delay table (CSV) or a recording (HDF5; extraction runs first)."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(
            f"measured data {p} does not exist (give a delay table CSV or a recording)"
        )
    try:
        with open(p, "rb") as fh:
            magic = fh.read(8)
    except OSError as exc:
        raise RecordingError(f"cannot read {p}: {exc.strerror or exc}") from exc
    if magic == b"\x89HDF\r\n\x1a\n":
        from timedexec.extraction import extract_recording

        if progress:
            print(f"discrepancy: {p} is a recording; extracting its delay table", file=sys.stderr)
        return extract_recording(p, progress=progress).table
    return DelayTable.read_csv(p)


# ---------------------------------------------------------------------------- helpers
def _outside_entry(
    cond: Conditions,
    resid: FloatArray,
    noise: NoiseFloor,
    delay: str,
    variables: dict[str, Variable],
    unit: UnitScore,
) -> dict[str, Any]:
    """An unexplained entry for a shape outside the vocabulary the search accepted: its
    joints, its variable and how far beyond the noise the residuals there are."""
    joints = [j for j in cond.joints if j in unit.joints] or list(cond.joints)
    mask = np.isin(cond.joint, joints)
    v = noise.pooled_var_s2[delay] / cond.n
    r = resid[mask]
    rms = float(np.sqrt(np.mean(r**2)))
    floor = float(np.sqrt(np.mean(v[mask])))
    excess = float(np.sqrt(max(rms**2 - floor**2, 0.0)))
    var = variables.get(unit.variable or "")
    fit = variable_fit(resid, var, mask) if var is not None else None
    what = delay.replace("_", " ")
    text = (
        f"{what} on joint{'s' if len(joints) > 1 else ''} {', '.join(map(str, joints))} "
        f"follows the {unit.label}, {excess * 1e3:.2f} ms RMS beyond the noise (held-out "
        f"error {unit.cv_mse_null_ms2:.3f} -> {unit.cv_mse_ms2:.3f} ms², p = {unit.p_value:.1e})"
    )
    if fit is not None:
        text += (
            f": highest ({fit['high_ms']:+.2f} ms) near {fit['variable']} = "
            f"{fit['high_at']:.2f} {fit['unit']}, lowest ({fit['low_ms']:+.2f} ms) near "
            f"{fit['variable']} = {fit['low_at']:.2f} {fit['unit']}"
        )
    text += ". No effect of the vocabulary explains it."
    return {
        "delay": delay,
        "joints": joints,
        "direction": "both",
        "variable": unit.variable if var is not None else None,
        "variable_label": f"{var.label} ({var.unit})" if var is not None else None,
        "share_explained_by_variable": fit["share"] if fit is not None else None,
        "conditions": int(mask.sum()),
        "mean_ms": float(r.mean() * 1e3),
        "rms_ms": rms * 1e3,
        "excess_rms_ms": excess * 1e3,
        "noise_ms": floor * 1e3,
        "p_value": unit.p_value,
        "description": text,
    }


def _lack_of_fit(fitted: FittedModel, noise: NoiseFloor, delay: str) -> dict[str, Any]:
    """F test of the residual variance of the condition means against pure error."""
    from scipy import stats

    r = fitted.resid_s[delay]
    m = len(r)
    df1 = max(m - fitted.n_fitted[delay], 1)
    pure = float(np.mean(noise.mean_var_s2[delay]))
    f_stat = float(np.sum(r**2) / df1 / pure) if pure > 0 else float("inf")
    if np.isfinite(noise.df):
        p = float(stats.f.sf(f_stat, df1, noise.df))
    else:
        p = float(stats.chi2.sf(f_stat * df1, df1))
    gap = float(np.sqrt(np.mean(r**2)))
    floor = noise.floor_s[delay]
    return {
        "f_statistic": f_stat,
        "df": [df1, noise.df if np.isfinite(noise.df) else None],
        "p_value": p,
        "gap_ms": gap * 1e3,
        "noise_floor_ms": floor * 1e3,
        "excess_ms": float(np.sqrt(max(gap**2 - floor**2, 0.0)) * 1e3),
    }


def _simulated_scatter(model: SimModel, effects: EffectSet, seed: int) -> dict[str, float]:
    """Per-trial variance of the delays from the simulator's own timing randomness at the
    measured conditions (the fallback noise floor)."""
    cond = model.cond
    m = len(cond)
    pick = np.unique(np.linspace(0, m - 1, min(m, 200)).round().astype(int))
    reps = 8
    rows = np.repeat(pick, reps)
    t = cond.t_start_s[rows] + np.tile(np.arange(reps, dtype=float), len(pick))
    # Closed-form effects shift every trial of a condition alike: no scatter.
    physical = EffectSet(tuple(e for e in effects if e.simulated))
    tab = simulate_delays(
        model.spec,
        cond.q_rad[rows],
        cond.joint[rows],
        cond.direction[rows],
        t,
        effects=physical,
        settings=model.settings,
        seed=seed + 7,
    )
    out = {}
    for d in DELAY_COLUMNS:
        y = tab[d].reshape(len(pick), reps)
        out[d] = float(np.mean(np.var(y, axis=1, ddof=1)))
    return out


def _spread_entry(
    cond: Conditions,
    resid: FloatArray,
    delay: str,
    lof: dict[str, Any],
    variables: dict[str, Variable],
    alpha: float,
) -> dict[str, Any]:
    """An unexplained entry for a lack of fit no joint or direction shows on its own: the
    variable the residuals follow best over all conditions, if any does significantly."""
    everything = np.ones(len(cond), dtype=bool)
    fits = [f for f in (variable_fit(resid, v, everything) for v in variables.values()) if f]
    best = max(fits, key=lambda f: f["share"]) if fits else None
    if best is not None and best["p_value"] >= alpha:
        best = None
    text = (
        f"{delay.replace('_', ' ')} disagrees with the simulation by {lof['excess_ms']:.2f} ms "
        "RMS beyond the noise, spread over all joints and directions (no single one "
        "stands out)"
    )
    if best:
        text += (
            f"; it follows the {best['label']} ({best['unit']}) best ({100 * best['share']:.0f} %)"
        )
    text += ". No effect of the vocabulary explains it."
    return {
        "delay": delay,
        "joints": list(cond.joints),
        "direction": "both",
        "variable": best["variable"] if best else None,
        "variable_label": f"{best['label']} ({best['unit']})" if best else None,
        "share_explained_by_variable": best["share"] if best else None,
        "conditions": len(cond),
        "excess_rms_ms": lof["excess_ms"],
        "rms_ms": lof["gap_ms"],
        "noise_ms": lof["noise_floor_ms"],
        "p_value": lof["p_value"],
        "description": text,
    }


# ---------------------------------------------------------------------------- the steps
@dataclass(eq=False)
class Search:
    """The state the steps share: what :func:`step_locate` set up, and the model that
    :func:`step_name` and :func:`step_add` grow.

    Attributes
    ----------
    model : SimModel
        The simulator at the measured conditions.
    noise : NoiseFloor
    start_effects : EffectSet
    variables, loc_vars : dict key -> Variable
        The conditions' variables (for explanations and figures) and those the residuals
        are located against.
    terms : TermContext
        The term families' variables and the frozen shapes.
    fitted : FittedModel
        The calibrated simulator (without the measured shapes).
    current : FittedModel
        ``fitted`` with the measured shapes of named effects: the model the gap is of.
    shapes : dict effect -> list of family keys
        Measured shapes attached to effects.
    steps, rejected, refined : lists
        Effects added (with evidence), rejected after recalibration, and refined by a shape.
    excluded : list of str
        Effects not to propose again.
    selections : dict delay -> Selection
        The last structural search.
    scores, final_scores : list of CandidateScore
        The last signature screen, and the last screen reported (the refit screen's when
        it ran).
    refinements : int
        Shapes attached to effects the model had.
    discover : bool
        Search beyond the vocabulary: test every name against the data-driven terms
        before giving it, and add the terms the vocabulary leaves.
    explained_away : list of str
        Effects whose proposal a data-driven term explained away (not proposed again
        until a discovery changes the model).
    discovered : list of DiscoveredTerm
        Terms outside the vocabulary added to the model.
    """

    model: SimModel
    noise: NoiseFloor
    start_effects: EffectSet
    variables: dict[str, Variable]
    loc_vars: dict[str, Variable]
    terms: TermContext
    fitted: FittedModel
    current: FittedModel
    alpha: float
    min_share: float
    seed: int
    say: Callable[[str], None]
    shapes: dict[str, list[str]] = field(default_factory=dict)
    steps: list[DiscrepancyStep] = field(default_factory=list)
    rejected: list[dict[str, Any]] = field(default_factory=list)
    refined: list[dict[str, Any]] = field(default_factory=list)
    excluded: list[str] = field(default_factory=list)
    selections: dict[str, Selection] = field(default_factory=dict)
    scores: list[CandidateScore] = field(default_factory=list)
    final_scores: list[CandidateScore] = field(default_factory=list)
    refinements: int = 0
    discover: bool = True
    explained_away: list[str] = field(default_factory=list)
    discovered: list[DiscoveredTerm] = field(default_factory=list)
    _library: Library | None = None

    @property
    def library(self) -> Library:
        """The candidate terms over the measured conditions (built on first use)."""
        if self._library is None:
            self._library = Library(self.model)
        return self._library


def step_locate(
    model: SimModel,
    noise: NoiseFloor,
    start_effects: EffectSet,
    *,
    alpha: float,
    min_share: float,
    seed: int,
    say: Callable[[str], None],
) -> tuple[Search, dict[str, Any], dict[str, Any]]:
    """Locate: calibrate the start model and find where it disagrees with the measurement.

    The start effects are calibrated to the measured condition means; the conditions'
    variables (joint angles, holding torque, inertia, time, direction and any an effect
    declares of its own) are computed from the simulator without effects; the lack of fit
    of each delay is F-tested against the noise floor and the residuals are located per
    joint and direction, per quarter of the sweep and against every variable.

    Returns the search state, the lack of fit and the location of each delay.
    """
    cond = model.cond
    say(f"calibrating the start model ({', '.join(start_effects.names) or 'base timing'})")
    fitted = calibrate(model, start_effects)
    sim0 = model.simulate(EffectSet())
    variables = condition_variables(cond, sim0["gravity_torque_nm"], model.true_inertia_kgm2)
    variables["joint"] = Variable(
        "joint", "actuated joint", "joint", "binary", cond.joint.astype(float)
    )
    loc_vars = {k: v for k, v in variables.items() if k != "joint"}
    # An effect's own variable serves its explanation and figures; residuals are located
    # against the workflow's variables only.
    for cls in EFFECTS.values():
        own = cls.own_variable(model.pose)
        if own is not None:
            variables.setdefault(own.key, own)
    terms = TermContext(model, sim0["gravity_torque_nm"])
    current = with_shapes(model, fitted, {}, terms)
    state = Search(
        model=model,
        noise=noise,
        start_effects=start_effects,
        variables=variables,
        loc_vars=loc_vars,
        terms=terms,
        fitted=fitted,
        current=current,
        alpha=alpha,
        min_share=min_share,
        seed=seed,
        say=say,
    )
    lof = {d: _lack_of_fit(current, noise, d) for d in DELAY_COLUMNS}
    where = {d: locate(cond, current.resid_s[d], noise, d, loc_vars) for d in DELAY_COLUMNS}
    return state, lof, where


def step_name(state: Search, min_excess_ms: float) -> Proposal | None:
    """Name: the effect (or further shape of a named one) the residuals call for, or None.

    Scores every registered effect the model lacks by its simulator signature, then
    searches the residuals of both delays for structure: first the families of effects
    the model lacks (and those outside the vocabulary), then, when none passes, the
    families of the effects it has (a shape their simulated form misses refines them). An
    effect that declares ``named_after_shapes`` (its signature looks like a reshaped effect
    of the model's) is named only when it explains the residuals better, held out, than
    the best such shape. When no structure is significant although the actuation delay does not fit, every
    simulated candidate is tried by recalibrating the whole model with it. Returns the
    first proposal (best evidence first).
    """
    s = state
    # Named by their measured shape alone: in the model. Explained away by a data term:
    # not this round.
    exclude = (*s.excluded, *s.explained_away, *s.shapes)
    excluded = [*s.excluded, *s.explained_away]
    scores = score_candidates(
        s.model,
        s.fitted,
        s.noise,
        alpha=s.alpha,
        min_share=s.min_share,
        seed=s.seed,
        exclude=exclude,
    )
    s.scores = s.final_scores = scores
    args = (s.model, s.fitted, s.shapes, s.terms, scores, s.noise, s.alpha, s.min_share)
    s.selections = search(*args, "name")
    proposals = find_proposals(s.selections, s.terms.families, excluded)
    if proposals and EFFECTS[proposals[0].effect].named_after_shapes:
        # Its signature looks like a reshaped effect of the model's: named only when it
        # explains the residuals better (held out) than the best such shape.
        refine = search(*args, "refine")
        shaped = find_proposals(refine, s.terms.families, excluded)
        held_out = "cv_mse_with_ms2"
        if shaped and shaped[0].evidence[held_out] <= proposals[0].evidence[held_out]:
            proposals, s.selections = shaped, refine
    if not proposals:
        refine = search(*args, "refine")
        proposals = find_proposals(refine, s.terms.families, excluded)
        if proposals or not any(sel.accepted for sel in s.selections.values()):
            s.selections = refine
    lof = _lack_of_fit(s.current, s.noise, "actuation_delay")
    if (
        not proposals
        and not s.selections["actuation_delay"].accepted
        and lof["p_value"] < s.alpha
        and lof["excess_ms"] >= min_excess_ms
    ):
        # Nothing of any shape is significant although the model does not fit: the
        # calibration may have bent the present effects to mimic a missing one.
        s.say(
            "the actuation delay does not fit but no structure is significant: "
            "recalibrating the model with each simulated candidate"
        )
        refit = refit_candidates(
            s.model,
            s.fitted,
            s.noise,
            scores,
            alpha=s.alpha,
            min_share=s.min_share,
            seed=s.seed,
            exclude=exclude,
        )
        s.final_scores = refit + [sc for sc in scores if EFFECTS[sc.name].closed_form is not None]
        proposals = [
            Proposal(sc.name, None, sc.to_dict(), sc.refit, sc.acts_on)
            for sc in refit
            if sc.significant
        ]
    for prop in proposals:
        if _accepted(s, prop):
            return prop
    return None


def _accepted(state: Search, prop: Proposal) -> bool:
    """The acceptance test of a vocabulary proposal (:mod:`timedexec.discrepancy._discover`):
    False, and the proposal listed under the rejected candidates, when a data-driven term
    explains what it would explain and more."""
    s = state
    if not s.discover or prop.delay != "actuation_delay":
        return True
    keys = [k for k in prop.evidence.get("kept", []) or [prop.family] if k in s.terms.families]
    if keys:
        cols = np.column_stack([s.terms.families[k].columns for k in keys])
    else:
        sc = next((c for c in s.scores if c.name == prop.effect), None)
        if sc is None or not sc.signature.size:
            return True
        cols = sc.signature
    check = vocabulary_check(
        s.library,
        s.model,
        s.fitted,
        s.shapes,
        s.terms,
        s.noise,
        cols,
        alpha=s.alpha,
        min_share=s.min_share,
    )
    if check is None:
        return True
    prop.evidence["vocabulary_check"] = check
    if not check["explained_away"]:
        return True
    s.say(
        f"{prop.effect} not named: the data-driven terms {'; '.join(check['terms'])} explain "
        f"what it would (p = {check['vocabulary_beyond_terms']['p_value']:.2g} for "
        f"{prop.effect} beyond them)"
    )
    s.rejected.append(
        {
            **prop.evidence,
            "effect": prop.effect,
            "rejected_because": "a data-driven term explains the residuals it would explain, "
            "and more (vocabulary_check)",
        }
    )
    s.explained_away.append(prop.effect)
    return False


def step_discover(state: Search) -> bool:
    """Discover: search the library of data-driven terms on what the model leaves and add
    the terms found (:func:`timedexec.discrepancy._discover.add_discovered`): each becomes
    an effect registered at run time, the model is recalibrated with them and re-run
    through the simulator. Returns True when terms were added."""
    s = state
    added = add_discovered(
        s.library,
        s.model,
        s.fitted,
        s.current,
        s.shapes,
        s.terms,
        s.noise,
        alpha=s.alpha,
        min_share=s.min_share,
        say=s.say,
    )
    if added is None:
        return False
    s.fitted, s.current, found, rejected = added
    if rejected is not None:
        s.rejected.append(rejected)
        return False
    s.discovered.extend(found)
    s.explained_away.clear()
    return True


def step_recheck(state: Search) -> None:
    """Recheck: once terms were discovered, a vocabulary effect named before them is
    withdrawn when it is no longer significant beside them
    (:func:`timedexec.discrepancy._discover.withdraw_names`). Updates ``state``."""
    s = state
    if not s.discovered:
        return
    s.fitted, s.current, s.shapes, withdrawn = withdraw_names(
        s.model, s.fitted, s.current, s.shapes, s.terms, s.noise, s.steps, s.alpha, s.say
    )
    s.rejected.extend(withdrawn)
    s.steps[:] = [st for st in s.steps if st.effect not in {w["effect"] for w in withdrawn}]


def step_add(state: Search, prop: Proposal) -> None:
    """Add: put the proposed effect into the model and confirm it.

    An effect the model has, proposed with a shape its simulated form does not reproduce,
    is *refined* (the shape attached; no new name). A new effect is recalibrated into the
    model (:func:`timedexec.discrepancy._grow.add_effect`); a drop of the gap that is not
    significant rejects it. Updates ``state``.
    """
    s = state
    if (prop.effect in s.fitted.effects or prop.effect in s.shapes) and (
        prop.family is None or prop.family not in s.terms.generic
    ):
        # An effect the model has, proposed again without a shape to attach (the refit
        # screen, or a family of the simulator's form): nothing to add.
        s.excluded.append(prop.effect)
        return
    if prop.effect in s.fitted.effects or prop.effect in s.shapes:
        assert prop.family is not None
        # A shape of an effect the model has (from the start or named earlier) that the
        # simulator's form does not reproduce: it becomes part of that effect's measured
        # shape; no new name.
        s.say(f"{prop.effect}: its measured shape also follows {prop.family}")
        g0 = gaps_ms(s.current)
        s.shapes.setdefault(prop.effect, []).append(s.terms.freeze(prop.family))
        s.current = with_shapes(s.model, s.fitted, s.shapes, s.terms)
        entry = {
            "effect": prop.effect,
            "family": prop.family,
            "family_label": s.terms.families[prop.family].label,
            "from_start_model": prop.effect in s.start_effects,
            "gap_before_ms": g0,
            "gap_after_ms": gaps_ms(s.current),
            "evidence": prop.evidence,
        }
        s.refined.append(entry)
        for st in s.steps:
            if st.effect == prop.effect:
                st.shape = st.shape or {}
                st.shape["families"] = list(s.shapes[prop.effect])
                st.shape.setdefault("refined_by", []).append(entry)
        s.refinements += 1
        return
    added = add_effect(
        prop,
        s.model,
        s.fitted,
        s.current,
        s.shapes,
        s.terms,
        s.scores,
        s.noise,
        s.variables,
        s.alpha,
        s.say,
    )
    if added is None:
        s.rejected.append(prop.evidence)
        s.excluded.append(prop.effect)
        return
    new_step, s.fitted, s.current, s.shapes = added
    ranking = [
        {
            "effect": u.effect if u.effect is not None else f"outside: {u.key}",
            "family": u.key,
            "cv_share_of_excess_explained": u.excess_share,
            "p_value": u.p_value,
            "significant": u.passed,
        }
        for u in s.selections[new_step.acts_on].first_ranking
    ]
    if not ranking:
        ranking = [
            {
                "effect": sc.name,
                "cv_share_of_excess_explained": sc.excess_share,
                "p_value": sc.p_value,
                "significant": sc.significant,
            }
            for sc in s.final_scores
        ]
    new_step.evidence["ranking"] = ranking
    s.steps.append(new_step)
    s.say(f"added {new_step.effect}: {new_step.explanation}")


def step_shrink(state: Search, min_excess_ms: float) -> dict[str, Any]:
    """Shrink: how far the gap fell, and what remains that no effect explains.

    The final model's lack of fit and location per delay; what remains with a
    significant lack of fit (or a shape outside the vocabulary the last search accepted)
    and more than ``min_excess_ms`` RMS above the floor is described as unexplained: which
    joints, which direction, which variable it follows. The order of the repeats is tested
    on its own. Bonferroni over the four tests (two per delay), so that a model that fits
    reports nothing unexplained with probability 1 - alpha.

    Returns ``lack_of_fit_after``, ``where_after`` and ``unexplained``.
    """
    s = state
    cond, fitted, noise, alpha = s.model.cond, s.current, s.noise, s.alpha
    lof_after = {d: _lack_of_fit(fitted, noise, d) for d in DELAY_COLUMNS}
    where_after = {d: locate(cond, fitted.resid_s[d], noise, d, s.loc_vars) for d in DELAY_COLUMNS}
    unexplained: list[dict[str, Any]] = []
    alpha_delay = alpha / (2 * len(DELAY_COLUMNS))
    for d in DELAY_COLUMNS:
        lof = lof_after[d]
        # A shape outside the vocabulary that the last search accepted is evidence too (on
        # one joint it is far more sensitive than the lack of fit over every condition),
        # at the same split of alpha.
        sel = s.selections.get(d)
        outside = [
            u
            for u in (sel.accepted if sel is not None else [])
            if u.effect is None and u.p_value < u.threshold / (2 * len(DELAY_COLUMNS))
        ]
        if lof["excess_ms"] < min_excess_ms or (lof["p_value"] >= alpha_delay and not outside):
            continue
        entries = unexplained_entries(cond, fitted.resid_s[d], noise, d, s.loc_vars, alpha=alpha)
        if not entries and outside:
            entries = [
                _outside_entry(cond, fitted.resid_s[d], noise, d, s.loc_vars, u) for u in outside
            ]
        if not entries:
            entries = [_spread_entry(cond, fitted.resid_s[d], d, lof, s.loc_vars, alpha)]
        unexplained.extend(entries)
    for d in DELAY_COLUMNS:
        # The order of the repeats (no model of condition means sees it).
        unexplained.extend(sequence_entries(cond, d, alpha=alpha_delay))
    return {"lack_of_fit_after": lof_after, "where_after": where_after, "unexplained": unexplained}


def _resolve_robot(
    table: DelayTable, robot: str | RobotSpec | None, period_s: float | None
) -> RobotSpec:
    """The robot of the analysis: given, or the table's only one."""
    if isinstance(robot, RobotSpec):
        return robot if period_s is None else robot.with_period(period_s)
    name = robot
    if name is None:
        robots = table.robots
        if len(robots) != 1:
            raise ConfigError(
                f"{table.source}: the table holds trials of {', '.join(robots)}; pick one with --robot"
            )
        name = robots[0]
    return get_robot(name, period_s=period_s)


def analyse_discrepancy(
    measured: DelayTable | str | os.PathLike[str],
    *,
    robot: str | RobotSpec | None = None,
    start: str | EffectSet = "default",
    period_s: float | None = None,
    alpha: float = 0.01,
    min_share: float = 0.05,
    min_excess_ms: float = 0.1,
    max_steps: int | None = None,
    seed: int = 0,
    discover: bool = True,
    progress: bool = False,
) -> DiscrepancyResult:
    """Find where the simulator disagrees with measured delays and name what is missing.

    Parameters
    ----------
    measured : DelayTable or path
        Measured delays: a table, a delay-table CSV or a recording (HDF5; extracted first).
    robot : str or RobotSpec, optional
        The robot (default: the table's only robot).
    start : str or EffectSet
        The model to start from: ``"base"`` (base timing only), ``"default"`` (the robot's
        default effects), a comma list of effect names, or an EffectSet.
    period_s : float, optional
        Controller period, s (KR 5: 0.012 or 0.004; default: the robot's).
    alpha : float
        Significance level of the tests (family-wise over the candidates of a step).
    min_share : float
        Smallest share of the excess (cross-validated) error a candidate must explain.
    min_excess_ms : float
        A lack of fit whose RMS excess over the noise floor is below this (ms) is not
        reported as unexplained (below the extraction's timing resolution).
    max_steps : int, optional
        Most effects to add (default: the size of the vocabulary).
    seed : int
        Seeds the cross-validation folds and the fallback noise simulation.
    discover : bool
        Look beyond the vocabulary (default): a name is given only where no data-driven
        term explains the residuals better, and terms the vocabulary leaves are searched
        in a library of forms, added to the model as effects registered at run time and
        reported under ``discovered``. False: the vocabulary only.
    progress : bool
        Status lines on stderr.

    Returns
    -------
    DiscrepancyResult

    Raises
    ------
    ConfigError
        Unknown effect names in ``start`` (the message lists the vocabulary), a table of
        several robots without ``robot``, bad parameters.
    RecordingError
        MEASURED cannot be read.
    """
    t_begin = time.perf_counter()

    def say(msg: str) -> None:
        if progress:
            print(f"discrepancy: {msg}", file=sys.stderr, flush=True)

    if not 0 < alpha < 1:
        raise ConfigError(f"alpha={alpha!r} must lie in (0, 1), e.g. 0.01")
    if not 0 <= min_share < 1:
        raise ConfigError(f"min_share={min_share!r} must lie in [0, 1)")
    table = (
        measured if isinstance(measured, DelayTable) else load_measured(measured, progress=progress)
    )
    spec = _resolve_robot(table, robot, period_s)
    if isinstance(start, EffectSet):
        start_effects, start_text = start, ",".join(start.names) or "base"
    else:
        start_effects, start_text = parse_effects(start, spec.name), start
    cond = group_conditions(table, robot=spec.name)
    say(f"{cond.n_trials:,} trials in {len(cond):,} conditions of {spec.name}")
    model = SimModel(spec, cond, seed=seed)
    warnings: list[str] = []
    if cond.n_dropped:
        warnings.append(f"{cond.n_dropped} trial(s) were flagged or had no delay and were left out")
    try:
        noise = replicate_noise(cond)
    except ConfigError:
        say("too few repeats: using the simulator's timing scatter as the noise floor")
        noise = replicate_noise(
            cond, fallback_var_s2=_simulated_scatter(model, start_effects, seed)
        )
    if noise.warning:
        warnings.append(noise.warning)

    state, lof_before, where_before = step_locate(
        model, noise, start_effects, alpha=alpha, min_share=min_share, seed=seed, say=say
    )
    before = state.current
    state.discover = discover
    limit = max_steps if max_steps is not None else len(EFFECTS.vocabulary)
    for _ in range(MAX_DISCOVERY_ROUNDS + 1):
        while len(state.steps) < limit and state.refinements <= 2 * len(EFFECTS.vocabulary):
            prop = step_name(state, min_excess_ms)
            if prop is None:
                say("no candidate effect is significant")
                break
            step_add(state, prop)
        if not discover or not step_discover(state):
            break
    step_recheck(state)
    remains = step_shrink(state, min_excess_ms)

    after = state.current
    final_structure = {
        d: {
            "accepted": [u.to_dict() for u in sel.accepted],
            "ranking": [u.to_dict() for u in sel.first_ranking[:12]],
        }
        for d, sel in state.selections.items()
    }
    runtime = time.perf_counter() - t_begin
    say(f"done in {runtime:.1f} s ({model.n_simulations} simulations)")
    return DiscrepancyResult(
        robot=spec.name,
        source=table.source,
        start=start_text,
        start_effects=list(start_effects.names),
        n_trials=cond.n_trials,
        n_conditions=len(cond),
        n_dropped=cond.n_dropped,
        added_effects=[s.effect for s in state.steps],
        gap_before_ms=gaps_ms(before),
        gap_after_ms=gaps_ms(after),
        noise=noise,
        steps=state.steps,
        unexplained=remains["unexplained"],
        lack_of_fit_before=lof_before,
        lack_of_fit_after=remains["lack_of_fit_after"],
        locations_before=where_before,
        locations_after=remains["where_after"],
        rejected=state.rejected,
        calibration_before=before.parameters(),
        calibration_after={
            **after.parameters(),
            "measured_shapes": shape_summary(after, state.shapes, state.terms),
        },
        warnings=warnings,
        runtime_s=runtime,
        simulations={
            "runs": model.n_simulations,
            "conditions_simulated": model.simulated_conditions,
            "seconds": model.sim_time_s,
        },
        settings={
            "alpha": alpha,
            "min_share": min_share,
            "min_excess_ms": min_excess_ms,
            "controller_period_s": spec.controller_period_s,
            "seed": seed,
        },
        cond=cond,
        variables=state.variables,
        before=before,
        after=after,
        period_s=spec.controller_period_s,
        final_candidates=[s.to_dict() for s in state.final_scores],
        final_structure=final_structure,
        refined_effects=state.refined,
        discovered=state.discovered,
    )
