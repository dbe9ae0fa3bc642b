"""timedexec.execution: delay-compensated, timed trajectory execution (see docs/execution.md).

:class:`TimedExecutor` wraps any :class:`~timedexec.drivers.RobotDriver` and a delay model:
jerk-limited Ruckig plans, per-joint command streams shifted by the predicted actuation
delay, states back-dated by the predicted response delay, timing bounds from the model's
uncertainty, and :meth:`TimedExecutor.plan_to_meet` for deadlines. Tasks: conveyor welding
on a straight belt (:func:`track_conveyor_seam`, with the tracking delays of
:class:`TrackingDelays`), the carousel seam (:func:`track_seam`) and interception.
"""

from __future__ import annotations

from timedexec.errors import StaleStateError, UnreachableError
from timedexec.execution._bounds import TimingBounds, delay_cdf, delay_quantile
from timedexec.execution._command import FRICTION_SPEED_RAD_S, FrictionFeed, friction_sign
from timedexec.execution._conveyor import (
    SEAM_KINDS,
    Conveyor,
    Seam,
    SeamPlan,
    WeldCell,
    default_cell,
    plan_seam,
)
from timedexec.execution._cycle import (
    COMMAND_UPLINK_S,
    DEFAULT_ROUND_TRIP_S,
    BoundaryLine,
    IntakeFix,
    SendPhase,
    wait_until,
)
from timedexec.execution._executor import TimedExecutor
from timedexec.execution._intake import find_intake_step, probe_intake
from timedexec.execution._log import CycleLog, ExecutionResult, intake_echo
from timedexec.execution._model import (
    BUNDLED_MODELS,
    DelayPredictions,
    DelayPredictor,
    FixedDelays,
    bundled_model_dir,
    check_model_robot,
    load_delay_model,
    model_period_s,
    predict_delays,
)
from timedexec.execution._plan import ExecutionLimits, JointPlan, check_target, plan_motion
from timedexec.execution._safety import (
    DEFAULT_WATCHDOG_TIMEOUT_S,
    REST_PACKAGES,
    REST_SPEED_RAD_S,
    ControllerWatchdog,
)
from timedexec.execution._state import StalenessLimits, StateEstimate, StreamJitter
from timedexec.execution._tasks import (
    SEAM_POSITION_GAIN_1_S,
    InterceptResult,
    SeamResult,
    compare_seam_tracking,
    intercept,
    solve_position_ik,
    tool_radius_m,
    track_seam,
)
from timedexec.execution._timing import MeetPlan
from timedexec.execution._tracking import (
    TrackingDelays,
    fit_dead_time_and_friction,
    fit_joint_lags,
    measure_tracking_delays,
    sampling_times_s,
)
from timedexec.execution._welding import (
    ConveyorRun,
    TorchErrors,
    prepare_shifted,
    track_conveyor_seam,
)

__all__ = [
    "BUNDLED_MODELS",
    "COMMAND_UPLINK_S",
    "DEFAULT_ROUND_TRIP_S",
    "DEFAULT_WATCHDOG_TIMEOUT_S",
    "FRICTION_SPEED_RAD_S",
    "REST_PACKAGES",
    "REST_SPEED_RAD_S",
    "SEAM_KINDS",
    "SEAM_POSITION_GAIN_1_S",
    "BoundaryLine",
    "ControllerWatchdog",
    "Conveyor",
    "ConveyorRun",
    "CycleLog",
    "DelayPredictions",
    "DelayPredictor",
    "ExecutionLimits",
    "ExecutionResult",
    "FixedDelays",
    "FrictionFeed",
    "IntakeFix",
    "InterceptResult",
    "JointPlan",
    "MeetPlan",
    "Seam",
    "SeamPlan",
    "SeamResult",
    "SendPhase",
    "StaleStateError",
    "StalenessLimits",
    "StateEstimate",
    "StreamJitter",
    "TimedExecutor",
    "TimingBounds",
    "TorchErrors",
    "TrackingDelays",
    "UnreachableError",
    "WeldCell",
    "bundled_model_dir",
    "check_model_robot",
    "check_target",
    "compare_seam_tracking",
    "default_cell",
    "delay_cdf",
    "delay_quantile",
    "find_intake_step",
    "fit_dead_time_and_friction",
    "fit_joint_lags",
    "friction_sign",
    "intake_echo",
    "intercept",
    "load_delay_model",
    "measure_tracking_delays",
    "model_period_s",
    "plan_motion",
    "plan_seam",
    "predict_delays",
    "prepare_shifted",
    "probe_intake",
    "sampling_times_s",
    "solve_position_ik",
    "tool_radius_m",
    "track_conveyor_seam",
    "track_seam",
    "wait_until",
]
