"""The discrepancy report: markdown plus PNG figures, for a robot engineer who does not
know the code."""

from __future__ import annotations

import io
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from timedexec._files import check_paths, make_dir, write_atomic
from timedexec._plot import subplots
from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS
from timedexec.effects import Variable, effect_type

__all__ = ["ReportSource", "write_report"]

_WORDS = {"actuation_delay": "actuation delay", "response_delay": "response delay"}


class _Step(Protocol):
    """What the report reads of one added effect (``DiscrepancyStep``)."""

    @property
    def effect(self) -> str: ...
    @property
    def acts_on(self) -> str: ...
    @property
    def explanation(self) -> str: ...
    @property
    def evidence(self) -> dict[str, Any]: ...
    @property
    def parameters(self) -> dict[str, Any]: ...
    @property
    def gap_after_ms(self) -> dict[str, float]: ...
    @property
    def resid_before_s(self) -> FloatArray: ...
    @property
    def resid_after_s(self) -> FloatArray: ...


class _Discovered(Protocol):
    """What the report reads of one discovered term (``DiscoveredTerm``)."""

    @property
    def description(self) -> str: ...
    @property
    def formula(self) -> str: ...
    @property
    def joints(self) -> list[int]: ...
    @property
    def inputs(self) -> list[str]: ...
    @property
    def gap_closed_ms(self) -> float: ...
    @property
    def evidence(self) -> dict[str, Any]: ...
    @property
    def resid_before_s(self) -> FloatArray: ...
    @property
    def resid_after_s(self) -> FloatArray: ...
    @property
    def input_values(self) -> dict[str, FloatArray]: ...
    @property
    def mask(self) -> NDArray[np.bool_]: ...


class _Conditions(Protocol):
    @property
    def joint(self) -> NDArray[np.int64]: ...
    @property
    def direction(self) -> NDArray[np.int64]: ...


class _Fitted(Protocol):
    @property
    def resid_s(self) -> dict[str, FloatArray]: ...


class _Noise(Protocol):
    def to_dict(self) -> dict[str, Any]: ...


class ReportSource(Protocol):
    """What the report reads of a result (``ReportSource``): the report is a leaf that
    imports nothing of the workflow."""

    @property
    def robot(self) -> str: ...
    @property
    def source(self) -> str: ...
    @property
    def start(self) -> str: ...
    @property
    def start_effects(self) -> list[str]: ...
    @property
    def n_trials(self) -> int: ...
    @property
    def n_conditions(self) -> int: ...
    @property
    def gap_before_ms(self) -> dict[str, float]: ...
    @property
    def gap_after_ms(self) -> dict[str, float]: ...
    @property
    def noise_floor_ms(self) -> dict[str, float]: ...
    @property
    def noise(self) -> _Noise: ...
    @property
    def steps(self) -> Sequence[_Step]: ...
    @property
    def unexplained(self) -> list[dict[str, Any]]: ...
    @property
    def lack_of_fit_before(self) -> dict[str, Any]: ...
    @property
    def lack_of_fit_after(self) -> dict[str, Any]: ...
    @property
    def locations_before(self) -> dict[str, Any]: ...
    @property
    def locations_after(self) -> dict[str, Any]: ...
    @property
    def rejected(self) -> list[dict[str, Any]]: ...
    @property
    def calibration_before(self) -> dict[str, Any]: ...
    @property
    def calibration_after(self) -> dict[str, Any]: ...
    @property
    def warnings(self) -> list[str]: ...
    @property
    def runtime_s(self) -> float: ...
    @property
    def simulations(self) -> dict[str, Any]: ...
    @property
    def settings(self) -> dict[str, Any]: ...
    @property
    def cond(self) -> _Conditions: ...
    @property
    def variables(self) -> Mapping[str, Variable]: ...
    @property
    def after(self) -> _Fitted: ...
    @property
    def refined_effects(self) -> list[dict[str, Any]]: ...
    @property
    def discovered(self) -> Sequence[_Discovered]: ...


