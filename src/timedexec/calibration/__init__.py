"""timedexec.calibration: the live trial runner (any driver + gyro) writing recordings.

A live run needs a :class:`~timedexec.recording.SweepProtocol` (the motion, the controller
period, the gyro's constants), never the simulator's settings.
"""

from __future__ import annotations

from timedexec.calibration._runner import CalibrationResult, GyroSource, run_calibration

__all__ = ["CalibrationResult", "GyroSource", "run_calibration"]
