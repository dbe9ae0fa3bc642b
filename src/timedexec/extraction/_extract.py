"""Delay extraction from a recording: gyro time base, filtering, onset and response timing.

Definitions (shared with the simulator's ground truth, :mod:`timedexec._signal`):

* **actuation delay** = the instant the physical joint speed reaches ``ONSET_FRACTION`` of the
  commanded speed, minus the instant the commanded ramp reaches the same speed after the
  command was sent;
* **response delay** = the age of the reported state on arrival: the time shift that best
  aligns the reported joint position with the physical one, and on a joint whose reported
  angle is a motor-side encoder's, the age of the motor's sample, the gear's deflection
  separated (``docs/architecture.md``).

Steps, vectorised across the trials of a chunk (``docs/recording-format.md`` states what
each step assumes of the recording):

1. **Contract.** Required fields, statics and header keys, units converted to SI
   (:mod:`._check`); the sensor's group delay and transport latency must be stated.
2. **Lossy stream.** Each trial's counter gives every frame's sample position
   (:func:`timedexec.sensors.relative_counter_rows`): duplicated and backward frames are
   dropped, lost samples leave gaps on a regular grid (filled by interpolation for the
   filters, weighted out of the fits, and counted).
3. **Gyro time base.** Counters are unwrapped across the sweep (the host time between
   trials fixes the number of wraps); the sensor clock is fitted per session as blended
   lower envelopes of the block arrivals, quadratic per window so that they follow the
   oscillator's drift, the window length chosen from the data, each stamp dated at the end
   of the device transfer that delivered it when the stamps show fixed transfers
   (:func:`timedexec.sensors.fit_clock_drifting`); the transport latency and the filter
   group delay are subtracted.
4. **Rates.** Zero-rate from the pre-command samples of the trial and its neighbours in
   time (the bias drifts slowly; pooling ~31 trials makes its error negligible; a trial off
   its neighbours' median keeps its own; a chunk reads its neighbours' first samples too,
   so the stream is read once), projection on the principal axis of the motion, gain
   calibrated so that the integrated gyro angle of the out pulse equals the reported joint
   displacement; per-trial noise σ from the data.
5. **Actuation** (method ``fit``): a coarse crossing from the low-pass filtered speed (the
   last sample below the level before the speed passes half the commanded speed), refined
   by a cubic least-squares fit in a window chosen per trial by Lepski's method, with its
   Cramér-Rao bound and a standard error (:mod:`._onset`). ``extrema`` (published): the
   time between the commanded and the measured speed maxima.
6. **Response** (method ``fit``): the shift of the integrated gyro angle onto the reported
   positions, each dated by its controller stamp (:mod:`._dating`: held-up packages and
   network jitter stay out of the fit; the mean lateness at arrival is added), fitted on
   increments between packages (the generalised least squares of a random-walk angle
   error), with a standard error; where a joint's trials show a gear's
   deflection (a motor-side encoder leads the link), the deflection is fitted with it as
   a function of the link acceleration (each trial's correction shrunk towards its joint's),
   and the standard error counts the gear law's uncertainty (:mod:`._response`). ``extrema``: the time between the
   measured and the reported speed maxima.
7. **Flags.** Trials that cannot be measured get a reason in the ``flag`` column and NaN
   delays: ``no_baseline``, ``clipped``, ``gyro_gap`` (lost samples cover what the estimate
   needs), ``package_gap``, ``no_motion``, ``no_onset``, ``gain`` (implausible gyro gain),
   ``response_fit``, ``uncertain`` (standard error above ``max_se_s``), ``damaged`` (the
   trial's rows lie in a chunk of the file that fails its checksum: the rest is extracted),
   ``bad_time`` (its ``t0_s`` or ``cmd_send_time_s`` is not finite: the trial is left out
   of every sweep-wide statistic, the others are extracted as if it were not there).
   A trial whose response delay alone cannot be trusted keeps both delays and a reason in
   ``response_flag``: ``deflection`` (its age depends on the unknown gear law by more than
   ``RESPONSE_GEAR_TOLERANCE_S``), ``deflection_joint`` (its joint's shared age does: the
   lag there is mostly the gear's play, ``DEFLECTION_PLAY_SHARE``), ``deflection_noise``
   (the gyro's noise pulled its joint's age with the deflection terms short by more than
   ``RESPONSE_NOISE_TOLERANCE_S``).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from timedexec._progress import Progress
from timedexec._signal import ONSET_FRACTION
from timedexec._types import FloatArray
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, RecordingError
from timedexec.extraction._check import OPTIONAL_FIELDS, REQUIRED_FIELDS
from timedexec.extraction._context import (
    SweepContext,
    open_rows,
    sweep_context,
)
from timedexec.extraction._dating import dated_by_controller
from timedexec.extraction._excluded import bad_time_rows, lost_trials
from timedexec.extraction._onset import (
    ONSET_WINDOWS_S,
    _parabolic_peak,
    _robust_sigma,
    _row_nanmedian,
    onset_adaptive,
)
from timedexec.extraction._response import (
    RESPONSE_FLAG_DEFLECTION,
    RESPONSE_FLAG_DEFLECTION_JOINT,
    RESPONSE_FLAG_DEFLECTION_NOISE,
    RESPONSE_SMOOTH_S,
    response_delay,
)
from timedexec.extraction._stationary import StillAnalysis
from timedexec.recording import DamagedChunkError, RecordingReader, damage_note
from timedexec.sensors import (
    relative_counter_rows,
)

__all__ = ["METHODS", "ExtractionResult", "extract_recording"]

METHODS = ("fit", "extrema")
#: Trials pooled (centred, same session) for the zero-rate: 31 trials span ~40 s, over which
#: an MPU-class bias drifts by < 0.01 °/s, while the pooled mean's noise falls 5.6x.
_BIAS_POOL = 31
#: Samples at the start of each window that lie before the command (pre_s is >= 0.05 s; the
#: first 40 ms are used so that a late clock or a slow USB block cannot reach the command).
_PRE_S = 0.04
#: When the reported position enters the first gain estimate: this long after the sensor
#: time the gyro angle ends, s (a typical response delay; the fit method then matches it
#: to the trial's measured response delay).
_GAIN_REPORT_S = 0.03
#: Timing error of an actuation delay outside its onset fit (the sensor clock fit, the send
#: stamp, the window choice), added in quadrature to its standard error, s. Measured on the
#: simulator's sweeps (300 trials per robot): without it the 95 % intervals covered 89 / 93
#: / 86 % (UR10 / KR 5 / UR10e), with 0.05 ms 96 / 95 / 92 %. Checked on the independent
#: generator's recordings (benchmarks/bench_extract_robustness.py, 300 trials each): clean,
#: clock, lossy, measured-constants and 2-10x noise conditions 87.3-94.0 % before, 91.7-96.0 %
#: with it (20x noise: 78.8 % either way, the onset's threshold region).
ACTUATION_SE_FLOOR_S = 5e-5
#: A trial is flagged "uncertain" when a delay's standard error exceeds this, s.
MAX_SE_S = 0.002
#: Lost samples that make a trial unmeasurable: over 30 % of the onset window, or over 20 %
#: of the out pulse (the gain and the response integrate it).
_MAX_MISSING_ONSET = 0.3
_MAX_MISSING_PULSE = 0.2
#: Plausible gyro gains (gyro angle over reported displacement); outside: flag ``gain``.
_GAIN_RANGE = (0.8, 1.25)
#: Every so many samples enter the covariance that finds the principal axis of the motion.
_COV_STRIDE = 4
#: Samples between the points at which the sensor clock model is evaluated for each row;
#: linear in between (the model's curvature makes that exact to < 1 ns).
_CLOCK_NODE_STEP = 64


@dataclass(frozen=True)
class ExtractionResult:
    """The delay table and what the extraction learnt about the sweep."""

    table: DelayTable
    cutoff_hz: float
    clock_rate_hz: float
    clock_rate_error_ppm: float
    still: StillAnalysis
    n_flagged: int
    clock: dict[str, Any] | None = None
    #: Rows (trials) in chunks that fail their checksum: left out of the extraction, in
    #: the table flagged ``damaged`` when their plan index can still be read.
    damaged_rows: int = 0

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        response_flags = self.table.reason_counts("response_flag")
        out = {
            "trials": len(self.table),
            "flagged": self.n_flagged,
            "flags": self.table.reason_counts("flag"),
            "response_flagged": sum(response_flags.values()),
            "response_flags": response_flags,
            "filter_cutoff_hz": self.cutoff_hz,
            "gyro_rate_hz": self.clock_rate_hz,
            "gyro_rate_error_ppm": self.clock_rate_error_ppm,
            "gyro_noise_density_dps_rthz": (
                np.rad2deg(self.still.noise_density_rad_s_rthz).round(5).tolist()
            ),
        }
        if self.clock is not None:
            out["gyro_clock"] = self.clock
        if self.damaged_rows:
            out["damaged_rows"] = self.damaged_rows
        for name in ("actuation_delay_se", "response_delay_se"):
            if name in self.table:
                v = self.table[name]
                v = v[np.isfinite(v)]
                out[f"{name}_median_ms"] = float(np.median(v) * 1e3) if v.size else None
        return out


def _pre_stats(
    counter: NDArray[Any], raw: NDArray[Any], m_pre: int, rate_scale: float
) -> tuple[FloatArray, FloatArray]:
    """Sum (rad/s, sensor axes) and count of each row's kept samples among its first
    ``m_pre`` sample positions (the zero-rate samples before the command)."""
    c16 = (
        counter
        if counter.dtype == np.uint16
        else (counter.astype(np.int64) % 65536).astype(np.uint16)
    )
    clean = np.all(np.diff(c16, axis=1) == 1, axis=1)
    pre = np.ones((len(counter), m_pre), dtype=bool)
    dirty = np.flatnonzero(~clean)
    if dirty.size:  # lost, duplicated or out-of-order frames: positions from the counter
        pos, keep = relative_counter_rows(counter[dirty])
        pre[dirty] = keep[:, :m_pre] & (pos[:, :m_pre] < m_pre)
    first = np.asarray(raw[:, :m_pre], dtype=np.float64)
    pre_sum = np.einsum("nm,nma->na", pre.astype(np.float64), first) * rate_scale
    return pre_sum, pre.sum(axis=1).astype(np.float64)


def _pool_bias(
    pre_sum: FloatArray, pre_n: FloatArray, nbr: NDArray[np.intp], valid: NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray]:
    """Zero-rate of each row from the pre-command samples of its neighbours in time.

    ``nbr`` (k, w) indexes the rows of ``pre_sum``/``pre_n`` around each row in time order
    (same session; its own row in the middle column), ``valid`` marks the real ones (a
    session's ends). A neighbour is pooled when its own zero-rate lies within 8 MAD of the
    window's median (a row taken while the arm moved or was knocked does not); a row that
    is itself off its window's median keeps its own zero-rate.
    """
    bias = pre_sum / np.maximum(pre_n, 1)[:, None]
    b = bias[nbr]  # (k, w, 3)
    ok = valid & (pre_n[nbr] > 0)
    bw = np.where(ok[..., None], b, np.nan)
    k, w, _ = b.shape
    flat = np.moveaxis(bw, 1, 2).reshape(k * 3, w)
    med = _row_nanmedian(flat).reshape(k, 3)
    dev = np.abs(b - med[:, None, :])
    mad = _row_nanmedian(np.moveaxis(np.where(ok[..., None], dev, np.nan), 1, 2).reshape(k * 3, w))
    mad = mad.reshape(k, 3) + 1e-12
    good = ok & np.all(dev < 8 * 1.4826 * mad[:, None, :] + 1e-9, axis=2)
    n_pool = np.sum(np.where(good, pre_n[nbr], 0.0), axis=1)
    pooled = np.sum(np.where(good[..., None], pre_sum[nbr], 0.0), axis=1)
    pooled /= np.maximum(n_pool, 1)[:, None]
    centre = nbr[:, w // 2]
    use = good[:, w // 2] & (n_pool > 0) & (np.sum(valid, axis=1) >= 3)
    out = np.where(use[:, None], pooled, bias[centre])
    out_n = np.where(use, n_pool, pre_n[centre])
    return out, out_n


def _grid(
    raw: NDArray[Any], counters: NDArray[Any]
) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """Gyro samples on each row's regular grid of sample positions 0..g-1.

    Returns the samples (lost ones interpolated from their neighbours), which grid
    positions were received, and which rows were clean (no loss, no duplicate)."""
    pos, keep = relative_counter_rows(counters)
    n, g = pos.shape
    out = np.asarray(raw, dtype=np.float64)
    have = np.ones((n, g), dtype=bool)
    clean = np.all(keep, axis=1) & (pos[:, -1] == g - 1)
    bad = np.flatnonzero(~clean)
    if bad.size == 0:
        return out, have, clean
    out = out.copy()
    for i in bad:  # few rows: a scatter and an interpolation each
        k = keep[i] & (pos[i] < g)
        p = pos[i][k]
        have[i] = False
        have[i, p] = True
        vals = out[i][k].copy()
        grid = np.arange(g)
        for a in range(out.shape[2]):
            out[i, :, a] = np.interp(grid, p, vals[:, a]) if p.size else 0.0
    return out, have, clean


def _sample_times(
    ctx: SweepContext, rows: NDArray[np.int64], t0: FloatArray, g: int, session: NDArray[np.int64]
) -> FloatArray:
    """Trial time of every grid position's sample (the physical instant it describes).

    The clock model (blended lines, windows of >= 4 s) bends by well under a nanosecond
    over _CLOCK_NODE_STEP samples, so it is evaluated every so many samples of a row and
    interpolated linearly in between (the full evaluation costs 10x more)."""
    nodes = np.r_[np.arange(0, g - 1, _CLOCK_NODE_STEP), g - 1].astype(np.float64)
    n_idx = ctx.n_first[rows][:, None] + nodes
    host = np.empty_like(n_idx)
    for sess in np.unique(session):
        m = session == sess
        host[m] = ctx.clocks[int(sess)].to_host_time(n_idx[m])
    host -= (ctx.contract.latency_s + t0)[:, None]
    # Segment m covers samples m·step .. m·step + step - 1 (the last one ends before
    # g - 1, the last node): broadcast each segment's start and slope over its samples.
    step = _CLOCK_NODE_STEP
    m = nodes.size - 1
    slope = np.diff(host, axis=1) / np.diff(nodes)
    seg = host[:, :-1, None] + slope[:, :, None] * np.arange(step, dtype=np.float64)
    out: FloatArray = np.empty((len(rows), g))
    out[:, : g - 1] = seg.reshape(len(rows), m * step)[:, : g - 1]
    out[:, g - 1] = host[:, -1]
    return out


def _span(t_g: FloatArray, lo: FloatArray | None, hi: FloatArray | None) -> slice:
    """Columns that hold, in every row, the samples between times ``lo`` and ``hi`` (per
    row; None: unbounded), with a margin of two samples. A row's sample times are a
    line to well under a sample (the sensor clock's curvature), so the line finds them."""
    g = t_g.shape[1]
    first = t_g[:, 0]
    step = (t_g[:, -1] - first) / (g - 1)
    a = 0 if lo is None else int(np.floor(np.nanmin((lo - first) / step))) - 2
    b = g if hi is None else int(np.ceil(np.nanmax((hi - first) / step))) + 3
    return slice(int(np.clip(a, 0, g)), int(np.clip(b, 0, g)))


def _filter_cols(y: FloatArray, taps: FloatArray, cols: slice) -> FloatArray:
    """``y`` low-pass filtered with the symmetric FIR ``taps`` (zero phase, zeros beyond
    the row's ends), on the columns ``cols`` only: the same values as filtering whole
    rows, from the columns the taps reach."""
    g = y.shape[1]
    reach = taps.size // 2
    lo, hi = cols.start, cols.stop
    if hi <= lo:
        return np.zeros((y.shape[0], 0))
    a, b = max(lo - reach, 0), min(hi + reach, g)
    part = signal.oaconvolve(y[:, a:b], taps[None, :], mode="same", axes=1)
    return np.asarray(part[:, lo - a : hi - a])


def _extract_chunk_inner(
    ctx: SweepContext,
    chunk: dict[str, NDArray[Any]],
    rows: NDArray[np.int64],
    method: str,
    traces: bool = False,
    max_se_s: float = MAX_SE_S,
) -> dict[str, NDArray[Any]]:
    n = len(rows)
    con = ctx.contract
    prof = ctx.profile
    t0 = chunk["t0_s"]
    t_send = chunk["cmd_send_time_s"]
    cmd = chunk["cmd_qd_rad_s"]
    joint = np.argmax(np.abs(cmd), axis=1)
    speed = np.abs(cmd[np.arange(n), joint])
    direction = np.sign(cmd[np.arange(n), joint])
    accel = prof["acceleration_rad_s2"]
    pulse = 2 * prof["speed_rad_s"] / accel + prof["hold_s"]
    flag = np.full(n, "", dtype=object)
    resp_flag = np.full(n, "", dtype=object)

    session = chunk["session"] if "session" in chunk else np.zeros(n, np.int64)
    raw = chunk["gyro_raw"]
    clipped = (
        np.any((raw >= 32767) | (raw <= -32767), axis=(1, 2))
        if raw.dtype.kind == "i"
        else (np.zeros(n, bool))
    )
    rates, have, _ = _grid(raw, chunk["gyro_counter"])  # as stored (counts or a rate unit)
    g = rates.shape[1]
    t_g = _sample_times(ctx, rows, t0, g, session)
    scale = con.scale["gyro_raw"]  # stored unit -> rad/s
    bias = chunk["bias"]  # (n, 3) pooled zero-rate, rad/s, sensor axes
    # The masks and sums below cover only the columns some row needs (t_g rises with the
    # column; _span finds the columns of a time interval in every row).
    s_pre = _span(t_g, None, t_send)
    pre = have[:, s_pre] & (t_g[:, s_pre] < t_send[:, None])
    # Principal axis of the motion (after the command): covariance of scale·r - bias from
    # the raw moments, on every _COV_STRIDE-th sample (the motion dwarfs the noise).
    s_cov = slice(_span(t_g, t_send, None).start, g, _COV_STRIDE)
    w_cov = ((t_g[:, s_cov] > t_send[:, None]) & have[:, s_cov]).astype(np.float64)
    r_cov = rates[:, s_cov]
    m2 = np.einsum("nga,ngb->nab", r_cov * w_cov[:, :, None], r_cov, optimize=True)
    m1 = np.einsum("nga,ng->na", r_cov, w_cov)
    cross = m1[:, :, None] * bias[:, None, :]
    cov = scale**2 * m2 - scale * (cross + cross.transpose(0, 2, 1))
    cov += w_cov.sum(axis=1)[:, None, None] * bias[:, :, None] * bias[:, None, :]
    _, vecs = np.linalg.eigh(cov)
    axis = vecs[:, :, -1]
    y = np.matmul(rates, axis[:, :, None])[:, :, 0]
    y *= scale
    y -= np.sum(bias * axis, axis=1)[:, None]  # speed along the axis, rad/s
    # The sensor's true sample spacing (its clock runs off nominal by up to ~1 %).
    dt = (t_g[:, -1] - t_g[:, 0]) / (g - 1)
    out_end = t_send + pulse + 0.12
    s_out = _span(t_g, t_send, out_end)
    in_out = (t_g[:, s_out] > t_send[:, None]) & (t_g[:, s_out] < out_end[:, None])
    sign = np.sign(np.sum(y[:, s_out] * in_out, axis=1))
    sign[sign == 0] = 1.0
    y *= sign[:, None]  # now positive in the out pulse: speed along the commanded direction

    # Reported state of the actuated joint.
    host = chunk["state_host_time_s"]
    q_rep = chunk["state_q_rad"][np.arange(n), :, joint].astype(np.float64)
    qd_rep = chunk["state_qd_rad_s"][np.arange(n), :, joint].astype(np.float64)
    # Lost or late packages: a trial is only unmeasurable when most packages are missing
    # or a long silence (> max(3 periods, 25 ms)) falls inside the out pulse.
    present = np.isfinite(host) & np.isfinite(q_rep)
    arrived = np.where(present, host, np.inf)
    order = np.sort(arrived, axis=1)
    gaps = np.diff(order, axis=1)
    gap_mid = order[:, :-1] + 0.5 * gaps
    in_pulse_window = (gap_mid > t_send[:, None]) & (gap_mid < (t_send + pulse + 0.15)[:, None])
    long_gap = np.any(
        np.isfinite(gaps) & (gaps > max(3 * ctx.period_s, 0.025)) & in_pulse_window, axis=1
    )
    package_gap = (present.mean(axis=1) < 0.5) | long_gap

    # Filtered speed (zero phase: the FIR is symmetric and centred) over the out pulse's
    # columns, the only ones the coarse crossing and the peak use.
    filt_out = _filter_cols(y, ctx.taps, s_out)
    level = ONSET_FRACTION * speed
    # Coarse crossing: the last sample below the level before the speed first passes half
    # the commanded speed (noise cannot fake that), then the next one.
    half_up = in_out & (filt_out >= 0.5 * speed[:, None])
    found = half_up.any(axis=1)
    m_out = filt_out.shape[1]
    k50_loc = np.where(found, np.argmax(half_up, axis=1), m_out)
    below = in_out & (filt_out < level[:, None]) & (np.arange(m_out) < k50_loc[:, None])
    k_c = s_out.start + np.where(
        below.any(axis=1), m_out - np.argmax(below[:, ::-1], axis=1), k50_loc
    )
    k_c = np.clip(np.where(found, k_c, g - 1), 0, g - 1)
    tau_coarse = np.where(found, t_g[np.arange(n), k_c] - t_send, np.nan)

    # Gain: integrated gyro angle of the out pulse against the reported displacement.
    pause_mid = t_send + np.nan_to_num(tau_coarse, nan=0.05) + pulse + prof["pause_s"] / 2
    q_start = np.array([q_rep[i][present[i]][0] if present[i].any() else np.nan
                        for i in range(n)])  # fmt: skip

    def reported_at(times: FloatArray) -> FloatArray:
        """The reported position at these host times (interpolated), rad."""
        return np.array([np.interp(times[i], host[i][present[i]], q_rep[i][present[i]])
                         if present[i].sum() > 1 else np.nan for i in range(n)])  # fmt: skip

    disp = (reported_at(pause_mid + _GAIN_REPORT_S) - q_start) * direction
    s_pulse = _span(t_g, t_send - 0.002, pause_mid)
    in_pulse = (t_g[:, s_pulse] >= (t_send - 0.002)[:, None]) & (
        t_g[:, s_pulse] <= pause_mid[:, None]
    )
    angle = np.sum(y[:, s_pulse] * in_pulse, axis=1) * dt
    gain = angle / np.where(np.abs(disp) > 1e-9, disp, np.nan)
    y_phys = y / gain[:, None]
    peak = np.max(filt_out / gain[:, None] * in_out, axis=1)
    sigma = _robust_sigma(y_phys[:, s_pre], pre)
    missing_pulse = 1.0 - np.sum(have[:, s_pulse] & in_pulse, axis=1) / np.maximum(
        in_pulse.sum(axis=1), 1
    )
    if traces or method != "fit":
        filt = _filter_cols(y, ctx.taps, slice(0, g)) if traces else np.zeros_like(y)
        filt[:, s_out] = filt_out
        filt_phys = filt / gain[:, None]
        in_out_full = np.zeros((n, g), dtype=bool)
        in_out_full[:, s_out] = in_out

    def recorded_flags() -> dict[str, NDArray[np.bool_]]:
        """What the trial recorded rules out (peak and gain as they stand when called)."""
        return {
            "no_motion": ~(peak > 0.5 * speed),
            "gain": ~((gain > _GAIN_RANGE[0]) & (gain < _GAIN_RANGE[1])),
            "gyro_gap": missing_pulse > _MAX_MISSING_PULSE,
        }

    n_cols = {}
    if method == "fit":
        q_rel = np.where(present, (q_rep - q_start[:, None]) * direction[:, None], np.nan)
        sound = ~clipped & ~package_gap & np.isfinite(gain)
        dated, lateness = dated_by_controller(
            host, chunk.get("state_controller_time_s"), present, con.period_s
        )
        rd = response_delay(
            t_g, y_phys, dated, q_rel, dt,
            np.full(n, 0.6 * ctx.period_s),
            smooth_samples=2 * round(RESPONSE_SMOOTH_S * ctx.fs_hz / 2) + 1,  # odd
            joint=joint, sound=sound, noise_rad_s=sigma,
        )  # fmt: skip
        resp, resp_se = rd.tau + lateness, rd.se
        resp_flag[rd.gear_flag] = RESPONSE_FLAG_DEFLECTION
        resp_flag[rd.joint_flag] = RESPONSE_FLAG_DEFLECTION_JOINT
        resp_flag[rd.noise_flag] = RESPONSE_FLAG_DEFLECTION_NOISE
        # The gain again, time-matched: the angle ends at pause_mid (sensor time), so the
        # displacement is the position *sampled* then, reported one response delay later.
        # The first guess (reported at +30 ms) is off when the joint still creeps in the
        # pause: on the independent KR 5 (12 Hz velocity loop) it scaled the speed ~1 %
        # high and moved the level crossing +0.12 ms (level/slope ~9 ms).
        q_at = reported_at(pause_mid + np.where(np.isfinite(resp), resp, _GAIN_REPORT_S))
        disp_at = (q_at - q_start) * direction
        matched = angle / np.where(np.abs(disp_at) > 1e-9, disp_at, np.nan)
        rescale = np.where(np.isfinite(matched), gain / matched, 1.0)
        gain = np.where(np.isfinite(matched), matched, gain)
        y_phys *= rescale[:, None]
        sigma = sigma * rescale
        peak = peak * rescale
        if traces:
            filt_phys *= rescale[:, None]
        # Trials of one joint and direction share their windows' bias; a trial flagged for
        # what it recorded (clipped, still, gaps, package silences, implausible gain) is
        # kept out of its group's statistics (-1: no group), so that it cannot move the
        # others' estimates.
        bad_recording = np.any(list(recorded_flags().values()), axis=0)
        usable = ~clipped & found & ~package_gap & ~bad_recording
        group = np.where(usable, 2 * joint + (direction > 0), -1)
        on = onset_adaptive(t_g, y_phys, have, k_c, level, sigma, 1.0 / ctx.fs_hz, group=group)
        act = on["onset"] - (t_send + level / accel)
        # Zero-rate error: the pooled mean of bias_n samples per axis, projected.
        sd_bias = sigma / np.sqrt(np.maximum(chunk["bias_n"], 1.0))
        act_se = np.sqrt(
            on["crb"] ** 2
            + on["misfit"] ** 2
            + on["bias"] ** 2
            + on["conflict"] ** 2
            + (sd_bias / on["slope"]) ** 2
            + ACTUATION_SE_FLOOR_S**2
        )
        missing_onset = on["missing"]
        n_cols = {
            "actuation_delay_se": act_se,
            "actuation_delay_crb": on["crb"],
            "response_delay_se": resp_se,
            "response_delay_shared_se": rd.shared_se,
            "response_deflection_s": rd.change,
            "onset_window_s": np.array([sum(w) for w in _windows()])[on["window"].astype(int)],
        }
    else:
        t_cmd_peak = t_send + pulse / 2
        kk = np.argmax(np.where(in_out_full, filt_phys, -np.inf), axis=1)
        t_meas = _parabolic_peak(t_g, filt_phys, kk)
        rep = np.where(
            (host > t_send[:, None]) & (host < out_end[:, None] + 0.03),
            qd_rep * direction[:, None],
            -np.inf,
        )
        kr = np.argmax(rep, axis=1)
        t_rep = host[np.arange(n), kr]
        act = t_meas - t_cmd_peak
        resp = t_rep - t_meas
        missing_onset = np.zeros(n)
        act_se = resp_se = np.zeros(n)

    recorded = recorded_flags()
    reasons = [
        (pre.sum(axis=1) < 0.01 * ctx.fs_hz, "no_baseline"),  # < 10 ms of zero-rate samples
        (clipped, "clipped"),
        ((missing_onset > _MAX_MISSING_ONSET) | recorded["gyro_gap"], "gyro_gap"),
        (package_gap, "package_gap"),
        (recorded["no_motion"], "no_motion"),
        (~found | ~np.isfinite(act), "no_onset"),
        (recorded["gain"], "gain"),
        (~np.isfinite(resp) | (resp < -ctx.period_s) | (resp > 0.25), "response_fit"),
        (~((act_se <= max_se_s) & (resp_se <= max_se_s)), "uncertain"),
    ]
    for mask, reason in reversed(reasons):
        flag[mask] = reason
    bad = flag != ""
    act = np.where(bad, np.nan, act)
    resp = np.where(bad, np.nan, resp)
    resp_flag[bad] = ""  # the trial's flag says it
    out = {"actuation_delay": act, "response_delay": resp, "flag": flag,
           "response_flag": resp_flag, "gyro_gain": gain,
           "gyro_noise_rad_s": sigma, "gyro_missing": 1.0 - have.mean(axis=1), **n_cols}  # fmt: skip
    if traces:
        out.update(
            gyro_time_s=t_g, gyro_speed_rad_s=y_phys, gyro_filtered_rad_s=filt_phys,
            state_time_s=host, state_speed_rad_s=qd_rep * direction[:, None],
            send_time_s=t_send, speed_rad_s=speed,
        )  # fmt: skip
    return out


def _windows() -> tuple[tuple[float, float], ...]:
    return ONSET_WINDOWS_S


def _run_rows(
    path: str, ctx: SweepContext, rows: NDArray[np.int64], method: str, max_se_s: float = MAX_SE_S
) -> dict[str, NDArray[Any]]:
    with open_rows(path, ctx.keep) as reader:
        chunk = _read_chunk(reader, rows, ctx)
    return _extract_chunk(ctx, chunk, rows, method, max_se_s=max_se_s)


def _read_chunk(
    reader: RecordingReader, rows: NDArray[np.int64], ctx: SweepContext
) -> dict[str, NDArray[Any]]:
    """The fields extraction needs for ``rows`` (``session`` where the recording has it),
    times, angles and speeds converted to SI (gyro rates stay as stored: see _grid), and
    each row's pooled zero-rate (``bias``, rad/s, sensor axes; ``bias_n`` samples behind
    it), for which the gyro of the _BIAS_POOL // 2 rows before and after each row in time
    is read too (the rows themselves and a margin: the stream is read once)."""
    contract = ctx.contract
    half = _BIAS_POOL // 2
    offs = np.arange(-half, half + 1)
    pos = ctx.time_rank[rows][:, None] + offs
    span = ctx.session_span[rows]
    valid = (pos >= span[:, :1]) & (pos < span[:, 1:])
    nbr_rows = ctx.time_order[np.clip(pos, 0, len(ctx.time_order) - 1)]
    union = np.unique(np.concatenate([rows, nbr_rows[valid]]))
    optional = [f for f in (*OPTIONAL_FIELDS, "session") if f in reader.fields]
    names = [*REQUIRED_FIELDS, *optional]
    at = np.searchsorted(union, rows)
    out: dict[str, NDArray[Any]] = {}
    for name in names:
        if name in ("gyro_raw", "gyro_counter"):
            out[name] = reader.read(name, rows=union)
        else:
            out[name] = reader.read(name, rows=rows)
    m_pre = max(int(_PRE_S * contract.fs_hz), 1)
    pre_sum, pre_n = _pre_stats(
        out["gyro_counter"], out["gyro_raw"], m_pre, contract.scale["gyro_raw"]
    )
    nbr = np.searchsorted(union, nbr_rows).astype(np.intp)
    out["bias"], out["bias_n"] = _pool_bias(pre_sum, pre_n, np.where(valid, nbr, 0), valid)
    if union.size != rows.size:
        out["gyro_raw"] = out["gyro_raw"][at]
        out["gyro_counter"] = out["gyro_counter"][at]
    for name, factor in contract.scale.items():
        if name not in ("gyro_raw", "gyro_counter", "trial") and factor != 1.0:
            out[name] = out[name].astype(np.float64) * factor
    return out


def _extract_chunk(
    ctx: SweepContext,
    chunk: dict[str, NDArray[Any]],
    rows: NDArray[np.int64],
    method: str,
    traces: bool = False,
    max_se_s: float = MAX_SE_S,
) -> dict[str, NDArray[Any]]:
    """Extract one chunk of trials. Unmeasurable trials carry NaN through the arithmetic
    and are flagged at the end, so invalid-value warnings are expected and silenced.
    ``traces=True`` also returns the signals behind the numbers (for figures)."""
    import warnings

    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN medians of flagged rows
        return _extract_chunk_inner(ctx, chunk, rows, method, traces, max_se_s)


def trial_traces(path: str | os.PathLike[str], rows: Any) -> dict[str, Any]:
    """Signals of recorded trials as the extraction sees them, for figures: gyro time and
    speed along the commanded direction (raw and filtered, rad/s), the reported speed at
    its arrival times, the send time, the commanded speed and the delays (trial time, s).
    Also the commanded profile (``profile``), the still PSD and the filter taps."""
    path = os.fspath(path)
    rows = np.atleast_1d(np.asarray(rows, dtype=np.int64))
    try:
        return _trial_traces(path, rows, None)
    except DamagedChunkError:
        # The policy of extract_recording: the damaged chunks' rows are left out of the
        # sweep's statistics; a trial asked for that lies in one is refused by name.
        with RecordingReader(path) as reader:
            damaged = np.flatnonzero(reader.damaged_rows())
            n = reader.n_trials
        hit = np.intersect1d(rows, damaged)
        if damaged.size == 0 or damaged.size == n:
            raise
        if hit.size:
            raise RecordingError(
                f"trial {int(hit[0])} of {path} lies in a damaged chunk (rows "
                f"{int(damaged[0])}..{int(damaged[-1])} fail their checksum); choose another "
                "trial (report --trial)"
            ) from None
        out = _trial_traces(path, rows, np.setdiff1d(np.arange(n), damaged))
        out["damage_note"] = damage_note(path, int(damaged.size), n)
        return out


def _trial_traces(
    path: str, rows: NDArray[np.int64], keep: NDArray[np.int64] | None
) -> dict[str, Any]:
    """:func:`trial_traces` with only the rows ``keep`` read (all when None)."""
    with open_rows(path, keep) as reader:
        ctx, still, cutoff, _, _ = sweep_context(reader, clock_window_s=None, numtaps=161)
        ctx = dataclasses.replace(ctx, keep=keep)
        local = rows if keep is None else np.searchsorted(keep, rows)
        chunk = _read_chunk(reader, local, ctx)
        truth = {
            k: reader.read(f"true_{k}_s", rows=local)
            for k in ("actuation_delay", "response_delay")
            if f"true_{k}_s" in reader.fields
        }
    out: dict[str, Any] = dict(_extract_chunk(ctx, chunk, local, "fit", traces=True))
    out.update(
        profile=dict(ctx.profile), still=still, taps=ctx.taps, cutoff_hz=cutoff,
        fs_hz=ctx.fs_hz, truth=truth, robot=ctx.robot,
    )  # fmt: skip
    return out


def extract_recording(
    path: str | os.PathLike[str],
    *,
    method: str = "fit",
    jobs: int = 1,
    chunk_trials: int = 512,
    clock_window_s: float | None = None,
    numtaps: int = 161,
    max_se_s: float = MAX_SE_S,
    progress: bool = True,
) -> ExtractionResult:
    """Extract the delay table of a recording.

    Parameters
    ----------
    path : path
        Recording written by ``timedexec simulate`` or ``timedexec calibrate``.
    method : {"fit", "extrema"}
        ``fit`` (default, sub-sample) or the published ``extrema`` method.
    jobs : int
        Worker processes (joblib; ``joblib.parallel_config`` chooses the backend, e.g. Dask).
    chunk_trials : int
        Trials per vectorised chunk.
    clock_window_s : float, optional
        Length of the blended windows in which the sensor clock is fitted, s; None (default)
        chooses it from the data (:func:`timedexec.sensors.fit_clock_drifting`).
    numtaps : int
        Low-pass FIR length (coarse crossing and figures only).
    max_se_s : float
        Trials whose actuation or response standard error exceeds this are flagged
        ``uncertain``, s.
    progress : bool
        Progress with ETA on stderr.

    Returns
    -------
    ExtractionResult
        The delay table (columns of ``timedexec.delays`` plus ``flag``,
        ``actuation_delay_se``, ``actuation_delay_crb``, ``response_delay_se`` (s),
        ``response_delay_shared_se`` (the part of ``response_delay_se`` the trials of the
        joint share — one error for all of them, not a trial's own; 0 where no joint of
        the arm showed a gear's deflection, s),
        ``response_deflection_s`` (how far separating a gear's deflection moved the
        response delay, s; NaN where the trial's joint showed none), ``response_flag``
        (why the response delay alone is not to be used, "" when fine), ``onset_window_s``,
        ``gyro_gain``, ``gyro_noise_rad_s`` and ``gyro_missing``; ``t_since_power_on``, s,
        where the header gives the robot's power-on, ``power_on_s``)
        and what was learnt of the sensor (clock offset and drift, filter, noise).

    Raises
    ------
    RecordingError
        The file is not a recording extraction can read: every missing field, static,
        header key and unconvertible unit is named.
    """
    if clock_window_s is not None and not (
        isinstance(clock_window_s, (int, float)) and clock_window_s > 0
    ):
        raise ConfigError(f"clock_window_s={clock_window_s!r} must be a positive number of "
                          "seconds, or None to choose it from the data")  # fmt: skip
    if not (isinstance(max_se_s, (int, float)) and max_se_s > 0):
        raise ConfigError(f"max_se_s={max_se_s!r} must be a positive number of seconds")
    if method not in METHODS:
        raise ConfigError(
            f"unknown extraction method {method!r}; choose one of {', '.join(METHODS)}"
        )
    if isinstance(jobs, bool) or not isinstance(jobs, int) or (jobs < 1 and jobs != -1):
        raise ConfigError(f"jobs={jobs!r} must be a positive integer, or -1 for every worker")
    path = os.fspath(path)
    kw: dict[str, Any] = {
        "method": method,
        "jobs": jobs,
        "chunk_trials": chunk_trials,
        "clock_window_s": clock_window_s,
        "numtaps": numtaps,
        "max_se_s": max_se_s,
        "progress": progress,
    }
    bad_time = bad_time_rows(path)
    try:
        return _extract(path, bad_time, **kw)
    except DamagedChunkError:
        # Say it per trial: leave the damaged chunks' rows out, flag those trials.
        with RecordingReader(path) as reader:
            damaged = np.flatnonzero(reader.damaged_rows())
            n = reader.n_trials
        if damaged.size == 0 or damaged.size == n:
            raise
        flags = {int(r): "damaged" for r in damaged}
        if bad_time is not None:
            flags = {**bad_time[1], **flags}
        rows = np.array(sorted(flags), dtype=np.int64)
        return _extract(path, (rows, flags), damaged_rows=int(damaged.size), **kw)


def _extract(
    path: str,
    excluded: tuple[NDArray[np.int64], dict[int, str]] | None,
    *,
    damaged_rows: int = 0,
    method: str,
    jobs: int,
    chunk_trials: int,
    clock_window_s: float | None,
    numtaps: int,
    max_se_s: float,
    progress: bool,
) -> ExtractionResult:
    """:func:`extract_recording` of the rows not in ``excluded`` (rows, and each row's flag;
    all rows when None); the excluded rows whose trial can be identified are in the table
    with their flag (``damaged``, ``bad_time``) and NaN delays."""
    keep = None
    left_out = None if excluded is None else excluded[0]
    if left_out is not None:
        with RecordingReader(path) as whole:
            keep = np.setdiff1d(np.arange(whole.n_trials), left_out)
    with open_rows(path, keep) as reader:
        ctx, still, cutoff, rate, clock_info = sweep_context(
            reader, clock_window_s=clock_window_s, numtaps=numtaps, jobs=jobs
        )
        ctx = dataclasses.replace(ctx, keep=keep)
        n = reader.n_trials
        trial = reader.read("trial")
        t0 = reader.read("t0_s") * ctx.contract.scale["t0_s"]
        plan_q = reader.static("plan_q_start_rad")
        plan_joint = reader.static("plan_joint")
        plan_dir = reader.static("plan_direction")
        power_on = reader.header.get("power_on_s")  # the robot's power-on, where known
        truth = {
            k: reader.read(f"true_{k}_s")
            for k in ("actuation_delay", "response_delay")
            if f"true_{k}_s" in reader.fields
        }
        if left_out is not None:
            lost, lost_t0, lost_rows = lost_trials(
                reader.whole, left_out, ctx.contract.scale["t0_s"]
            )
    chunks = [np.arange(s, min(s + chunk_trials, n)) for s in range(0, n, chunk_trials)]
    bar = Progress(n, f"extract ({method})", enabled=progress)
    if jobs == 1:
        parts = []
        for rows in chunks:
            parts.append(_run_rows(path, ctx, rows, method, max_se_s))
            bar.update(len(rows))
    else:
        from joblib import Parallel, delayed

        parts = []
        for part, rows in zip(
            Parallel(n_jobs=jobs, return_as="generator")(
                delayed(_run_rows)(path, ctx, rows, method, max_se_s) for rows in chunks
            ),
            chunks,
            strict=True,
        ):
            parts.append(part)
            bar.update(len(rows))
    bar.close()
    res = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    cols: dict[str, Any] = {
        "trial": trial,
        "robot": ctx.robot,
        "joint": plan_joint[trial],
        "direction": plan_dir[trial],
        **{f"q{i + 1}": plan_q[trial, i] for i in range(6)},
        "t_start": t0,
        "actuation_delay": res["actuation_delay"],
        "response_delay": res["response_delay"],
    }
    for k, v in truth.items():
        cols[f"true_{k}"] = v
    cols["flag"] = res["flag"]
    cols["response_flag"] = res["response_flag"]
    for k in ("actuation_delay_se", "actuation_delay_crb", "response_delay_se",
              "response_delay_shared_se", "response_deflection_s", "onset_window_s",
              "gyro_gain", "gyro_noise_rad_s", "gyro_missing"):  # fmt: skip
        if k in res:
            cols[k] = res[k]
    if left_out is not None and excluded is not None and lost.size:
        known = {
            "trial": lost,
            "joint": plan_joint[lost],
            "direction": plan_dir[lost],
            **{f"q{i + 1}": plan_q[lost, i] for i in range(6)},
            "t_start": np.where(np.isfinite(lost_t0), lost_t0, np.nan),
            "flag": np.array([excluded[1][int(r)] for r in lost_rows]),
            "response_flag": np.full(lost.size, "", dtype=object),
        }
        for k, v in cols.items():
            if isinstance(v, np.ndarray):
                add = known.get(k, np.full(lost.size, np.nan))
                cols[k] = np.concatenate([v, np.asarray(add, dtype=np.result_type(v, add))])
        trial = cols["trial"]
        # A left-out trial's start time may be what is wrong with it: it sits between its
        # neighbours in the sweep (t_start dates the trial for drift; it is no measurement).
        t_start = np.asarray(cols["t_start"], dtype=np.float64)
        bad = ~np.isfinite(t_start)
        if bad.any() and (~bad).any():
            t_start[bad] = np.interp(trial[bad], trial[~bad], t_start[~bad])
            cols["t_start"] = t_start
    if power_on is not None:  # the thermal clock: time since the robot was powered on
        cols["t_since_power_on"] = np.asarray(cols["t_start"], dtype=float) - float(power_on)
    order = np.argsort(trial)
    table = DelayTable(
        {k: (v[order] if isinstance(v, np.ndarray) else v) for k, v in cols.items()}, source=path
    )
    n_flagged = int(np.sum(cols["flag"] != ""))
    return ExtractionResult(
        table=table,
        cutoff_hz=cutoff,
        clock_rate_hz=rate,
        clock_rate_error_ppm=(rate / ctx.fs_hz - 1) * 1e6,
        still=still,
        n_flagged=n_flagged,
        clock=clock_info,
        damaged_rows=damaged_rows,
    )
