"""The discrepancy workflow's result: the steps (one per effect added) and the result
object whose ``to_dict()`` is the OUT.json document."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._files import write_atomic
from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._conditions import Conditions, NoiseFloor
from timedexec.discrepancy._model import FittedModel
from timedexec.discrepancy._report import write_report
from timedexec.effects import Variable, effect_type

__all__ = ["DiscoveredTerm", "DiscrepancyResult", "DiscrepancyStep"]


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
    #: RMS of what the effect adds to its delay over the conditions, about its mean, ms.
    size_ms: float | None = None
    #: The structural term that named it (``load``, ``direction_x_load``, ...) in words.
    family: str | None = None
    #: Gap after adding the effect in the simulator's own form only (without the measured
    #: shape), ms per delay; equal to ``gap_after_ms`` when no shape was needed.
    gap_after_simulator_form_ms: dict[str, float] | None = None
    #: The measured shape beyond the simulator's form: families, columns, RMS (ms), test.
    shape: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        e = effect_type(self.effect)
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
            "size_ms": self.size_ms,
            "family": self.family,
            "gap_after_simulator_form_ms": self.gap_after_simulator_form_ms,
            "shape": self.shape,
        }


@dataclass(eq=False)
class DiscoveredTerm:
    """A term outside the vocabulary that discovery added to the model (a data-driven
    effect registered at run time, :class:`timedexec.effects.DataTerm`).

    Attributes
    ----------
    effect : DataTerm
        The registered effect with its fitted coefficients (simulate it with
        ``EffectSet((*effects, term.effect))``).
    description : str
        The term in words, with its uncertainty and the gap it closes.
    parameters : dict
        Its coefficients and shape parameters in physical units, each with a standard
        error.
    gap_closed_ms : float
        How much of the actuation gap the term closes with the rest of the final model
        in place (gap without it, the other linear parts refitted, minus the final gap), ms.
    gap_before_ms, gap_after_ms : dict delay -> ms
        The gaps of the model before and after the discovery step that added it.
    gap_after_resimulated_ms : dict delay -> ms
        The gaps after that step with every effect, the discovered ones included, run
        through the batch simulator (not the closed form): the re-run.
    share_of_excess_explained : float
        Share of the excess actuation gap (above the floor) the step removed.
    evidence : dict
        The selection's evidence (F test against the library's Bonferroni threshold,
        held-out errors, runners-up) and the confirmation test of the step.
    resid_before_s, resid_after_s : ndarray (m,)
        Actuation residuals, s, of the model after the step that added the term, without
        the term's contribution (the partial residual: what the term explains, on top of
        what it leaves) and with it (for the figure).
    input_values : dict name -> ndarray (m,)
        Its inputs at the conditions (for the figure).
    mask : ndarray of bool (m,)
        The conditions it acts on (its joints and direction).
    """

    effect: Any
    description: str
    parameters: dict[str, Any]
    gap_closed_ms: float
    gap_before_ms: dict[str, float]
    gap_after_ms: dict[str, float]
    gap_after_resimulated_ms: dict[str, float]
    share_of_excess_explained: float
    evidence: dict[str, Any]
    resid_before_s: FloatArray
    resid_after_s: FloatArray
    input_values: dict[str, FloatArray]
    mask: NDArray[np.bool_]

    @property
    def joints(self) -> list[int]:
        """The joints it acts on."""
        return list(self.effect.joints)

    @property
    def inputs(self) -> list[str]:
        """What it depends on (``qK`` rad, ``tauK`` N·m)."""
        return list(self.effect.inputs)

    @property
    def formula(self) -> str:
        """The term as a formula in ms."""
        return str(self.effect.formula())

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (an entry of ``"discovered"``)."""
        e = self.effect
        return {
            "effect": e.name,
            "joints": self.joints,
            "inputs": self.inputs,
            "form": e.form,
            "direction": {0: "both", 1: "positive", -1: "negative"}[e.direction],
            "formula": self.formula,
            "description": self.description,
            "parameters": self.parameters,
            "size_per_joint": self.parameters.get("size_per_joint", {}),
            "gap_closed_ms": self.gap_closed_ms,
            "gap_before_ms": self.gap_before_ms,
            "gap_after_ms": self.gap_after_ms,
            "gap_after_resimulated_ms": self.gap_after_resimulated_ms,
            "share_of_excess_gap_explained": self.share_of_excess_explained,
            "evidence": self.evidence,
            "definition": e.to_dict(),
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
    #: The last structural search per delay: the families accepted (with their evidence)
    #: and the ranking of every family at its first step.
    final_structure: dict[str, Any] = field(default_factory=dict)
    #: Shapes added to effects the model already had (the simulator's form of them does
    #: not reproduce the measured dependence): effect, family, gaps before/after, evidence.
    refined_effects: list[dict[str, Any]] = field(default_factory=list)
    #: Terms outside the vocabulary that discovery added (each a registered data term).
    discovered: list[DiscoveredTerm] = field(default_factory=list)

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
            "final_structure": self.final_structure,
            "refined_effects": self.refined_effects,
            "discovered": [t.to_dict() for t in self.discovered],
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
        for t in self.discovered:
            lines.append(f"  discovered (outside the vocabulary): {t.description}")
            lines.append(f"    {t.formula}")
        for u in self.unexplained:
            lines.append(f"  unexplained: {u['description']}")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)
