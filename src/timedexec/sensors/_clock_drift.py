"""A sensor clock that drifts: blended lower-envelope curves over windows of the sweep.

Cheap MEMS oscillators drift by tens to hundreds of ppm over a sweep (temperature), so one
line (:mod:`._clock`) cannot date a six-minute recording; here half-overlapping windows are
each fitted with a lower envelope (a quadratic in the sample index) and blended, the
window length chosen from the data, and — for devices that send fixed-size transfers —
each stamp re-dated at the end of the transfer that delivered it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError
from timedexec.sensors._clock import (
    _check_pairs,
    _envelope_from_candidates,
    _nominal_fit,
    fit_clock_lower_envelope,
)

__all__ = ["DriftingClockFit", "fit_clock_drifting"]


@dataclass(frozen=True, kw_only=True)
class DriftingClockFit:
    """A sensor clock that drifts: overlapping lower-envelope curves, blended.

    Window ``m`` is centred at ``centres[m]`` (sample index) and spans ``±half_width``
    samples; neighbouring windows overlap by half. Each window's curve is
    ``t = t_ref_s + period_s·(n - n_ref) + curvature_s·(n - n_ref)²`` (a line when the
    curvature is 0). The host time of index n is the average of the two nearest windows'
    curves weighted by a triangle (1 at a window's centre, 0 at its neighbour's), so the
    model is continuous and follows slow drift.

    Attributes
    ----------
    centres : ndarray, shape (w,)
        Window centres, sample index.
    half_width : float
        Window half width, samples (window length ``2·half_width``).
    n_ref, t_ref_s, period_s : ndarray, shape (w,)
        Each window's reference index, its host time (s) and the period there (s per
        sample).
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    curvature_s : ndarray, shape (w,) or (0,)
        Each window's quadratic coefficient, s per sample² (half the period's change per
        sample: a rate drifting by D ppm/s gives -D·1e-6/(2·rate²)); empty: lines.
    spread_s : float
        Structure left in the per-group minimum residuals (5-95 % range of their running
        median), s: what decided the window length.
    outlier_groups : int
        Groups left out because they lay far below their neighbours.
    transfer_phase : int
        Sample index (modulo the transfer length) at which the device's transfers end,
        when the arrivals showed one (see :func:`fit_clock_drifting`); -1: none found or
        not searched.
    """

    centres: NDArray[np.float64]
    half_width: float
    n_ref: NDArray[np.float64]
    t_ref_s: NDArray[np.float64]
    period_s: NDArray[np.float64]
    nominal_rate_hz: float
    spread_s: float = 0.0
    outlier_groups: int = 0
    curvature_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    transfer_phase: int = -1

    @property
    def window_s(self) -> float:
        """Window length, s (nominal)."""
        return 2.0 * self.half_width / self.nominal_rate_hz

    @property
    def rate_error_ppm(self) -> NDArray[np.float64]:
        """Each window's rate relative to nominal, ppm."""
        return (1.0 / (self.period_s * self.nominal_rate_hz) - 1.0) * 1e6

    @property
    def drift_ppm(self) -> float:
        """Range of the windows' rate errors (max - min), ppm."""
        ppm = self.rate_error_ppm
        return float(ppm.max() - ppm.min()) if ppm.size else 0.0

    def to_host_time(self, n: ArrayLike) -> NDArray[np.float64]:
        """Host time of (fractional) sample index ``n`` (any shape), s."""
        x = np.asarray(n, dtype=np.float64)
        w = self.centres.shape[0]
        curv = self.curvature_s if self.curvature_s.size else np.zeros(w)

        def curve(m: NDArray[np.int64] | int) -> NDArray[np.float64]:
            d = x - self.n_ref[m]
            out: NDArray[np.float64] = self.t_ref_s[m] + d * (self.period_s[m] + curv[m] * d)
            return out

        if w == 1:
            return curve(0)
        pos = np.clip((x - self.centres[0]) / self.half_width, 0.0, w - 1.0)
        m = np.minimum(np.floor(pos).astype(np.int64), w - 2)
        frac = pos - m
        lo = curve(m)
        blended: NDArray[np.float64] = lo + frac * (curve(m + 1) - lo)
        return blended

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe summary: window length, mean rate error and drift (ppm)."""
        ppm = self.rate_error_ppm
        return {
            "window_s": self.window_s,
            "windows": int(self.centres.shape[0]),
            "rate_error_ppm": float(np.mean(ppm)),
            "rate_error_ppm_min": float(ppm.min()),
            "rate_error_ppm_max": float(ppm.max()),
            "drift_ppm": self.drift_ppm,
            "residual_structure_s": self.spread_s,
            "outlier_groups": self.outlier_groups,
            "transfer_phase": self.transfer_phase,
            "curved": bool(self.curvature_s.size and np.any(self.curvature_s != 0)),
        }


def _running(x: NDArray[np.float64], k: int, stat: Any) -> NDArray[np.float64]:
    """``stat`` (np.median, np.min) over a centred window of k values, the ends held."""
    if x.shape[0] <= k:
        return np.full_like(x, float(stat(x)))
    xp = np.pad(x, k // 2, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(xp, k)
    return np.asarray(stat(win, axis=1), dtype=np.float64)


#: Samples per bin whose lowest arrival (relative to a window's line) is a candidate of
#: the window's curved envelope: 0.25 s at 8 kHz, over which a drift of a few ppm/s bends
#: the offset by < 0.1 µs.
_CURVE_BIN = 2000


def _envelope_curved(
    n: NDArray[np.int64], t: NDArray[np.float64], nominal_rate_hz: float
) -> tuple[float, float, float, float]:
    """Lower envelope of arrivals by a quadratic in the sample index, as high as possible
    on average over the arrivals: the linear program of the line envelope (Moon, Skelly
    and Towsley 1999) with a curvature term. Returns (n_ref, t_ref, period, curvature) at
    the arrivals' mean index; the line envelope (curvature 0) when there are too few
    distinct arrivals or the program fails."""
    line = _envelope_from_candidates(
        n, t, float(np.mean(n)), nominal_rate_hz, int(n.shape[0]), int(n[-1] - n[0])
    )
    n_c = float(np.mean(n))
    t_line = line.t_ref_s + (n_c - line.n_ref) * line.period_s
    as_line = (n_c, t_line, line.period_s, 0.0)
    r = t - (line.t_ref_s + (n - line.n_ref).astype(np.float64) * line.period_s)
    bins = (n - n[0]) // _CURVE_BIN
    order = np.lexsort((r, bins))
    first = np.r_[True, np.diff(bins[order]) != 0]
    sel = order[first]
    if sel.size < 8:
        return as_line
    from scipy.optimize import linprog

    half = max(0.5 * float(n[-1] - n[0]), 1.0)
    x = (n[sel] - n_c) / half
    a_ub = np.column_stack([np.ones_like(x), x, x * x])
    res = linprog(
        -a_ub.sum(axis=0), A_ub=a_ub, b_ub=r[sel], bounds=[(None, None)] * 3, method="highs"
    )
    if res.status != 0 or not np.all(np.isfinite(res.x)):
        return as_line
    a, b, c = (float(v) for v in res.x)
    return n_c, t_line + a, line.period_s + b / half, c / half**2


def _windows_fit(
    n: NDArray[np.int64],
    t: NDArray[np.float64],
    half: float,
    nominal_rate_hz: float,
    curved: bool = False,
) -> tuple[NDArray[np.float64], ...]:
    """Centres, and per window n_ref, t_ref, period and curvature of the envelopes of
    half-overlapping windows of ``2·half`` samples (lines unless ``curved``)."""

    def envelope(nw: NDArray[np.int64], tw: NDArray[np.float64]) -> tuple[float, ...]:
        if curved:
            return _envelope_curved(nw, tw, nominal_rate_hz)
        fit = _envelope_from_candidates(
            nw, tw, float(np.mean(nw)), nominal_rate_hz, int(nw.shape[0]), int(nw[-1] - nw[0])
        )
        return float(fit.n_ref), fit.t_ref_s, fit.period_s, 0.0

    lo, hi = float(n[0]), float(n[-1])
    w = max(math.ceil((hi - lo) / half) + 1, 1)
    if w == 1 or hi - lo <= 2 * half:
        if n.shape[0] < 2 or n[-1] == n[0]:
            fit = fit_clock_lower_envelope(n, t, nominal_rate_hz=nominal_rate_hz)
            one: tuple[float, ...] = (float(fit.n_ref), fit.t_ref_s, fit.period_s, 0.0)
        else:
            one = envelope(n, t)
        return (np.array([0.5 * (lo + hi)]), *(np.array([v]) for v in one))
    centres: NDArray[np.float64] = lo + np.arange(w, dtype=np.float64) * half
    par = np.full((4, w), np.nan)
    edges = np.asarray(np.searchsorted(n, np.r_[centres - half, centres + half]), dtype=np.int64)
    for m in range(w):
        a, b = int(edges[m]), int(edges[w + m])
        if b - a < 2 or n[b - 1] == n[a]:  # an empty window (a pause): borrow a neighbour's
            continue
        par[:, m] = envelope(n[a:b], t[a:b])
    good = np.flatnonzero(np.isfinite(par[2]))
    for empty in np.flatnonzero(~np.isfinite(par[2])).tolist():
        j = int(good[np.argmin(np.abs(good - empty))])
        par[:, empty] = par[:, j]
    return centres, par[0], par[1], par[2], par[3]


def fit_clock_drifting(
    n: ArrayLike,
    t: ArrayLike,
    group: ArrayLike,
    *,
    nominal_rate_hz: float = 8000.0,
    window_s: float | None = None,
    min_window_s: float = 4.0,
    max_window_s: float = 240.0,
    tolerance_s: float = 20e-6,
    curved: bool = True,
    transfer_samples: int | None = None,
) -> DriftingClockFit:
    """Lower-envelope clock fit that follows slow oscillator drift (temperature).

    The arrivals are split into half-overlapping windows, each fitted with a lower
    envelope — a quadratic in the sample index (``curved``, default: the linear program
    of :func:`fit_clock_lower_envelope` with a curvature term, so that a rate that keeps
    drifting within a window does not bend the offset) or a line — and blended (see
    :class:`DriftingClockFit`). Unless ``window_s`` is given, the window length is chosen
    from the data: starting from the whole span (at most ``max_window_s``) it is halved
    while the per-group minimum residuals (groups are e.g. trials) still show structure —
    the 5-95 % range of their running minimum over 31 groups above ``tolerance_s`` — and
    the windows stay at least ``min_window_s`` and 31 groups long (a group's lowest
    arrival may sit a few samples above the envelope when its recorded blocks do not end
    where the device's transfers end; one group in 31 touching it is enough). A drift
    of the rate by D ppm/s bends the time offset by D·1e-6·L²/8 within a window of L s,
    which is what the residual structure measures. Groups whose minimum lies more than
    max(10 MAD, 0.5 ms) below their neighbours' (a wrongly indexed stretch) are left out.

    **Transfer phase** (``transfer_samples`` = B). A stamp dates the transfer that
    delivered a sample; a device that sends fixed transfers of B samples ends them at
    indices of one residue modulo B, so a stamp reaches the minimum latency for its own
    sample only when that sample ends a transfer, and is late by up to B - 1 sample
    periods otherwise — by the same amount for every block of a group whose blocks start
    elsewhere. With few groups touching the envelope the curves then bulge between them
    (independent recordings: sample times -50..+310 µs off over a sweep, response delays
    0.04-0.09 ms short). So the residue is searched: each stamp re-dated to the end of its
    transfer under each candidate, the one under which clearly the fewest consecutive
    groups' lowest stamps disagree (by more than a quarter sample) is kept, if it is
    unique and clearly better than the stamps as they are (:func:`_transfer_phase`); a recorder whose reads do
    not follow the device's transfers shows none and keeps its stamps.

    Parameters
    ----------
    n : array_like of int, shape (k,)
        Unwrapped sample indices (any order).
    t : array_like of float, shape (k,)
        Host arrival times, s.
    group : array_like of int, shape (k,)
        Group of each arrival (a trial); used to judge the residual structure.
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    window_s : float, optional
        Fixed window length, s (no search).
    min_window_s, max_window_s : float
        Bounds of the window search, s (the lower one at least 31 groups' span).
    tolerance_s : float
        Residual structure accepted, s (20 µs: a tenth of the 0.2 ms drift target).
    transfer_samples : int, optional
        Samples per device transfer, when transfers are of fixed size (the phase search
        above); None: stamps taken as they are.
    curved : bool
        Quadratic envelopes per window (True) or lines. On the independent recordings of
        ``benchmarks/bench_extract_robustness.py`` (-1500 ppm, 300 ppm exponential
        warm-up over 6 min, 31-trial windows) curves cut the actuation RMSE from 0.33 to
        0.12 ms; a clock without drift loses 5 µs of RMSE to the extra freedom.

    Returns
    -------
    DriftingClockFit
    """
    n_arr, t_arr = _check_pairs(n, t)
    g_arr = np.asarray(group).reshape(-1)
    if g_arr.shape != n_arr.shape:
        raise ConfigError("group must have one entry per arrival")
    fit_windows = functools.partial(
        _fit_drifting, nominal_rate_hz=nominal_rate_hz, window_s=window_s,
        min_window_s=min_window_s, max_window_s=max_window_s, tolerance_s=tolerance_s,
        curved=curved,
    )  # fmt: skip
    fit = fit_windows(n_arr, t_arr, g_arr)
    if transfer_samples is None or transfer_samples < 2 or n_arr.shape[0] < 2:
        return fit
    phase = _transfer_phase(fit, n_arr, t_arr, g_arr, int(transfer_samples))
    if phase < 0:
        return fit
    n_end = n_arr + (phase - n_arr) % transfer_samples  # each stamp's transfer end
    refit = fit_windows(n_end, t_arr, g_arr)
    return DriftingClockFit(**{**refit.__dict__, "transfer_phase": phase})


def _transfer_phase(
    fit: DriftingClockFit,
    n: NDArray[np.int64],
    t: NDArray[np.float64],
    group: NDArray[np.int64],
    b: int,
) -> int:
    """Residue (mod b) of the device's transfer ends, or -1 (see fit_clock_drifting)."""
    resid = t - fit.to_host_time(n)
    uniq, g_idx = np.unique(group, return_inverse=True)
    if uniq.shape[0] < 8:
        return -1
    g_first = np.full(uniq.shape[0], np.iinfo(np.int64).max)
    np.minimum.at(g_first, g_idx, n)
    order = np.argsort(g_first)
    period = float(np.median(fit.period_s))

    def disagreeing(extra: NDArray[np.float64]) -> int:
        """Consecutive groups whose lowest stamps, re-dated by ``extra``, differ by more
        than a quarter sample."""
        m = np.full(uniq.shape[0], np.inf)
        np.minimum.at(m, g_idx, resid - extra)
        return int(np.sum(~(np.abs(np.diff(m[order])) < 0.25 * period)))

    none = disagreeing(np.zeros_like(resid))
    counts = np.array([disagreeing(((p - n) % b).astype(np.float64) * period) for p in range(b)])
    best = int(np.argmin(counts))
    runner_up = int(np.min(np.delete(counts, best)))
    # A phase must leave clearly fewer pairs disagreeing than the stamps as they are and
    # than any other phase (a neighbouring phase differs only for the groups of one
    # residue). Where the groups show only a few residues several phases tie: a file
    # whose counters were off by one for some trials had seven phases tied, and taking
    # one moved every sample by 0.5 ms. Independent recordings, 96 trials: the phase 5
    # disagreeing pairs, the next 24, none 84; 48 trials: 1, 5 and 37.
    margin = 2 * int(counts[best]) + 2
    if none >= margin and runner_up >= margin:
        return best
    return -1


def _fit_drifting(
    n_arr: NDArray[np.int64],
    t_arr: NDArray[np.float64],
    g_arr: NDArray[np.int64],
    *,
    nominal_rate_hz: float,
    window_s: float | None,
    min_window_s: float,
    max_window_s: float,
    tolerance_s: float,
    curved: bool,
) -> DriftingClockFit:
    """fit_clock_drifting on checked arrays, stamps as they are."""
    if n_arr.shape[0] < 2:
        fit = _nominal_fit(n_arr, t_arr, nominal_rate_hz)
        return DriftingClockFit(
            centres=np.array([float(fit.n_ref)]), half_width=1.0,
            n_ref=np.array([float(fit.n_ref)]), t_ref_s=np.array([fit.t_ref_s]),
            period_s=np.array([fit.period_s]), nominal_rate_hz=nominal_rate_hz,
        )  # fmt: skip
    order = np.lexsort((t_arr, n_arr))
    n_arr, t_arr, g_arr = n_arr[order], t_arr[order], g_arr[order]
    uniq, g_idx = np.unique(g_arr, return_inverse=True)
    n_groups = uniq.shape[0]
    # Groups in time order (by their first index).
    g_first = np.full(n_groups, np.iinfo(np.int64).max)
    np.minimum.at(g_first, g_idx, n_arr)
    g_rank = np.empty(n_groups, dtype=np.int64)
    g_rank[np.argsort(g_first)] = np.arange(n_groups)

    def group_minima(model: DriftingClockFit) -> NDArray[np.float64]:
        resid = t_arr - model.to_host_time(n_arr)
        m = np.full(n_groups, np.inf)
        np.minimum.at(m, g_idx, resid)
        return m[np.argsort(g_rank)]  # in time order

    span_s = float(n_arr[-1] - n_arr[0]) / nominal_rate_hz
    # A group's lowest arrival may sit a few samples above the envelope (its recorded
    # blocks need not end where the device's transfers end), so the structure is judged on
    # the running minimum over group_span groups, and a window spans at least that many.
    group_span = 31
    spacing = float(np.median(np.diff(np.sort(g_first)))) / nominal_rate_hz if n_groups > 1 else 0.0
    min_window_s = max(min_window_s, group_span * spacing)
    length = window_s if window_s is not None else min(max(span_s, min_window_s), max_window_s)
    keep = np.ones(n_arr.shape[0], dtype=bool)
    n_out = 0
    while True:
        half = 0.5 * length * nominal_rate_hz
        centres, n_ref, t_ref, per, curv = _windows_fit(
            n_arr[keep], t_arr[keep], half, nominal_rate_hz, curved
        )
        model = DriftingClockFit(
            centres=centres,
            half_width=half,
            n_ref=n_ref,
            t_ref_s=t_ref,
            period_s=per,
            nominal_rate_hz=nominal_rate_hz,
            outlier_groups=n_out,
            curvature_s=curv,
        )
        mins = group_minima(model)
        centre = _running(mins, 7, np.median)
        mad = float(np.median(np.abs(mins - centre))) + 1e-9
        low = mins < centre - max(10.0 * mad, 5e-4)
        smooth = _running(np.where(low, np.inf, mins), group_span, np.min)
        if low.any() and n_out == 0:
            bad_groups = np.argsort(g_rank)[low]
            keep &= ~np.isin(g_idx, bad_groups)
            n_out = int(low.sum())
            continue
        ok = smooth[~low] if (~low).any() else smooth
        spread = float(np.percentile(ok, 95) - np.percentile(ok, 5)) if ok.size > 2 else 0.0
        model = DriftingClockFit(**{**model.__dict__, "spread_s": spread})
        if window_s is not None or spread <= tolerance_s or length / 2 < min_window_s:
            return model
        length /= 2