def _save(fig: Any, path: Path) -> None:
    """Render to PNG in memory, then write atomically (the output-path policy of
    :mod:`timedexec._files`: never over a symlink, a device or a folder)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    write_atomic(path, buf.getvalue())


def _jitter(x: NDArray[np.float64], kind: str, seed: int = 0) -> NDArray[np.float64]:
    if kind != "binary":
        return x
    rng = np.random.default_rng(seed)
    out: NDArray[np.float64] = x + rng.uniform(-0.15, 0.15, len(x))
    return out


def _residual_panel(
    ax: Any,
    var: Variable,
    resid_ms: NDArray[np.float64],
    joints: NDArray[np.int64],
    floor_ms: float,
    title: str,
    mask: NDArray[np.bool_] | None = None,
) -> None:
    sel = np.ones(len(resid_ms), dtype=bool) if mask is None else mask
    x = _jitter(var.values, var.kind)
    for j in np.unique(joints[sel]):
        m = sel & (joints == j)
        ax.scatter(x[m], resid_ms[m], s=8, alpha=0.6, label=f"joint {j}")
    ax.axhline(0.0, color="k", lw=0.8)
    ax.axhspan(-floor_ms, floor_ms, color="0.85", zorder=0, label="± noise floor")
    if var.kind != "binary" and sel.sum() > 20:
        xs = var.values[sel]
        edges = np.quantile(xs, np.linspace(0, 1, 11))
        idx = np.clip(np.searchsorted(edges, xs, side="right") - 1, 0, 9)
        centres = [xs[idx == k].mean() for k in range(10) if np.any(idx == k)]
        means = [resid_ms[sel][idx == k].mean() for k in range(10) if np.any(idx == k)]
        ax.plot(centres, means, color="k", lw=2, label="binned mean")
    ax.set_xlabel(f"{var.label} ({var.unit})")
    ax.set_ylabel("measured - simulated mean (ms)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)


def _gap_figure(result: ReportSource, path: Path) -> None:
    labels = ["start"] + [f"+ {s.effect}" for s in result.steps]
    if result.discovered:
        labels.append(f"+ {len(result.discovered)} discovered")
    fig, axes = subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    floor = result.noise_floor_ms
    for ax, d in zip(axes, DELAY_COLUMNS, strict=True):
        values = [result.gap_before_ms[d]] + [s.gap_after_ms[d] for s in result.steps]
        if result.discovered:
            values.append(result.gap_after_ms[d])
        ax.bar(range(len(values)), values, color="tab:blue")
        ax.axhline(floor[d], color="k", ls="--", label=f"noise floor {floor[d]:.2f} ms")
        ax.axhline(1.25 * floor[d], color="tab:red", ls=":", label="noise floor + 25 %")
        ax.set_xticks(range(len(values)), labels, rotation=20, ha="right")
        ax.set_ylabel("gap: RMS of measured - simulated mean (ms)")
        ax.set_title(_WORDS[d])
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    _save(fig, path)


def _where_figure(result: ReportSource, path: Path) -> None:
    fig, axes = subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    for ax, d in zip(axes, DELAY_COLUMNS, strict=True):
        before = result.locations_before[d]["by_joint_direction"]
        after = result.locations_after[d]["by_joint_direction"]
        names = [f"J{g['joint']} {'+' if g['direction'] > 0 else '-'}" for g in before]
        x = np.arange(len(names))
        ax.bar(x - 0.2, [g["rms_ms"] for g in before], 0.4, label="start model")
        ax.bar(x + 0.2, [g["rms_ms"] for g in after], 0.4, label="final model")
        ax.plot(x, [g["noise_ms"] for g in before], "k_", ms=18, mew=2, label="noise floor")
        ax.set_xticks(x, names)
        ax.set_ylabel("RMS of measured - simulated mean (ms)")
        ax.set_title(f"{_WORDS[d]} per joint and direction")
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    _save(fig, path)


def _step_figure(result: ReportSource, k: int, path: Path) -> None:

    step = result.steps[k]
    var = result.variables[effect_type(step.effect).variable_key]
    floor = result.noise_floor_ms[step.acts_on]
    fig, axes = subplots(1, 2, figsize=(11, 4), sharey=True, constrained_layout=True)
    joints = result.cond.joint
    _residual_panel(
        axes[0], var, step.resid_before_s * 1e3, joints, floor, f"before adding {step.effect}"
    )
    _residual_panel(
        axes[1], var, step.resid_after_s * 1e3, joints, floor, f"after adding {step.effect}"
    )
    axes[1].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{_WORDS[step.acts_on]}: residuals against {var.label}", fontsize=11)
    _save(fig, path)


def _discovered_figure(result: ReportSource, k: int, path: Path) -> None:
    """Residuals of the actuation delay on the term's joints and direction against each of
    its inputs: without the term (the final model's residual plus the term) and with it."""
    term = result.discovered[k]
    floor = result.noise_floor_ms["actuation_delay"]
    rows = len(term.inputs)
    fig, axes = subplots(
        rows, 2, figsize=(11, 4 * rows), sharey=True, squeeze=False, constrained_layout=True
    )
    for r, name in enumerate(term.inputs):
        unit = "rad" if name.startswith("q") else "N·m"
        label = (
            f"{name} (joint {name[1:]} angle)"
            if name.startswith("q")
            else (f"{name} (gravity torque of joint {name[3:]})")
        )
        var = Variable(name, label, unit, "angle", term.input_values[name])
        for c, (resid, when) in enumerate(
            ((term.resid_before_s, "without"), (term.resid_after_s, "with"))
        ):
            _residual_panel(
                axes[r][c],
                var,
                resid * 1e3,
                result.cond.joint,
                floor,
                f"{when} the discovered term",
                term.mask,
            )
    axes[0][1].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"actuation delay: {term.formula}", fontsize=9)
    _save(fig, path)


