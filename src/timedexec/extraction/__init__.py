"""timedexec.extraction: stationary analysis, filtering and delay extraction -> delay table."""

from __future__ import annotations

from timedexec.extraction._extract import (
    METHODS,
    REQUIRED_FIELDS,
    ExtractionResult,
    extract_recording,
    trial_traces,
)
from timedexec.extraction._stationary import StillAnalysis, analyse_still, design_lowpass

__all__ = [
    "METHODS",
    "REQUIRED_FIELDS",
    "ExtractionResult",
    "StillAnalysis",
    "analyse_still",
    "design_lowpass",
    "extract_recording",
    "trial_traces",
]
