"""Sub-sample time-shift fitting, shared by the simulator's ground truth and the extraction.

The actuation delay of a trial is *defined* as the time shift that best aligns the physical
joint speed with the commanded speed profile (least squares, with a free gain and offset),
and the response delay as the shift that best aligns the reported state with the physical
one. The simulator computes the truth with this fit on its noise-free physics; the
extraction applies the same fit to the gyro and the reported packages. A shift is what the
executor compensates, so this is the delay that matters for timing; it is also measurable
to microseconds (``notes/rsi-imu-ruckig.md``: least-squares fits reached 1-2 µs RMS where
peak timing reached about 50 µs).

Model per row: ``y(t) ≈ g · f(t - τ) + b``, solved by Gauss-Newton on (g, b, τ), vectorised
across rows.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from timedexec._types import FloatArray

__all__ = ["ONSET_FRACTION", "fit_shift", "interp_rows"]

#: The motion onset of a calibration trial is when the joint speed reaches this fraction of
#: the commanded speed; the actuation delay is that instant minus the instant the commanded
#: ramp reaches the same speed (the simulator's truth and the extraction both use it).
ONSET_FRACTION = 0.1

Template = Callable[[FloatArray], FloatArray]


def fit_shift(
    t: FloatArray,
    y: FloatArray,
    f: Template,
    df: Template,
    tau0: FloatArray,
    *,
    weights: FloatArray | None = None,
    iterations: int = 12,
    max_step_s: float = 0.004,
    fit_gain: bool = True,
    fit_offset: bool = True,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Least-squares time shift of ``f`` to ``y``, per row.

    Parameters
    ----------
    t : ndarray, shape (n, m)
        Sample times, s.
    y : ndarray, shape (n, m)
        Samples (NaN samples are ignored).
    f, df : callable
        Template and its time derivative; called with arrays of shape (n, m) of times
        ``t - τ`` (one row per fit).
    tau0 : ndarray, shape (n,)
        Starting shifts, s (within a few ms of the answer).
    weights : ndarray, shape (n, m), optional
        Sample weights (0 excludes a sample).
    iterations, max_step_s : int, float
        Gauss-Newton iterations and the largest shift change per iteration (s).
    fit_gain, fit_offset : bool
        Whether the gain g and the offset b are free (else 1 and 0).

    Returns
    -------
    tau, gain, offset, rms : ndarray, shape (n,)
        Fitted shift (s), gain, offset and the RMS residual.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    w = np.ones_like(y) if weights is None else np.asarray(weights, dtype=float).copy()
    valid = np.isfinite(y)
    w = np.where(valid, w, 0.0)
    y = np.where(valid, y, 0.0)
    tau = np.asarray(tau0, dtype=float).copy()
    n = y.shape[0]
    g = np.ones(n)
    b = np.zeros(n)
    for _ in range(iterations):
        x = t - tau[:, None]
        fx = f(x)
        dfx = df(x)
        r = y - g[:, None] * fx - b[:, None]
        cols: list[FloatArray | None] = [-g[:, None] * dfx]  # d(model)/d(tau)
        if fit_gain:
            cols.append(fx)
        if fit_offset:
            cols.append(None)  # the constant column, handled without materialising it
        p = len(cols)
        a = np.empty((n, p, p))
        rhs = np.empty((n, p))
        for i, ci in enumerate(cols):
            wi = w if ci is None else w * ci
            rhs[:, i] = np.sum(wi * r, axis=1)
            for j in range(i, p):
                cj = cols[j]
                a[:, i, j] = a[:, j, i] = np.sum(wi if cj is None else wi * cj, axis=1)
        a += np.eye(p) * 1e-12 * (np.trace(a, axis1=1, axis2=2)[:, None, None] + 1e-30)
        step = np.linalg.solve(a, rhs[..., None])[..., 0]
        dtau = np.clip(step[:, 0], -max_step_s, max_step_s)
        tau += dtau
        k = 1
        if fit_gain:
            g = g + step[:, k]
            k += 1
        if fit_offset:
            b = b + step[:, k]
        if np.all(np.abs(dtau) < 1e-9):
            break
    x = t - tau[:, None]
    r = (y - g[:, None] * f(x) - b[:, None]) * np.sqrt(w)
    rms = np.sqrt(np.sum(r**2, axis=1) / np.maximum(np.sum(w > 0, axis=1), 1))
    return tau, g, b, rms


def interp_rows(hist: FloatArray, pos: FloatArray) -> FloatArray:
    """Linear interpolation of each row of ``hist`` (n, G) at fractional indices ``pos``
    (n, m); positions outside [0, G-1] take the end values."""
    g = hist.shape[1]
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, g - 2)
    frac = np.clip(pos - i0, 0.0, 1.0)
    lo = np.take_along_axis(hist, i0, axis=1)
    hi = np.take_along_axis(hist, i0 + 1, axis=1)
    return lo + frac * (hi - lo)
