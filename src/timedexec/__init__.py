"""timedexec: temporally precise execution for industrial robot arms.

Controllers act late (actuation delay) and report late (response delay). timedexec measures
both with an external gyro, learns per-joint models with uncertainty and executes
trajectories so that the physical motion happens when it was planned.
"""

from __future__ import annotations

from timedexec._version import __version__
from timedexec.errors import (
    ConfigError,
    DriverError,
    DriverTimeout,
    ModelError,
    ProtocolError,
    RecordingError,
    SensorError,
    TimedExecError,
)

__all__ = [
    "ConfigError",
    "DriverError",
    "DriverTimeout",
    "ModelError",
    "ProtocolError",
    "RecordingError",
    "SensorError",
    "TimedExecError",
    "__version__",
]
