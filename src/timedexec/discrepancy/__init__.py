"""timedexec.discrepancy: where the simulation and the measured delays disagree, which
effect of the vocabulary is missing, and how much of the gap adding it closes.

>>> from timedexec.discrepancy import analyse_discrepancy      # doctest: +SKIP
>>> result = analyse_discrepancy("ur10-delays.csv", start="base")   # doctest: +SKIP
>>> result.added_effects, result.gap_after_ms, result.noise_floor_ms  # doctest: +SKIP

The search over structure (:func:`forward_select` over :class:`TermFamily` sets from
:func:`actuation_families` / :func:`response_families`) names effects by the shape of the
disagreement — main effects and interactions (direction x load, direction x joint, time x
joint) under a hierarchy rule and a parsimony test, stopped by a held-out criterion.

Beyond the vocabulary (issue 36, ``discover=True``): a name is given only where no
data-driven term of the library (slopes, hinges, harmonics, products and bumps in the joint
angles or another joint's gravity torque, per joint or shared) explains the residuals
better; what the vocabulary leaves is selected from that library (Bonferroni F test,
leave-one-configuration-out cross-validation, the simplest of the equally good), added to
the simulator as an effect registered at run time and reported under ``discovered``
(:attr:`DiscrepancyResult.discovered`, :class:`DiscoveredTerm`).

See docs/discrepancy.md.
"""

from __future__ import annotations

from timedexec.discrepancy._candidates import CandidateScore, score_candidates
from timedexec.discrepancy._conditions import (
    Conditions,
    NoiseFloor,
    group_conditions,
    replicate_noise,
)
from timedexec.discrepancy._model import (
    FittedModel,
    SimModel,
    calibrate,
    deterministic_settings,
)
from timedexec.discrepancy._report import write_report
from timedexec.discrepancy._result import DiscoveredTerm
from timedexec.discrepancy._select import Selection, UnitScore, forward_select
from timedexec.discrepancy._terms import TermFamily, actuation_families, response_families
from timedexec.discrepancy._workflow import (
    DiscrepancyResult,
    DiscrepancyStep,
    analyse_discrepancy,
    load_measured,
)

__all__ = [
    "CandidateScore",
    "Conditions",
    "DiscoveredTerm",
    "DiscrepancyResult",
    "DiscrepancyStep",
    "FittedModel",
    "NoiseFloor",
    "Selection",
    "SimModel",
    "TermFamily",
    "UnitScore",
    "actuation_families",
    "analyse_discrepancy",
    "calibrate",
    "deterministic_settings",
    "forward_select",
    "group_conditions",
    "load_measured",
    "replicate_noise",
    "response_families",
    "score_candidates",
    "write_report",
]
