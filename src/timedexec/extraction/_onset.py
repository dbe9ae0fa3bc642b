"""Noise-adaptive onset timing with a standard error.

**Onset.** Near the level crossing the physical speed is modelled as a cubic polynomial
``p(t)`` plus white Gaussian noise of standard deviation σ (estimated per trial from the
still samples before the command). For a window of N samples the least-squares root
``p(t*) = level`` is the maximum-likelihood estimate of the crossing under that model, and
its delta-method variance

    var(t*) = σ² · gᵀ (XᵀWX)⁻¹ g / p'(t*)²,   g = (1, x*, x*², x*³)

is the Cramér-Rao bound of the crossing time for the model (X the cubic design, W the
weights: 0 for lost samples). A longer window lowers the bound but lets the breakaway kink
and the approach to the plateau bias the cubic; so the window is chosen per trial by
Lepski's method (Lepski, Mammen and Spokoiny, Ann. Statist. 25(3), 1997): of a ladder of
growing windows, take the largest whose estimate agrees with every smaller window's within
κ of that window's standard deviation (κ from ``LEPSKI_KAPPA``, rising with that standard
deviation beyond ``LEPSKI_NOISE_SCALE_S``). Clean data keep the short window
(bias-limited), noisy data widen it (variance-limited); the error grows smoothly with the
noise. The reported standard error adds to the bound the zero-rate (baseline) uncertainty,
the window's bias allowance, the disagreement of the wider windows the test rejected (the
median excess over noise: the threshold region at high noise) and a misfit term: where the fit's
residuals exceed the noise (reduced chi-square above 1: a resonance or the breakaway the
cubic does not follow) the bound is scaled by the excess (independent recordings, 95 %
coverage: UR10 88.7 -> 91.0 %, KR 5 90.3 -> 91.3 %, 10x noise 91.9 -> 94.0 %).

The response delay's fit is in :mod:`._response`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray

__all__ = [
    "LEPSKI_KAPPA",
    "LEPSKI_NOISE_SCALE_S",
    "ONSET_WINDOWS_S",
    "ladder_cap",
    "onset_adaptive",
]


#: Ladder of fit windows (before, after the coarse crossing), s. The first is the window
#: the extraction used before issue 14 (clean data keep it); each next one is ~1.35x wider,
#: after the crossing only: before it lies the breakaway kink, after it the speed keeps
#: rising towards the plateau.
ONSET_WINDOWS_S: tuple[tuple[float, float], ...] = (
    (0.005, 0.010),
    (0.005, 0.014),
    (0.005, 0.019),
    (0.005, 0.026),
    (0.005, 0.035),
    (0.005, 0.046),
)
#: Lepski threshold: a wider window is accepted while its estimate lies within this many
#: standard deviations of every narrower window's. Measured on the independent recordings
#: (benchmarks/bench_extract_robustness.py): 2.0 let the cubic's bias near the breakaway
#: kink (0.1-0.2 ms) through on clean data; 1.0 keeps clean data near the first window.
LEPSKI_KAPPA = 1.0
#: Standard deviation (s) of a narrower window's estimate above which the Lepski threshold
#: rises from ``LEPSKI_KAPPA`` towards ``LEPSKI_KAPPA + 1``: κ = 1 + sd²/(sd² + s0²). At 1 sd
#: a wider window is rejected by chance alone on 32 % of comparisons, which is right
#: where the windows' bias (0.05-0.15 ms) is of the order of their noise (clean data) but
#: stopped the ladder early where the noise dwarfs any bias. Independent recordings, 300
#: trials, two seeds (actuation RMSE, κ = 1 -> this): 10x noise 1.05 / 0.97 -> 0.88 /
#: 0.79 ms, 5x 0.52 / 0.53 -> 0.48 / 0.45, 3x 0.30 / 0.33 -> 0.30 / 0.29; clean
#: within ±0.003 ms (UR10, UR10e, KR 5 0.157 / 0.148 -> 0.159 / 0.147) and on our
#: simulator within ±0.002 ms. s0 = 0.3 ms gained the same at 10x and lost 0.003-0.006 ms
#: clean; a fixed κ = 2 gained more at 10x (0.87 / 0.78) but cost up to 0.04 ms clean.
LEPSKI_NOISE_SCALE_S = 0.5e-3
_SCALE = 0.005  # s: the polynomial's abscissa unit (keeps the normal equations well scaled)


def _cubic_roots(
    t_g: FloatArray,
    y: FloatArray,
    w: FloatArray,
    k: NDArray[np.int64],
    level: FloatArray,
    dt: float,
    windows: tuple[tuple[float, float], ...],
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Weighted cubic fits around sample ``k`` and their roots at ``level``, one per window.

    The windows share their left edge, so the normal equations of every window are
    prefix sums of one set of per-sample moments (x⁰..x⁶ and y·x⁰..x³, x the abscissa
    relative to sample k in units of _SCALE): one pass over the widest window instead of
    one per window.

    Returns, each of shape (len(windows), n): the crossing time (s), the root's variance
    factor gᵀ(XᵀWX)⁻¹g/p'² (s² per (rad/s)² of noise variance), the slope p'(t*)
    (rad/s²) and the mean squared residual of the fit ((rad/s)², per degree of freedom)."""
    n, g = y.shape
    los = [round(wd[0] / dt) for wd in windows]
    his = [round(wd[1] / dt) for wd in windows]
    if len(set(los)) != 1:
        raise ValueError("onset windows must share their left edge")
    lo = -los[0]
    offs = np.arange(lo, max(his) + 1)
    raw_idx = k[:, None] + offs
    inside = (raw_idx >= 0) & (raw_idx < g)
    idx = np.clip(raw_idx, 0, g - 1)
    yy = np.take_along_axis(y, idx, axis=1)
    ww = np.take_along_axis(w, idx, axis=1) * inside
    yy = np.where(np.isfinite(yy), yy, 0.0)
    tc = t_g[np.arange(n), k]
    xs = (np.take_along_axis(t_g, idx, axis=1) - tc[:, None]) / _SCALE
    pw = np.empty((7, *xs.shape))
    pw[0] = ww
    for p in range(1, 7):
        np.multiply(pw[p - 1], xs, out=pw[p])
    mom = np.cumsum(pw, axis=2)  # (7, n, m): Σ w·x^p over the window's first j+1 samples
    ymom = np.cumsum(pw[:4] * yy, axis=2)  # (4, n, m): Σ w·y·x^p
    y2mom = np.cumsum(ww * yy * yy, axis=1)  # (n, m): Σ w·y²
    est, var, slopes, msr = [], [], [], []
    pairs = np.add.outer(np.arange(4), np.arange(4))
    for hi in his:
        j = hi - lo  # column of the window's last sample
        a = np.moveaxis(mom[:, :, j][pairs], -1, 0)  # (n, 4, 4)
        b = ymom[:, :, j].T  # (n, 4)
        # Relative ridge against round-off; the absolute one keeps a window without samples
        # (a trial flagged anyway) solvable.
        a = a + np.eye(4) * (1e-9 * np.trace(a, axis1=1, axis2=2)[:, None, None] + 1e-12)
        coef = np.linalg.solve(a, b[..., None])[..., 0]
        root = np.zeros(n)
        x_lo, x_hi = lo * dt / _SCALE, hi * dt / _SCALE
        for _ in range(8):
            val = coef[:, 0] + coef[:, 1] * root + coef[:, 2] * root**2 + coef[:, 3] * root**3
            dp = coef[:, 1] + 2 * coef[:, 2] * root + 3 * coef[:, 3] * root**2
            step = (val - level) / np.where(np.abs(dp) > 1e-9, dp, np.nan)
            root = np.clip(root - step, x_lo, x_hi)
        dp = coef[:, 1] + 2 * coef[:, 2] * root + 3 * coef[:, 3] * root**2
        gvec = np.stack([np.ones(n), root, root**2, root**3], axis=-1)
        ainv_g = np.linalg.solve(a, gvec[..., None])[..., 0]
        quad = np.einsum("ni,ni->n", gvec, ainv_g)
        slope = dp / _SCALE
        # Residual sum of squares of the least-squares fit: yᵀWy - coefᵀXᵀWy.
        rss = y2mom[:, j] - np.einsum("ni,ni->n", coef, b)
        msr.append(np.maximum(rss, 0.0) / np.maximum(mom[0, :, j] - 4.0, 1.0))
        est.append(tc + root * _SCALE)
        var.append(quad / np.where(np.abs(slope) > 1e-9, slope, np.nan) ** 2)
        slopes.append(slope)
    return np.array(est), np.array(var), np.array(slopes), np.array(msr)


