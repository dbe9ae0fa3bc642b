"""The "phys" method: a Bayesian linear model on the physics of the start pose.

Why this method: the paper explains the actuation delay by gravity and static friction
(joint 2, which lifts the most, is the slowest; the start pose dominates because static
friction exceeds kinetic friction) and names inertia beside them. The published models
must find those quantities in the sines and cosines of six angles. This one computes them
from the robot's own rigid-body model (:mod:`timedexec.robots`, the source of every number
about a robot) and fits a linear model on them, per joint:

    delay = w · [1, d, τ, |τ|, d·τ, I, √I  (, e^(-t/T_k) for T_k = 0.25 ... 4 h)]

with ``d`` the direction (±1), ``τ`` the gravity torque the actuated joint holds at the
start pose (N·m: breakaway torque grows with the load; ``d·τ`` > 0 moves against
gravity), ``I`` its reflected inertia there (kg·m²: the velocity loop's rise time grows
like ``√I`` for a PI loop, its natural period, up to ``I`` for a P loop, its time
constant) and, with a time input, a warm-up of unknown time constant as five decays the
prior can shrink.
The combined model gives each joint its own block of these coefficients.

Bayesian linear regression (Bishop, *Pattern Recognition and Machine Learning*, §3.3 and
§3.5): Gaussian prior ``N(0, α⁻¹)`` on the standardised slopes (the intercepts free),
trial noise ``β⁻¹``, both set by maximising the evidence (MacKay's fixed point, §3.5.2,
eqs. 3.91-3.95) on replicate-collapsed data (condition means weighted by their counts plus
the within-condition sum of squares: exact). The predictive distribution is exact: mean
``φᵀm``, variance of the mean ``φᵀSφ``, trial noise ``β⁻¹``.

What it costs: 7 coefficients per joint (12 with the time input) and their covariance
instead of hundreds of conditions; a fit is a fixed point on a matrix of a few dozen rows
(milliseconds). The bundle stores the coefficients, their covariance and, to refuse a
bundle whose robot model changed since training, the physical terms at a few training
inputs (re-computed and compared at load). A prediction evaluates the robot's gravity
torque and inertia at the start pose: slower than the GP's (docs/models.md).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.learning._base import DelayEstimator, not_fitted
from timedexec.learning._features import check_x, check_xy, collapse_replicates
from timedexec.learning._method import DelayMethod, ModelInputs
from timedexec.robots import RobotSpec, get_robot, gravity_torque, joint_inertia

__all__ = ["METHOD", "PhysicalLinearModel"]


#: Warm-up time constants of the time basis, hours.
WARMUP_H = (0.25, 0.5, 1.0, 2.0, 4.0)
_POSE_TERMS = ("direction", "tau_nm", "abs_tau_nm", "dir_x_tau_nm", "inertia_kgm2", "sqrt_inertia")
_N_REFERENCE = 8  # training inputs whose terms a bundle keeps, to detect a changed robot model


def _terms(inputs: ModelInputs) -> tuple[str, ...]:
    return _POSE_TERMS + (tuple(f"warmup_{t:g}h" for t in WARMUP_H) if inputs.time_input else ())


def _physics(
    X: FloatArray, inputs: ModelInputs, spec: RobotSpec
) -> tuple[NDArray[np.intp], FloatArray]:
    """Decode encoded inputs X (n, d): each row's block (its joint's index in the
    combined model, else 0) and its physical terms (n, k), in :func:`_terms` order."""
    n = len(X)
    q = np.arctan2(X[:, 0:12:2], X[:, 1:12:2])  # the same pose: both are 2π-periodic in q
    direction = X[:, 12]
    if inputs.joint is None:
        block = np.argmax(X[:, 13 : 13 + len(inputs.joints)], axis=1)
        joint = np.asarray(inputs.joints)[block]
    else:
        block = np.zeros(n, dtype=np.intp)
        joint = np.full(n, inputs.joint)
    rows = np.arange(n)
    tau = gravity_torque(spec, q)[rows, joint - 1]
    inertia = joint_inertia(spec, q)[rows, joint - 1]
    cols = [direction, tau, np.abs(tau), direction * tau, inertia, np.sqrt(inertia)]
    if inputs.time_input:
        cols += [np.exp(-X[:, -1] / t) for t in WARMUP_H]
    return block, np.column_stack(cols)


def _design(
    block: NDArray[np.intp], phys: FloatArray, x_mean: FloatArray, x_scale: FloatArray
) -> FloatArray:
    """Rows ``onehot(block) ⊗ [1, standardised terms]``: shape (n, blocks·(k + 1))."""
    n, k = phys.shape
    Z = np.zeros((n, len(x_mean), k + 1))
    rows = np.arange(n)
    Z[rows, block, 0] = 1.0
    Z[rows, block, 1:] = (phys - x_mean[block]) / x_scale[block]
    return Z.reshape(n, -1)


def _check_columns(X: FloatArray, inputs: ModelInputs) -> None:
    """Refuse rows whose direction is not ±1 or whose one-hot names no single joint."""
    bad = np.abs(X[:, 12]) != 1.0
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ConfigError(
            f"PhysicalLinearModel.fit: X row {row}: direction {X[row, 12]} must be +1 or -1"
        )
    if inputs.joint is None:
        hot = X[:, 13 : 13 + len(inputs.joints)]
        bad = (np.count_nonzero(hot, axis=1) != 1) | (hot.max(axis=1) != 1.0)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                f"PhysicalLinearModel.fit: X row {row} has no single joint in its one-hot "
                f"columns {hot[row].tolist()}; encode it with "
                f"encode_inputs(..., joints={inputs.joints})"
            )


class _Predictor:
    """The fitted model from its arrays: numpy and :mod:`timedexec.robots` only."""

    def __init__(self, arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> None:
        self.inputs = inputs
        self.spec = get_robot(inputs.robot)
        self.x_mean = np.asarray(arrays["x_mean"], dtype=float)
        self.x_scale = np.asarray(arrays["x_scale"], dtype=float)
        self.coef = np.asarray(arrays["coef"], dtype=float)
        self.cov = np.asarray(arrays["cov"], dtype=float)
        y_mean, y_std, noise_var = (float(v) for v in arrays["scalars"])
        self.y_mean, self.y_std = y_mean, y_std
        self.noise_var_s2 = noise_var

    def predict(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Mean delay (n,), s, and the variance of the mean (n,), s², at encoded X (n, d)."""
        return self.from_terms(*_physics(X, self.inputs, self.spec))

    def from_terms(
        self, block: NDArray[np.intp], phys: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`predict` from the rows' blocks and physical terms (:func:`_physics`)."""
        Z = _design(block, phys, self.x_mean, self.x_scale)
        mean = self.y_mean + self.y_std * (Z @ self.coef)
        var = self.y_std**2 * np.einsum("ij,jk,ik->i", Z, self.cov, Z)
        return mean, np.maximum(var, 0.0)

    def predict_one(self, x: FloatArray) -> tuple[float, float]:
        """:meth:`predict` of one encoded input (d,): floats."""
        mean, var = self.predict(x[None, :])
        return float(mean[0]), float(var[0])


class _Pair:
    """A joint's actuation and response models on one evaluation of the robot's physics
    (the gravity torque and inertia cost most of a prediction)."""

    def __init__(self, act: _Predictor, resp: _Predictor) -> None:
        self.act, self.resp = act, resp

    def predict_one(self, x: FloatArray) -> tuple[float, float, float, float]:
        """``(act mean, act var, resp mean, resp var)`` at one encoded input (d,), s and s²."""
        terms = _physics(x[None, :], self.act.inputs, self.act.spec)
        am, av = self.act.from_terms(*terms)
        rm, rv = self.resp.from_terms(*terms)
        return float(am[0]), float(av[0]), float(rm[0]), float(rv[0])


def _pair(act: _Predictor, resp: _Predictor) -> _Pair | None:
    return _Pair(act, resp) if act.inputs == resp.inputs else None


class PhysicalLinearModel(DelayEstimator):
    """Bayesian linear regression of a delay on the physics of the start pose.

    Parameters
    ----------
    inputs : ModelInputs
        What the encoded input columns mean: the robot (its gravity torque and inertia come
        from :mod:`timedexec.robots`), the joint of a per-joint model or the combined
        model's joints, and whether the sweep time is the last column. Required.
    max_iter : int
        Largest number of evidence fixed-point iterations.
    tol : float
        Relative change of ``α`` and ``β`` below which the iteration stops.

    Attributes
    ----------
    terms_ : tuple of str
        The physical terms of each joint's block, after its intercept.
    coef_ : ndarray, shape (p,)
        Posterior mean of the weights on the standardised design (normalised target).
    cov_ : ndarray, shape (p, p)
        Posterior covariance of the weights.
    x_mean_, x_scale_ : ndarray, shape (blocks, k)
        Standardisation of each block's terms.
    y_mean_, y_std_ : float
        Target normalisation, s.
    alpha_, beta_ : float
        Prior precision of the slopes and noise precision (normalised units).
    noise_std_ : float
        Trial noise standard deviation, s.
    effective_parameters_ : float
        Well-determined parameters ``γ`` plus the free intercepts.
    n_iter_ : int
        Fixed-point iterations used.
    reference_X_, reference_terms_ : ndarray, shape (r, d) and (r, k)
        Up to 8 training inputs and their physical terms (a bundle re-computes and compares
        them at load).
    predictor_ : object
        The deployed predictor built from :meth:`to_arrays` (what a bundle runs).
    """

    def __init__(
        self, *, inputs: ModelInputs | None = None, max_iter: int = 500, tol: float = 1e-10
    ) -> None:
        self.inputs = inputs
        self.max_iter = max_iter
        self.tol = tol

    def _check_params(self) -> ModelInputs:
        if not isinstance(self.inputs, ModelInputs):
            raise ConfigError(
                f"PhysicalLinearModel: inputs={self.inputs!r}; it needs the model's inputs "
                "(robot, joint, columns) to compute gravity torque and inertia: "
                "make_estimator('phys', inputs=ModelInputs.of('ur10', '2', joints, False))"
            )
        if (
            isinstance(self.max_iter, bool)
            or not isinstance(self.max_iter, int)
            or self.max_iter < 1
        ):
            raise ConfigError(
                f"PhysicalLinearModel: max_iter={self.max_iter!r} must be an integer >= 1"
            )
        if not (isinstance(self.tol, int | float) and 0 < self.tol < 1):
            raise ConfigError(f"PhysicalLinearModel: tol={self.tol!r} must lie in (0, 1)")
        return self.inputs

    def fit(self, X: ArrayLike, y: ArrayLike) -> PhysicalLinearModel:
        """Fit on encoded inputs X (n, d) and delays y (n,), s."""
        inputs = self._check_params()
        Xa, ya = check_xy(X, y, "PhysicalLinearModel.fit")
        n_features = len(inputs.feature_names())
        if Xa.shape[1] != n_features:
            raise ConfigError(
                f"PhysicalLinearModel.fit: X has {Xa.shape[1]} columns; the inputs "
                f"{inputs} have {n_features} ({', '.join(inputs.feature_names())})"
            )
        _check_columns(Xa, inputs)
        col = collapse_replicates(Xa, ya)
        block, phys = _physics(col.X, inputs, get_robot(inputs.robot))
        n_blocks = 1 if inputs.joint is not None else len(inputs.joints)
        w = col.count
        x_mean = np.zeros((n_blocks, phys.shape[1]))
        x_scale = np.ones((n_blocks, phys.shape[1]))
        for b in range(n_blocks):
            sel = block == b
            if sel.any():
                x_mean[b] = np.average(phys[sel], axis=0, weights=w[sel])
                sd = np.sqrt(np.average((phys[sel] - x_mean[b]) ** 2, axis=0, weights=w[sel]))
                x_scale[b] = np.where(sd > 1e-12 * np.maximum(np.abs(x_mean[b]), 1.0), sd, 1.0)
        self.y_mean_ = float(ya.mean())
        self.y_std_ = float(ya.std()) or 1.0
        Z = _design(block, phys, x_mean, x_scale)
        t = (col.mean - self.y_mean_) / self.y_std_
        within = col.within_ss / self.y_std_**2
        free = np.zeros(Z.shape[1], dtype=bool)
        free[:: phys.shape[1] + 1] = True  # each block's intercept
        alpha, beta, m, S, gamma, it = _evidence(
            Z, t, w, within, col.n, free, self.max_iter, self.tol
        )
        self.n_features_in_ = Xa.shape[1]
        self.terms_ = _terms(inputs)
        self.x_mean_, self.x_scale_ = x_mean, x_scale
        self.coef_, self.cov_ = m, S
        self.alpha_, self.beta_ = alpha, beta
        self.noise_std_ = float(self.y_std_ / np.sqrt(beta))
        self.effective_parameters_ = float(gamma + free.sum())
        self.n_iter_ = it
        ref = np.unique(np.linspace(0, len(col.X) - 1, min(_N_REFERENCE, len(col.X))).astype(int))
        self.reference_X_ = col.X[ref]
        self.reference_terms_ = phys[ref]
        self.predictor_ = _Predictor(self.to_arrays(), inputs)
        return self

    def predict(self, X: ArrayLike, return_std: bool = False) -> Any:
        """Mean delay (n,), s, at encoded inputs X (n, d); with ``return_std`` also the
        standard deviation of a single trial (the mean's uncertainty and the trial noise)."""
        pred = getattr(self, "predictor_", None)
        if pred is None:
            raise not_fitted("PhysicalLinearModel")
        Xa = check_x(X, self.n_features_in_, "PhysicalLinearModel.predict")
        mean, var = pred.predict(Xa)
        if not return_std:
            return mean
        return mean, np.sqrt(var + pred.noise_var_s2)

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The fitted model as named numeric arrays (for a model bundle)."""
        return {
            "x_mean": self.x_mean_,
            "x_scale": self.x_scale_,
            "coef": self.coef_,
            "cov": self.cov_,
            "scalars": np.array([self.y_mean_, self.y_std_, self.noise_std_**2]),
            "reference_X": self.reference_X_,
            "reference_terms": self.reference_terms_,
        }


def _evidence(
    Z: FloatArray,
    t: FloatArray,
    w: FloatArray,
    within: float,
    n_trials: int,
    free: NDArray[np.bool_],
    max_iter: int,
    tol: float,
) -> tuple[float, float, FloatArray, FloatArray, float, int]:
    """Evidence maximisation for ``α`` (slopes) and ``β`` (noise), Bishop eqs. 3.91-3.95,
    weighted by the condition counts ``w``; ``free`` columns get no prior.

    Returns ``(α, β, m, S, γ, iterations)``: posterior mean and covariance, the number of
    well-determined slopes.
    """
    G = Z.T @ (w[:, None] * Z)
    b = Z.T @ (w * t)
    prior = np.diag((~free).astype(float))
    pen = ~free

    def posterior(alpha: float, beta: float) -> tuple[FloatArray, FloatArray]:
        inv = np.linalg.inv(beta * G + alpha * prior)
        S = np.asarray(0.5 * (inv + inv.T), dtype=np.float64)  # symmetric to rounding
        return beta * (S @ b), S

    alpha, beta, gamma, iterations = 1.0, 1.0, 0.0, 0
    while iterations < max_iter:
        iterations += 1
        m, S = posterior(alpha, beta)
        gamma = float(np.sum(1.0 - alpha * np.diag(S)[pen]))  # well-determined slopes
        r = t - Z @ m
        e_data = within + float(w @ (r * r))  # the trials' squared error (exact, collapsed)
        e_weights = float(m[pen] @ m[pen])
        alpha_new = min(max(gamma / e_weights, 1e-12), 1e12) if e_weights > 0 else 1e12
        dof = max(n_trials - gamma - float(free.sum()), 1.0)
        beta_new = dof / e_data if e_data > 0 else 1e12
        done = abs(alpha_new - alpha) <= tol * alpha and abs(beta_new - beta) <= tol * beta
        alpha, beta = alpha_new, beta_new
        if done:
            break
    m, S = posterior(alpha, beta)
    return alpha, beta, m, S, gamma, iterations


def _info(est: PhysicalLinearModel) -> dict[str, Any]:
    k = len(est.terms_)
    slopes = est.coef_.reshape(-1, k + 1)[:, 1:] * est.y_std_ / est.x_scale_
    inputs = est.inputs
    assert inputs is not None
    blocks = [inputs.key] if inputs.joint is not None else [str(j) for j in inputs.joints]
    return {
        "terms": list(est.terms_),
        "slope_s_per_unit": {
            blk: [float(v) for v in row] for blk, row in zip(blocks, slopes, strict=True)
        },
        "noise_std_s": est.noise_std_,
        "prior_precision": est.alpha_,
        "effective_parameters": est.effective_parameters_,
        "iterations": int(est.n_iter_),
    }


def _predictor(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> _Predictor:
    return _Predictor(arrays, inputs)


def _check(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> str:
    blocks = 1 if inputs.joint is not None else len(inputs.joints)
    k = len(_terms(inputs))
    if arrays["x_mean"].shape != (blocks, k) or len(arrays["coef"]) != blocks * (k + 1):
        return (
            f"arrays for {blocks} block(s) of {k} terms expected, got x_mean "
            f"{arrays['x_mean'].shape} and coef {arrays['coef'].shape}"
        )
    reference = np.asarray(arrays["reference_X"], dtype=float)
    _, terms = _physics(reference, inputs, get_robot(inputs.robot))
    if not np.allclose(terms, arrays["reference_terms"], rtol=1e-9, atol=1e-12):
        return (
            f"the gravity torque and inertia of robot {inputs.robot!r} in this timedexec differ "
            "from those the phys model was trained with (the robot model changed): retrain"
        )
    return ""


#: "b" blocks (1, or the combined model's joints), "k" terms per block, "p" = b·(k + 1)
#: weights, "r" reference inputs, "f" input columns.
METHOD = DelayMethod(
    name="phys",
    label="physical linear model",
    description="Bayesian linear regression on the gravity torque and inertia of the actuated "
    "joint at the start pose (from the robot's rigid-body model), direction and warm-up; "
    "mean and standard deviation",
    estimator=lambda inputs, random_state: PhysicalLinearModel(inputs=inputs),
    fit_cost=0.2,
    arrays=(
        ("x_mean", ("b", "k")),
        ("x_scale", ("b", "k")),
        ("coef", ("p",)),
        ("cov", ("p", "p")),
        ("scalars", ("3",)),
        ("reference_X", ("r", "f")),
        ("reference_terms", ("r", "k")),
    ),
    predictor=_predictor,
    info=_info,
    variance=True,
    pair=_pair,
    check=_check,
    default=False,
)
