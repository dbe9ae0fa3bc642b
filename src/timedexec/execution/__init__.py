"""timedexec.execution: delay-compensated, timed trajectory execution (see docs/execution.md).

:class:`TimedExecutor` wraps any :class:`~timedexec.drivers.RobotDriver` and a delay model:
jerk-limited Ruckig plans, per-joint command streams shifted by the predicted actuation
delay, states back-dated by the predicted response delay, timing bounds from the model's
uncertainty, and :meth:`TimedExecutor.plan_to_meet` for deadlines.
"""

from __future__ import annotations

from timedexec.errors import StaleStateError, UnreachableError
from timedexec.execution._bounds import TimingBounds, delay_cdf, delay_quantile
from timedexec.execution._executor import TimedExecutor
from timedexec.execution._log import CycleLog, ExecutionResult
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
from timedexec.execution._state import StalenessLimits, StateEstimate
from timedexec.execution._tasks import (
    InterceptResult,
    SeamResult,
    compare_seam_tracking,
    intercept,
    solve_position_ik,
    tool_radius_m,
    track_seam,
)
from timedexec.execution._timing import MeetPlan

__all__ = [
    "BUNDLED_MODELS",
    "CycleLog",
    "DelayPredictions",
    "DelayPredictor",
    "ExecutionLimits",
    "ExecutionResult",
    "FixedDelays",
    "InterceptResult",
    "JointPlan",
    "MeetPlan",
    "SeamResult",
    "StaleStateError",
    "StalenessLimits",
    "StateEstimate",
    "TimedExecutor",
    "TimingBounds",
    "UnreachableError",
    "bundled_model_dir",
    "check_model_robot",
    "check_target",
    "compare_seam_tracking",
    "delay_cdf",
    "delay_quantile",
    "intercept",
    "load_delay_model",
    "model_period_s",
    "plan_motion",
    "predict_delays",
    "solve_position_ik",
    "tool_radius_m",
    "track_seam",
]
