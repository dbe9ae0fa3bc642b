"""timedexec.recording: the calibration-sweep contract, shared by live runs and the simulator.

* :class:`RecordingWriter` / :class:`RecordingReader`: the crash-safe HDF5 store (journal,
  resume after any interruption, atomic finish);
* the schema: :class:`GyroHeader`, :func:`trial_fields`, :func:`trial_layout`;
* the plan and protocol: :class:`SweepPlan` (which trial runs where), :class:`TrialProfile`
  (the motion of one trial), :class:`SweepProtocol` (how a sweep runs on any robot;
  ``SweepProtocol.for_robot`` gives a robot's defaults from its spec, no simulator needed).

See ``docs/recording-format.md``.
"""

from __future__ import annotations

from timedexec.recording._fields import Field
from timedexec.recording._gyro import GyroHeader
from timedexec.recording._plan import FULL_SWEEP_TRIALS, SweepPlan, calibration_ranges
from timedexec.recording._protocol import FORMAT_NAME, FORMAT_VERSION
from timedexec.recording._reader import DamagedChunkError, RecordingReader
from timedexec.recording._schema import TrialLayout, trial_fields, trial_layout
from timedexec.recording._sweep_protocol import SweepProtocol, TrialProfile
from timedexec.recording._writer import RecordingWriter

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FULL_SWEEP_TRIALS",
    "DamagedChunkError",
    "Field",
    "GyroHeader",
    "RecordingReader",
    "RecordingWriter",
    "SweepPlan",
    "SweepProtocol",
    "TrialLayout",
    "TrialProfile",
    "calibration_ranges",
    "trial_fields",
    "trial_layout",
]
