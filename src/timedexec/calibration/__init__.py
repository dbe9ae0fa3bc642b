"""timedexec.calibration: the live trial runner (any driver + gyro) writing recordings, and
the ground truth of live runs against the protocol twins."""

from __future__ import annotations

from timedexec.calibration._runner import CalibrationResult, GyroSource, run_calibration
from timedexec.calibration._twin_truth import (
    HostTimeTap,
    TruthComparison,
    TwinTruth,
    compare_with_truth,
    twin_truth_table,
)

__all__ = [
    "CalibrationResult",
    "GyroSource",
    "HostTimeTap",
    "TruthComparison",
    "TwinTruth",
    "compare_with_truth",
    "run_calibration",
    "twin_truth_table",
]
