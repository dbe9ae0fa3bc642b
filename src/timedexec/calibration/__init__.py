"""timedexec.calibration: the live trial runner (any driver + gyro) writing recordings.

A live run needs a :class:`~timedexec.recording.SweepProtocol` (the motion, the controller
period, the gyro's constants), never the simulator's settings. Before anything is written a
pre-flight checks that the gyro streams at its rate and turns with the robot
(:class:`PreflightReport` says what it measured).
"""

from __future__ import annotations

from timedexec.calibration._preflight import PreflightReport
from timedexec.calibration._runner import CalibrationResult, run_calibration
from timedexec.calibration._session import GyroSource

__all__ = ["CalibrationResult", "GyroSource", "PreflightReport", "run_calibration"]
