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
    from timedexec.execution import ExecutorSettings, TimedExecutor
    from timedexec.learning import DelayModel, DelayPrediction

__all__ = [
    "ConfigError",
    "DelayModel",
    "DelayPrediction",
    "DriverError",
    "DriverTimeout",
    "ExecutorSettings",
    "ModelError",
    "ProtocolError",
    "RecordingError",
    "SensorError",
    "TimedExecError",
    "TimedExecutor",
    "__version__",
]


def __getattr__(name: str) -> Any:
    # The model and the executor load on first use: `import timedexec` stays light.
    if name in ("DelayModel", "DelayPrediction"):
        from timedexec import learning

        return getattr(learning, name)
    if name in ("TimedExecutor", "ExecutorSettings"):
        from timedexec import execution

        return getattr(execution, name)
    raise AttributeError(f"module 'timedexec' has no attribute {name!r}")
