"""An independent generator of calibration recordings, for testing the extraction.

Written from ``docs/recording-format.md`` alone: it imports nothing of timedexec but the
public recording writer (``timedexec.recording.RecordingWriter`` / ``Field``), and
deliberately models the physics *differently* from :mod:`timedexec.sim`, so that an
extractor tuned on the simulator is tested on data it was not built on:

========================  ==========================================  ============================
part                      here                                        timedexec.sim
========================  ==========================================  ============================
joint                     two-mass: PI velocity loop on the motor,    one mass, velocity loop,
                          compliant gear (20-45 Hz resonance), motor  breakaway friction
                          stiction (breakaway 1-5 ms), link damping
reference                 1 ms fine-interpolator steps                continuous ramp
sensor filter             2nd-order digital Butterworth (IIR; its     pure delay
                          DC group delay is the "measured" constant)
noise                     white, Gaussian, after the filter           white, Gaussian
sensor clock              offset + exponential warm-up drift (ppm),   constant ppm
                          integrated phase
USB                       blocks of B samples, gamma jitter, host     exponential jitter
                          stalls, lost and duplicated blocks
state stream              gamma latency, rare lost packages           exponential latency
========================  ==========================================  ============================

Ground truth follows the definitions of ``docs/architecture.md``: the actuation delay is
the instant the link's physical speed reaches 10 % of the commanded speed minus the
instant the commanded ramp reaches that speed after the send; the response delay is the
mean age of the reported state on arrival. The reported position is the link-side angle
(the robot's belief of the physical joint), so the truth is the age of the state, not the
gear's compliance.

Usage (as a library)::

    from independent_sweep import Conditions, write_independent_sweep
    write_independent_sweep("rec.h5", "ur10", 300, Conditions(noise_factor=3), seed=1)
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from timedexec.recording import Field, RecordingWriter

FloatArray = NDArray[np.float64]

#: Simulator default noise density, °/s/√Hz (the "1x" of the benchmark's noise axis).
BASE_NOISE_DPS_RTHZ = 0.005
ONSET_FRACTION = 0.1  # docs/architecture.md: onset at 10 % of the commanded speed

ROBOTS: dict[str, dict[str, Any]] = {
    # period s, pipeline cycles, velocity-loop bandwidth Hz, vendor, extra response cycles
    "ur10": {"period": 0.008, "pipeline": 2, "bw": 25.0, "vendor": "universal_robots", "extra": 0},
    "ur10e": {"period": 0.002, "pipeline": 6, "bw": 30.0, "vendor": "universal_robots", "extra": 0},
    "kr5": {"period": 0.012, "pipeline": 6, "bw": 12.0, "vendor": "kuka", "extra": 1},
}


@dataclass(frozen=True, kw_only=True)
class Conditions:
    """What is hard about a recording.

    Parameters
    ----------
    noise_factor : float
        Gyro white-noise density relative to 0.005 °/s/√Hz.
    clock_offset_ppm : float
        Sensor oscillator error at the start of the sweep, ppm.
    clock_drift_ppm : float
        Warm-up drift over the sweep (exponential, time constant a third of the sweep), ppm.
    block_loss, block_dup : float
        Probability that a USB block is lost / delivered twice.
    dup_trial_fraction : float
        Fraction of trials that get exactly one duplicated block (on top of ``block_dup``).
    sensor_cutoff_hz : float
        Cutoff of the sensor's 2nd-order Butterworth filter (230 Hz: DC group delay about
        0.98 ms at 8 kHz; 80 Hz: about 2.8 ms).
    header_group_delay_s, header_transport_latency_s : float or None
        What the recording header states; None = the true (measured) value. Use
        ``math.nan`` to leave the key out of the header.
    usb_latency_s : float
        Minimum latency of a USB block to the host, s.
    usb_jitter_s : float
        Mean excess latency (gamma, shape 2), s.
    stall_probability : float
        Per block: a host stall delays it (and the following blocks) by 0.5-4 ms.
    package_loss : float
        Probability that a state package is lost (NaN arrival).
    held_up : float
        Fraction of trials in which a stall (3-20 ms, anywhere in the trial: a controller
        or host thread that stopped) holds up the state packages due then; they arrive in a
        burst when it ends (gamma gaps of ~30 µs). Drawn from its own generator: the other
        draws, and so every recording without it, stay as they were.
    controller_stamps : bool
        Write ``state_controller_time_s``: the controller's cycle count times its period on
        its own clock (an origin of 5000-6000 s, 60 ppm slower than the host's), the
        nominal instant of each sample (the true one jitters by 5 µs).
    rate_unit : str
        Unit attribute of ``gyro_raw``: ``"LSB"`` (counts, header sensitivity) only.
    """

    noise_factor: float = 1.0
    clock_offset_ppm: float = 3000.0
    clock_drift_ppm: float = 0.0
    block_loss: float = 0.0
    block_dup: float = 0.0
    dup_trial_fraction: float = 0.0
    sensor_cutoff_hz: float = 230.0
    header_group_delay_s: float | None = None
    header_transport_latency_s: float | None = None
    usb_latency_s: float = 0.0007
    usb_jitter_s: float = 0.0003
    stall_probability: float = 0.002
    package_loss: float = 0.002
    held_up: float = 0.0
    controller_stamps: bool = False
    rate_unit: str = "LSB"


def butter_group_delay_s(cutoff_hz: float, fs_hz: float) -> float:
    """DC group delay of the sensor's 2nd-order digital Butterworth filter, s."""
    b, a = signal.butter(2, cutoff_hz, fs=fs_hz)
    # First moment of the impulse response over its sum = group delay at DC, samples.
    h = signal.lfilter(b, a, np.r_[1.0, np.zeros(20000)])
    return float(np.sum(np.arange(h.size) * h) / np.sum(h)) / fs_hz


def _profile(t: FloatArray, speed: float, accel: float, hold: float, pause: float) -> FloatArray:
    """Commanded speed (>= 0 out, <= 0 back) of the out-and-back trapezoid at time t >= 0."""
    ramp = speed / accel
    pulse = 2 * ramp + hold

    def one(x: FloatArray) -> FloatArray:
        up = np.clip(x, 0, ramp) * accel
        down = np.clip(pulse - x, 0, ramp) * accel
        return np.where((x > 0) & (x < pulse), np.minimum(up, down), 0.0)

    return one(t) - one(t - pulse - pause)


class _Clock:
    """Sensor oscillator: phase(t) = f0·(t - t_origin) + f0·1e-6·∫ppm, host sweep time t."""

    def __init__(self, f0: float, offset_ppm: float, drift_ppm: float, sweep_s: float) -> None:
        self.f0, self.off, self.drift, self.T = f0, offset_ppm, drift_ppm, max(sweep_s, 1.0)
        self.t_origin = -0.37  # sample 0 was taken before the sweep started

    def ppm(self, t: FloatArray) -> FloatArray:
        x = np.asarray(t) / self.T
        return self.off + self.drift * (1 - np.exp(-3 * x)) / (1 - math.exp(-3))

    def phase(self, t: FloatArray) -> FloatArray:
        t = np.asarray(t, dtype=np.float64)
        s = t - self.t_origin
        c = self.drift * self.T / (1 - math.exp(-3))
        integral = self.off * s + c * (t / self.T + (np.exp(-3 * t / self.T) - 1) / 3)
        return self.f0 * s + self.f0 * 1e-6 * integral

    def time_of(self, k: ArrayLike) -> FloatArray:
        """Host sweep time at which sample index k is taken (Newton on the phase)."""
        kf = np.asarray(k, dtype=np.float64)
        t = self.t_origin + kf / self.f0
        for _ in range(4):
            t = t - (self.phase(t) - kf) / (self.f0 * (1 + 1e-6 * self.ppm(t)))
        return t


def joint_params(
    rng: np.random.Generator, n: int, bw_hz: float, prof: dict[str, float]
) -> dict[str, FloatArray]:
    """Per-trial parameters of the two-mass joint (drawn in the order the sweep draws them)."""
    jm, jl = 1.0, rng.uniform(1.0, 2.5, n)
    f_res = rng.uniform(20.0, 45.0, n)
    zeta = rng.uniform(0.08, 0.25, n)
    t_break = rng.uniform(0.001, 0.005, n)
    return {"jm": np.full(n, jm), "jl": jl, "f_res": f_res, "zeta": zeta, "t_break": t_break,
            "bw": np.full(n, bw_hz)}  # fmt: skip


def _joint_physics(
    rng: np.random.Generator,
    t_ref: FloatArray,
    direction: FloatArray,
    grid: FloatArray,
    bw_hz: float,
    prof: dict[str, float],
) -> tuple[FloatArray, FloatArray]:
    """Link speed and angle (n, len(grid)) of a two-mass joint, semi-implicit Euler."""
    par = joint_params(rng, len(t_ref), bw_hz, prof)
    return joint_response(par, t_ref, direction, grid, prof)


def joint_response(
    par: dict[str, FloatArray],
    t_ref: FloatArray,
    direction: FloatArray,
    grid: FloatArray,
    prof: dict[str, float],
) -> tuple[FloatArray, FloatArray]:
    """Link speed and angle (n, len(grid)) of the joints ``par`` (see :func:`joint_params`)
    following the out-and-back profile from ``t_ref``, semi-implicit Euler on ``grid``."""
    n = len(t_ref)
    dt = float(grid[1] - grid[0])
    jm, jl, bw_hz = par["jm"], par["jl"], par["bw"]
    kp = jm * 2 * np.pi * bw_hz * (1 + jl / jm) * 0.5
    ki = kp * 2 * np.pi * bw_hz / 5
    k_s = jl * (2 * np.pi * par["f_res"]) ** 2
    c_s = 2 * par["zeta"] * np.sqrt(k_s * jl)
    f_static = kp * prof["acceleration_rad_s2"] * par["t_break"]
    f_kin = 0.6 * f_static
    b_link = 0.02 * jl
    fine = 0.001  # the drive's fine interpolator period, s
    wm = np.zeros(n)
    qm = np.zeros(n)
    wl = np.zeros(n)
    ql = np.zeros(n)
    integ = np.zeros(n)
    stuck = np.ones(n, dtype=bool)
    out_w = np.zeros((n, grid.size))
    out_q = np.zeros((n, grid.size))  # link angle from 0 at the grid's start
    start = int(np.searchsorted(grid, t_ref.min() - 0.002))
    for i in range(start, grid.size):
        x = grid[i] - t_ref
        x = np.where(x > 0, np.ceil(x / fine) * fine, x)
        ref = direction * _profile(x, prof["speed_rad_s"], prof["acceleration_rad_s2"],
                                   prof["hold_s"], prof["pause_s"])  # fmt: skip
        err = ref - wm
        integ += err * dt
        u = kp * err + ki * integ
        spring = k_s * (qm - ql) + c_s * (wm - wl)
        drive = u - spring
        breaks = stuck & (np.abs(drive) > f_static)
        stuck = stuck & ~breaks
        fric = np.where(stuck, 0.0, f_kin * np.sign(np.where(wm != 0, wm, drive)))
        acc_m = np.where(stuck, 0.0, (drive - fric) / jm)
        wm_new = wm + acc_m * dt
        # Kinetic friction cannot reverse the motion: stop (and stick) at zero crossings.
        crossing = ~stuck & (np.sign(wm_new) != np.sign(wm)) & (wm != 0)
        stick_again = crossing & (np.abs(drive) <= f_static)
        wm = np.where(stick_again, 0.0, wm_new)
        stuck = stuck | stick_again
        qm = qm + wm * dt
        acc_l = (spring - b_link * wl) / jl
        wl = wl + acc_l * dt
        ql = ql + wl * dt
        out_w[:, i] = wl
    # The link angle as the integral of the link speed the gyro sees (trapezoid between grid
    # points). The Euler state ``ql`` runs half a step (31 µs) ahead of ``wl``: reported
    # as the position it made every reported state look 31 µs younger than its true age.
    out_q[:, 1:] = np.cumsum(0.5 * (out_w[:, 1:] + out_w[:, :-1]), axis=1) * dt
    return out_w, out_q


def _interp_uniform(values: FloatArray, t0: float, dt: float, t: FloatArray) -> FloatArray:
    """Row-wise linear interpolation of values (n, G) on a uniform grid at times t (n, m)."""
    pos = (t - t0) / dt
    g = values.shape[1]
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, g - 2)
    frac = np.clip(pos - i0, 0.0, 1.0)
    lo = np.take_along_axis(values, i0, axis=1)
    hi = np.take_along_axis(values, i0 + 1, axis=1)
    return lo + frac * (hi - lo)