#: Fewest trials of a group whose windows' mean disagreement caps its ladder.
_CAP_MIN_TRIALS = 16


def ladder_cap(
    t_all: FloatArray, sd_all: FloatArray, group: NDArray[np.int64] | None
) -> NDArray[np.int64]:
    """Widest window each trial's ladder may reach: per group of trials with the same
    dynamics, the window of least estimated mean squared error.

    A window's bias is the same for trials of one joint and direction, so it shows in the
    group's *median* step between consecutive windows long before one trial's Lepski test
    can see it (a KR 5's widest window: +0.12 ms, about one standard deviation). Taking
    the narrowest window as unbiased, window j's bias is the sum of the median steps up to
    it (less their sampling error) and its mean squared error that squared plus the
    group's median variance. Independent recordings, two seeds (actuation RMSE, clean):
    KR 5 0.159 / 0.147 -> 0.148 / 0.143 ms, UR10e 0.120 / 0.120 -> 0.107 / 0.111, UR10
    0.11 either way; our simulator (400 trials) UR10 / UR10e / KR 5 0.104 / 0.100 / 0.113
    -> 0.096 / 0.095 / 0.110. Only where the narrowest window's standard deviation
    is below ``LEPSKI_NOISE_SCALE_S``: beyond it the narrow windows' roots jump (the
    threshold region), the narrowest is no longer the unbiased one, and the cap chose
    too narrow (20x noise: 1.52 -> 2.10 ms). Medians, not means, for the same reason."""
    w, n = t_all.shape
    cap = np.full(n, w - 1, dtype=np.int64)
    keys = np.zeros(n, dtype=np.int64) if group is None else np.asarray(group)
    for key in np.unique(keys[keys >= 0]):
        rows = np.flatnonzero((keys == key) & np.all(np.isfinite(t_all), axis=0))
        if rows.size < _CAP_MIN_TRIALS or np.median(sd_all[0, rows]) > LEPSKI_NOISE_SCALE_S:
            continue
        steps = np.diff(t_all[:, rows], axis=0)
        se_step = 1.2533 * np.std(steps, axis=1) / np.sqrt(rows.size)  # of a median
        bias = np.r_[0.0, np.cumsum(np.median(steps, axis=1))]
        se_bias = np.r_[0.0, np.sqrt(np.cumsum(se_step**2))]
        mse = np.maximum(bias**2 - se_bias**2, 0.0) + np.median(sd_all[:, rows] ** 2, axis=1)
        cap[keys == key] = int(np.argmin(mse))
    return cap