def _unexplained_figure(result: ReportSource, entry: dict[str, Any], path: Path) -> None:
    d = entry["delay"]
    cond = result.cond
    mask = np.isin(cond.joint, entry["joints"])
    if entry["direction"] != "both":
        mask &= cond.direction == int(entry["direction"])
    key = entry["variable"] or "time"
    var = result.variables[key]
    fig, ax = subplots(figsize=(7, 4), constrained_layout=True)
    _residual_panel(
        ax,
        var,
        result.after.resid_s[d] * 1e3,
        cond.joint,
        result.noise_floor_ms[d],
        f"unexplained {_WORDS[d]}",
        mask,
    )
    ax.legend(fontsize=7)
    _save(fig, path)


def _fmt_p(p: float) -> str:
    return f"{p:.1e}" if p < 1e-3 else f"{p:.3f}"


def _lines_intro(result: ReportSource) -> list[str]:
    fl = result.noise_floor_ms
    out = [
        f"# Where the simulated {result.robot} disagrees with the measurement",
        "",
        f"Measured data: `{result.source}` — {result.n_trials:,} trials in "
        f"{result.n_conditions:,} conditions (a condition is one start configuration, one "
        "moving joint and one direction; its repeats are averaged).",
        f"Start model: **{result.start}** "
        f"({', '.join(result.start_effects) or 'the base timing of the controller only'}).",
        "",
        "## In short",
        "",
    ]
    if result.steps:
        out.append(
            f"The simulation was missing {len(result.steps)} effect"
            f"{'s' if len(result.steps) > 1 else ''}, found in this order:"
        )
        out.append("")
        for k, s in enumerate(result.steps, 1):
            out.append(f"{k}. **{s.effect}** ({effect_type(s.effect).meaning}): {s.explanation}.")
        out.append("")
    else:
        out.append(
            "No effect of the vocabulary is missing: no candidate explains a significant part "
            "of the disagreement."
        )
        out.append("")
    for d in DELAY_COLUMNS:
        out.append(
            f"- {_WORDS[d].capitalize()}: gap {result.gap_before_ms[d]:.2f} ms before, "
            f"{result.gap_after_ms[d]:.2f} ms after; the noise floor is {fl[d]:.2f} ms "
            f"({result.gap_after_ms[d] / fl[d]:.2f} x the floor)."
        )
    out.append("")
    if result.discovered:
        out.append(
            f"Outside the vocabulary, {len(result.discovered)} term"
            f"{'s were' if len(result.discovered) > 1 else ' was'} discovered and added to "
            "the simulator (see *Discovered*):"
        )
        out.append("")
        out += [f"- {t.description}." for t in result.discovered]
        out.append("")
    if result.unexplained:
        out.append(
            "Something remains that no effect of the vocabulary explains (see *Unexplained* "
            "below); it is reported where it sits, not forced onto a name."
        )
    else:
        out.append("Nothing significant remains unexplained.")
    out.append("")
    return out


def _lines_terms() -> list[str]:
    return [
        "## What the numbers mean",
        "",
        "- **Actuation delay**: from the command leaving the PC to the joint physically "
        "moving (10 % of the commanded speed, measured by the gyro).",
        "- **Response delay**: how old the state the controller publishes is when it "
        "arrives (the motion shows up this much later in the reported joint positions).",
        "- **Gap**: the root mean square, over all conditions, of the measured mean delay "
        "minus the simulated mean delay (ms).",
        "- **Noise floor**: the gap that the scatter of the repeats alone would give, "
        "sqrt(mean over conditions of s²/n) with s the standard deviation of a condition's "
        "repeats and n their number. A perfect simulation has a gap at the noise floor.",
        "- **Lack-of-fit test**: whether the gap is larger than the noise floor by more than "
        "chance (F test of the condition-mean residuals against the repeat scatter); a "
        "small p-value means something is missing.",
        "- **Share of the gap explained**: how much of the gap *above the noise floor* "
        "(gap² - floor²) an added effect removed.",
        "",
    ]


