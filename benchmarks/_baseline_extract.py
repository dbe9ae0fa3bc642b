"""FROZEN COPY of timedexec.extraction._extract before issue 14 (git f0f160a), kept so that
benchmarks/bench_extract_robustness.py can time and score old and new in the same run.
Verbatim except that it imports the still analysis through the public face. Do not edit.

Original docstring follows.

Delay extraction from a recording: gyro time base, filtering, onset and response timing.

Definitions (shared with the simulator's ground truth, :mod:`timedexec._signal`):

* **actuation delay** = the instant the physical joint speed reaches ``ONSET_FRACTION`` of the
  commanded speed, minus the instant the commanded ramp reaches the same speed after the
  command was sent;
* **response delay** = the time shift that best aligns the reported joint position with the
  physical one (the age of the reported state on arrival).

Steps, vectorised across the trials of a chunk:

1. **Gyro time base.** Counters are unwrapped across the sweep (the host time between
   trials fixes the number of wraps); the sensor clock is fitted per time window as the
   lower envelope of the block arrival times (``timedexec.sensors``); the two known constant
   latencies — the minimum transport latency and the sensor's filter group delay, both in
   the recording header — are subtracted.
2. **Rates.** Counts to rad/s, zero-rate from the trial's pre-command samples, projection on
   the principal axis of the motion, gain calibrated so that the integrated gyro angle of
   the out pulse equals the reported joint displacement (this absorbs the sensor's ±3 %
   scale error and the projection).
3. **Actuation** (method ``fit``): a coarse crossing from the low-pass filtered speed (FIR
   designed from the still recording's PSD, zero phase), refined by a local cubic
   least-squares fit of the unfiltered samples around it. Method ``extrema`` (published):
   the time between the commanded and the measured speed maxima.
4. **Response** (method ``fit``): Gauss-Newton least-squares shift of the integrated gyro
   angle onto the reported positions (:func:`timedexec._signal.fit_shift`). ``extrema``:
   the time between the measured and the reported speed maxima.
5. **Flags.** Trials that cannot be measured get a reason in the ``flag`` column and NaN
   delays: ``no_motion``, ``clipped``, ``gyro_gap``, ``package_gap``, ``no_onset``,
   ``gain`` (implausible gyro gain), ``response_fit``.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from timedexec._progress import Progress
from timedexec._signal import ONSET_FRACTION, fit_shift, interp_rows
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, RecordingError
from timedexec.extraction import StillAnalysis, analyse_still, design_lowpass
from timedexec.recording import RecordingReader
from timedexec.sensors import fit_clock_lower_envelope, unwrap_counter

__all__ = ["METHODS", "ExtractionResult", "extract_recording"]

METHODS = ("fit", "extrema")
#: Segments per trial whose lowest block arrival enters the clock fits: at least this many,
#: more for short sweeps (about _ENVELOPE_POINTS points in all; the hull is O(points)).
_ENVELOPE_SEGMENTS = 8
_ENVELOPE_POINTS = 200_000
FloatArray = NDArray[np.float64]

REQUIRED_FIELDS = (
    "trial",
    "t0_s",
    "cmd_send_time_s",
    "cmd_qd_rad_s",
    "state_host_time_s",
    "state_q_rad",
    "state_qd_rad_s",
    "gyro_raw",
    "gyro_counter",
    "gyro_block_host_time_s",
)


@dataclass(frozen=True)
class _Context:
    """Sweep-wide facts every chunk needs."""

    robot: str
    period_s: float
    profile: dict[str, float]
    lsb_per_dps: float
    fs_hz: float
    block: int
    latency_s: float  # transport latency + group delay, subtracted from fitted sample times
    taps: FloatArray
    windows: tuple[FloatArray, FloatArray, FloatArray]  # (t_start, n_ref, host time) per window
    window_session: NDArray[np.int64]  # session of each window
    clock_period_s: FloatArray  # per window
    clock_offset: FloatArray  # per window: host time at n_ref
    n_first: FloatArray  # unwrapped index of each recorded row's first sample
    vendor: str


@dataclass(frozen=True)
class ExtractionResult:
    """The delay table and what the extraction learnt about the sweep."""

    table: DelayTable
    cutoff_hz: float
    clock_rate_hz: float
    clock_rate_error_ppm: float
    still: StillAnalysis
    n_flagged: int

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        flags = [f for f in self.table["flag"] if f]
        counts: dict[str, int] = {}
        for f in flags:
            counts[f] = counts.get(f, 0) + 1
        return {
            "trials": len(self.table),
            "flagged": self.n_flagged,
            "flags": counts,
            "filter_cutoff_hz": self.cutoff_hz,
            "gyro_rate_hz": self.clock_rate_hz,
            "gyro_rate_error_ppm": self.clock_rate_error_ppm,
            "gyro_noise_density_dps_rthz": (
                np.rad2deg(self.still.noise_density_rad_s_rthz).round(5).tolist()
            ),
        }


def _rates(raw: NDArray[Any], lsb_per_dps: float) -> FloatArray:
    return np.deg2rad(np.asarray(raw, dtype=np.float64) / lsb_per_dps)


def _unwrap_rows(
    first_counter: NDArray[np.int64],
    first_time: FloatArray,
    start_index: int,
    start_time: float,
    rate_hz: float,
) -> NDArray[np.int64]:
    """Unwrapped index of each row's first sample: rows are in time order; the host time
    elapsed since the previous row decides how many 65536 wraps lie in between."""
    prev_c = np.r_[start_index % 65536, first_counter[:-1]]
    prev_t = np.r_[start_time, first_time[:-1]]
    dc = (first_counter - prev_c) % 65536
    expected = (first_time - prev_t) * rate_hz
    wraps = np.round((expected - dc) / 65536.0)
    return start_index + np.cumsum(dc + 65536 * wraps).astype(np.int64)


def _context(
    reader: RecordingReader, *, clock_window_s: float, numtaps: int
) -> tuple[_Context, StillAnalysis, float, float]:
    header = reader.header
    for key in ("profile", "gyro", "controller_period_s", "robot"):
        if key not in header:
            raise RecordingError(
                f"{reader.path}: the recording header lacks {key!r}; it was not written by "
                "timedexec simulate/calibrate (or by an older version)"
            )
    missing = [f for f in REQUIRED_FIELDS if f not in reader.fields]
    if missing:
        raise RecordingError(f"{reader.path}: the recording lacks field(s) {', '.join(missing)}")
    if reader.n_trials == 0:
        raise ConfigError(f"{reader.path}: the recording holds no trials (an empty sweep)")
    gyro = header["gyro"]
    lsb = float(gyro["lsb_per_dps"])
    fs = float(gyro["nominal_rate_hz"])
    block = int(gyro["block_samples"])
    latency = float(gyro.get("transport_latency_s", 0.0)) + float(gyro.get("group_delay_s", 0.0))

    # Still recording: zero-rate and noise PSD; its counter anchors the unwrap.
    still_raw = reader.static("still_gyro_raw")
    still = analyse_still(_rates(still_raw, lsb), fs)
    still_counter = reader.static("still_gyro_counter")
    still_blocks = reader.static("still_gyro_block_host_time_s")
    n_still = unwrap_counter(still_counter)
    still_fit = fit_clock_lower_envelope(
        n_still[block - 1 :: block][: len(still_blocks)], still_blocks, nominal_rate_hz=fs
    )

    # Unwrap every row's first sample, per session (a resumed run is a new gyro stream and
    # host clock), in time order; the still recording anchors session 0.
    t0 = reader.read("t0_s")
    session = reader.read("session") if "session" in reader.fields else np.zeros(len(t0), np.int64)
    first_counter = np.concatenate(
        [c["gyro_counter"][:, 0] for c in reader.iter_chunks(4096, names=["gyro_counter"])]
    ).astype(np.int64)
    blocks = reader.read("gyro_block_host_time_s").astype(np.float64)
    first_time = t0 + blocks[:, 0] - (block - 1) / still_fit.rate_hz  # ~ arrival of sample 0
    n_first = np.empty(len(t0), dtype=np.int64)
    for sess in np.unique(session):
        rows = np.flatnonzero(session == sess)
        rows = rows[np.argsort(t0[rows])]
        if sess == session.min():
            anchor_n = int(n_still[-1])
            anchor_t = float(still_fit.to_host_time(n_still[-1])[()])
        else:  # a new stream: its first trial anchors it
            anchor_n, anchor_t = int(first_counter[rows[0]]), float(first_time[rows[0]])
        n_first[rows] = _unwrap_rows(
            first_counter[rows], first_time[rows], anchor_n, anchor_t, still_fit.rate_hz
        )

    # Clock fits per session and time window (lower envelope of block arrivals). Only the
    # lowest arrivals can lie on a lower envelope: relative to the still recording's line,
    # keep each trial's minimum in each of a few segments (the line's slope error over one
    # trial is far below the arrival jitter): ~700 points per trial become 8 or more.
    n_blocks = blocks.shape[1]
    block_last_all = n_first[:, None] + (np.arange(n_blocks) + 1) * block - 1
    block_time_all = t0[:, None] + blocks
    resid = block_time_all - (
        still_fit.t_ref_s + (block_last_all - still_fit.n_ref) * still_fit.period_s
    )
    segments = int(np.clip(_ENVELOPE_POINTS // max(len(t0), 1), _ENVELOPE_SEGMENTS, n_blocks))
    edges_b = np.linspace(0, n_blocks, segments + 1).astype(int)
    keep = np.stack(
        [
            lo + np.argmin(resid[:, lo:hi], axis=1)
            for lo, hi in itertools.pairwise(edges_b)
        ],
        axis=1,
    )
    block_last = np.take_along_axis(block_last_all, keep, axis=1)
    block_time = np.take_along_axis(block_time_all, keep, axis=1)
    edges_list, sess_list = [], []
    for sess in np.unique(session):
        ts = t0[session == sess]
        e = np.arange(ts.min(), ts.max() + clock_window_s, clock_window_s)
        edges_list.append(e)
        sess_list.append(np.full(len(e), sess))
    edges = np.concatenate(edges_list)
    edge_session = np.concatenate(sess_list)
    win = _window_of(edges, edge_session, t0, session)
    periods = np.empty(len(edges))
    offsets = np.empty(len(edges))
    refs = np.empty(len(edges))
    for w in range(len(edges)):
        rows = np.flatnonzero(win == w)
        if len(rows) == 0:
            periods[w], offsets[w], refs[w] = (
                still_fit.period_s,
                float(still_fit.t_ref_s),
                still_fit.n_ref,
            )
            continue
        n_pts = block_last[rows].ravel()
        t_pts = block_time[rows].ravel()
        if w == 0:
            n_pts = np.r_[n_still[block - 1 :: block][: len(still_blocks)], n_pts]
            t_pts = np.r_[still_blocks, t_pts]
        fit = fit_clock_lower_envelope(n_pts, t_pts, nominal_rate_hz=fs)
        periods[w], offsets[w], refs[w] = fit.period_s, fit.t_ref_s, fit.n_ref
    main = session == session.min()
    overall = fit_clock_lower_envelope(
        block_last[main].ravel(), block_time[main].ravel(), nominal_rate_hz=fs
    )

    # Filter from the PSDs (a few trials' motion against the still noise).
    sample_rows = np.linspace(0, reader.n_trials - 1, min(32, reader.n_trials)).astype(int)
    raw = reader.read("gyro_raw", rows=np.unique(sample_rows))
    motion = np.linalg.norm(_rates(raw, lsb) - still.bias_rad_s, axis=2)
    taps, cutoff = design_lowpass(still, motion, fs, numtaps=numtaps)
    ctx = _Context(
        robot=str(header["robot"]["name"]),
        period_s=float(header["controller_period_s"]),
        profile={
            k: float(header["profile"][k])
            for k in ("speed_rad_s", "acceleration_rad_s2", "hold_s", "pause_s")
        },
        lsb_per_dps=lsb,
        fs_hz=fs,
        block=block,
        latency_s=latency,
        taps=taps,
        windows=(edges, refs, offsets),
        window_session=edge_session,
        clock_period_s=periods,
        clock_offset=offsets,
        n_first=n_first.astype(np.float64),
        vendor=str(header["robot"].get("vendor", "")),
    )
    return ctx, still, cutoff, overall.rate_hz


def _window_of(
    edges: FloatArray, edge_session: NDArray[np.int64], t0: FloatArray, session: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Index of the clock-fit window (same session, last start <= t0) of each row."""
    out = np.empty(len(t0), dtype=np.int64)
    for sess in np.unique(session):
        idx = np.flatnonzero(edge_session == sess)
        rows = session == sess
        k = np.clip(np.searchsorted(edges[idx], t0[rows], side="right") - 1, 0, len(idx) - 1)
        out[rows] = idx[k]
    return out


