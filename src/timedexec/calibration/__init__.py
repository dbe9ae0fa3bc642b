"""timedexec.calibration: calibration sweeps on a robot (any driver + gyro) into recordings.

A live run needs a :class:`~timedexec.recording.SweepProtocol` (the motion, the controller
period, the gyro's constants), never the simulator's settings. Before anything is written a
pre-flight checks that the gyro streams at its rate and turns with the robot
(:class:`PreflightReport` says what it measured).

Two kinds of sweep: the published fixed plan (:func:`run_calibration`) and the adaptive
sweep (:func:`run_adaptive`), which chooses each batch of trials from a Gaussian-process
model of the batches before it (sequential design, :mod:`~timedexec.calibration._design`),
stops at a budget of robot time or when another 10 minutes would no longer help, and is
resumable from the recording (docs/calibration.md). It runs on a :class:`DriverRunner`
(any driver) or any other :class:`TrialRunner` (the batch simulator's,
``timedexec.sim.SimulatedRunner``).
"""

from __future__ import annotations

from timedexec.calibration._adaptive import (
    NOTE_FIELDS,
    AdaptiveResult,
    TrialRunner,
    read_design_log,
    run_adaptive,
)
from timedexec.calibration._design import AdaptiveSettings, Workspace, design_pool
from timedexec.calibration._figure import plot_design_log
from timedexec.calibration._preflight import PreflightReport
from timedexec.calibration._runner import CalibrationResult, DriverRunner, run_calibration
from timedexec.calibration._session import GyroSource

__all__ = [
    "NOTE_FIELDS",
    "AdaptiveResult",
    "AdaptiveSettings",
    "CalibrationResult",
    "DriverRunner",
    "GyroSource",
    "PreflightReport",
    "TrialRunner",
    "Workspace",
    "design_pool",
    "plot_design_log",
    "read_design_log",
    "run_adaptive",
    "run_calibration",
]