def _lines_summary_table(result: ReportSource) -> list[str]:
    out = [
        "| delay | gap at start (ms) | gap at end (ms) | noise floor (ms) | lack of fit p, start | lack of fit p, end |",
        "|---|---|---|---|---|---|",
    ]
    for d in DELAY_COLUMNS:
        out.append(
            f"| {_WORDS[d]} | {result.gap_before_ms[d]:.3f} | {result.gap_after_ms[d]:.3f} | "
            f"{result.noise_floor_ms[d]:.3f} | {_fmt_p(result.lack_of_fit_before[d]['p_value'])} | "
            f"{_fmt_p(result.lack_of_fit_after[d]['p_value'])} |"
        )
    return [*out, "", "![gap per step](gap_per_step.png)", ""]


def _lines_steps(result: ReportSource, figures: list[str]) -> list[str]:
    out: list[str] = []
    for k, s in enumerate(result.steps):
        e = effect_type(s.effect)
        ev = s.evidence
        out += [
            f"## Step {k + 1}: {s.effect}",
            "",
            f"*{e.meaning}* (acts on the {_WORDS[s.acts_on]}; follows {e.variable}).",
            "",
            f"What it does: {s.explanation}.",
            "",
            _evidence_sentence(ev, result.settings["alpha"]),
            "",
        ]
        out += [
            "| candidate | share of excess explained (CV) | p-value | significant |",
            "|---|---|---|---|",
        ]
        for r in ev["ranking"]:
            name = (
                r["effect"]
                if r.get("family") in (None, r["effect"])
                else (f"{r['effect'] or 'no effect'} ({r['family']})")
            )
            share = r["cv_share_of_excess_explained"]
            out.append(
                f"| {name} | {'-' if share is None else f'{100 * share:.0f} %'} | "
                f"{_fmt_p(r['p_value'])} | {'yes' if r['significant'] else 'no'} |"
            )
        out += ["", f"Fitted parameters: `{_compact(s.parameters)}`", ""]
        out += [f"![step {k + 1}]({figures[k]})", ""]
    return out


def _method_words(method: str) -> str:
    if method == "refit":
        return "the whole model recalibrated with the effect added"
    if method == "structure":
        return "the structural search over main effects and interactions"
    return "the effect's signature fitted to the residuals"


def _evidence_sentence(ev: dict[str, Any], alpha: float) -> str:
    """One paragraph: how the effect was chosen and how strongly."""
    if ev["method"] == "structure":
        cv = "leave one condition out"
        found = (
            f"it was found as the family *{ev['family_label']}*"
            + (f", preferred to its parts ({', '.join(ev['scored_with'])})" if ev["scored_with"]
               else "")
            + f"; held-out z = {ev['held_out_z']:.1f}. "
        )  # fmt: skip
    else:
        cv = "5 folds of conditions"
        found = ""
    text = (
        f"Evidence ({_method_words(ev['method'])}): {found}With the effect, the "
        f"cross-validated error of the condition means ({cv}) falls from "
        f"{ev['cv_mse_without_ms2']:.3f} to {ev['cv_mse_with_ms2']:.3f} ms², "
        f"{100 * ev['cv_share_of_excess_explained']:.0f} % of its excess over the noise; "
        f"F = {ev['f_statistic']:.1f}, p = {_fmt_p(ev['p_value'])} (significant below "
        f"{alpha} / number of candidates)."
    )
    confirmation = ev.get("confirmation")
    if confirmation is not None:
        text += (
            " After recalibration the gap fell significantly (p = "
            f"{_fmt_p(confirmation['p_value'])})."
        )
    return text


def _lines_refined(result: ReportSource) -> list[str]:
    """Effects the model had whose simulated form missed the measured dependence."""
    if not result.refined_effects:
        return []
    out = [
        "## Effects refined",
        "",
        "Effects the start model already had, whose simulated form did not reproduce the "
        "measured dependence; a shape was added to them:",
        "",
        "| effect | shape added | gap before (ms) | gap after (ms) |",
        "|---|---|---|---|",
    ]
    for r in result.refined_effects:
        before, after = r["gap_before_ms"], r["gap_after_ms"]
        out.append(
            f"| {r['effect']} | {r['family_label']} | "
            + ", ".join(f"{before[d]:.3f}" for d in DELAY_COLUMNS)
            + " | "
            + ", ".join(f"{after[d]:.3f}" for d in DELAY_COLUMNS)
            + " |"
        )
    return [*out, "", "(gaps: actuation, response)", ""]