def onset_adaptive(
    t_g: FloatArray,
    y: FloatArray,
    have: NDArray[np.bool_],
    k_coarse: NDArray[np.int64],
    level: FloatArray,
    sigma: FloatArray,
    dt: float,
    group: NDArray[np.int64] | None = None,
) -> dict[str, FloatArray]:
    """Crossing of ``level`` with a window chosen per trial (Lepski) and its uncertainty.

    Parameters
    ----------
    t_g : ndarray, shape (n, g)
        Sample times, s.
    y : ndarray, shape (n, g)
        Speed along the commanded direction, rad/s (lost samples: any finite value).
    have : ndarray of bool, shape (n, g)
        Samples actually received.
    k_coarse : ndarray of int, shape (n,)
        Sample index of the coarse crossing.
    level : ndarray, shape (n,)
        Onset level, rad/s.
    sigma : ndarray, shape (n,)
        White-noise standard deviation of ``y`` per sample, rad/s.
    dt : float
        Nominal sample spacing, s.
    group : ndarray of int, shape (n,), optional
        Trials of one joint and direction (same dynamics): the widest window is chosen per
        group (:func:`ladder_cap`); -1: a trial in no group (its full ladder, and it does
        not count in any group's statistics); None: one group.

    Returns
    -------
    dict
        ``onset`` (s), ``crb`` (s, square root of the bound for the chosen window),
        ``bias`` (s, allowance for the window's bias), ``conflict`` (s, the rejected
        wider windows' median disagreement beyond noise), ``misfit`` (s, the bound scaled by
        the residuals' excess over the noise), ``window`` (index into
        :data:`ONSET_WINDOWS_S`), ``slope`` (rad/s², at the crossing), ``missing``
        (fraction of the chosen window's samples lost).
    """
    w = have.astype(np.float64)
    n = y.shape[0]
    k = k_coarse
    t_all, vf_all, sl_all, msr_all = _cubic_roots(t_g, y, w, k, level, dt, ONSET_WINDOWS_S)
    sd_all = sigma * np.sqrt(np.abs(vf_all))
    cap = ladder_cap(t_all, sd_all, group)
    chosen = np.zeros(n, dtype=np.int64)
    alive = np.ones(n, dtype=bool)
    for j in range(1, len(ONSET_WINDOWS_S)):
        sd = sd_all[:j]
        kappa = LEPSKI_KAPPA + sd**2 / (sd**2 + LEPSKI_NOISE_SCALE_S**2)
        agree = np.all(np.abs(t_all[j] - t_all[:j]) <= kappa * sd, axis=0) & np.isfinite(t_all[j])
        alive &= agree & (j <= cap)
        chosen[alive] = j
    r = np.arange(n)
    lo = np.array([round(wd[0] / dt) for wd in ONSET_WINDOWS_S])[chosen]
    hi = np.array([round(wd[1] / dt) for wd in ONSET_WINDOWS_S])[chosen]
    offs = np.arange(-lo.max(), hi.max() + 1)
    idx = k[:, None] + offs
    in_win = (offs >= -lo[:, None]) & (offs <= hi[:, None]) & (idx >= 0) & (idx < y.shape[1])
    got = np.take_along_axis(have, np.clip(idx, 0, y.shape[1] - 1), axis=1) & in_win
    missing = 1.0 - got.sum(axis=1) / np.maximum(in_win.sum(axis=1), 1)
    # Bias allowance: how far the chosen window moved the estimate from the narrowest
    # (least biased) one, beyond what their noise explains (var(t0 - tj) ~ sd0² - sdj² for
    # nested least-squares fits).
    d2 = (t_all[chosen, r] - t_all[0]) ** 2 - np.maximum(sd_all[0] ** 2 - sd_all[chosen, r] ** 2, 0)
    # Conflict: the wider windows the Lepski test rejected disagree with the chosen one
    # beyond what their noise explains (same construction as the bias allowance); the
    # median over them, so that one wider window's own bias does not count as the chosen
    # one's error. At high noise that is the threshold region: a narrow window's root has
    # jumped, errors of several standard deviations the bound does not see, and every wider
    # window witnesses it. Independent recordings, 95 % coverage without the term / the
    # next wider window alone / the median of all wider: 20x noise 78.8 / 89.0 / 92.9 %
    # (RMSE 2.25 / 1.88 / 1.62 ms of the trials kept), 10x 94.0 / 96.9 / 96.9 %, clean
    # unchanged (96-97 %); our simulator 95.8-98.2 -> 97.0-98.8 % (400 trials per robot).
    # A trial it makes too uncertain is flagged (``max_se_s``), not trusted.
    ladder = np.arange(len(ONSET_WINDOWS_S))[:, None]
    wider = (ladder > chosen[None, :]) & (ladder <= cap[None, :])
    dev2 = (t_all - t_all[chosen, r]) ** 2 - np.maximum(sd_all[chosen, r] ** 2 - sd_all**2, 0)
    dev2 = np.where(wider & np.isfinite(dev2), dev2, np.nan)
    witnessed = np.isfinite(dev2).any(axis=0)
    dn2 = np.zeros(n)
    dn2[witnessed] = np.nanmedian(dev2[:, witnessed], axis=0)
    conflict = np.sqrt(np.maximum(dn2, 0.0))
    # Misfit: residuals beyond the noise mean a signal the cubic does not follow (the
    # joint's resonance, the breakaway); its variance is scaled by the reduced chi-square.
    chi2 = msr_all[chosen, r] / np.maximum(sigma**2, 1e-30)
    misfit = sd_all[chosen, r] * np.sqrt(np.maximum(chi2 - 1.0, 0.0))
    return {
        "conflict": conflict,
        "misfit": misfit,
        "onset": t_all[chosen, r],
        "crb": sd_all[chosen, r],
        "bias": np.sqrt(np.maximum(d2, 0.0)),
        "window": chosen.astype(np.float64),
        "slope": sl_all[chosen, r],
        "missing": missing,
    }


