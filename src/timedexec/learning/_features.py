"""Model inputs as published (start configuration, actuated joint, direction) and replicates.

Encoding
--------
Each joint angle enters as its sine and cosine: a robot's gravity torque and inertia are
trigonometric polynomials of the angles, and a UR joint's range of ±2π makes q and q ± 2π
the same pose, which raw angles would place far apart. The direction is ±1. A combined
model (all joints in one) adds a one-hot column per joint it was trained on. Columns that
are constant in the training data (q6 = 0 throughout a sweep: the flange carries the gyro)
are kept in the order but carry no information; every estimator tolerates them.
Optionally (``time_input``) the sweep time in hours is the last column: it lets a model
separate the warm-up drift of the delays from their pose dependence.

Replicates
----------
A sweep repeats each condition (start configuration, joint, direction) about ten times. For
a model of the conditional mean with homoscedastic trial noise, the condition means, counts
and the pooled within-condition sum of squares are exact sufficient statistics: the sum of
squared errors over the trials is ``S_within + Σ n_i (ȳ_i - f(x_i))²``. Every estimator
here trains on the collapsed form (:func:`collapse_replicates`), which is about ten times
smaller and gives the same fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError

__all__ = [
    "Collapsed",
    "collapse_replicates",
    "encode_inputs",
    "feature_names",
]


_N_JOINTS = 6


def feature_names(
    joints: tuple[int, ...] | None = None, time_input: bool = False
) -> tuple[str, ...]:
    """Column names of :func:`encode_inputs`, in order.

    Parameters
    ----------
    joints : tuple of int, optional
        The joints of a combined model (one-hot columns ``joint_J``); None for a per-joint model.
    time_input : bool
        Whether the sweep time ``t_h`` (hours since the sweep started) is the last column.
    """
    names = [f"{f}_q{i}" for i in range(1, _N_JOINTS + 1) for f in ("sin", "cos")]
    names.append("direction")
    if joints is not None:
        names.extend(f"joint_{j}" for j in joints)
    if time_input:
        names.append("t_h")
    return tuple(names)


def encode_inputs(
    q_rad: ArrayLike,
    direction: ArrayLike,
    joint: ArrayLike | None = None,
    joints: tuple[int, ...] | None = None,
    t_h: ArrayLike | None = None,
) -> FloatArray:
    """Encode start configuration, direction (and joint) as model inputs.

    Parameters
    ----------
    q_rad : array, shape (n, 6) or (6,)
        Start configurations, rad.
    direction : array, shape (n,) or scalar
        +1 or -1.
    joint : array, shape (n,) or scalar, optional
        Actuated joints (1-based); needed with ``joints``.
    joints : tuple of int, optional
        Joints of a combined model: adds one one-hot column per joint. A joint outside
        ``joints`` raises :class:`~timedexec.errors.ConfigError`.
    t_h : array, shape (n,) or scalar, optional
        Sweep time, hours since the sweep started (models with a time input): last column.

    Returns
    -------
    ndarray, shape (n, 13 [+ len(joints)] [+ 1])
        Columns as :func:`feature_names` lists them.
    """
    q = np.asarray(q_rad, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != _N_JOINTS:
        raise ConfigError(f"start configurations must have shape (n, 6), got {q.shape}")
    n = q.shape[0]
    d = np.broadcast_to(np.asarray(direction, dtype=float), (n,))
    n_hot = len(joints) if joints is not None else 0
    cols = 2 * _N_JOINTS + 1 + n_hot + (1 if t_h is not None else 0)
    out = np.empty((n, cols))
    out[:, 0 : 2 * _N_JOINTS : 2] = np.sin(q)
    out[:, 1 : 2 * _N_JOINTS : 2] = np.cos(q)
    out[:, 2 * _N_JOINTS] = d
    if joints is not None:
        if joint is None:
            raise ConfigError("a combined model needs the actuated joint of every row")
        jt = np.broadcast_to(np.asarray(joint), (n,))
        known = np.isin(jt, joints)
        if not known.all():
            row = int(np.flatnonzero(~known)[0])
            raise ConfigError(
                f"row {row}: joint {jt[row]} is not one of the model's joints "
                f"{', '.join(map(str, joints))}"
            )
        out[:, 2 * _N_JOINTS + 1 : 2 * _N_JOINTS + 1 + n_hot] = (
            jt[:, None] == np.asarray(joints)[None, :]
        )
    if t_h is not None:
        out[:, -1] = np.broadcast_to(np.asarray(t_h, dtype=float), (n,))
    return out


@dataclass(frozen=True)
class Collapsed:
    """Replicates collapsed to distinct input rows (exact sufficient statistics).

    Attributes
    ----------
    X : ndarray, shape (m, d)
        Distinct input rows.
    mean : ndarray, shape (m,)
        Mean target per row.
    count : ndarray, shape (m,)
        Number of trials per row (float, for weighting).
    within_ss : float
        Sum over rows of the squared deviations of the trials from their row mean.
    n : int
        Number of trials.
    inverse : ndarray of int, shape (n,)
        Row of ``X`` each trial belongs to.
    """

    X: FloatArray
    mean: FloatArray
    count: FloatArray
    within_ss: float
    n: int
    inverse: NDArray[np.intp]


def collapse_replicates(X: ArrayLike, y: ArrayLike) -> Collapsed:
    """Group identical input rows; return their means, counts and the within sum of squares.

    Rows are identical when every feature is bit-equal (a sweep's repeats share their start
    configuration exactly; a delay table's CSV round-trips floats exactly).
    """
    Xa = np.ascontiguousarray(X, dtype=float)
    ya = np.asarray(y, dtype=float)
    if Xa.ndim != 2 or ya.shape != (Xa.shape[0],):
        raise ConfigError(f"X must be (n, d) and y (n,), got {Xa.shape} and {ya.shape}")
    uniq, inverse = np.unique(Xa, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    count = np.bincount(inverse, minlength=len(uniq)).astype(float)
    mean = np.bincount(inverse, weights=ya, minlength=len(uniq)) / count
    within_ss = float(np.sum((ya - mean[inverse]) ** 2))
    return Collapsed(
        X=uniq, mean=mean, count=count, within_ss=within_ss, n=len(ya), inverse=inverse
    )


def check_xy(X: ArrayLike, y: ArrayLike, who: str) -> tuple[FloatArray, FloatArray]:
    """Validate a training set: 2-D finite X, 1-D finite y of the same length, not empty."""
    Xa = np.asarray(X, dtype=float)
    ya = np.asarray(y, dtype=float)
    if Xa.ndim != 2:
        raise ConfigError(f"{who}: X must be 2-D (n_samples, n_features), got shape {Xa.shape}")
    if ya.ndim != 1 or len(ya) != len(Xa):
        raise ConfigError(
            f"{who}: y must be 1-D with one value per row of X ({len(Xa)}), got shape {ya.shape}"
        )
    if len(ya) == 0:
        raise ConfigError(f"{who}: the training set is empty; give at least one trial")
    bad = ~np.isfinite(Xa)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise ConfigError(
            f"{who}: X row {row} column {col} is {Xa[row, col]}; inputs must be finite"
        )
    bad_y = ~np.isfinite(ya)
    if bad_y.any():
        row = int(np.flatnonzero(bad_y)[0])
        raise ConfigError(f"{who}: y row {row} is {ya[row]}; targets must be finite")
    return Xa, ya


def check_x(X: ArrayLike, n_features: int, who: str) -> FloatArray:
    """Validate prediction inputs: 2-D, finite, the training number of features."""
    Xa = np.asarray(X, dtype=float)
    if Xa.ndim == 1:
        Xa = Xa[None, :]
    if Xa.ndim != 2 or Xa.shape[1] != n_features:
        raise ConfigError(
            f"{who}: X must have shape (n, {n_features}) like the training data, got {Xa.shape}"
        )
    bad = ~np.isfinite(Xa)
    if bad.any():
        row, col = (int(v) for v in np.argwhere(bad)[0])
        raise ConfigError(
            f"{who}: X row {row} column {col} is {Xa[row, col]}; inputs must be finite"
        )
    return Xa


def standardise(X: FloatArray, weight: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Column means and scales (weighted); a constant column gets scale 1."""
    w = np.ones(len(X)) if weight is None else weight
    mean = np.average(X, axis=0, weights=w)
    scale = np.sqrt(np.average((X - mean) ** 2, axis=0, weights=w))
    scale[scale < 1e-12] = 1.0
    return mean, scale
