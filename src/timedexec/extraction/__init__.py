"""timedexec.extraction: recording -> delay table.

Stationary analysis, lossy-stream repair, drift-following gyro clock, filtering,
noise-adaptive onset timing with standard errors and Cramér-Rao bounds, response timing
(and where it puts each trial's sampling instants, :func:`sampling_offsets`);
:func:`check_recording` lists every way a file departs from ``docs/recording-format.md``.
"""

from __future__ import annotations

from timedexec.extraction._check import (
    REQUIRED_FIELDS,
    REQUIRED_HEADER,
    REQUIRED_STATICS,
    UNITS,
    check_recording,
)
from timedexec.extraction._dating import sampling_offsets
from timedexec.extraction._extract import (
    MAX_SE_S,
    METHODS,
    ExtractionResult,
    extract_recording,
    trial_traces,
)
from timedexec.extraction._onset import (
    LEPSKI_KAPPA,
    LEPSKI_NOISE_SCALE_S,
    ONSET_WINDOWS_S,
    ladder_cap,
)
from timedexec.extraction._response import (
    RESPONSE_FLAG_DEFLECTION,
    RESPONSE_FLAG_DEFLECTION_JOINT,
    RESPONSE_FLAG_DEFLECTION_NOISE,
)
from timedexec.extraction._stationary import StillAnalysis, analyse_still, design_lowpass

#: Every reason extraction writes in the ``response_flag`` column (``timedexec.delays``).
RESPONSE_FLAGS = (
    RESPONSE_FLAG_DEFLECTION,
    RESPONSE_FLAG_DEFLECTION_JOINT,
    RESPONSE_FLAG_DEFLECTION_NOISE,
)

__all__ = [
    "LEPSKI_KAPPA",
    "LEPSKI_NOISE_SCALE_S",
    "MAX_SE_S",
    "METHODS",
    "ONSET_WINDOWS_S",
    "REQUIRED_FIELDS",
    "REQUIRED_HEADER",
    "REQUIRED_STATICS",
    "RESPONSE_FLAGS",
    "UNITS",
    "ExtractionResult",
    "StillAnalysis",
    "analyse_still",
    "check_recording",
    "design_lowpass",
    "extract_recording",
    "ladder_cap",
    "sampling_offsets",
    "trial_traces",
]
