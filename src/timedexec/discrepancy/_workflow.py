"""The discrepancy workflow: calibrate, locate, name the missing effect, add it, repeat.

1. Simulate the measured conditions with the start effect set and calibrate its parameters
   (``_model.calibrate``).
2. Locate the disagreement per joint, direction, configuration variable and time against
   the noise floor of the replicates (``_locate``); a lack-of-fit F test says whether
   anything is missing at all.
3. Score every effect of the vocabulary the model lacks (``_candidates``); take the best
   significant one.
4. Add it, recalibrate everything, and confirm that the gap fell significantly; repeat
   until no candidate is significant. What remains is reported as unexplained, with where it
   sits — never forced onto a name.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._files import write_atomic
from timedexec.delays import DELAY_COLUMNS, DelayTable
from timedexec.discrepancy._candidates import (
    CandidateScore,
    compare_models,
    initial_effect,
    n_new_params,
    refit_candidates,
    score_candidates,
)
from timedexec.discrepancy._conditions import (
    Conditions,
    NoiseFloor,
    group_conditions,
    replicate_noise,
)
from timedexec.discrepancy._locate import (
    EFFECT_VARIABLE,
    Variable,
    condition_variables,
    locate,
    unexplained_entries,
    variable_fit,
)
from timedexec.discrepancy._model import (
    FittedModel,
    SimModel,
    calibrate,
)
from timedexec.effects import (
    Direction,
    Effect,
    EffectSet,
    GravityDirection,
    GravityLoad,
    Inertia,
    JointOffset,
    ResponseExtraCycle,
    ThermalDrift,
    make_effect,
    parse_effects,
)
from timedexec.errors import ConfigError, RecordingError
from timedexec.robots import RobotSpec, get_robot
from timedexec.sim import simulate_delays

__all__ = ["DiscrepancyResult", "DiscrepancyStep", "analyse_discrepancy", "load_measured"]

FloatArray = NDArray[np.float64]


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


# ---------------------------------------------------------------------------- results
@dataclass(eq=False)
class DiscrepancyStep:
    """One effect added to the model, with its evidence and what it changed."""

    effect: str
    acts_on: str
    explanation: str
    evidence: dict[str, Any]
    parameters: dict[str, Any]
    observed: dict[str, Any]
    gap_before_ms: dict[str, float]
    gap_after_ms: dict[str, float]
    share_of_excess_explained: float
    resid_before_s: FloatArray
    resid_after_s: FloatArray

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        e = make_effect(self.effect)
        return {
            "effect": self.effect,
            "acts_on": self.acts_on,
            "meaning": e.meaning,
            "variable": e.variable,
            "explanation": self.explanation,
            "evidence": self.evidence,
            "parameters": self.parameters,
            "observed": self.observed,
            "gap_before_ms": self.gap_before_ms,
            "gap_after_ms": self.gap_after_ms,
            "share_of_excess_gap_explained": self.share_of_excess_explained,
        }


@dataclass(eq=False)
class DiscrepancyResult:
    """What :func:`analyse_discrepancy` found. ``to_dict()`` is the OUT.json content."""

    robot: str
    source: str
    start: str
    start_effects: list[str]
    n_trials: int
    n_conditions: int
    n_dropped: int
    added_effects: list[str]
    gap_before_ms: dict[str, float]
    gap_after_ms: dict[str, float]
    noise: NoiseFloor
    steps: list[DiscrepancyStep]
    unexplained: list[dict[str, Any]]
    lack_of_fit_before: dict[str, Any]
    lack_of_fit_after: dict[str, Any]
    locations_before: dict[str, Any]
    locations_after: dict[str, Any]
    rejected: list[dict[str, Any]]
    calibration_before: dict[str, Any]
    calibration_after: dict[str, Any]
    warnings: list[str]
    runtime_s: float
    simulations: dict[str, Any]
    settings: dict[str, Any]
    cond: Conditions
    variables: dict[str, Variable]
    before: FittedModel
    after: FittedModel
    period_s: float
    final_candidates: list[dict[str, Any]] = field(default_factory=list)

    @property
    def noise_floor_ms(self) -> dict[str, float]:
        """Noise floor per delay, ms."""
        return {k: v * 1e3 for k, v in self.noise.floor_s.items()}

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe result (the OUT.json document)."""
        return {
            "robot": self.robot,
            "measured": self.source,
            "trials": self.n_trials,
            "conditions": self.n_conditions,
            "trials_dropped": self.n_dropped,
            "start": self.start,
            "start_effects": self.start_effects,
            "added_effects": self.added_effects,
            "gap_before_ms": self.gap_before_ms,
            "gap_after_ms": self.gap_after_ms,
            "noise_floor_ms": self.noise_floor_ms,
            "noise_floor": self.noise.to_dict(),
            "steps": [s.to_dict() for s in self.steps],
            "unexplained": self.unexplained,
            "lack_of_fit_before": self.lack_of_fit_before,
            "lack_of_fit_after": self.lack_of_fit_after,
            "where_before": self.locations_before,
            "where_after": self.locations_after,
            "rejected_candidates": self.rejected,
            "final_candidates": self.final_candidates,
            "calibration_before": self.calibration_before,
            "calibration_after": self.calibration_after,
            "warnings": self.warnings,
            "settings": self.settings,
            "runtime_s": self.runtime_s,
            "simulations": self.simulations,
        }

    def write_json(self, path: str | os.PathLike[str]) -> Path:
        """Write :meth:`to_dict` as JSON (atomically)."""
        return write_atomic(path, json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n")

    def write_report(self, directory: str | os.PathLike[str]) -> Path:
        """Write the engineer's report (markdown + PNG figures) into ``directory``;
        returns the markdown file."""
        from timedexec.discrepancy._report import write_report

        return write_report(self, directory)

    def summary_text(self) -> str:
        """A few lines for the terminal."""
        fl = self.noise_floor_ms
        lines = [
            f"discrepancy of {self.robot}: {self.n_trials:,} trials in {self.n_conditions:,} "
            f"conditions; start: {self.start} ({', '.join(self.start_effects) or 'base timing only'})",
        ]
        for d in DELAY_COLUMNS:
            lines.append(
                f"  {d.replace('_', ' '):16s} gap {self.gap_before_ms[d]:6.2f} ms -> "
                f"{self.gap_after_ms[d]:6.2f} ms   noise floor {fl[d]:5.2f} ms"
            )
        if self.steps:
            for k, s in enumerate(self.steps, 1):
                lines.append(f"  step {k}: added {s.effect}: {s.explanation}")
        else:
            lines.append("  no effect of the vocabulary is missing (none significant)")
        for u in self.unexplained:
            lines.append(f"  unexplained: {u['description']}")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------- helpers
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


def _gaps_ms(fitted: FittedModel) -> dict[str, float]:
    return {d: fitted.gap_s(d) * 1e3 for d in DELAY_COLUMNS}


def _describe_parameters(effect: Effect, model: SimModel) -> dict[str, Any]:
    """Fitted parameters in physical units."""
    joints = model.cond.joints
    if isinstance(effect, GravityLoad):
        return {
            "friction_per_load": effect.friction_per_load,
            "unit": "N·m of extra breakaway torque per N·m of holding torque",
        }
    if isinstance(effect, GravityDirection):
        return {
            "friction_per_load": effect.friction_per_load,
            "unit": "N·m of breakaway torque change per N·m of direction x holding torque",
        }
    if isinstance(effect, Direction):
        return {
            "asymmetry": {f"joint {j}": effect.asymmetry[j - 1] for j in joints},
            "unit": "breakaway torque scale 1 + asymmetry x direction (fraction)",
        }
    if isinstance(effect, Inertia):
        return {"scale": effect.scale, "unit": "x the robot spec's link inertia"}
    if isinstance(effect, ThermalDrift):
        return {
            "cold_excess": effect.cold_excess,
            "time_constant_s": effect.time_constant_s,
            "unit": "friction excess at sweep start (fraction); warm-up time constant (s)",
        }
    if isinstance(effect, JointOffset):
        return {
            "offsets_ms": {f"joint {j}": effect.offsets_s[j - 1] * 1e3 for j in joints},
            "unit": "ms of extra dead time per joint (the smallest is 0; the robot constant holds the rest)",
        }
    if isinstance(effect, ResponseExtraCycle):
        return {
            "cycles": effect.cycles,
            "period_ms": model.period_s * 1e3,
            "unit": "whole controller periods between sampling and sending",
        }
    return effect.to_dict()


def _observed(
    name: str,
    model: SimModel,
    after: FittedModel,
    variables: dict[str, Variable],
) -> tuple[dict[str, Any], str]:
    """What the added effect does to the delays, in observable units, and a sentence."""
    cond = model.cond
    joints = cond.joints
    eff = after.effects.get(name)
    if isinstance(eff, JointOffset):
        offsets = eff.offsets_s
        ref = min(joints, key=lambda j: offsets[j - 1])
        parts = [f"joint {j} {offsets[j - 1] * 1e3:+.2f} ms" for j in joints if j != ref]
        return {"offset_ms": {f"joint {j}": offsets[j - 1] * 1e3 for j in joints}}, (
            f"actuation delay per joint, relative to joint {ref}: " + ", ".join(parts)
        )
    if isinstance(eff, ResponseExtraCycle):
        extra = eff.cycles * model.period_s * 1e3
        mean = float(np.mean(cond.mean_s["response_delay"]) * 1e3)
        return {"extra_ms": extra, "measured_mean_response_ms": mean}, (
            f"the measured response delay (mean {mean:.2f} ms) exceeds what sampling and "
            f"sending within one {model.period_s * 1e3:.1f} ms cycle can give; the state "
            f"leaves {eff.cycles} more period{'s' if eff.cycles > 1 else ''} later "
            f"(+{extra:.1f} ms)"
        )
    without = after.effects.without(name)
    contrib = (after.sim["actuation_delay"] - model.simulate(without)["actuation_delay"]) * 1e3
    if isinstance(eff, Direction):
        per: dict[str, float] = {}
        ranked: list[tuple[float, str]] = []
        for j in joints:
            mk = cond.joint == j
            pos = contrib[mk & (cond.direction == 1)]
            neg = contrib[mk & (cond.direction == -1)]
            if len(pos) and len(neg):
                diff = float(pos.mean() - neg.mean())
                per[f"joint {j}"] = diff
                side = "positive" if diff > 0 else "negative"
                ranked.append(
                    (abs(diff), f"joint {j} moves {abs(diff):.2f} ms later in the {side} direction")
                )
        ranked.sort(reverse=True)
        return {"positive_minus_negative_ms": per}, "; ".join(text for _, text in ranked)
    if isinstance(eff, ThermalDrift):
        t = cond.t_start_s
        early, late = t <= np.quantile(t, 0.1), t >= np.quantile(t, 0.9)
        first, last = float(contrib[early].mean()), float(contrib[late].mean())
        minutes = eff.time_constant_s / 60
        return {"first_tenth_ms": first, "last_tenth_ms": last, "time_constant_min": minutes}, (
            f"actuation delay is {first:.2f} ms longer in the first tenth of the sweep and "
            f"{last:.2f} ms longer in the last (friction relaxes with a time constant of "
            f"{minutes:.0f} min)"
        )
    var = variables[EFFECT_VARIABLE[name]]
    slopes: dict[str, float] = {}
    rows: list[tuple[float, str]] = []
    for j in joints:
        mk = cond.joint == j
        if np.sqrt(np.mean(contrib[mk] ** 2)) < 0.02:
            continue  # the effect does (next to) nothing on this joint
        x, y = var.values[mk], contrib[mk]
        slope, intercept = np.polyfit(x, y, 1) if np.ptp(x) > 0 else (0.0, float(y.mean()))
        slopes[f"joint {j}"] = float(slope)
        lo, hi = float(x.min()), float(x.max())
        text = (
            f"joint {j} by {slope:+.3f} ms per {var.unit} ({intercept + slope * lo:+.2f} ms at "
            f"{lo:.3g} to {intercept + slope * hi:+.2f} ms at {hi:.3g} {var.unit})"
        )
        rows.append((float(np.ptp(y)), text))
    rows.sort(reverse=True)
    verb = "grows" if name in ("gravity_load", "inertia") else "changes"
    head = f"actuation delay {verb} with the {var.label}"
    texts = [t for _, t in rows]
    return {f"slope_ms_per_{var.unit}": slopes}, head + (": " + "; ".join(texts) if texts else "")


def _simulated_scatter(model: SimModel, effects: EffectSet, seed: int) -> dict[str, float]:
    """Per-trial variance of the delays from the simulator's own timing randomness at the
    measured conditions (the fallback noise floor)."""
    cond = model.cond
    m = len(cond)
    pick = np.unique(np.linspace(0, m - 1, min(m, 200)).round().astype(int))
    reps = 8
    rows = np.repeat(pick, reps)
    t = cond.t_start_s[rows] + np.tile(np.arange(reps, dtype=float), len(pick))
    physical = EffectSet(tuple(e for e in effects if e.name != "joint_offset"))
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


# ---------------------------------------------------------------------------- workflow
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
    if isinstance(measured, DelayTable):
        table = measured
    else:
        table = load_measured(measured, progress=progress)
    if isinstance(robot, RobotSpec):
        spec = robot if period_s is None else robot.with_period(period_s)
    else:
        name = robot
        if name is None:
            robots = table.robots
            if len(robots) != 1:
                raise ConfigError(
                    f"{table.source}: the table holds trials of {', '.join(robots)}; pick one with --robot"
                )
            name = robots[0]
        spec = get_robot(name, period_s=period_s)
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
    say(f"calibrating the start model ({', '.join(start_effects.names) or 'base timing'})")
    fitted = calibrate(model, start_effects)
    before = fitted
    sim0 = model.simulate(EffectSet())
    variables = condition_variables(cond, sim0["gravity_torque_nm"], model.true_inertia_kgm2)
    variables["joint"] = Variable(
        "joint", "actuated joint", "joint", "binary", cond.joint.astype(float)
    )
    loc_vars = {k: v for k, v in variables.items() if k != "joint"}
    lof_before = {d: _lack_of_fit(fitted, noise, d) for d in DELAY_COLUMNS}
    where_before = {d: locate(cond, fitted.resid_s[d], noise, d, loc_vars) for d in DELAY_COLUMNS}
    steps: list[DiscrepancyStep] = []
    rejected: list[dict[str, Any]] = []
    excluded: list[str] = []
    limit = max_steps if max_steps is not None else 7
    final_scores: list[CandidateScore] = []
    while len(steps) < limit:
        scores = score_candidates(
            model,
            fitted,
            noise,
            alpha=alpha,
            min_share=min_share,
            seed=seed,
            exclude=tuple(excluded),
        )
        final_scores = scores
        significant = [s for s in scores if s.significant]
        lof = _lack_of_fit(fitted, noise, "actuation_delay")
        if not significant and lof["p_value"] < alpha and lof["excess_ms"] >= min_excess_ms:
            say(
                "the actuation delay does not fit but no signature is significant: "
                "recalibrating the model with each simulated candidate"
            )
            scores = refit_candidates(
                model,
                fitted,
                noise,
                scores,
                alpha=alpha,
                min_share=min_share,
                seed=seed,
                exclude=tuple(excluded),
            ) + [s for s in scores if s.acts_on != "actuation_delay" or s.name == "joint_offset"]
            final_scores = scores
            significant = [s for s in scores if s.significant]
        if not significant:
            say("no candidate effect is significant")
            break
        # The candidate was picked with the multiplicity correction; its confirmation tests
        # one pre-selected hypothesis at the plain level.
        threshold = alpha
        added = False
        for cand in significant:
            say(
                f"candidate {cand.name}: explains {100 * cand.excess_share:.0f} % of the excess "
                f"(cross-validated), p = {cand.p_value:.2g}"
                + ("" if cand.refit is not None else "; recalibrating")
            )
            if cand.refit is not None:
                new = cand.refit
            else:
                new = calibrate(model, fitted.effects.with_effect(initial_effect(cand, model)))
            check = compare_models(
                fitted, new, noise, cand.acts_on, n_new_params(cand.name, model), threshold
            )
            if not check["confirmed"]:
                say(f"{cand.name} rejected: the recalibrated model is not significantly closer")
                rejected.append({**cand.to_dict(), "confirmation": check})
                excluded.append(cand.name)
                continue
            delay = cand.acts_on
            g0, g1 = fitted.gap_s(delay), new.gap_s(delay)
            floor = noise.floor_s[delay]
            excess0 = max(g0**2 - floor**2, 1e-30)
            share = float(np.clip((g0**2 - g1**2) / excess0, 0.0, 1.0))
            eff = new.effects.get(cand.name)
            assert eff is not None
            observed, sentence = _observed(cand.name, model, new, variables)
            explanation = (
                f"{sentence}; explains {100 * share:.0f} % of the {delay.replace('_', ' ')} gap "
                f"above the noise floor ({g0 * 1e3:.2f} -> {g1 * 1e3:.2f} ms, noise floor "
                f"{floor * 1e3:.2f} ms)"
            )
            ranking = [
                {
                    "effect": s.name,
                    "cv_share_of_excess_explained": s.excess_share,
                    "p_value": s.p_value,
                    "significant": s.significant,
                }
                for s in scores
            ]
            steps.append(
                DiscrepancyStep(
                    effect=cand.name,
                    acts_on=delay,
                    explanation=explanation,
                    evidence={**cand.to_dict(), "confirmation": check, "ranking": ranking},
                    parameters=_describe_parameters(eff, model),
                    observed=observed,
                    gap_before_ms=_gaps_ms(fitted),
                    gap_after_ms=_gaps_ms(new),
                    share_of_excess_explained=share,
                    resid_before_s=fitted.resid_s[delay].copy(),
                    resid_after_s=new.resid_s[delay].copy(),
                )
            )
            say(f"added {cand.name}: {explanation}")
            fitted = new
            added = True
            break
        if not added:
            break
    lof_after = {d: _lack_of_fit(fitted, noise, d) for d in DELAY_COLUMNS}
    where_after = {d: locate(cond, fitted.resid_s[d], noise, d, loc_vars) for d in DELAY_COLUMNS}
    unexplained: list[dict[str, Any]] = []
    for d in DELAY_COLUMNS:
        lof = lof_after[d]
        if lof["p_value"] >= alpha or lof["excess_ms"] < min_excess_ms:
            continue
        entries = unexplained_entries(cond, fitted.resid_s[d], noise, d, loc_vars, alpha=alpha)
        if not entries:
            everything = np.ones(len(cond), dtype=bool)
            fits = [
                f
                for f in (variable_fit(fitted.resid_s[d], v, everything) for v in loc_vars.values())
                if f
            ]
            best = max(fits, key=lambda f: f["share"]) if fits else None
            text = (
                f"{d.replace('_', ' ')} disagrees with the simulation by {lof['excess_ms']:.2f} ms "
                "RMS beyond the noise, spread over all joints and directions (no single one "
                "stands out)"
            )
            if best and best["p_value"] < alpha:
                text += f"; it follows the {best['label']} ({best['unit']}) best ({100 * best['share']:.0f} %)"
            text += ". No effect of the vocabulary explains it."
            entries = [
                {
                    "delay": d,
                    "joints": list(cond.joints),
                    "direction": "both",
                    "variable": best["variable"] if best and best["p_value"] < alpha else None,
                    "variable_label": f"{best['label']} ({best['unit']})"
                    if best and best["p_value"] < alpha
                    else None,
                    "share_explained_by_variable": best["share"]
                    if best and best["p_value"] < alpha
                    else None,
                    "conditions": len(cond),
                    "excess_rms_ms": lof["excess_ms"],
                    "rms_ms": lof["gap_ms"],
                    "noise_ms": lof["noise_floor_ms"],
                    "p_value": lof["p_value"],
                    "description": text,
                }
            ]
        unexplained.extend(entries)
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
        added_effects=[s.effect for s in steps],
        gap_before_ms=_gaps_ms(before),
        gap_after_ms=_gaps_ms(fitted),
        noise=noise,
        steps=steps,
        unexplained=unexplained,
        lack_of_fit_before=lof_before,
        lack_of_fit_after=lof_after,
        locations_before=where_before,
        locations_after=where_after,
        rejected=rejected,
        calibration_before=before.parameters(),
        calibration_after=fitted.parameters(),
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
        variables=variables,
        before=before,
        after=fitted,
        period_s=spec.controller_period_s,
        final_candidates=[s.to_dict() for s in final_scores],
    )