def _compact(d: dict[str, Any]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k}: {fmt(x)}" for k, x in v.items()) + "}"
        return str(v)

    return ", ".join(f"{k} = {fmt(v)}" for k, v in d.items())


def _lines_discovered(result: ReportSource, figures: list[str]) -> list[str]:
    """Terms outside the vocabulary: in words, as a formula, the evidence and a figure."""
    if not result.discovered:
        return []
    out = [
        "## Discovered outside the vocabulary",
        "",
        "No effect of the vocabulary explains these dependences (a vocabulary name was "
        "given only where no data-driven term explains the residuals better). Each was "
        "chosen from a library of physically motivated forms (slopes, hinges of a cable "
        "that tightens, periodic drive terms, local bumps of a contact, in one or two "
        "angles or another joint's gravity torque, on one direction or both) by "
        "leave-one-configuration-out cross-validation and a Bonferroni F test over the "
        "library, the simplest of the equally good kept, then added to the simulator as an "
        "effect of its own and the model re-run.",
        "",
    ]
    for k, (t, fig) in enumerate(zip(result.discovered, figures, strict=True)):
        ev = t.evidence
        parts = ev.get("parts", [ev])
        first = parts[0]
        out += [
            f"### Discovered term {k + 1}: joint{'s' if len(t.joints) > 1 else ''} "
            f"{', '.join(map(str, t.joints))}, {', '.join(t.inputs)}",
            "",
            f"{t.description}.",
            "",
            f"Formula: `{t.formula}`",
            "",
            f"It closes {t.gap_closed_ms:.2f} ms of the actuation gap. Evidence: F = "
            f"{first['f_statistic']:.1f}, p = {_fmt_p(first['p_value'])} (significant below "
            f"{_fmt_p(first['library_size_threshold_p'])}, alpha over the library); held out "
            f"(leave one configuration out) the error falls from "
            f"{first['cv_mse_without_ms2']:.3f} to {first['cv_mse_with_ms2']:.3f} ms² "
            f"(z = {first['held_out_z']:.1f})"
            + (f"; one shape serves {len(parts)} joints" if len(parts) > 1 else "")
            + ".",
            "",
            f"![discovered term {k + 1}]({fig})",
            "",
        ]
    return out


def _lines_unexplained(result: ReportSource, figures: list[str]) -> list[str]:
    out = ["## Unexplained", ""]
    if not result.unexplained:
        lof = result.lack_of_fit_after
        out.append(
            "Nothing: the final model's gap is at the noise floor (lack-of-fit p = "
            + ", ".join(f"{_fmt_p(lof[d]['p_value'])} for the {_WORDS[d]}" for d in DELAY_COLUMNS)
            + ")."
        )
        return [*out, ""]
    for entry, fig in zip(result.unexplained, figures, strict=True):
        out += [f"- {entry['description']}", "", f"  ![unexplained]({fig})", ""]
    out.append(
        "These disagreements are real (beyond the repeat scatter) but no effect of the "
        "vocabulary reproduces them; look for a cause outside the simulator's physics "
        "(a mechanical or controller property of this robot, or the measurement set-up)."
    )
    return [*out, ""]


def _lines_where(result: ReportSource) -> list[str]:
    out = [
        "## Where the disagreement sat",
        "",
        "Per joint and direction: mean and RMS of measured minus simulated condition "
        "means, the noise floor of that group and the p-value of a chi-square test against "
        "the noise (small: the group disagrees beyond the scatter).",
        "",
        "![per joint and direction](where.png)",
        "",
    ]
    for label, where in (
        ("start model", result.locations_before),
        ("final model", result.locations_after),
    ):
        for d in DELAY_COLUMNS:
            out += [
                f"**{_WORDS[d].capitalize()}, {label}**",
                "",
                "| joint | direction | conditions | mean (ms) | RMS (ms) | noise (ms) | p |",
                "|---|---|---|---|---|---|---|",
            ]
            for g in where[d]["by_joint_direction"]:
                out.append(
                    f"| {g['joint']} | {'+' if g['direction'] > 0 else '-'} | {g['conditions']} | "
                    f"{g['mean_ms']:+.2f} | {g['rms_ms']:.2f} | {g['noise_ms']:.2f} | {_fmt_p(g['p_value'])} |"
                )
            out += ["", "| sweep time (s) | mean (ms) | RMS (ms) | p |", "|---|---|---|---|"]
            for t in where[d]["by_time"]:
                out.append(
                    f"| {t['from_s']:.0f} - {t['to_s']:.0f} | {t['mean_ms']:+.2f} | "
                    f"{t['rms_ms']:.2f} | {_fmt_p(t['p_value'])} |"
                )
            out.append("")
    return out


