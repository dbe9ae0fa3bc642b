"""timedexec.calibration: the live trial runner (any driver + gyro) writing recordings."""

from __future__ import annotations

from timedexec.calibration._runner import CalibrationResult, GyroSource, run_calibration

__all__ = ["CalibrationResult", "GyroSource", "run_calibration"]