def _sample_times(
    ctx: _Context,
    rows: NDArray[np.int64],
    t0: FloatArray,
    counters: NDArray[Any],
    session: NDArray[np.int64],
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Trial time of every gyro sample (physical instant it describes) and a gap flag."""
    edges, refs, offsets = ctx.windows
    w = _window_of(edges, ctx.window_session, t0, session)
    c = counters.astype(np.int32)
    steps = np.diff(c, axis=1) % 65536
    gap = np.any(steps != 1, axis=1)
    g = c.shape[1]
    n = np.broadcast_to(np.arange(g, dtype=np.float64), (len(rows), g)).copy()
    if gap.any():  # only rows with gaps need their indices rebuilt from the counter steps
        n[gap, 1:] = np.cumsum(steps[gap], axis=1)
    n += ctx.n_first[rows][:, None]
    host = offsets[w][:, None] + (n - refs[w][:, None]) * ctx.clock_period_s[w][:, None]
    return host - ctx.latency_s - t0[:, None], gap


def _extract_chunk_inner(
    ctx: _Context,
    chunk: dict[str, NDArray[Any]],
    rows: NDArray[np.int64],
    method: str,
    traces: bool = False,
) -> dict[str, NDArray[Any]]:
    n = len(rows)
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

    session = chunk["session"] if "session" in chunk else np.zeros(n, np.int64)
    t_g, gyro_gap = _sample_times(ctx, rows, t0, chunk["gyro_counter"], session)
    raw = chunk["gyro_raw"]
    clipped = np.any((raw >= 32767) | (raw <= -32767), axis=(1, 2))
    counts = raw.astype(np.float32)
    pre = (t_g < (t_send + 0.003)[:, None]).astype(np.float32)
    bias = np.matmul(pre[:, None, :], counts)[:, 0, :] / np.maximum(pre.sum(axis=1), 1)[:, None]
    counts -= bias[:, None, :]
    # Principal axis of the motion (after the command), batched 3x3 covariances.
    active = (t_g > t_send[:, None]).astype(np.float32)
    cov = np.matmul(counts.transpose(0, 2, 1), counts * active[:, :, None])
    _, vecs = np.linalg.eigh(cov.astype(np.float64))
    axis = vecs[:, :, -1].astype(np.float32)
    y = np.matmul(counts, axis[:, :, None])[:, :, 0].astype(np.float64)
    y *= np.deg2rad(1.0) / ctx.lsb_per_dps  # counts -> rad/s
    # The sensor's true sample spacing (its clock runs off nominal by up to ~1 %).
    dt = (t_g[:, -1] - t_g[:, 0]) / (t_g.shape[1] - 1)
    out_end = t_send + pulse + 0.12
    in_out = (t_g > t_send[:, None]) & (t_g < out_end[:, None])
    sign = np.sign(np.sum(y * in_out, axis=1))
    sign[sign == 0] = 1.0
    y *= sign[:, None]  # now positive in the out pulse: speed along the commanded direction

    # Reported state of the actuated joint.
    host = chunk["state_host_time_s"]
    q_rep = chunk["state_q_rad"][np.arange(n), :, joint].astype(np.float64)
    qd_rep = chunk["state_qd_rad_s"][np.arange(n), :, joint].astype(np.float64)
    # Lost or late packages: the response fit takes irregular samples, so a trial is only
    # unmeasurable when most packages are missing or a long silence (> max(3 periods,
    # 25 ms)) falls inside the out pulse, where the motion is timed.
    present = np.isfinite(host)
    arrived = np.where(present, host, np.inf)
    order = np.sort(arrived, axis=1)
    gaps = np.diff(order, axis=1)
    gap_mid = order[:, :-1] + 0.5 * gaps
    in_pulse_window = (gap_mid > t_send[:, None]) & (gap_mid < (t_send + pulse + 0.15)[:, None])
    long_gap = np.any(
        np.isfinite(gaps) & (gaps > max(3 * ctx.period_s, 0.025)) & in_pulse_window, axis=1
    )
    package_gap = (present.mean(axis=1) < 0.5) | long_gap

    # Filtered speed (zero phase), coarse onset and delay.
    # Zero phase: the FIR is symmetric (linear phase) and "same" centres its output.
    filt = signal.oaconvolve(y, ctx.taps[None, :], mode="same", axes=1)
    level = ONSET_FRACTION * speed
    after = (t_g > t_send[:, None]) & (filt >= level[:, None])
    found = after.any(axis=1)
    k_c = np.argmax(after, axis=1)
    t_coarse = t_g[np.arange(n), k_c]
    tau_coarse = np.where(found, t_coarse - t_send, np.nan)

    # Gain: integrated gyro angle of the out pulse against the reported displacement.
    pause_mid = t_send + np.nan_to_num(tau_coarse, nan=0.05) + pulse + prof["pause_s"] / 2
    q_start = q_rep[:, 0]
    q_mid = (
        np.array([np.interp(pause_mid[i] + 0.03, host[i], q_rep[i]) for i in range(n)])
        if n
        else np.zeros(0)
    )
    disp = (q_mid - q_start) * direction
    in_pulse = (t_g >= (t_send - 0.002)[:, None]) & (t_g <= pause_mid[:, None])
    angle = np.sum(y * in_pulse, axis=1) * dt
    gain = angle / np.where(np.abs(disp) > 1e-9, disp, np.nan)
    y_phys = y / gain[:, None]
    filt_phys = filt / gain[:, None]
    peak = np.max(filt_phys * in_out, axis=1)

    if method == "fit":
        act = _onset_fit(t_g, y_phys, filt_phys, t_send, level, 1.0 / ctx.fs_hz) - (
            t_send + level / accel
        )
        resp = _response_fit(t_g, y_phys, host, q_rep, direction, ctx.period_s, dt)
    else:
        t_cmd_peak = t_send + pulse / 2
        kk = np.argmax(np.where(in_out, filt_phys, -np.inf), axis=1)
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

    reasons = [
        (pre.sum(axis=1) < 0.01 * ctx.fs_hz, "no_baseline"),  # < 10 ms of zero-rate samples
        (clipped, "clipped"),
        (gyro_gap, "gyro_gap"),
        (package_gap, "package_gap"),
        (~(peak > 0.5 * speed), "no_motion"),
        (~found | ~np.isfinite(act), "no_onset"),
        (~((gain > 0.8) & (gain < 1.25)), "gain"),
        (~np.isfinite(resp) | (resp < -ctx.period_s) | (resp > 0.25), "response_fit"),
    ]
    for mask, reason in reversed(reasons):
        flag[mask] = reason
    bad = flag != ""
    act = np.where(bad, np.nan, act)
    resp = np.where(bad, np.nan, resp)
    out = {"actuation_delay": act, "response_delay": resp, "flag": flag, "gyro_gain": gain}
    if traces:
        out.update(
            gyro_time_s=t_g, gyro_speed_rad_s=y_phys, gyro_filtered_rad_s=filt_phys,
            state_time_s=host, state_speed_rad_s=qd_rep * direction[:, None],
            send_time_s=t_send, speed_rad_s=speed,
        )  # fmt: skip
    return out


ONSET_WINDOW_S = (-0.005, 0.010)  # wider averages more noise; measured bias < 0.03 ms


def _onset_fit(
    t_g: FloatArray,
    y: FloatArray,
    filt: FloatArray,
    t_send: FloatArray,
    level: FloatArray,
    dt: float,
) -> FloatArray:
    """Crossing of ``level`` refined by a local cubic fit of the unfiltered samples.

    The window :data:`ONSET_WINDOW_S` around the coarse crossing stays clear of the
    breakaway kink (several ms earlier) and averages ~120 samples."""
    n, g = y.shape
    after = (t_g > t_send[:, None]) & (filt >= level[:, None])
    k = np.argmax(after, axis=1)
    lo, hi = round(ONSET_WINDOW_S[0] / dt), round(ONSET_WINDOW_S[1] / dt)
    offs = np.arange(lo, hi + 1)
    idx = np.clip(k[:, None] + offs, 0, g - 1)
    yy = np.take_along_axis(y, idx, axis=1)
    tc = np.take_along_axis(t_g, k[:, None], axis=1)[:, 0]
    x = np.take_along_axis(t_g, idx, axis=1) - tc[:, None]
    scale = 0.005
    xs = x / scale
    vander = np.stack([np.ones_like(xs), xs, xs**2, xs**3], axis=-1)
    a = np.einsum("nmi,nmj->nij", vander, vander)
    b = np.einsum("nmi,nm->ni", vander, yy)
    coef = np.linalg.solve(a, b[..., None])[..., 0]
    # Newton iterations for p(x) = level from the coarse crossing.
    root = np.zeros(n)
    for _ in range(8):
        p = coef[:, 0] + coef[:, 1] * root + coef[:, 2] * root**2 + coef[:, 3] * root**3
        dp = coef[:, 1] + 2 * coef[:, 2] * root + 3 * coef[:, 3] * root**2
        step = (p - level) / np.where(np.abs(dp) > 1e-9, dp, np.nan)
        root = np.clip(root - step, lo * dt / scale, hi * dt / scale)
    return tc + root * scale


def _response_fit(
    t_g: FloatArray,
    y: FloatArray,
    host: FloatArray,
    q_rep: FloatArray,
    direction: FloatArray,
    period: float,
    dt: FloatArray,
) -> FloatArray:
    """Least-squares shift of the integrated gyro angle onto the reported positions.

    ``dt`` (n,) is each row's true sample spacing; the angle is integrated with the
    trapezoid rule so that sample k holds the angle at its own instant."""
    dt = dt[:, None]
    angle = (
        np.concatenate(
            [np.zeros((len(y), 1)), np.cumsum(0.5 * (y[:, 1:] + y[:, :-1]), axis=1)], axis=1
        )
        * dt
    )  # physical joint angle change along the commanded direction
    q_rel = (q_rep - q_rep[:, :1]) * direction[:, None]
    first = t_g[:, 0]

    def f(x: FloatArray) -> FloatArray:
        return interp_rows(angle, (x - first[:, None]) / dt)

    def df(x: FloatArray) -> FloatArray:
        return interp_rows(y, (x - first[:, None]) / dt)

    ok = np.isfinite(host) & (host > (first + 0.03)[:, None])
    # Lost packages carry NaN times: they are weighted out (their y is NaN), but the
    # template is still evaluated there, so give them a harmless finite time.
    host = np.where(ok, host, (first + 0.1)[:, None])
    tau, _, _, _ = fit_shift(
        host,
        np.where(ok, q_rel, np.nan),
        f,
        df,
        np.full(len(host), 0.6 * period),
        iterations=20,
        max_step_s=0.004,
        fit_gain=False,
        fit_offset=True,
    )
    # fit_shift models y(t) = f(t - tau): tau is how much older the reported state is.
    return tau


def _parabolic_peak(t: FloatArray, y: FloatArray, k: NDArray[np.int64]) -> FloatArray:
    n, g = y.shape
    k = np.clip(k, 1, g - 2)
    r = np.arange(n)
    y0, y1, y2 = y[r, k - 1], y[r, k], y[r, k + 1]
    den = y0 - 2 * y1 + y2
    frac = np.where(np.abs(den) > 1e-15, 0.5 * (y0 - y2) / den, 0.0)
    return t[r, k] + np.clip(frac, -1, 1) * (t[r, k + 1] - t[r, k])


def _run_rows(
    path: str, ctx: _Context, rows: NDArray[np.int64], method: str
) -> dict[str, NDArray[Any]]:
    with RecordingReader(path) as reader:
        chunk = _read_chunk(reader, rows)
    return _extract_chunk(ctx, chunk, rows, method)


def _read_chunk(reader: RecordingReader, rows: NDArray[np.int64]) -> dict[str, NDArray[Any]]:
    """The fields extraction needs for ``rows`` (``session`` where the recording has it)."""
    names = [*REQUIRED_FIELDS, *(["session"] if "session" in reader.fields else [])]
    return {name: reader.read(name, rows=rows) for name in names}


def _extract_chunk(
    ctx: _Context,
    chunk: dict[str, NDArray[Any]],
    rows: NDArray[np.int64],
    method: str,
    traces: bool = False,
) -> dict[str, NDArray[Any]]:
    """Extract one chunk of trials. Unmeasurable trials carry NaN through the arithmetic
    and are flagged at the end, so invalid-value warnings are expected and silenced.
    ``traces=True`` also returns the signals behind the numbers (for figures)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return _extract_chunk_inner(ctx, chunk, rows, method, traces)


def trial_traces(path: str | os.PathLike[str], rows: Any) -> dict[str, Any]:
    """Signals of recorded trials as the extraction sees them, for figures: gyro time and
    speed along the commanded direction (raw and filtered, rad/s), the reported speed at
    its arrival times, the send time, the commanded speed and the delays (trial time, s).
    Also the commanded profile (``profile``), the still PSD and the filter taps."""
    path = os.fspath(path)
    rows = np.atleast_1d(np.asarray(rows, dtype=np.int64))
    with RecordingReader(path) as reader:
        ctx, still, cutoff, _ = _context(reader, clock_window_s=120.0, numtaps=161)
        chunk = _read_chunk(reader, rows)
        truth = {
            k: reader.read(f"true_{k}_s", rows=rows)
            for k in ("actuation_delay", "response_delay")
            if f"true_{k}_s" in reader.fields
        }
    out: dict[str, Any] = dict(_extract_chunk(ctx, chunk, rows, "fit", traces=True))
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
    clock_window_s: float = 120.0,
    numtaps: int = 161,
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
    clock_window_s : float
        Length of the windows in which the sensor clock is fitted, s.
    numtaps : int
        Low-pass FIR length.
    progress : bool
        Progress with ETA on stderr.
    """
    if method not in METHODS:
        raise ConfigError(
            f"unknown extraction method {method!r}; choose one of {', '.join(METHODS)}"
        )
    if isinstance(jobs, bool) or not isinstance(jobs, int) or (jobs < 1 and jobs != -1):
        raise ConfigError(f"jobs={jobs!r} must be a positive integer, or -1 for every worker")
    path = os.fspath(path)
    with RecordingReader(path) as reader:
        ctx, still, cutoff, rate = _context(reader, clock_window_s=clock_window_s, numtaps=numtaps)
        n = reader.n_trials
        trial = reader.read("trial")
        t0 = reader.read("t0_s")
        plan_q = reader.static("plan_q_start_rad")
        plan_joint = reader.static("plan_joint")
        plan_dir = reader.static("plan_direction")
        truth = {
            k: reader.read(f"true_{k}_s")
            for k in ("actuation_delay", "response_delay")
            if f"true_{k}_s" in reader.fields
        }
    chunks = [np.arange(s, min(s + chunk_trials, n)) for s in range(0, n, chunk_trials)]
    bar = Progress(n, f"extract ({method})", enabled=progress)
    if jobs == 1:
        parts = []
        for rows in chunks:
            parts.append(_run_rows(path, ctx, rows, method))
            bar.update(len(rows))
    else:
        from joblib import Parallel, delayed

        parts = []
        for part, rows in zip(
            Parallel(n_jobs=jobs, return_as="generator")(
                delayed(_run_rows)(path, ctx, rows, method) for rows in chunks
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
    cols["gyro_gain"] = res["gyro_gain"]
    order = np.argsort(trial)
    table = DelayTable(
        {k: (v[order] if isinstance(v, np.ndarray) else v) for k, v in cols.items()}, source=path
    )
    n_flagged = int(np.sum(res["flag"] != ""))
    return ExtractionResult(
        table=table,
        cutoff_hz=cutoff,
        clock_rate_hz=rate,
        clock_rate_error_ppm=(rate / ctx.fs_hz - 1) * 1e6,
        still=still,
        n_flagged=n_flagged,
    )
