"""Batch sweep simulation in virtual time, vectorised across trials.

Each trial produces exactly what a live trial records (host arrival time, controller time,
reported q and qd of every state package; the command's send time and speed profile; the
gyro stream with its sample counter and the host arrival time of each USB block) plus the
ground truth (true onset, true actuation and response delays).

Time line of one trial (host clock, trial time 0 = arrival of the trigger package):

1. The controller samples its state at cycle boundary ``s_0``; the package leaves after the
   packing phase (plus whole periods with ``response_extra_cycle``) and reaches the host at 0.
2. The host sends the command at ``t_send`` (processing time); it reaches the controller
   after the network latency and is taken at the next cycle boundary (intake).
3. After ``pipeline_cycles`` periods (plus the joint's drive offset) the reference reaches
   the drive; the velocity loop builds torque until the joint breaks away; the true onset is
   when its speed reaches ``onset_threshold_rad_s``.
4. Every later boundary is sampled and published the same way.

Randomness: one generator per fixed block of trials, seeded from ``(seed, block start)``, so
the output depends on the seed only — not on the number of worker processes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._signal import ONSET_FRACTION, interp_rows
from timedexec._types import FloatArray
from timedexec.effects import EffectSet, Pose
from timedexec.recording import SweepPlan, trial_layout
from timedexec.robots import RobotSpec, get_robot_entry, joint_axis_in_tool
from timedexec.sim._physics import (
    JointBank,
    drive_delay_s,
    joint_params,
    pulse_profile,
    response_delay_s,
)
from timedexec.sim._settings import SimSettings

__all__ = [
    "BLOCK_TRIALS",
    "WARM_START_S",
    "SweepClock",
    "iter_blocks",
    "simulate_block",
    "sweep_clock",
]

#: Trials per random-number block (fixed: changing it changes the output for a seed).
BLOCK_TRIALS = 512
#: A warm start: the robot was powered on this long before the sweep began, s (four of
#: ``thermal_drift``'s default hour-long time constants: friction within 1.1 % of warm).
WARM_START_S = 4 * 3600.0


@dataclass(frozen=True)
class SweepClock:
    """Sweep-wide hidden truths: trial start times and the gyro's clock, bias and scale."""

    t0_s: FloatArray  # (n,) host sweep time of each trial's trigger package, s
    gyro_offset_s: float  # host sweep time of gyro sample 0, s
    gyro_counter0: int  # counter value of sample 0
    gyro_bias_dps: FloatArray  # (3,)
    gyro_bias_drift_dps_per_s: FloatArray  # (3,)
    gyro_scale: FloatArray  # (3,)
    controller_boot_s: float  # controller clock value at host sweep time 0, s
    #: host sweep time of the robot's power-on, s: 0 for a cold start, ``-WARM_START_S``
    #: for a warm one; the thermal state (``thermal_drift``) runs on ``t0_s - power_on_s``
    power_on_s: float = 0.0

    @property
    def thermal_s(self) -> FloatArray:
        """Time since power-on of each trial's start, s (what ``thermal_drift`` sees)."""
        return self.t0_s - self.power_on_s

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe ground truth of the sweep's sensor (for the recording header)."""
        return {
            "gyro_offset_s": self.gyro_offset_s,
            "gyro_counter0": self.gyro_counter0,
            "gyro_bias_dps": self.gyro_bias_dps.tolist(),
            "gyro_bias_drift_dps_per_s": self.gyro_bias_drift_dps_per_s.tolist(),
            "gyro_scale": self.gyro_scale.tolist(),
            "controller_boot_s": self.controller_boot_s,
        }


