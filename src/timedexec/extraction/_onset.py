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
``LEPSKI_KAPPA`` of that window's standard deviation. Clean data keep the short window
(bias-limited), noisy data widen it (variance-limited); the error grows smoothly with the
noise. The reported standard error adds the zero-rate (baseline) uncertainty to the bound.

**Response.** The reported positions are aligned with the integrated gyro angle. The angle
of a white-noise rate is a random walk, so a least-squares fit of positions weights the
late, noisy part of the walk as if it were exact; the generalised least-squares fit of a
random-walk error is the fit of *increments* between consecutive packages (independent
errors, variance ∝ their time span). Model per increment j:
``Δq_j = A(h_j - τ) - A(h_{j-1} - τ) + c·(h_j - h_{j-1})`` (c absorbs a rate offset),
solved by Gauss-Newton for (τ, c); the standard error of τ comes from the residuals.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from timedexec._signal import interp_rows

__all__ = ["LEPSKI_KAPPA", "ONSET_WINDOWS_S", "onset_adaptive", "response_increments"]

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
_SCALE = 0.005  # s: the polynomial's abscissa unit (keeps the normal equations well scaled)


def _cubic_root(
    t_g: FloatArray,
    y: FloatArray,
    w: FloatArray,
    k: NDArray[np.int64],
    level: FloatArray,
    dt: float,
    window: tuple[float, float],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted cubic fit around sample ``k`` and its root at ``level``.

    Returns the crossing time (s), the root's variance factor gᵀ(XᵀWX)⁻¹g·scale²/p'² (s²
    per (rad/s)² of noise variance) and the slope p'(t*) (rad/s²)."""
    n, g = y.shape
    lo, hi = -round(window[0] / dt), round(window[1] / dt)
    offs = np.arange(lo, hi + 1)
    idx = np.clip(k[:, None] + offs, 0, g - 1)
    inside = ((k[:, None] + offs) >= 0) & ((k[:, None] + offs) < g)
    yy = np.take_along_axis(y, idx, axis=1)
    ww = np.take_along_axis(w, idx, axis=1) * inside
    tc = np.take_along_axis(t_g, k[:, None], axis=1)[:, 0]
    xs = (np.take_along_axis(t_g, idx, axis=1) - tc[:, None]) / _SCALE
    vander = np.stack([np.ones_like(xs), xs, xs**2, xs**3], axis=-1)
    a = np.einsum("nmi,nmj->nij", vander * ww[..., None], vander)
    # Relative ridge against round-off; the absolute one keeps a window without samples
    # (a trial flagged anyway) solvable.
    a += np.eye(4) * (1e-9 * np.trace(a, axis1=1, axis2=2)[:, None, None] + 1e-12)
    yy = np.where(np.isfinite(yy), yy, 0.0)
    b = np.einsum("nmi,nm->ni", vander * ww[..., None], yy)
    coef = np.linalg.solve(a, b[..., None])[..., 0]
    root = np.zeros(n)
    x_lo, x_hi = lo * dt / _SCALE, hi * dt / _SCALE
    for _ in range(8):
        p = coef[:, 0] + coef[:, 1] * root + coef[:, 2] * root**2 + coef[:, 3] * root**3
        dp = coef[:, 1] + 2 * coef[:, 2] * root + 3 * coef[:, 3] * root**2
        step = (p - level) / np.where(np.abs(dp) > 1e-9, dp, np.nan)
        root = np.clip(root - step, x_lo, x_hi)
    dp = coef[:, 1] + 2 * coef[:, 2] * root + 3 * coef[:, 3] * root**2
    gvec = np.stack([np.ones(n), root, root**2, root**3], axis=-1)
    ainv_g = np.linalg.solve(a, gvec[..., None])[..., 0]
    quad = np.einsum("ni,ni->n", gvec, ainv_g)
    slope = dp / _SCALE
    var_factor = quad / np.where(np.abs(slope) > 1e-9, slope, np.nan) ** 2
    return tc + root * _SCALE, var_factor, slope


def onset_adaptive(
    t_g: FloatArray,
    y: FloatArray,
    have: NDArray[np.bool_],
    k_coarse: NDArray[np.int64],
    level: FloatArray,
    sigma: FloatArray,
    dt: float,
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

    Returns
    -------
    dict
        ``onset`` (s), ``crb`` (s, square root of the bound for the chosen window),
        ``bias`` (s, allowance for the window's bias), ``window`` (index into :data:`ONSET_WINDOWS_S`), ``slope`` (rad/s², at the
        crossing), ``missing`` (fraction of the chosen window's samples lost).
    """
    w = have.astype(np.float64)
    n = y.shape[0]
    est, sd, slopes = [], [], []
    k = k_coarse
    for window in ONSET_WINDOWS_S:
        t_on, vf, slope = _cubic_root(t_g, y, w, k, level, dt, window)
        est.append(t_on)
        sd.append(sigma * np.sqrt(np.abs(vf)))
        slopes.append(slope)
    t_all, sd_all, sl_all = np.array(est), np.array(sd), np.array(slopes)
    chosen = np.zeros(n, dtype=np.int64)
    alive = np.ones(n, dtype=bool)
    for j in range(1, len(ONSET_WINDOWS_S)):
        agree = np.all(
            np.abs(t_all[j] - t_all[:j]) <= LEPSKI_KAPPA * sd_all[:j], axis=0
        ) & np.isfinite(t_all[j])
        alive &= agree
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
    return {
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

    Returns
    -------
    tau, se : ndarray, shape (n,)
        Age of the reported state (s) and its standard error (s).
    """
    n = y.shape[0]
    d = dt[:, None]
    angle = np.concatenate(
        [np.zeros((n, 1)), np.cumsum(0.5 * (y[:, 1:] + y[:, :-1]), axis=1)], axis=1
    ) * d
    first = t_g[:, :1]
    ok = np.isfinite(host) & np.isfinite(q_rel)
    # Pair each valid package with the previous valid one.
    idx = np.where(ok, np.arange(host.shape[1]), -1)
    prev = np.maximum.accumulate(np.concatenate([np.full((n, 1), -1), idx[:, :-1]], axis=1), axis=1)
    use = ok & (prev >= 0)
    pj = np.clip(prev, 0, None)
    h1 = np.where(use, host, 0.0)
    h0 = np.where(use, np.take_along_axis(host, pj, axis=1), 0.0)
    dq = np.where(use, q_rel - np.take_along_axis(q_rel, pj, axis=1), 0.0)
    use &= (h0 > first + 0.03) & (h1 < t_g[:, -1:] - 0.005)
    span = np.where(use, h1 - h0, 1.0)
    typical = np.nanmedian(np.where(use, span, np.nan), axis=1, keepdims=True)
    wgt = np.where(use, typical / span, 0.0)
    wgt = np.nan_to_num(wgt)
    tau = np.asarray(tau0, dtype=np.float64).copy()
    c = np.zeros(n)

    def at(hist: FloatArray, x: FloatArray) -> FloatArray:
        return interp_rows(hist, (x - first) / d)

    for _ in range(iterations):
        a1, a0 = at(angle, h1 - tau[:, None]), at(angle, h0 - tau[:, None])
        v1, v0 = at(y, h1 - tau[:, None]), at(y, h0 - tau[:, None])
        r = dq - (a1 - a0) - c[:, None] * (h1 - h0)
        j_tau = -(v1 - v0)
        j_c = h1 - h0
        s_tt = np.sum(wgt * j_tau * j_tau, axis=1)
        s_tc = np.sum(wgt * j_tau * j_c, axis=1)
        s_cc = np.sum(wgt * j_c * j_c, axis=1) + 1e-18
        b_t = np.sum(wgt * j_tau * r, axis=1)
        b_c = np.sum(wgt * j_c * r, axis=1)
        det = s_tt * s_cc - s_tc**2
        det = np.where(np.abs(det) > 1e-30, det, np.nan)
        d_tau = (s_cc * b_t - s_tc * b_c) / det
        d_c = (s_tt * b_c - s_tc * b_t) / det
        d_tau = np.clip(np.nan_to_num(d_tau), -max_step_s, max_step_s)
        tau += d_tau
        c += np.nan_to_num(d_c)
        if np.all(np.abs(d_tau) < 1e-9):
            break
    a1, a0 = at(angle, h1 - tau[:, None]), at(angle, h0 - tau[:, None])
    r = dq - (a1 - a0) - c[:, None] * (h1 - h0)
    m = np.maximum(np.sum(use, axis=1) - 2, 1)
    s2 = np.sum(wgt * r * r, axis=1) / m
    se = np.sqrt(s2 * s_cc / det)
    return tau, se
