"""timedexec.tasks: what the timed executor is for — conveyor tracking, welding, interception.

Built on :mod:`timedexec.execution`'s public face (a :class:`~timedexec.execution.TimedExecutor`
streams every task); real-robot code, no simulator. docs/welding.md.

* **Welding on a straight belt** (every joint moving): the seam in space and time and the
  joint plan that follows it (:class:`Conveyor`, :class:`Seam`, :class:`WeldCell`,
  :func:`default_cell`, :func:`plan_seam` -> :class:`SeamPlan`), run through an executor
  and measured at the torch (:func:`track_conveyor_seam` -> :class:`ConveyorRun`,
  :class:`TorchErrors`; :func:`prepare_shifted` for a chosen per-joint shift).
* **The delay a tracking arm keeps** (not the onset delay the models learn): measured from
  reported positions (:func:`fit_joint_lags`, :func:`sampling_times_s`,
  :func:`measure_tracking_delays`) and modelled as a dead time plus friction offsets
  (:class:`TrackingDelays`, :func:`fit_dead_time_and_friction`, :func:`fit_tracking` ->
  :class:`TrackingFit`), calibrated on runs of the task or on constant-speed phases
  (:class:`TrackingPhases`, :func:`run_tracking_phases` -> :class:`PhaseRun`,
  :func:`fit_tracking_phases`, :meth:`TrackingDelays.calibrate_phases`).
* **A seam on a carousel** followed with the base joint (:func:`track_seam` ->
  :class:`SeamResult`, :func:`compare_seam_tracking`, :func:`tool_radius_m`).
* **Interception**: the tool where a moving object will be, by a deadline at a confidence
  (:func:`intercept` -> :class:`InterceptResult`, :func:`solve_position_ik`).
"""

from __future__ import annotations

from timedexec.tasks._carousel import (
    SEAM_POSITION_GAIN_1_S,
    SeamResult,
    compare_seam_tracking,
    tool_radius_m,
    track_seam,
)
from timedexec.tasks._conveyor import (
    SEAM_KINDS,
    Conveyor,
    Seam,
    SeamPlan,
    WeldCell,
    default_cell,
    plan_seam,
)
from timedexec.tasks._intercept import InterceptResult, intercept, solve_position_ik
from timedexec.tasks._lag_fit import (
    TrackingFit,
    fit_dead_time_and_friction,
    fit_joint_lags,
    fit_tracking,
    measure_tracking_delays,
    sampling_times_s,
)
from timedexec.tasks._tracking import (
    MAX_CALIBRATION_RUNS,
    PHASE_SPEEDS_RAD_S,
    TRACKING_FILE,
    PhaseRun,
    TrackingDelays,
    TrackingPhases,
    fit_tracking_phases,
    run_tracking_phases,
)
from timedexec.tasks._welding import (
    ConveyorRun,
    TorchErrors,
    prepare_shifted,
    track_conveyor_seam,
)

__all__ = [
    "MAX_CALIBRATION_RUNS",
    "PHASE_SPEEDS_RAD_S",
    "SEAM_KINDS",
    "SEAM_POSITION_GAIN_1_S",
    "TRACKING_FILE",
    "Conveyor",
    "ConveyorRun",
    "InterceptResult",
    "PhaseRun",
    "Seam",
    "SeamPlan",
    "SeamResult",
    "TorchErrors",
    "TrackingDelays",
    "TrackingFit",
    "TrackingPhases",
    "WeldCell",
    "compare_seam_tracking",
    "default_cell",
    "fit_dead_time_and_friction",
    "fit_joint_lags",
    "fit_tracking",
    "fit_tracking_phases",
    "intercept",
    "measure_tracking_delays",
    "plan_seam",
    "prepare_shifted",
    "run_tracking_phases",
    "sampling_times_s",
    "solve_position_ik",
    "tool_radius_m",
    "track_conveyor_seam",
    "track_seam",
]