def sweep_clock(
    plan: SweepPlan, settings: SimSettings, seed: int, *, warm: bool = False
) -> SweepClock:
    """Draw the sweep-wide truths and lay out the trials in time.

    A still recording of the protocol's ``still_s`` opens the sweep; each trial takes its
    record window plus ``trial_gap_s``; moving to a new configuration adds ``config_move_s``.
    ``warm``: the robot was powered on :data:`WARM_START_S` before the sweep clock's zero
    (a robot taken out of production); otherwise at zero (cold).
    """
    rng = np.random.default_rng([seed, 0xC10C])
    gyro, protocol = settings.gyro, settings.protocol
    trial_s = protocol.profile.pre_s + protocol.profile.record_s + protocol.trial_gap_s
    new_config = np.r_[True, plan.config_index[1:] != plan.config_index[:-1]]
    step = trial_s + np.where(new_config, protocol.config_move_s, 0.0)
    # Small host-side scheduling jitter between trials (the runner waits for a package).
    step = step + rng.uniform(0.0, protocol.controller_period_s, len(plan))
    t0 = protocol.still_s + protocol.profile.pre_s + np.cumsum(step) - step[0]
    hours = 1.0 / 3600.0
    return SweepClock(
        t0_s=t0,
        gyro_offset_s=float(rng.uniform(-1.0, 0.0)),
        gyro_counter0=int(rng.integers(0, 65536)),
        gyro_bias_dps=rng.uniform(-gyro.bias_dps, gyro.bias_dps, 3),
        gyro_bias_drift_dps_per_s=rng.choice([-1.0, 1.0], 3) * gyro.bias_drift_dps_per_hour * hours,
        gyro_scale=1.0 + rng.uniform(-gyro.scale_error, gyro.scale_error, 3),
        controller_boot_s=float(rng.uniform(100.0, 5000.0)),
        power_on_s=-WARM_START_S if warm else 0.0,
    )