def _usb(
    rng: np.random.Generator,
    first_index: int,
    sample_t: FloatArray,
    block: int,
    cond: Conditions,
    force_dup: bool,
) -> tuple[NDArray[np.int64], FloatArray]:
    """Rows as received: (position in the generated run, arrival time), loss and duplicates
    applied to whole USB blocks (blocks aligned to multiples of ``block`` in the index)."""
    m = sample_t.size
    lead = (-first_index) % block  # samples before the first full block boundary
    bounds = np.r_[0, np.arange(lead, m, block), m]
    bounds = np.unique(bounds)
    starts, ends = bounds[:-1], bounds[1:]
    nb = starts.size
    last_t = sample_t[ends - 1]
    jitter = rng.gamma(2.0, cond.usb_jitter_s / 2.0, nb)
    stall = np.where(rng.random(nb) < cond.stall_probability, rng.uniform(5e-4, 4e-3, nb), 0.0)
    arrival = np.maximum.accumulate(last_t + cond.usb_latency_s + jitter + stall)
    copies = np.ones(nb, dtype=np.int64)
    copies[rng.random(nb) < cond.block_loss] = 0
    copies[(rng.random(nb) < cond.block_dup) & (copies == 1)] = 2
    if force_dup:
        b = int(rng.integers(nb // 8, nb - 1))
        copies[b] = 2 if copies[b] else 1
    rows: list[NDArray[np.int64]] = []
    times: list[FloatArray] = []
    for blk in np.flatnonzero(copies).tolist():
        for c in range(int(copies[blk])):
            rows.append(np.arange(starts[blk], ends[blk]))
            # The copy arrives with the next transfer, 0.1-1 ms later.
            times.append(
                np.full(ends[blk] - starts[blk], arrival[blk] + c * rng.uniform(1e-4, 1e-3))
            )
    r = np.concatenate(rows)
    t = np.concatenate(times)
    order = np.argsort(t, kind="stable")
    return r[order], t[order]


def write_independent_sweep(
    path: str | Path,
    robot: str,
    n_trials: int,
    cond: Conditions | None = None,
    *,
    seed: int = 0,
    still_s: float = 5.0,
) -> Path:
    """Write a recording of ``n_trials`` trials in the documented format.

    Parameters
    ----------
    path : path
        New HDF5 file.
    robot : {"ur10", "ur10e", "kr5"}
        Controller timing and loop bandwidth (see :data:`ROBOTS`).
    n_trials : int
        Trials.
    cond : Conditions
        Noise, clock, USB and header conditions.
    seed : int
        Seed of every random draw.
    still_s : float
        Stationary recording before the sweep, s.

    Returns
    -------
    Path
        ``path``.
    """
    cond = cond or Conditions()
    rng = np.random.default_rng([seed, 0x1D3])
    r = ROBOTS[robot]
    period = float(r["period"])
    fs = 8000.0
    block = 8
    lsb = 65.5  # ±500 °/s: 32768/500 = 65.536 nominal; the datasheet's 65.5 is what is set
    prof = {"speed_rad_s": 0.4, "acceleration_rad_s2": 8.0, "hold_s": 0.05, "pause_s": 0.15,
            "pre_s": 0.05, "record_s": 0.65}  # fmt: skip
    n_pk = math.floor(prof["record_s"] / period)
    n_g = round((prof["pre_s"] + prof["record_s"]) * fs)
    n_g -= n_g % block
    n_b = n_g // block
    group_delay = butter_group_delay_s(cond.sensor_cutoff_hz, fs)
    b_f, a_f = signal.butter(2, cond.sensor_cutoff_hz, fs=fs)

    # Sweep layout: still recording, then trials every ~1.1 s (+ moves between configurations).
    joints = np.array([1, 2, 3, 5])
    joint = joints[rng.integers(0, 4, n_trials)]
    direction = rng.choice([-1, 1], n_trials)
    config = np.arange(n_trials) // 8
    q_cfg = rng.uniform(-2.0, 2.0, (config.max() + 1, 6))
    q_cfg[:, 5] = 0.0
    q_start = q_cfg[config]
    step = 1.0 + rng.uniform(0, period, n_trials) + np.where(np.arange(n_trials) % 8 == 0, 0.4, 0)
    t0 = still_s + 0.5 + np.cumsum(step) - step[0]
    clock = _Clock(fs, cond.clock_offset_ppm, cond.clock_drift_ppm, float(t0[-1] + 1.0))
    sigma_lsb = BASE_NOISE_DPS_RTHZ * cond.noise_factor * math.sqrt(fs / 2) * lsb
    bias_dps = rng.uniform(-3, 3, 3)
    bias_drift = rng.uniform(-0.2, 0.2, 3) / 3600  # °/s per s
    scale = 1 + rng.uniform(-0.03, 0.03, 3)
    counter0 = int(rng.integers(0, 65536))

    def sensor_counts(true_dps: FloatArray, t_host: FloatArray) -> NDArray[np.int16]:
        """(…, m, 3) true °/s after the filter -> int16 counts with bias, scale, noise."""
        x = true_dps * scale + bias_dps + bias_drift * t_host[..., None]
        x = x * lsb + rng.standard_normal(x.shape) * sigma_lsb
        return np.clip(np.rint(x), -32768, 32767).astype(np.int16)

    # ---- still recording ------------------------------------------------------------------
    k_lo = int(np.ceil(clock.phase(np.array(0.0))))
    m_still = int(still_s * fs)
    k_still = k_lo + np.arange(m_still)
    t_still = clock.time_of(k_still)
    rows_s, arr_s = _usb(rng, k_lo, t_still, block, cond, False)
    rows_s = rows_s[: len(rows_s) - len(rows_s) % block]
    arr_s = arr_s[: len(rows_s)]
    still_raw = sensor_counts(np.zeros((m_still, 3)), t_still)[rows_s]
    still_counter = ((counter0 + k_still[rows_s]) % 65536).astype(np.uint16)
    still_blocks = arr_s[block - 1 :: block]

    # ---- controller and command timing ------------------------------------------------------
    pack = rng.uniform(0.02 * period, 0.97 * period, n_trials) + r["extra"] * period
    lat = 0.0003 + rng.gamma(2.0, 0.0001, (n_trials, n_pk))
    s0 = -(pack + lat[:, 0])
    jit = rng.normal(0, 5e-6, (n_trials, n_pk))
    jit[:, 0] = 0
    sample_t = s0[:, None] + np.arange(n_pk) * period + jit
    arrival = sample_t + pack[:, None] + lat
    arrival[:, 0] = 0.0
    arrival[:, 1:][rng.random((n_trials, n_pk - 1)) < cond.package_loss] = np.nan
    stall_rng = np.random.default_rng([seed, 17])  # draws the others do not see
    for i in np.flatnonzero(stall_rng.random(n_trials) < cond.held_up):
        start = stall_rng.uniform(0.0, sample_t[i, -1])
        end = start + stall_rng.uniform(0.003, 0.02)
        held = np.flatnonzero((arrival[i] > start) & (arrival[i] < end))
        arrival[i, held] = end + np.cumsum(stall_rng.gamma(2.0, 1.5e-5, held.size))
        got = np.isfinite(arrival[i])
        arrival[i, got] = np.maximum.accumulate(arrival[i, got])  # a stream keeps its order
    t_send = 0.00015 + rng.exponential(2e-5, n_trials)
    at_ctrl = t_send + 0.00025 + rng.gamma(2.0, 5e-5, n_trials)
    intake = s0 + np.ceil((at_ctrl - s0) / period) * period
    drive_offset = np.array([0.0, 0.0008, 0.0004, 0.0, 0.0012, 0.0])[joint - 1]
    t_ref = intake + r["pipeline"] * period + drive_offset

    # ---- physics on a 16 kHz trial-time grid --------------------------------------------------
    dt_p = 1.0 / 16000
    n_grid = round((prof["pre_s"] + prof["record_s"] + 0.03) / dt_p)
    grid: FloatArray = -prof["pre_s"] - 0.01 + np.arange(n_grid, dtype=np.float64) * dt_p
    w_link, q_link = _joint_physics(rng, t_ref, direction.astype(float), grid, r["bw"], prof)
    level = ONSET_FRACTION * prof["speed_rad_s"]
    v_dir = w_link * direction[:, None]
    above = (v_dir >= level) & (grid > 0)
    k = np.argmax(above, axis=1)
    ii = np.arange(n_trials)
    v0, v1 = v_dir[ii, k - 1], v_dir[ii, k]
    onset = grid[k - 1] + (level - v0) / (v1 - v0) * dt_p
    true_act = onset - (t_send + level / prof["acceleration_rad_s2"])
    true_resp = np.nanmean(np.where(np.isfinite(arrival), arrival - sample_t, np.nan), axis=1)
    q_rep_j = q_start[ii, joint - 1][:, None] + _interp_uniform(q_link, grid[0], dt_p, sample_t)
    w_rep_j = _interp_uniform(w_link, grid[0], dt_p, sample_t)
    if r["vendor"] == "kuka":
        w_rep_j = np.diff(q_rep_j, axis=1, prepend=q_rep_j[:, :1]) / period
    state_q = np.repeat(q_start[:, None, :], n_pk, axis=1)
    state_q[ii, :, joint - 1] = q_rep_j
    state_qd = np.zeros_like(state_q)
    state_qd[ii, :, joint - 1] = w_rep_j
    lost = ~np.isfinite(arrival)  # a lost package: nothing of it is recorded
    state_q[lost] = np.nan
    state_qd[lost] = np.nan
    boot = 5000.0 + stall_rng.uniform(0.0, 1000.0)
    stamps = boot + (np.round((t0 + s0) / period)[:, None] + np.arange(n_pk)) * period / (
        1.0 + 60e-6
    )
    stamps[lost] = np.nan

    # ---- gyro per trial -----------------------------------------------------------------------
    axis = rng.normal(size=(n_trials, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    dup_trials = rng.random(n_trials) < cond.dup_trial_fraction
    margin = 400 + int(n_g * 6 * (cond.block_loss + 0.002))
    gyro_raw = np.empty((n_trials, n_g, 3), np.int16)
    gyro_counter = np.empty((n_trials, n_g), np.uint16)
    gyro_blocks = np.empty((n_trials, n_b), np.float32)
    filt_warm = 200  # samples before the window so the filter starts in steady state
    for i in range(n_trials):
        k_first = int(np.ceil(clock.phase(np.array(t0[i] - prof["pre_s"]))))
        k_all = k_first - filt_warm + np.arange(n_g + margin + filt_warm)
        t_host = clock.time_of(k_all)
        t_trial = t_host - t0[i]
        w = np.interp(t_trial, grid, w_link[i], left=0.0, right=0.0)
        true_dps = np.degrees(signal.lfilter(b_f, a_f, w))[:, None] * axis[i]
        counts = sensor_counts(true_dps, t_host)
        rows, arr = _usb(rng, int(k_all[0]), t_host, block, cond, bool(dup_trials[i]))
        sel = rows[k_all[rows] >= k_first][:n_g]
        arr = arr[k_all[rows] >= k_first][:n_g]
        if sel.size < n_g:
            raise RuntimeError("margin too small for the block loss; raise it")
        gyro_raw[i] = counts[sel]
        gyro_counter[i] = (counter0 + k_all[sel]) % 65536
        gyro_blocks[i] = arr[block - 1 :: block] - t0[i]

    header_gd = group_delay if cond.header_group_delay_s is None else cond.header_group_delay_s
    header_tl = (
        cond.usb_latency_s
        if cond.header_transport_latency_s is None
        else cond.header_transport_latency_s
    )
    gyro_hdr: dict[str, Any] = {
        "full_scale_dps": 500,
        "nominal_rate_hz": fs,
        "block_samples": block,
        "lsb_per_dps": lsb,
    }
    if not math.isnan(header_gd):
        gyro_hdr["group_delay_s"] = header_gd
    if not math.isnan(header_tl):
        gyro_hdr["transport_latency_s"] = header_tl
    header = {
        "source": "independent_sweep (tests/independent_sweep.py)",
        "robot": {"name": robot, "vendor": r["vendor"]},
        "profile": prof,
        "controller_period_s": period,
        "gyro": gyro_hdr,
        "conditions": json.loads(json.dumps(dataclasses.asdict(cond))),
        "truth": {"group_delay_s": group_delay, "seed": seed},
    }
    fields = [
        Field("trial", (), "int64", "", "plan index"),
        Field("t0_s", (), "float64", "s", "host sweep time of trial time 0"),
        Field("cmd_send_time_s", (), "float64", "s", "command send time, trial time"),
        Field("cmd_qd_rad_s", (6,), "float64", "rad/s", "commanded joint speeds"),
        Field("state_host_time_s", (n_pk,), "float64", "s", "package arrival, trial time"),
        Field("state_q_rad", (n_pk, 6), "float32", "rad", "reported joint positions"),
        Field("state_qd_rad_s", (n_pk, 6), "float32", "rad/s", "reported joint speeds"),
        Field("gyro_raw", (n_g, 3), "int16", cond.rate_unit, "gyro counts"),
        Field("gyro_counter", (n_g,), "uint16", "", "sample counter"),
        Field("gyro_block_host_time_s", (n_b,), "float32", "s", "block arrival, trial time"),
        Field("true_actuation_delay_s", (), "float64", "s", "ground truth"),
        Field("true_response_delay_s", (), "float64", "s", "ground truth"),
    ]
    stamped = {"state_controller_time_s": stamps} if cond.controller_stamps else {}
    if stamped:
        fields.append(
            Field("state_controller_time_s", (n_pk,), "float64", "s", "controller time stamp")
        )
    path = Path(path)
    with RecordingWriter(path, header=header, fields=fields, fsync=False) as w:
        w.write_static("plan_q_start_rad", q_start, unit="rad")
        w.write_static("plan_joint", joint.astype(np.int64))
        w.write_static("plan_direction", direction.astype(np.int64))
        w.write_static("still_gyro_raw", still_raw, unit=cond.rate_unit)
        w.write_static("still_gyro_counter", still_counter)
        w.write_static("still_gyro_block_host_time_s", still_blocks, unit="s")
        w.append({
            "trial": np.arange(n_trials, dtype=np.int64),
            "t0_s": t0,
            "cmd_send_time_s": t_send,
            "cmd_qd_rad_s": np.where(np.arange(6) == (joint - 1)[:, None],
                                     direction[:, None] * prof["speed_rad_s"], 0.0),
            "state_host_time_s": arrival,
            "state_q_rad": state_q.astype(np.float32),
            "state_qd_rad_s": state_qd.astype(np.float32),
            "gyro_raw": gyro_raw,
            "gyro_counter": gyro_counter,
            "gyro_block_host_time_s": gyro_blocks,
            "true_actuation_delay_s": true_act,
            "true_response_delay_s": true_resp,
            **stamped,
        })  # fmt: skip
    return path
