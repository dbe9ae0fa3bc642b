"""timedexec.sim: the simulated robots.

Joint physics, control-box timing and the gyro; the batch sweep simulator (virtual time,
vectorised across trials); the stepped controller behind the protocol twins; the sweep plan;
the recording format.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from timedexec.sim._controller import (
    ControllerSim,
    CycleResult,
    MoveJ,
    ServoJ,
    SpeedJ,
    SpeedStop,
    StatePacket,
    StopJ,
    TruthEvent,
)
from timedexec.sim._physics import JointBank, JointParams, pulse_profile
from timedexec.sim._plan import SweepPlan, calibration_ranges
from timedexec.sim._recording import (
    FORMAT_NAME,
    FORMAT_VERSION,
    Field,
    RecordingReader,
    RecordingWriter,
)
from timedexec.sim._settings import (
    GyroSettings,
    ServoSettings,
    SimSettings,
    TimingSettings,
    TrialProfile,
    default_settings,
)
from timedexec.sim._sweep import simulate_delays, simulate_sweep, truth_table

if TYPE_CHECKING:
    from timedexec.sim._gyro_twin import GyroFrameSource, GyroTwin
    from timedexec.sim._rsi_twin import RSITwin, read_rsi_truth
    from timedexec.sim._ur_twin import URTwin, read_truth, run_ur_twin

# Protocol twins load on first use: they pull in sockets, multiprocessing and pty code.
_LAZY = {
    "URTwin": "timedexec.sim._ur_twin",
    "run_ur_twin": "timedexec.sim._ur_twin",
    "read_truth": "timedexec.sim._ur_twin",
    "RSITwin": "timedexec.sim._rsi_twin",
    "read_rsi_truth": "timedexec.sim._rsi_twin",
    "GyroTwin": "timedexec.sim._gyro_twin",
    "GyroFrameSource": "timedexec.sim._gyro_twin",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'timedexec.sim' has no attribute {name!r}")


__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "ControllerSim",
    "CycleResult",
    "Field",
    "GyroFrameSource",
    "GyroSettings",
    "GyroTwin",
    "JointBank",
    "JointParams",
    "MoveJ",
    "RSITwin",
    "RecordingReader",
    "RecordingWriter",
    "ServoJ",
    "ServoSettings",
    "SimSettings",
    "SpeedJ",
    "SpeedStop",
    "StatePacket",
    "StopJ",
    "SweepPlan",
    "TimingSettings",
    "TrialProfile",
    "TruthEvent",
    "URTwin",
    "calibration_ranges",
    "default_settings",
    "pulse_profile",
    "read_rsi_truth",
    "read_truth",
    "run_ur_twin",
    "simulate_delays",
    "simulate_sweep",
    "truth_table",
]
