"""timedexec: temporally precise execution for industrial robot arms.

Controllers act late (actuation delay) and report late (response delay). timedexec measures
both with an external gyro, learns per-joint models with uncertainty and executes
trajectories so that the physical motion happens when it was planned.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

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

if TYPE_CHECKING:
    from timedexec.learning import DelayModel

__all__ = [
    "ConfigError",
    "DelayModel",
    "DriverError",
    "DriverTimeout",
    "ModelError",
    "ProtocolError",
    "RecordingError",
    "SensorError",
    "TimedExecError",
    "__version__",
]


def __getattr__(name: str) -> Any:
    # The fast predictor loads on first use: `import timedexec` stays light.
    if name == "DelayModel":
        from timedexec.learning import DelayModel

        return DelayModel
    raise AttributeError(f"module 'timedexec' has no attribute {name!r}")
