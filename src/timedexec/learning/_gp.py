"""The "gpr" method: a Gaussian process on replicate-collapsed delays, exact or FITC, mean and std."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.learning._base import DelayEstimator, not_fitted
from timedexec.learning._features import check_x, check_xy, collapse_replicates, standardise
from timedexec.learning._gpcore import (
    GPPairPredictor,
    GPPredictor,
    build_predictor,
    neg_log_likelihood,
    predictor_from_arrays,
)
from timedexec.learning._method import DelayMethod, ModelInputs
from timedexec.learning._threads import single_threaded_blas

__all__ = ["METHOD", "DelayGP"]


class DelayGP(DelayEstimator):
    """Gaussian-process regression of a delay, trained on condition means.

    Kernel ``σ_f² exp(-½ Σ_l (x_l - x'_l)² / ℓ_l²)`` (one length scale per input) plus
    trial noise ``σ_n²``; inputs standardised, targets normalised to zero mean and unit
    variance over the trials (as scikit-learn's ``normalize_y=True``).

    Replicates (identical input rows) are collapsed to their means, counts and the
    within-condition sum of squares, which are exact sufficient statistics: the fitted
    model, its hyperparameters' likelihood and its predictions equal those of a GP on every
    trial (see :mod:`timedexec.learning._gpcore`), at the cost of the number of distinct
    conditions ``M`` instead of the number of trials.

    * ``M <= max_exact_conditions``: exact conditioning (a Cholesky factor of ``M × M``).
    * larger: FITC on ``n_inducing`` k-means centres of the conditions (in the length-scale
      metric).

    Hyperparameters maximise the exact likelihood of a random subset of at most
    ``max_hyper_conditions`` conditions (all their trials), with L-BFGS-B and analytic
    gradients; the model is then conditioned on all conditions.

    Parameters
    ----------
    optimize : bool
        Fit the hyperparameters; if False use the initial values below.
    length_scale : float or array of shape (d,), optional
        Initial length scales in standardised input units; default ``sqrt(d)``.
    signal_variance, noise_variance : float, optional
        Initial ``σ_f²`` and ``σ_n²`` in normalised target units; default from the
        within-condition scatter.
    length_scale_bounds, signal_variance_bounds, noise_variance_bounds : (float, float)
        Optimisation bounds.
    n_restarts_optimizer : int
        Extra optimisations from random log-uniform starts within the bounds.
    max_hyper_conditions : int
        Largest number of conditions the likelihood is optimised on.
    max_exact_conditions : int
        Largest number of conditions conditioned on exactly; above, FITC.
    n_inducing : int
        Inducing inputs for FITC.
    max_variance_conditions : int or None
        The predictive variance is exact up to this many conditions; above, it is the
        exact variance given a well-spread subset of this many conditions, an upper bound
        that keeps one prediction ``O(s²)`` (see
        :func:`~timedexec.learning._gpcore.build_predictor`). None: always exact. The
        mean always uses every condition.
    random_state : int, Generator or None
        Subset and restart draws, k-means.

    Attributes
    ----------
    predictor_ : GPPredictor
        The conditioned model in pure-numpy predictor form (what a bundle stores).
    length_scale_ : ndarray, shape (d,)
        Length scales in standardised input units.
    signal_variance_, noise_variance_ : float
        ``σ_f²``, ``σ_n²`` in normalised target units.
    noise_std_ : float
        Trial noise standard deviation in target units (s for delays).
    x_mean_, x_scale_ : ndarray, shape (d,)
        Input standardisation.
    y_mean_, y_std_ : float
        Target normalisation over the trials.
    X_train_, y_train_, counts_ : ndarray
        Distinct conditions (encoded inputs), their mean targets and trial counts.
    within_ss_ : float
        Within-condition sum of squares (target units squared).
    n_trials_ : int
        Number of training trials.
    sparse_ : bool
        Whether FITC was used.
    inducing_points_ : ndarray, shape (n_inducing, d) or None
        FITC inducing inputs (encoded input units).
    log_marginal_likelihood_value_ : float
        Log marginal likelihood of the optimisation subset at the optimum.
    """

    def __init__(
        self,
        *,
        optimize: bool = True,
        length_scale: float | ArrayLike | None = None,
        signal_variance: float | None = None,
        noise_variance: float | None = None,
        length_scale_bounds: tuple[float, float] = (1e-2, 1e3),
        signal_variance_bounds: tuple[float, float] = (1e-6, 1e2),
        noise_variance_bounds: tuple[float, float] = (1e-6, 1e1),
        n_restarts_optimizer: int = 0,
        max_hyper_conditions: int = 400,
        max_exact_conditions: int = 4000,
        n_inducing: int = 1000,
        max_variance_conditions: int | None = 200,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.optimize = optimize
        self.length_scale = length_scale
        self.signal_variance = signal_variance
        self.noise_variance = noise_variance
        self.length_scale_bounds = length_scale_bounds
        self.signal_variance_bounds = signal_variance_bounds
        self.noise_variance_bounds = noise_variance_bounds
        self.n_restarts_optimizer = n_restarts_optimizer
        self.max_hyper_conditions = max_hyper_conditions
        self.max_exact_conditions = max_exact_conditions
        self.n_inducing = n_inducing
        self.max_variance_conditions = max_variance_conditions
        self.random_state = random_state

    # ------------------------------------------------------------------ fit
    def _check_params(self) -> None:
        for name in ("length_scale_bounds", "signal_variance_bounds", "noise_variance_bounds"):
            lo, hi = getattr(self, name)
            if not 0 < lo < hi < np.inf:
                raise ConfigError(f"DelayGP: {name}=({lo}, {hi}) needs 0 < low < high < inf")
        for name, low in (
            ("n_restarts_optimizer", 0),
            ("max_hyper_conditions", 2),
            ("max_exact_conditions", 2),
            ("n_inducing", 2),
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
                raise ConfigError(f"DelayGP: {name}={v!r} must be an integer >= {low}")
        mvc = self.max_variance_conditions
        if mvc is not None and (
            isinstance(mvc, bool) or not isinstance(mvc, int | np.integer) or mvc < 2
        ):
            raise ConfigError(
                f"DelayGP: max_variance_conditions={mvc!r} must be None or an integer >= 2"
            )

    def fit(self, X: ArrayLike, y: ArrayLike) -> DelayGP:
        """Fit hyperparameters and condition on all trials.

        Parameters
        ----------
        X : array, shape (n, d)
            Encoded inputs (:func:`~timedexec.learning.encode_inputs`).
        y : array, shape (n,)
            Delays, s.
        """
        with single_threaded_blas():
            return self._fit(X, y)

    def _fit(self, X: ArrayLike, y: ArrayLike) -> DelayGP:
        self._check_params()
        Xa, ya = check_xy(X, y, "DelayGP.fit")
        rng = np.random.default_rng(self.random_state)
        col = collapse_replicates(Xa, ya)
        d = Xa.shape[1]
        self.n_features_in_ = d
        self.x_mean_, self.x_scale_ = standardise(col.X, col.count)
        y_mean = float(ya.mean())
        y_std = float(ya.std())
        if not y_std > 0:
            y_std = 1.0
        self.y_mean_, self.y_std_ = y_mean, y_std
        Xs = (col.X - self.x_mean_) / self.x_scale_
        ybar = (col.mean - y_mean) / y_std
        wss = col.within_ss / y_std**2
        self.X_train_, self.y_train_, self.counts_ = col.X, col.mean, col.count
        self.within_ss_, self.n_trials_ = col.within_ss, col.n
        m = len(ybar)

        theta0 = self._initial_theta(d, wss, col.n, m)
        bounds = self._bounds(d)
        if self.optimize:
            from scipy.optimize import minimize  # here: loading a bundle needs no optimiser

            if m > self.max_hyper_conditions:
                sub = np.sort(rng.choice(m, size=self.max_hyper_conditions, replace=False))
            else:
                sub = np.arange(m)
            cnt = col.count[sub]
            # The subset's within scatter: trials of the chosen conditions only.
            sub_mask = np.zeros(m, dtype=bool)
            sub_mask[sub] = True
            resid = ya - col.mean[col.inverse]
            wss_sub = float(np.sum(resid[sub_mask[col.inverse]] ** 2)) / y_std**2
            n_sub = int(cnt.sum())
            args = (Xs[sub], ybar[sub], cnt, wss_sub, n_sub)
            starts = [theta0]
            lo = np.array([b[0] for b in bounds])
            hi = np.array([b[1] for b in bounds])
            starts += [rng.uniform(lo, hi) for _ in range(int(self.n_restarts_optimizer))]
            best: tuple[float, FloatArray] | None = None
            for start in starts:
                res = minimize(
                    neg_log_likelihood,
                    start,
                    args=args,
                    jac=True,
                    method="L-BFGS-B",
                    bounds=bounds,
                    options={"maxiter": 200, "ftol": 1e-7, "gtol": 1e-4},
                )
                if best is None or res.fun < best[0]:
                    best = (float(res.fun), np.asarray(res.x, dtype=float))
            assert best is not None
            theta = best[1]
            self.log_marginal_likelihood_value_ = -best[0]
        else:
            theta = theta0
            self.log_marginal_likelihood_value_ = -neg_log_likelihood(
                theta, Xs, ybar, col.count, wss, col.n
            )[0]
        ell = np.exp(theta[:d])
        sf2 = float(np.exp(theta[d]))
        sn2 = float(np.exp(theta[d + 1]))
        self.length_scale_ = ell
        self.signal_variance_ = sf2
        self.noise_variance_ = sn2
        self.noise_std_ = float(np.sqrt(sn2) * y_std)

        if m <= self.max_exact_conditions:
            self.sparse_ = False
            self.inducing_points_ = None
        else:
            self.sparse_ = True
            Zs = self._inducing(Xs / ell, rng) * ell
            self.inducing_points_ = Zs * self.x_scale_ + self.x_mean_
        self.predictor_ = build_predictor(**self._state())
        return self

    def _initial_theta(self, d: int, wss: float, n: int, m: int) -> FloatArray:
        if self.length_scale is None:
            ell = np.full(d, np.sqrt(d))
        else:
            ell = np.broadcast_to(np.asarray(self.length_scale, dtype=float), (d,)).copy()
            if not np.all(ell > 0):
                raise ConfigError(f"DelayGP: length_scale={self.length_scale!r} must be > 0")
        if self.noise_variance is not None:
            sn2 = float(self.noise_variance)
        elif n > m:
            sn2 = wss / (n - m)
        else:
            sn2 = 0.5
        sf2 = (
            float(self.signal_variance)
            if self.signal_variance is not None
            else max(1.0 - sn2, 0.05)
        )
        if not (sn2 > 0 and sf2 > 0):
            raise ConfigError("DelayGP: signal_variance and noise_variance must be > 0")
        lo_n, hi_n = self.noise_variance_bounds
        lo_s, hi_s = self.signal_variance_bounds
        lo_l, hi_l = self.length_scale_bounds
        theta = np.concatenate(
            [
                np.log(np.clip(ell, lo_l, hi_l)),
                [np.log(np.clip(sf2, lo_s, hi_s)), np.log(np.clip(sn2, lo_n, hi_n))],
            ]
        )
        return theta

    def _bounds(self, d: int) -> list[tuple[float, float]]:
        lo_l, hi_l = np.log(self.length_scale_bounds)
        return [(float(lo_l), float(hi_l))] * d + [
            tuple(np.log(self.signal_variance_bounds)),  # type: ignore[list-item]
            tuple(np.log(self.noise_variance_bounds)),  # type: ignore[list-item]
        ]

    def _inducing(self, Xl: FloatArray, rng: np.random.Generator) -> FloatArray:
        from sklearn.cluster import MiniBatchKMeans

        k = min(int(self.n_inducing), len(Xl))
        km = MiniBatchKMeans(
            n_clusters=k,
            random_state=int(rng.integers(2**31 - 1)),
            n_init=3,
            batch_size=4096,
        ).fit(Xl)
        return np.asarray(km.cluster_centers_, dtype=float)

    # -------------------------------------------------------------- predict
    def predict(self, X: ArrayLike, return_std: bool = False, include_noise: bool = True) -> Any:
        """Predictive mean and optionally standard deviation.

        Parameters
        ----------
        X : array, shape (n, d)
            Encoded inputs.
        return_std : bool
            Also return the standard deviation.
        include_noise : bool
            True (default): the std of a single future trial, ``sqrt(latent var + σ_n²)``;
            False: the std of the mean delay at X (the latent function's uncertainty).

        Returns
        -------
        mean : ndarray, shape (n,)
        std : ndarray, shape (n,), only with ``return_std``
        """
        pred = self._fitted()
        Xa = check_x(X, self.n_features_in_, "DelayGP.predict")
        if not return_std:
            return pred.predict_mean(Xa)
        mean, var = pred.predict(Xa)
        if include_noise:
            var = var + pred.noise_var_s2
        return mean, np.sqrt(var)

    def _fitted(self) -> GPPredictor:
        pred = getattr(self, "predictor_", None)
        if pred is None:
            raise not_fitted("DelayGP")
        return pred  # type: ignore[no-any-return]

    def log_marginal_likelihood(self, X: ArrayLike, y: ArrayLike) -> float:
        """Log marginal likelihood of trials (X, y) under the fitted hyperparameters.

        Equals scikit-learn's ``log_marginal_likelihood`` of the equivalent model
        (:meth:`to_sklearn`) fitted on the same trials.
        """
        self._fitted()
        Xa, ya = check_xy(X, y, "DelayGP.log_marginal_likelihood")
        col = collapse_replicates(Xa, ya)
        y_mean, y_std = float(ya.mean()), float(ya.std()) or 1.0
        theta = np.concatenate(
            [
                np.log(self.length_scale_),
                [np.log(self.signal_variance_), np.log(self.noise_variance_)],
            ]
        )
        Xs = (col.X - self.x_mean_) / self.x_scale_
        return -neg_log_likelihood(
            theta,
            Xs,
            (col.mean - y_mean) / y_std,
            col.count,
            col.within_ss / y_std**2,
            col.n,
        )[0]

    def to_sklearn(self) -> Any:
        """An unfitted scikit-learn ``GaussianProcessRegressor`` with the same kernel.

        Fit it on the same trials (encoded inputs, delays) to reproduce this model's
        predictions: ``ConstantKernel(σ_f²) * RBF(ℓ · x_scale) + WhiteKernel(σ_n²)``,
        ``normalize_y=True``, ``alpha=0``, no optimiser. Its ``predict(return_std=True)``
        includes the noise, like :meth:`predict` with ``include_noise=True``. For
        verification and benchmarks; exact models only (the standard deviations agree
        where the variance is exact, i.e. up to ``max_variance_conditions`` conditions).
        """
        pred = self._fitted()
        if self.sparse_:
            raise ConfigError("DelayGP.to_sklearn: a FITC model has no exact scikit-learn twin")
        del pred
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import RBF, WhiteKernel
        from sklearn.gaussian_process.kernels import ConstantKernel as C

        kernel = C(self.signal_variance_, "fixed") * RBF(
            self.length_scale_ * self.x_scale_, "fixed"
        ) + WhiteKernel(self.noise_variance_, "fixed")
        return GaussianProcessRegressor(kernel, alpha=0.0, normalize_y=True, optimizer=None)

    def _state(self) -> dict[str, Any]:
        return {
            "X_train": self.X_train_,
            "y_train": self.y_train_,
            "counts": self.counts_,
            "x_mean": self.x_mean_,
            "x_scale": self.x_scale_,
            "length_scale": self.length_scale_,
            "signal_var": self.signal_variance_,
            "noise_var": self.noise_variance_,
            "y_mean": self.y_mean_,
            "y_std": self.y_std_,
            "inducing": self.inducing_points_,
            "max_variance_conditions": self.max_variance_conditions,
        }

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The fitted model as named numeric arrays (for a model bundle).

        The sufficient statistics and hyperparameters, not the ``M × M`` matrices:
        :func:`~timedexec.learning._gpcore.predictor_from_arrays` rebuilds the predictor with the code ``fit`` used.
        """
        self._fitted()
        st = self._state()
        out: dict[str, NDArray[Any]] = {
            k: np.asarray(st[k], dtype=float)
            for k in ("X_train", "y_train", "counts", "x_mean", "x_scale", "length_scale")
        }
        out["scalars"] = np.array(
            [st["signal_var"], st["noise_var"], st["y_mean"], st["y_std"]], dtype=float
        )
        if st["inducing"] is not None:
            out["inducing"] = np.asarray(st["inducing"], dtype=float)
        mvc = st["max_variance_conditions"]
        out["max_variance_conditions"] = np.array(0 if mvc is None else int(mvc), dtype=np.int64)
        return out


def _info(est: DelayGP) -> dict[str, Any]:
    return {
        "length_scale": [float(v) for v in est.length_scale_],
        "signal_variance": float(est.signal_variance_),
        "noise_variance": float(est.noise_variance_),
        "noise_std_s": float(est.noise_std_),
        "sparse": bool(est.sparse_),
        "conditions": len(est.y_train_),
    }


def _predictor(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> GPPredictor:
    return predictor_from_arrays(arrays)


#: "f" input columns, "n" the conditions. Optional beyond these: "inducing" (FITC's inducing
#: inputs) and "max_variance_conditions" (the variance subset's size).
METHOD = DelayMethod(
    name="gpr",
    label="Gaussian process",
    description="squared-exponential kernel with one length scale per input; mean and "
    "standard deviation, which the executor's timing bounds use (as published)",
    estimator=lambda inputs, random_state: DelayGP(random_state=random_state),
    fit_cost=5.0,
    arrays=(
        ("X_train", ("n", "f")),
        ("y_train", ("n",)),
        ("counts", ("n",)),
        ("x_mean", ("f",)),
        ("x_scale", ("f",)),
        ("length_scale", ("f",)),
        ("scalars", ("4",)),
    ),
    predictor=_predictor,
    info=_info,
    variance=True,
    pair=GPPairPredictor.from_pair,
)
