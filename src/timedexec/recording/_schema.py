"""What a calibration recording holds: the per-trial fields and their sizes.

The live runner (:mod:`timedexec.calibration`) and the batch simulator (:mod:`timedexec.sim`)
write the same fields, sized by the sweep protocol (:class:`~timedexec.recording.SweepProtocol`);
extraction reads them. ``docs/recording-format.md`` describes the container and these fields.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from timedexec.recording._fields import Field
from timedexec.recording._sweep_protocol import SweepProtocol

__all__ = ["TrialLayout", "trial_fields", "trial_layout"]


@dataclass(frozen=True)
class TrialLayout:
    """Fixed per-trial array sizes of a sweep."""

    n_packages: int
    n_gyro: int
    n_blocks: int


def trial_layout(protocol: SweepProtocol) -> TrialLayout:
    """Package and gyro-sample counts per trial of a sweep run with ``protocol``."""
    prof, gyro = protocol.profile, protocol.gyro
    n_packages = math.floor(prof.record_s / protocol.controller_period_s)
    n_gyro = round((prof.pre_s + prof.record_s) * gyro.nominal_rate_hz)
    n_gyro -= n_gyro % gyro.block_samples
    return TrialLayout(n_packages, n_gyro, n_gyro // gyro.block_samples)


def trial_fields(protocol: SweepProtocol, *, truth: bool = True) -> list[Field]:
    """The per-trial fields of a recording made with ``protocol``.

    The live runner records the same fields except the ``true_*`` ground truth.
    """
    lay = trial_layout(protocol)
    p, g, b = lay.n_packages, lay.n_gyro, lay.n_blocks
    fields = [
        Field("trial", (), "int64", "", "plan index of the trial"),
        Field(
            "t0_s",
            (),
            "float64",
            "s",
            "host sweep time of the trigger package's arrival (trial time 0)",
        ),
        Field("cmd_send_time_s", (), "float64", "s", "host send time of the command, trial time"),
        Field("cmd_qd_rad_s", (6,), "float64", "rad/s", "commanded joint speeds of the out pulse"),
        Field(
            "state_host_time_s",
            (p,),
            "float64",
            "s",
            "host arrival time of each state package, trial time (NaN: none)",
        ),
        Field(
            "state_controller_time_s", (p,), "float64", "s", "controller time stamp of each package"
        ),
        Field("state_q_rad", (p, 6), "float32", "rad", "reported joint positions"),
        Field(
            "state_qd_rad_s",
            (p, 6),
            "float32",
            "rad/s",
            "reported joint speeds (RSI: host backward difference)",
        ),
        Field("gyro_raw", (g, 3), "int16", "LSB", "gyro rate counts, sensor axes"),
        Field("gyro_counter", (g,), "uint16", "", "sensor sample counter (wraps at 65536)"),
        Field(
            "gyro_block_host_time_s",
            (b,),
            "float32",
            "s",
            "host arrival time of each block of gyro samples, trial time",
        ),
    ]
    if truth:
        fields += [
            Field(
                "true_onset_s",
                (),
                "float64",
                "s",
                "physical speed reaches the onset threshold, trial time",
            ),
            Field(
                "true_actuation_delay_s",
                (),
                "float64",
                "s",
                "true onset - (send time + commanded ramp time to the threshold)",
            ),
            Field(
                "true_response_delay_s",
                (),
                "float64",
                "s",
                "mean (package arrival - its sampling instant)",
            ),
            Field(
                "true_reference_start_s",
                (),
                "float64",
                "s",
                "reference reaches the drive, trial time",
            ),
            Field("true_intake_s", (), "float64", "s", "controller takes the command, trial time"),
            Field(
                "true_gravity_torque_nm",
                (),
                "float64",
                "N·m",
                "holding torque of the actuated joint",
            ),
            Field(
                "true_inertia_kgm2",
                (),
                "float64",
                "kg·m²",
                "reflected inertia of the actuated joint",
            ),
        ]
    return fields