def _row_nanmedian(x: FloatArray) -> FloatArray:
    """Median of each row's finite values (NaN for a row without any): one sort of the
    whole array instead of a Python-level loop over rows (``np.nanmedian`` on rows)."""
    srt = np.sort(x, axis=1)  # NaN sort last
    c = np.sum(np.isfinite(x), axis=1)
    r = np.arange(x.shape[0])
    lo = srt[r, np.maximum((c - 1) // 2, 0)]
    hi = srt[r, np.maximum(c // 2, 0)]
    return np.where(c > 0, 0.5 * (lo + np.where(c % 2 == 1, lo, hi)), np.nan)


def _robust_sigma(y: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    """White-noise standard deviation per row from first differences (MAD, robust to a
    slow trend and to outliers), over the masked samples."""
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size < 2:
        return np.full(y.shape[0], np.nan)
    span = slice(int(cols[0]), int(cols[-1]) + 1)  # the masked samples lie in one stretch
    ys, ms = y[:, span], mask[:, span]
    d = np.where(ms[:, 1:] & ms[:, :-1], np.diff(ys, axis=1), np.nan)
    med = _row_nanmedian(d)
    mad = _row_nanmedian(np.abs(d - med[:, None]))
    return np.asarray(1.4826 * mad / np.sqrt(2.0))


def _parabolic_peak(t: FloatArray, y: FloatArray, k: NDArray[np.int64]) -> FloatArray:
    n, g = y.shape
    k = np.clip(k, 1, g - 2)
    r = np.arange(n)
    y0, y1, y2 = y[r, k - 1], y[r, k], y[r, k + 1]
    den = y0 - 2 * y1 + y2
    frac = np.where(np.abs(den) > 1e-15, 0.5 * (y0 - y2) / den, 0.0)
    return t[r, k] + np.clip(frac, -1, 1) * (t[r, k + 1] - t[r, k])
