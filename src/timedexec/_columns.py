"""Columns over conditions: the shapes a delay may follow, built from arrays.

Shared by the effects (each declares the term families of its own shape,
:meth:`timedexec.effects.Effect.term_families`) and the discrepancy workflow (the shapes
outside the vocabulary). Every function takes per-condition arrays of length ``m``: the
actuated joint (1-based), the joints present, a variable; none knows an effect by name.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray

__all__ = [
    "CHANGE_POINT_DF",
    "MIN_SPREAD",
    "change_point",
    "normalised_per_joint",
    "per_joint_columns",
    "stack_columns",
    "sweep_fraction",
    "time_basis",
]


#: Smallest spread of a variable over a joint's conditions for a family to use it.
MIN_SPREAD = 1e-6

#: Degrees of freedom charged for choosing a change point on the residuals (a search over
#: 37 positions: the likelihood-ratio statistic of an unknown change point exceeds a
#: one-column chi-square by about as much as two more columns would).
CHANGE_POINT_DF = 2


def stack_columns(cols: list[FloatArray], m: int) -> FloatArray:
    """Columns with a non-zero spread, each scaled to unit RMS, as an (m, k) array."""
    keep = []
    for c in cols:
        rms = float(np.sqrt(np.mean(c**2)))
        if rms > 1e-12 and np.ptp(c) > 1e-12:
            keep.append(c / rms)
    return np.column_stack(keep) if keep else np.zeros((m, 0))


def _function(f: str, x: FloatArray) -> FloatArray:
    """The named function of ``x`` (the per-joint bases' vocabulary)."""
    if f == "x":
        return x
    if f == "x2":
        return x**2
    if f == "sqrt":
        return np.sqrt(np.abs(x))
    if f == "x|x|":
        return x * np.abs(x)
    if f == "sign_sqrt":
        return np.sign(x) * np.sqrt(np.abs(x))
    if f == "1-s":
        return 1.0 - x
    if f == "hinge_half":
        return np.maximum(0.5 - x, 0.0)
    if f == "fast":
        return np.exp(-x / 0.1)
    raise KeyError(f)


def per_joint_columns(
    joint: NDArray[np.int64],
    joints: tuple[int, ...],
    x: FloatArray,
    funcs: list[str],
    *,
    min_spread: float = MIN_SPREAD,
) -> tuple[list[FloatArray], tuple[int, ...]]:
    """``f(x)`` on each joint's conditions (zero elsewhere) for each named function
    (``x``, ``x2``, ``sqrt``, ``x|x|``, ``sign_sqrt``, ``1-s``, ``hinge_half``, ``fast``).

    Returns the columns and the joints whose ``x`` spreads by more than ``min_spread``
    (the others get no column)."""
    cols: list[FloatArray] = []
    used: list[int] = []
    for j in joints:
        mk = joint == j
        if np.ptp(x[mk]) <= min_spread:
            continue
        used.append(j)
        xj = x[mk]
        for f in funcs:
            col = np.zeros(len(joint))
            col[mk] = _function(f, xj)
            cols.append(col)
    return cols, tuple(used)


def normalised_per_joint(
    joint: NDArray[np.int64], joints: tuple[int, ...], x: FloatArray
) -> FloatArray:
    """``x / max |x|`` over each joint's conditions (0 where a joint's x is all 0)."""
    out = np.zeros(len(joint))
    for j in joints:
        mk = joint == j
        top = float(np.max(np.abs(x[mk]))) if mk.any() else 0.0
        if top > 0:
            out[mk] = x[mk] / top
    return out


def sweep_fraction(t_start_s: FloatArray) -> FloatArray:
    """Sweep time of each condition as a fraction of the sweep, 0..1."""
    t = t_start_s
    span = float(np.ptp(t)) if len(t) else 0.0
    out: FloatArray = (t - t.min()) / span if span > 0 else np.zeros(len(t))
    return out


def time_basis(s: FloatArray) -> list[FloatArray]:
    """Functions of the sweep fraction that vanish at its end: a linear spline with knots
    at 1/4, 1/2, 3/4 and a fast early decay."""
    return [
        1.0 - s,
        np.maximum(0.75 - s, 0.0),
        np.maximum(0.5 - s, 0.0),
        np.maximum(0.25 - s, 0.0),
        np.exp(-s / 0.05),
    ]


def change_point(
    s: FloatArray, r: FloatArray, mask: NDArray[np.bool_] | None = None
) -> float | None:
    """The sweep fraction at which a step best explains ``r`` over the conditions of
    ``mask`` (least squares of ``r`` on a constant, a slope and ``[s < c]``, ``c`` on a grid
    of 37 quantiles of ``s`` between 5 % and 95 %). None when there are too few conditions.

    A warm-up that ends abruptly (a mode switch, grease reaching its temperature) is a
    step; a linear spline with fixed knots smears it over a knot interval and leaves a
    misfit the size of the step near it.
    """
    x = s if mask is None else s[mask]
    y = r if mask is None else r[mask]
    if len(x) < 12 or np.ptp(x) <= 0:
        return None
    grid = np.unique(np.quantile(x, np.linspace(0.05, 0.95, 37)))
    best: tuple[float, float] | None = None
    for c in grid:
        a = np.column_stack([np.ones(len(x)), x, (x < c).astype(float)])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        ss = float(np.sum((y - a @ coef) ** 2))
        if best is None or ss < best[0]:
            best = (ss, float(c))
    return None if best is None else best[1]
