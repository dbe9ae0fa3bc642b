"""timedexec.monitoring: watch a deployed delay model from the robot's own data (no gyro).

:class:`DelayMonitor` takes *moves* (a joint's commanded speed leaving zero from rest) from
a calibration recording's robot stream (:func:`moves_from_recording`), from an executor's
cycle log, saved (:func:`save_cycle_log` / :func:`load_cycle_log`) or live
(:meth:`DelayMonitor.follow`), measures each move's lag from command to the state stream
showing the motion (actuation + response, sub-period by inverting the commanded ramp),
compares it with the model's prediction and runs a two-sided CUSUM per joint whose
threshold is set from a false-alarm rate. See docs/monitor.md.
"""

from __future__ import annotations

from timedexec.monitoring._cusum import (
    arl_one_sided,
    arl_two_sided,
    false_alarm_rate,
    run_lengths,
    threshold_for_arl,
)
from timedexec.monitoring._figure import monitor_figure
from timedexec.monitoring._monitor import (
    LRV_LAGS,
    SCORE_CLIP,
    Alert,
    DelayMonitor,
    JointState,
    RecalibrationPlan,
    describe_alert,
    standardize,
    warmup_reference,
)
from timedexec.monitoring._moves import (
    HIGH_FRACTION,
    LOG_FORMAT,
    LOW_FRACTION,
    Move,
    MoveExtractor,
    collapse_conditions,
    load_cycle_log,
    move_lag_s,
    moves_from_recording,
    moves_from_trials,
    save_cycle_log,
)

__all__ = [
    "HIGH_FRACTION",
    "LOG_FORMAT",
    "LOW_FRACTION",
    "LRV_LAGS",
    "SCORE_CLIP",
    "Alert",
    "DelayMonitor",
    "JointState",
    "Move",
    "MoveExtractor",
    "RecalibrationPlan",
    "arl_one_sided",
    "arl_two_sided",
    "collapse_conditions",
    "describe_alert",
    "false_alarm_rate",
    "load_cycle_log",
    "monitor_figure",
    "move_lag_s",
    "moves_from_recording",
    "moves_from_trials",
    "run_lengths",
    "save_cycle_log",
    "standardize",
    "threshold_for_arl",
    "warmup_reference",
]