def simulate_block(
    spec: RobotSpec,
    settings: SimSettings,
    effects: EffectSet,
    plan: SweepPlan,
    clock: SweepClock,
    rows: NDArray[np.int64],
    seed: int,
    *,
    truth_only: bool = False,
) -> dict[str, NDArray[Any]]:
    """Simulate the trials ``rows`` (plan indices of one random block).

    Returns a batch for :meth:`RecordingWriter.append`: every per-trial field of the
    recording (see ``docs/recording-format.md``) with a leading axis ``len(rows)``.
    ``truth_only=True`` returns only ``trial``, ``t0_s`` and the ``true_*`` fields and stops
    integrating once every onset is found (for learning, discrepancy and evaluation work
    that needs many delays fast); the delays are identical to a full run's.
    """
    rng = np.random.default_rng([seed, 1, int(rows[0])])
    n = len(rows)
    lay = trial_layout(settings.protocol)
    timing, gyro, prof = settings.timing, settings.gyro, settings.protocol.profile
    period = settings.protocol.controller_period_s
    joint = plan.joint[rows]
    direction = plan.direction[rows].astype(float)
    q_start = plan.q_start_rad[rows]
    t0 = clock.t0_s[rows]
    col = joint - 1

    # -- control-box timing -------------------------------------------------------------
    extra_s = response_delay_s(effects, period)
    phase = rng.uniform(*timing.packing_phase_s, n)
    k = np.arange(lay.n_packages)
    latency = timing.to_host_latency_s + rng.exponential(
        timing.to_host_jitter_s or 1e-12, (n, lay.n_packages)
    )
    jitter = rng.normal(0.0, timing.cycle_jitter_s, (n, lay.n_packages))
    jitter[:, 0] = 0.0
    s0 = -(phase + extra_s + latency[:, 0])
    sample_t = s0[:, None] + k * period + jitter
    arrival = sample_t + (phase + extra_s)[:, None] + latency
    arrival[:, 0] = 0.0  # trial time 0 is the trigger package's arrival (exact by construction)
    t_send = timing.host_processing_s + rng.exponential(20e-6, n)
    at_controller = (
        t_send
        + timing.to_controller_latency_s
        + rng.exponential(timing.to_controller_jitter_s or 1e-12, n)
    )
    intake = s0 + np.ceil((at_controller - s0) / period) * period
    thermal = t0 - clock.power_on_s  # time since power-on: the thermal state's clock
    pose = Pose(spec=spec, q_start_rad=q_start, joint=joint, t_start_s=thermal, direction=direction)
    drive_offset = drive_delay_s(effects, pose)
    t_ref = (
        intake
        + timing.pipeline_cycles * period
        + rng.normal(0.0, timing.cycle_jitter_s, n)
        + drive_offset
    )

    # -- gyro grid (the sensor's own clock) ------------------------------------------------
    f_true = gyro.true_rate_hz
    dt = 1.0 / f_true
    n_first = np.ceil((t0 - prof.pre_s - clock.gyro_offset_s) * f_true).astype(np.int64)
    g_first = clock.gyro_offset_s + n_first * dt - t0  # trial time of the first sample, s

    # -- joint physics at half the gyro rate ------------------------------------------------
    # Integrating at 4 kHz (every other gyro sample) halves the cost; the slowest loop
    # (velocity, <= 160 rad/s) sees 0.04 rad per step and the current loop is discretised
    # exactly. Gyro samples in between are interpolated. Histories hold the state at the
    # start of each step, stamped with that time.
    params, tau_g, j_true = joint_params(spec, settings, effects, q_start, joint, thermal)
    q_j0 = q_start[np.arange(n), col]
    stride = 2
    dt_phys = stride * dt
    n_phys = lay.n_gyro // stride + 1
    onset_level = ONSET_FRACTION * prof.speed_rad_s
    bank = JointBank(params, q_j0, dt_phys, onset_level)
    bank.arm_onset(np.ones(n, dtype=bool))
    t_phys = g_first[None, :] + np.arange(n_phys)[:, None] * dt_phys  # (steps, n)
    v_ref = direction * pulse_profile(t_phys - t_ref, **prof.template)  # (steps, n)
    v_hist = np.empty((n_phys, n))
    q_hist = np.empty((n_phys, n))
    moving_from = np.nonzero(np.any(v_ref != 0.0, axis=1))[0]
    first = int(moving_from[0]) if len(moving_from) else n_phys
    last_ref = int(moving_from[-1]) if len(moving_from) else 0
    v_hist[:first] = 0.0
    q_hist[:first] = q_j0
    i = first
    while i < n_phys:
        v_hist[i] = bank.v
        q_hist[i] = bank.q
        if truth_only and i % 32 == 0 and not np.isnan(bank.onset_s).any():
            break
        # Past every reference and with every joint at rest, nothing changes any more.
        if i > last_ref and i % 32 == 0 and bank.stuck.all():
            v_hist[i:] = 0.0
            q_hist[i:] = bank.q
            break
        bank.step(v_ref[i], t_phys[i])
        i += 1
    onset = bank.onset_s
    v_hist = np.ascontiguousarray(v_hist.T)
    q_hist = np.ascontiguousarray(q_hist.T)

    # -- ground truth: onset against the commanded ramp reaching the same speed -------------
    actuation = onset - (t_send + onset_level / prof.acceleration_rad_s2)

    truth = {
        "true_onset_s": onset,
        "true_actuation_delay_s": actuation,
        "true_response_delay_s": np.mean(arrival - sample_t, axis=1),
        "true_reference_start_s": t_ref,
        "true_intake_s": intake,
        "true_gravity_torque_nm": tau_g,
        "true_inertia_kgm2": j_true,
    }
    if truth_only:
        return {"trial": rows.astype(np.int64), "t0_s": t0, **truth}

    # -- reported state packages -------------------------------------------------------------
    pos = (sample_t - g_first[:, None]) / dt_phys
    q_rep = interp_rows(q_hist, pos)
    q_pkg = np.repeat(q_start[:, None, :], lay.n_packages, axis=1)
    qd_pkg = np.zeros_like(q_pkg)
    r = np.arange(n)
    q_pkg[r, :, col] = q_rep
    if not get_robot_entry(spec.name).timing.state_velocity:
        # Positions only (RSI); the host differentiates (a T/2 lag, documented).
        qd_rep = np.diff(q_rep, axis=1, prepend=q_rep[:, :1]) / period
    else:
        qd_rep = interp_rows(v_hist, pos)
    qd_pkg[r, :, col] = qd_rep
    controller_time = (
        clock.controller_boot_s + np.round((t0 + s0) / period)[:, None] * period + k * period
    )

    # -- gyro samples ------------------------------------------------------------------------
    shift = gyro.group_delay_s * f_true  # the sensor's filter delays what it reports
    idx = (np.arange(lay.n_gyro) - shift) / stride
    v_delayed = interp_rows(v_hist, np.broadcast_to(idx, (n, lay.n_gyro)))
    axis = joint_axis_in_tool(spec, q_start, joint)  # (n, 3)
    sigma_dps = gyro.noise_density_dps_rthz * math.sqrt(f_true / 2.0)
    lsb = np.float32(gyro.lsb_per_dps)
    # Bias at the trial's time: its drift within one trial (< 1e-4 °/s) is below a count.
    bias = clock.gyro_bias_dps + clock.gyro_bias_drift_dps_per_s * t0[:, None]  # (n, 3)
    gain = (axis * clock.gyro_scale * (180.0 / np.pi) * gyro.lsb_per_dps).astype(np.float32)
    counts = rng.standard_normal((n, lay.n_gyro, 3), dtype=np.float32)
    counts *= np.float32(sigma_dps) * lsb
    counts += (bias * gyro.lsb_per_dps).astype(np.float32)[:, None, :]
    counts += v_delayed.astype(np.float32)[:, :, None] * gain[:, None, :]
    np.rint(counts, out=counts)
    np.clip(counts, -32768, 32767, out=counts)
    gyro_raw = counts.astype(np.int16)
    counter = ((clock.gyro_counter0 + n_first[:, None] + np.arange(lay.n_gyro)) % 65536).astype(
        np.uint16
    )
    last = g_first[:, None] + ((np.arange(lay.n_blocks) + 1) * gyro.block_samples - 1) * dt
    blocks = last + gyro.usb_latency_s + rng.exponential(gyro.usb_jitter_s or 1e-12, last.shape)
    blocks = np.maximum.accumulate(blocks, axis=1)  # USB delivers in order

    return {
        "trial": rows.astype(np.int64),
        "t0_s": t0,
        "cmd_send_time_s": t_send,
        "cmd_qd_rad_s": np.where(
            np.arange(6) == col[:, None], direction[:, None] * prof.speed_rad_s, 0.0
        ),
        "state_host_time_s": arrival,
        "state_controller_time_s": controller_time,
        "state_q_rad": q_pkg.astype(np.float32),
        "state_qd_rad_s": qd_pkg.astype(np.float32),
        "gyro_raw": gyro_raw,
        "gyro_counter": counter,
        "gyro_block_host_time_s": blocks.astype(np.float32),
        **truth,
    }


def iter_blocks(
    n_trials: int, done: NDArray[np.int64] | None = None
) -> Iterator[NDArray[np.int64]]:
    """Whole plan-index blocks of :data:`BLOCK_TRIALS` that hold a trial not yet ``done``.

    Blocks are always whole so that their random stream (keyed by the block start) and
    hence their trials are the same on a resumed run; the caller drops the done rows.
    """
    completed = np.zeros(n_trials, dtype=bool)
    if done is not None and len(done):
        completed[done] = True
    for start in range(0, n_trials, BLOCK_TRIALS):
        rows = np.arange(start, min(start + BLOCK_TRIALS, n_trials))
        if not completed[rows].all():
            yield rows


ProgressFn = Callable[[int, int], None]
