"""timedexec.execution: delay-compensated, timed trajectory execution (see docs/execution.md).

:class:`TimedExecutor` wraps any :class:`~timedexec.drivers.RobotDriver` and a delay model:
jerk-limited Ruckig plans, per-joint command streams shifted by the predicted actuation
delay, states back-dated by the predicted response delay, timing bounds from the model's
uncertainty, and :meth:`TimedExecutor.plan_to_meet` for deadlines; its options are one
:class:`ExecutorSettings`. The tasks built on it (conveyor tracking, welding, interception)
are :mod:`timedexec.tasks`.

The face, by what it is for:

* the executor and its options: :class:`TimedExecutor`, :class:`ExecutorSettings`,
  :class:`StalenessLimits`, :class:`ExecutionLimits`;
* plans and what a run gives back: :class:`JointPlan`, :func:`plan_motion`,
  :class:`MeetPlan`, :class:`ExecutionResult`, :class:`CycleLog`, :class:`StateEstimate`,
  :class:`TimingBounds`;
* the delay models the loop reads: :class:`DelayPredictor` (the protocol),
  :class:`DelayPredictions`, :class:`FixedDelays`, :func:`load_delay_model`,
  :func:`predict_delays`, :func:`check_model_robot`, :func:`model_period_s`,
  :func:`model_echo_depth`;
* the feed-forward a tracking model's friction offsets ride on: :class:`FrictionFeed`;
* the cycle lock and what measures it on a cell: :class:`SendPhase`, :class:`BoundaryLine`,
  :class:`IntakeFix`, :func:`probe_intake`, :func:`intake_echo`.
"""

from __future__ import annotations

from timedexec.execution._bounds import TimingBounds
from timedexec.execution._command import FrictionFeed
from timedexec.execution._cycle import COMMAND_UPLINK_S, BoundaryLine, IntakeFix, SendPhase
from timedexec.execution._executor import TimedExecutor
from timedexec.execution._intake import probe_intake
from timedexec.execution._log import CycleLog, ExecutionResult, intake_echo
from timedexec.execution._model import (
    DelayPredictions,
    DelayPredictor,
    FixedDelays,
    check_model_robot,
    load_delay_model,
    model_echo_depth,
    model_period_s,
    predict_delays,
)
from timedexec.execution._plan import ExecutionLimits, JointPlan, plan_motion
from timedexec.execution._settings import ExecutorSettings
from timedexec.execution._state import StalenessLimits, StateEstimate
from timedexec.execution._timing import MeetPlan

__all__ = [
    "COMMAND_UPLINK_S",
    "BoundaryLine",
    "CycleLog",
    "DelayPredictions",
    "DelayPredictor",
    "ExecutionLimits",
    "ExecutionResult",
    "ExecutorSettings",
    "FixedDelays",
    "FrictionFeed",
    "IntakeFix",
    "JointPlan",
    "MeetPlan",
    "SendPhase",
    "StalenessLimits",
    "StateEstimate",
    "TimedExecutor",
    "TimingBounds",
    "check_model_robot",
    "intake_echo",
    "load_delay_model",
    "model_echo_depth",
    "model_period_s",
    "plan_motion",
    "predict_delays",
    "probe_intake",
]
