"""Noise-adaptive onset timing and the response shift, each with a standard error.

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

**Response.** The reported positions are aligned with the integrated gyro angle. The angle
of a white-noise rate is a random walk, so a least-squares fit of positions weights the
late, noisy part of the walk as if it were exact; the generalised least-squares fit of a
random-walk error is the fit of *increments* between consecutive packages (independent
errors, variance ∝ their time span). Model per increment j:
``Δq_j = k·(A(h_j - τ) - A(h_{j-1} - τ)) + c·(h_j - h_{j-1})`` (c absorbs a rate offset,
k a gain error), solved by Gauss-Newton for (τ, c, k) with the exact derivative of the
(linearly interpolated) angle and a backtracking line search, which converges to the
least-squares minimum (a fixed number of plain Gauss-Newton steps with the interpolated
speed as the derivative stopped up to 50 µs short of it, and could cycle). The standard
error of τ is the sandwich of the two errors the increments carry — the angle's random
walk, measured where the joint rests, and each package's latency jitter times the speed,
which enters neighbouring increments with opposite signs — with the sensor's and the
network's variances pooled over the chunk's trials (see the code's notes).

The gyro rate is averaged over ``RESPONSE_SMOOTH_S`` (a centred, odd-length moving
average: zero phase) before it is integrated. The raw angle's noise is a random walk, rough
at the sample scale; shifting it by τ resamples that roughness, so the cost is rough in τ
and its minimum wanders further than the residuals' curvature says (the error grew faster
than the noise, and the standard error did not follow). The average makes the angle smooth
at the scale of τ's uncertainty; over a ramp it offsets the angle by a constant, which the
increments cancel. See ``RESPONSE_SMOOTH_S`` for the measurements.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

__all__ = [
    "LEPSKI_KAPPA",
    "LEPSKI_NOISE_SCALE_S",
    "ONSET_WINDOWS_S",
    "RESPONSE_SMOOTH_S",
    "ladder_cap",
    "onset_adaptive",
    "response_increments",
]

FloatArray = NDArray[np.float64]

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
#: Step halvings of the response fit's line search before a row is taken as converged.
_LINE_SEARCH_HALVINGS = 6
#: Half the baseline of the angle's slope in the response's standard error, s.
_SE_SLOPE_S = 0.002
#: Width of the moving average of the gyro rate in the response fit, s (97 samples at
#: 8 kHz). Measured on the independent recordings (benchmarks/bench_extract_robustness.py,
#: 300 trials each; response RMSE and 95 % coverage of its standard error, without -> with):
#: UR10 clean 0.051 -> 0.047 ms, 10x noise 0.298 -> 0.149 ms (coverage 78 -> 98 %), 20x
#: 0.966 -> 0.265 ms (35 -> 94 %); clean UR10e 0.145 -> 0.042 ms. The width: on the UR10e
#: (2 ms packages) at 10x noise one period (2 ms) gave 0.436 ms, 4 ms 0.254 ms, 12 ms
#: 0.171 ms (68 / 93 / 99.7 % coverage); 20 ms gained little more and excludes more of each
#: trial's ends. An even length shifted the estimate by half a sample (63 µs).
RESPONSE_SMOOTH_S = 0.012
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


def response_increments(
    t_g: FloatArray,
    y: FloatArray,
    host: FloatArray,
    q_rel: FloatArray,
    dt: FloatArray,
    tau0: FloatArray,
    *,
    smooth_samples: int = 1,
    iterations: int = 15,
    max_step_s: float = 0.004,
) -> tuple[FloatArray, FloatArray]:
    """Shift τ of the reported positions behind the gyro angle, fitted on increments.

    Parameters
    ----------
    t_g : ndarray, shape (n, g)
        Gyro sample times, s (uniform per row).
    y : ndarray, shape (n, g)
        Physical speed along the commanded direction, rad/s.
    host : ndarray, shape (n, p)
        Package arrival times, s (NaN: lost or excluded).
    q_rel : ndarray, shape (n, p)
        Reported position change along the commanded direction, rad (NaN: lost).
    dt : ndarray, shape (n,)
        Each row's sample spacing, s.
    tau0 : ndarray, shape (n,)
        Starting shifts, s.
    smooth_samples : int, default 1
        Width of the centred moving average applied to ``y`` before it is integrated
        (odd: zero phase); 1 leaves it as it is. See the module notes.

    Returns
    -------
    tau, se : ndarray, shape (n,)
        Age of the reported state (s) and its standard error (s).
    """
    n, g = y.shape
    d = dt[:, None]
    if smooth_samples % 2 == 0 or smooth_samples < 1:
        raise ValueError(f"smooth_samples={smooth_samples} must be odd and >= 1 (zero phase)")
    if smooth_samples > 1:
        y = uniform_filter1d(y, smooth_samples, axis=1, mode="nearest")
    edge = (smooth_samples // 2) * d  # the ends, where the average is padded
    angle = (
        np.concatenate([np.zeros((n, 1)), np.cumsum(0.5 * (y[:, 1:] + y[:, :-1]), axis=1)], axis=1)
        * d
    )
    first = t_g[:, :1]
    ok = np.isfinite(host) & np.isfinite(q_rel)
    # Pair each valid package with the previous valid one.
    idx = np.where(ok, np.arange(host.shape[1]), -1)
    prev = np.maximum.accumulate(np.concatenate([np.full((n, 1), -1), idx[:, :-1]], axis=1), axis=1)
    use = ok & (prev >= 0)
    pj = np.clip(prev, 0, None)
    h = np.where(ok, host, 0.0)
    h1 = np.where(use, host, 0.0)
    h0 = np.where(use, np.take_along_axis(host, pj, axis=1), 0.0)
    dq = np.where(use, q_rel - np.take_along_axis(q_rel, pj, axis=1), 0.0)
    use &= (h0 > first + 0.03 + edge) & (h1 < t_g[:, -1:] - 0.005 - edge)
    span = np.where(use, h1 - h0, 1.0)
    typical = np.nanmedian(np.where(use, span, np.nan), axis=1, keepdims=True)
    wgt = np.where(use, typical / span, 0.0)
    wgt = np.nan_to_num(wgt)
    j_c = h1 - h0
    tau = np.asarray(tau0, dtype=np.float64).copy()
    c = np.zeros(n)
    k = np.ones(n)
    flat_angle = angle.ravel()

    def at(rows: NDArray[np.intp], x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The gyro angle at times x of ``rows`` (linear interpolation, the ends held) and
        its derivative with respect to x (the interpolant's slope; 0 past the ends)."""
        pos = (x - first[rows]) / d[rows]
        i0 = np.clip(np.floor(pos).astype(np.int64), 0, g - 2)
        frac = np.clip(pos - i0, 0.0, 1.0)
        flat = i0 + (rows * g)[:, None]
        lo = flat_angle[flat]
        hi = flat_angle[flat + 1]
        inside = (pos >= 0.0) & (pos <= g - 1)
        return lo + frac * (hi - lo), np.where(inside, (hi - lo) / d[rows], 0.0)

    def incr(rows: NDArray[np.intp], x: FloatArray) -> FloatArray:
        """Increments x_j - x_prev(j) of per-package values of ``rows``."""
        out: FloatArray = x - np.take_along_axis(x, pj[rows], axis=1)
        return out

    def residual(
        rows: NDArray[np.intp], a_all: FloatArray, c_r: FloatArray, k_r: FloatArray
    ) -> FloatArray:
        out: FloatArray = dq[rows] - k_r[:, None] * incr(rows, a_all) - c_r[:, None] * j_c[rows]
        return out

    def cost(
        rows: NDArray[np.intp], a_all: FloatArray, c_r: FloatArray, k_r: FloatArray
    ) -> FloatArray:
        res = residual(rows, a_all, c_r, k_r)
        out: FloatArray = np.sum(wgt[rows] * res * res, axis=1)
        return out

    def normal(w_: FloatArray, cols: list[FloatArray]) -> FloatArray:
        """Σ w·Jᵢ·Jⱼ per row, (rows, p, p), with a relative ridge against round-off."""
        a = np.stack([np.stack([np.sum(w_ * ci * cj, axis=1) for cj in cols], -1)
                      for ci in cols], -2)  # fmt: skip
        diag = np.einsum("nii->ni", a)
        ridged: FloatArray = a + np.eye(len(cols)) * (1e-12 * diag[:, None, :] + 1e-30)
        return ridged

    # Gauss-Newton on (τ, c, k) with the exact derivative of the interpolated angle and a
    # backtracking line search (the interpolant's slope jumps where a package crosses a
    # sample, so full steps can cycle); the angle at each package's time serves as the
    # end of one increment and the start of the next. c absorbs a rate offset, k a gain
    # error of the gyro (the out pulse's gain calibration is ~1 % off where the joint
    # still creeps in the pause: on the independent KR 5 the residuals were 7x the gyro's
    # noise, correlated over 2-4 packages). A row stops when its accepted step falls
    # below 1 ns or no step along its direction lowers the cost.
    rows = np.arange(n)
    a_cur, s_cur = at(rows, h - tau[:, None])
    f_cur = cost(rows, a_cur, c, k)
    active = rows
    for _ in range(iterations):
        if active.size == 0:
            break
        r_ = active
        w_ = wgt[r_]
        res = residual(r_, a_cur[r_], c[r_], k[r_])
        cols = [-k[r_, None] * incr(r_, s_cur[r_]), j_c[r_], incr(r_, a_cur[r_])]
        a = normal(w_, cols)
        b = np.stack([np.sum(w_ * ci * res, axis=1) for ci in cols], -1)
        ok_a = np.all(np.isfinite(a), axis=(1, 2)) & (np.abs(np.linalg.det(a)) > 0)
        delta = np.zeros_like(b)
        delta[ok_a] = np.linalg.solve(a[ok_a], b[ok_a][..., None])[..., 0]
        delta[:, 0] = np.clip(delta[:, 0], -max_step_s, max_step_s)
        step = np.ones(r_.size)
        pending = np.arange(r_.size)
        moved = np.zeros(r_.size)
        for _ in range(_LINE_SEARCH_HALVINGS):
            rr = r_[pending]
            tau_try = tau[rr] + step[pending] * delta[pending, 0]
            c_try = c[rr] + step[pending] * delta[pending, 1]
            k_try = k[rr] + step[pending] * delta[pending, 2]
            a_try, s_try = at(rr, h[rr] - tau_try[:, None])
            f_try = cost(rr, a_try, c_try, k_try)
            better = f_try <= f_cur[rr]
            acc = pending[better]
            ra = rr[better]
            tau[ra], c[ra], k[ra] = tau_try[better], c_try[better], k_try[better]
            a_cur[ra], s_cur[ra], f_cur[ra] = a_try[better], s_try[better], f_try[better]
            moved[acc] = np.abs(step[acc] * delta[acc, 0])
            pending = pending[~better]
            if pending.size == 0:
                break
            step[pending] *= 0.5
        active = r_[moved >= 1e-9]
    res = np.where(use, residual(rows, a_cur, c, k), 0.0)
    # The standard error with the slope of the angle over ±2 ms as the derivative: the
    # one-sample slope carries the gyro's white noise, which inflates Σ w·J² (and so
    # shrinks the error) as the noise grows (95 % coverage at 10x noise: 55 % -> 78 %).
    ap, _ = at(rows, h - tau[:, None] + _SE_SLOPE_S)
    am, _ = at(rows, h - tau[:, None] - _SE_SLOPE_S)
    speed = k[:, None] * (ap - am) / (2 * _SE_SLOPE_S)  # at each package's sample time
    cols = [np.where(use, -incr(rows, speed), 0.0), np.where(use, j_c, 0.0),
            np.where(use, incr(rows, a_cur), 0.0)]  # fmt: skip
    # Two errors reach the increments. The gyro angle's random walk: increments of
    # variance ∝ their span (the weights), correlated over the moving average's width.
    # And each package's *timing*: its latency jitter ε shifts its level by v·ε, which
    # enters two neighbouring increments with opposite signs (E[e_j e_j+1] = -v_j²·σ_ε²).
    # Counted as independent noise, the second made the standard error 2-9x the error
    # (clean: 99-100 % coverage on the independent recordings and our simulator). The
    # first is measured where the joint rests (no level error there: its lag-0..L
    # covariances γ_l), σ_ε² from the lag-1 covariance in motion beyond γ_1, and the error
    # of τ is the sandwich A⁻¹ Q A⁻¹ (A = JᵀWJ) of the covariance they give, positive by
    # construction. (σ_r² as the residual variance beyond the level part took up the
    # level estimate's error: a 10 % low σ_ε made it 7x the rest increments' variance.)
    n_use = np.maximum(np.sum(use, axis=1), 1)
    dof = n_use / np.maximum(n_use - len(cols), 1)
    v2 = np.where(use, speed, 0.0) ** 2
    v2_prev = np.where(use, np.take_along_axis(v2, pj, axis=1), 0.0)
    rest = use & (v2 + v2_prev <= (0.05 * np.max(np.abs(speed), axis=1, keepdims=True)) ** 2)
    has_rest = np.sum(rest, axis=1) >= 8
    typical_s = float(np.nanmedian(typical)) if np.isfinite(typical).any() else 1.0
    lags = int(min(max(math.ceil(smooth_samples * float(np.median(dt)) / typical_s), 1), 16))
    gamma = np.zeros((n, lags + 1))
    for lag in range(lags + 1):
        pair = rest[:, lag:] & rest[:, : rest.shape[1] - lag]
        prod = np.where(pair, res[:, lag:] * res[:, : res.shape[1] - lag], 0.0)
        gamma[:, lag] = np.sum(prod, axis=1) / np.maximum(np.sum(pair, axis=1), 1) * dof
    both = use[:, 1:] & use[:, :-1]
    lag1 = np.sum(np.where(both, res[:, 1:] * res[:, :-1], 0.0), axis=1)
    lag1 -= np.where(has_rest, gamma[:, 1], 0.0) * np.sum(both, axis=1)
    s_e2 = np.maximum(
        -lag1 / np.maximum(np.sum(np.where(both, v2[:, :-1], 0.0), axis=1), 1e-30), 0.0
    )
    # Without 8 increments at rest: σ_r² as the variance beyond the level part, no lags.
    gamma[~has_rest] = 0.0
    gamma[~has_rest, 0] = np.maximum(
        np.sum(wgt * (res * res * dof[:, None] - s_e2[:, None] * (v2 + v2_prev)), axis=1) / n_use,
        0.0,
    )[~has_rest]
    # Both are properties of the sensor and of the network, not of a trial: estimated per
    # trial from ~35 increments each, they scattered the standard error enough to give
    # the errors heavy tails (99th percentile of |error / se| 3.0-4.4 instead of 2.6:
    # 88-93 % coverage); the chunk's median is used, and a trial's own estimate where it
    # exceeds three times that (a disturbance of that trial: the ratio of two variance
    # estimates from ~35 increments stays below 2 on 99.9 % of trials).
    own_g, own_e = gamma[:, 0].copy(), s_e2.copy()
    if has_rest.any():
        pooled = np.median(gamma[has_rest], axis=0)
        gamma = np.where((has_rest & (own_g <= 3.0 * pooled[0]))[:, None], pooled, gamma)
    s_e2 = np.where(own_e > 3.0 * np.median(own_e), own_e, np.median(own_e))
    span_rel = np.where(use, 1.0 / np.where(wgt > 0, wgt, 1.0), 0.0)  # span / typical
    wcols = [wgt * ci for ci in cols]
    # Level k is the end of increment k and the start of the next: its error enters the
    # weighted scores as v_k·ε_k·(g_k - g_k+1), g = w·J.
    dcols = [np.diff(np.pad(x, ((0, 0), (0, 1))), axis=1) for x in wcols]

    def cov(i: int, j: int) -> FloatArray:
        out: FloatArray = gamma[:, 0] * np.sum(wcols[i] * wcols[j] * span_rel, axis=1)
        for lag in range(1, lags + 1):
            a_, b_ = wcols[i], wcols[j]
            out = out + gamma[:, lag] * np.sum(
                a_[:, lag:] * b_[:, :-lag] + a_[:, :-lag] * b_[:, lag:], axis=1
            )
        out = out + s_e2 * np.sum(v2 * dcols[i] * dcols[j], axis=1)
        return out

    q = np.stack([np.stack([cov(i, j) for j in range(len(cols))], -1)
                  for i in range(len(cols))], -2)  # fmt: skip
    a = normal(wgt, cols)
    ok_a = np.all(np.isfinite(a), axis=(1, 2)) & (np.abs(np.linalg.det(a)) > 0)
    se = np.full(n, np.nan)
    if ok_a.any():
        a_inv = np.linalg.inv(a[ok_a])
        se[ok_a] = np.sqrt(np.einsum("ni,nij,nj->n", a_inv[:, 0], q[ok_a], a_inv[:, 0]))
    return tau, se


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
