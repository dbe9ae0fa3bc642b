"""timedexec.sim: the simulated robots (simulation only: no sockets, no pseudo-terminals).

Joint physics (:class:`JointBank` for a batch, :class:`JointChain` for one arm, parameters from
:func:`joint_params`), the control box's timing (:class:`ControllerSim`, stepped
cycle by cycle, behind the protocol twins of :mod:`timedexec.twins`), the simulated gyro
(:class:`GyroFrameSource` and its rate sources), the settings calibrated to the published
statistics (:func:`default_settings`) and the vectorised batch sweep
(:func:`simulate_sweep`, :func:`simulate_delays`), which writes through
:mod:`timedexec.recording`, also as the robot of an adaptive sweep
(:class:`SimulatedRunner`). A warm start (:data:`WARM_START_S`) puts the robot's power-on
hours before the sweep.
"""

from __future__ import annotations

from timedexec.sim._batch import (
    BLOCK_TRIALS,
    WARM_START_S,
    SweepClock,
    simulate_block,
    sweep_clock,
)
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
from timedexec.sim._gyro import (
    DEFAULT_BIAS_DPS,
    FULL_SCALE_SENSITIVITY,
    GyroFrameSource,
    RateSource,
    constant_rate_source,
    device_frames,
    sine_rate_source,
    step_rate_source,
)
from timedexec.sim._physics import JointBank, JointChain, JointParams, joint_params, pulse_profile
from timedexec.sim._runner import SimulatedRunner
from timedexec.sim._settings import (
    GyroModel,
    ServoSettings,
    SimSettings,
    TimingSettings,
    default_settings,
)
from timedexec.sim._sweep import SweepResult, simulate_delays, simulate_sweep, truth_table

__all__ = [
    "BLOCK_TRIALS",
    "DEFAULT_BIAS_DPS",
    "FULL_SCALE_SENSITIVITY",
    "WARM_START_S",
    "ControllerSim",
    "CycleResult",
    "GyroFrameSource",
    "GyroModel",
    "JointBank",
    "JointChain",
    "JointParams",
    "MoveJ",
    "RateSource",
    "ServoJ",
    "ServoSettings",
    "SimSettings",
    "SimulatedRunner",
    "SpeedJ",
    "SpeedStop",
    "StatePacket",
    "StopJ",
    "SweepClock",
    "SweepResult",
    "TimingSettings",
    "TruthEvent",
    "constant_rate_source",
    "default_settings",
    "device_frames",
    "joint_params",
    "pulse_profile",
    "simulate_block",
    "simulate_delays",
    "simulate_sweep",
    "sine_rate_source",
    "step_rate_source",
    "sweep_clock",
    "truth_table",
]