def _lines_model(result: ReportSource) -> list[str]:
    out = ["## The calibrated model", ""]
    for label, cal in (("start", result.calibration_before), ("final", result.calibration_after)):
        out.append(
            f"- {label}: robot constants actuation {cal['actuation_offset_ms']:+.2f} ms, "
            f"response {cal['response_offset_ms']:+.2f} ms (added to the simulator's base "
            "timing, whose pipeline and packing phase are not known for a real robot); "
            "effects: " + ("; ".join(_compact(e) for e in cal["effects"]) or "none")
        )
    out.append("")
    if result.rejected:
        out.append(
            "Candidates that looked significant but did not reduce the gap significantly "
            "once calibrated (not added): " + ", ".join(r["effect"] for r in result.rejected)
        )
        out.append("")
    return out


def _lines_method(result: ReportSource) -> list[str]:
    nf = result.noise.to_dict()
    out = ["## How this was computed", ""]
    out.append(
        "The simulator ran every measured condition (start configuration, joint, direction, "
        "time in the sweep) with the controller's timing randomness replaced by its mean. Its "
        "effect parameters were calibrated to the measured condition means by least squares "
        "with the simulator in the loop. Each effect of the vocabulary that the model lacked "
        "was then scored against the residuals: its signature (how switching it on changes "
        "every condition) was fitted to the residuals, cross-validated over 5 folds of "
        "conditions and F-tested against the repeat scatter (Bonferroni over the candidates). "
        "The best significant one was added, everything recalibrated, and the loop repeated "
        "until no candidate was significant."
    )
    out.append("")
    out.append(
        f"Noise floor source: {nf['source']} (pure-error degrees of freedom: "
        f"{nf['pure_error_df']}); trial-to-trial standard deviation "
        + ", ".join(f"{v:.2f} ms ({_WORDS[k]})" for k, v in nf["trial_sd_ms"].items())
        + "."
    )
    out.append("")
    if result.warnings:
        out += ["## Warnings", ""] + [f"- {w}" for w in result.warnings] + [""]
    out.append(
        f"Runtime {result.runtime_s:.1f} s, {result.simulations['runs']} simulator runs "
        f"({result.simulations['conditions_simulated']:,} simulated conditions)."
    )
    return [*out, ""]


def write_report(result: ReportSource, directory: str | os.PathLike[str]) -> Path:
    """Write ``report.md`` and its PNG figures into ``directory`` (created if missing).

    Returns the path of the markdown file.
    """
    folder = Path(directory)
    step_figs = [f"step{k + 1}_{s.effect}.png" for k, s in enumerate(result.steps)]
    un_figs = [f"unexplained{k + 1}.png" for k in range(len(result.unexplained))]
    disc_figs = [f"discovered{k + 1}.png" for k in range(len(result.discovered))]
    names = ["gap_per_step.png", "where.png", *step_figs, *disc_figs, *un_figs, "report.md"]
    check_paths(
        inputs={"measured data": result.source} if os.path.exists(result.source) else {},
        outputs={f"report file {n}": folder / n for n in names},
        folders={"report folder": folder},
    )
    out = make_dir(folder, "report folder")
    _gap_figure(result, out / "gap_per_step.png")
    _where_figure(result, out / "where.png")
    for k, name in enumerate(step_figs):
        _step_figure(result, k, out / name)
    for k, name in enumerate(disc_figs):
        _discovered_figure(result, k, out / name)
    for entry, name in zip(result.unexplained, un_figs, strict=True):
        _unexplained_figure(result, entry, out / name)
    lines = (
        _lines_intro(result)
        + _lines_terms()
        + _lines_summary_table(result)
        + _lines_steps(result, step_figs)
        + _lines_refined(result)
        + _lines_discovered(result, disc_figs)
        + _lines_unexplained(result, un_figs)
        + _lines_where(result)
        + _lines_model(result)
        + _lines_method(result)
    )
    return write_atomic(out / "report.md", "\n".join(lines))
