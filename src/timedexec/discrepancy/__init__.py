"""timedexec.discrepancy: where the simulation and the measured delays disagree, which
effect of the vocabulary is missing, and how much of the gap adding it closes.

>>> from timedexec.discrepancy import analyse_discrepancy      # doctest: +SKIP
>>> result = analyse_discrepancy("ur10-delays.csv", start="base")   # doctest: +SKIP
>>> result.added_effects, result.gap_after_ms, result.noise_floor_ms  # doctest: +SKIP

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
    SIMULATED_EFFECTS,
    FittedModel,
    SimModel,
    calibrate,
    deterministic_settings,
)
from timedexec.discrepancy._report import write_report
from timedexec.discrepancy._workflow import (
    DiscrepancyResult,
    DiscrepancyStep,
    analyse_discrepancy,
    load_measured,
)

__all__ = [
    "SIMULATED_EFFECTS",
    "deterministic_settings",
    "CandidateScore",
    "Conditions",
    "DiscrepancyResult",
    "DiscrepancyStep",
    "FittedModel",
    "NoiseFloor",
    "SimModel",
    "analyse_discrepancy",
    "calibrate",
    "group_conditions",
    "load_measured",
    "replicate_noise",
    "score_candidates",
    "write_report",
]
