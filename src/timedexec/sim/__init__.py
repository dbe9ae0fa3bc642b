"""timedexec.sim: the simulated robots.

Joint physics, control-box timing and the gyro; the batch sweep simulator (virtual time,
vectorised across trials); the stepped controller behind the protocol twins; the sweep plan;
the recording format.
"""

from __future__ import annotations

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
from timedexec.sim._settings import (
    GyroSettings,
    ServoSettings,
    SimSettings,
    TimingSettings,
    TrialProfile,
    default_settings,
)

__all__ = [
    "ControllerSim",
    "CycleResult",
    "GyroSettings",
    "JointBank",
    "JointParams",
    "MoveJ",
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
    "calibration_ranges",
    "default_settings",
    "pulse_profile",
]
