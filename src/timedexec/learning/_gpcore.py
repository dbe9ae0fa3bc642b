"""Gaussian-process mathematics on replicate-collapsed data (numpy and scipy only).

Model (Rasmussen & Williams 2006, ch. 2 and 5): trial ``j`` of condition ``i`` is
``y_ij = f(x_i) + ε_ij`` with ``f ~ GP(0, k)``, ``k(x, x') = σ_f² exp(-½ Σ_l (x_l -
x'_l)² / ℓ_l²)`` (squared exponential with one length scale per input, "ARD") and
``ε ~ N(0, σ_n²)``. With the condition means ``ȳ_i`` and counts ``n_i``:

* ``ȳ ~ N(0, K + D)``, ``D = diag(σ_n² / n_i)`` — the posterior of ``f`` given the means
  equals the posterior given every trial (the means are sufficient statistics);
* the full log marginal likelihood of the trials is
  ``log N(ȳ | 0, K + D) - ½ S_w / σ_n² - ½ (N - M) log(2π σ_n²) - ½ Σ_i log n_i``
  (``S_w`` the within-condition sum of squares, ``N`` trials, ``M`` conditions): an
  orthonormal change of variables separates each condition's mean from its ``n_i - 1``
  contrasts, which see only the noise. This is the likelihood scikit-learn's
  ``GaussianProcessRegressor`` computes on all trials, at a cost of ``M³`` instead of ``N³``.

Sparse conditioning (FITC, Snelson & Ghahramani 2006; Quiñonero-Candela & Rasmussen 2005,
eq. 23) on inducing inputs ``Z`` when ``M`` is too large for a Cholesky factor: the
conditions keep their own noise ``σ_n² / n_i`` plus FITC's diagonal correction.

Both exact and sparse conditioning end in the same predictor form: with ``k_*`` the kernel
vector between a query and the "centres" (the conditions, or ``Z``),
``mean = k_*·α`` and ``latent var = σ_f² - k_*ᵀ B k_*``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.errors import ModelError

# scipy.linalg is imported in the functions that factorise (fits, conditioning), so that
# importing timedexec.learning (the CLI does, for --methods) stays light.

__all__ = [
    "GPPairPredictor",
    "GPPredictor",
    "build_predictor",
    "condition_exact",
    "condition_fitc",
    "neg_log_likelihood",
    "predictor_from_arrays",
    "spread_subset",
]


_LOG_2PI = float(np.log(2.0 * np.pi))


def sq_dist(A: FloatArray, B: FloatArray) -> FloatArray:
    """Squared Euclidean distances between the rows of A (n, d) and B (m, d), shape (n, m)."""
    a2 = np.einsum("ij,ij->i", A, A)
    b2 = np.einsum("ij,ij->i", B, B)
    d2: FloatArray = a2[:, None] + b2[None, :] - 2.0 * (A @ B.T)
    np.maximum(d2, 0.0, out=d2)
    return d2


def _kernel(Xs: FloatArray, Zs: FloatArray, signal_var: float) -> FloatArray:
    """k between inputs already divided by their length scales."""
    out: FloatArray = signal_var * np.exp(-0.5 * sq_dist(Xs, Zs))
    return out


def _cholesky(K: FloatArray, what: str) -> FloatArray:
    """Lower Cholesky factor; on failure retry with growing jitter, then raise ModelError."""
    scale = float(np.mean(np.diag(K)))
    for jitter in (0.0, 1e-10, 1e-8, 1e-6):
        try:
            L = np.linalg.cholesky(K + (jitter * scale) * np.eye(len(K)) if jitter else K)
            return np.asarray(L, dtype=np.float64)
        except np.linalg.LinAlgError:
            continue
    raise ModelError(
        f"{what}: the kernel matrix is not positive definite even with jitter; the inputs "
        "may hold near-duplicate rows with a tiny noise level (raise the noise bound)"
    )


def _inverse_from_cholesky(L: FloatArray) -> FloatArray:
    """(L Lᵀ)⁻¹ from the lower factor L (LAPACK potri), full symmetric."""
    import scipy.linalg as sla

    inv, info = sla.lapack.dpotri(L, lower=1)
    if info != 0:
        raise ModelError(f"GP: inverting the kernel matrix failed (LAPACK potri info={info})")
    inv = np.tril(inv)
    inv += np.tril(inv, -1).T
    return np.asarray(inv, dtype=float)


def neg_log_likelihood(
    theta: FloatArray,
    Xs: FloatArray,
    ybar: FloatArray,
    count: FloatArray,
    within_ss: float,
    n_trials: int,
) -> tuple[float, FloatArray]:
    """Negative log marginal likelihood of all trials and its gradient.

    Parameters
    ----------
    theta : ndarray, shape (d + 2,)
        ``log ℓ_1 .. log ℓ_d, log σ_f², log σ_n²``.
    Xs : ndarray, shape (m, d)
        Condition inputs (standardised).
    ybar, count : ndarray, shape (m,)
        Condition means (normalised targets) and trial counts.
    within_ss : float
        Within-condition sum of squares (normalised targets).
    n_trials : int
        Number of trials, ``Σ count``.
    """
    import scipy.linalg as sla

    d = Xs.shape[1]
    ell = np.exp(theta[:d])
    sf2 = float(np.exp(theta[d]))
    sn2 = float(np.exp(theta[d + 1]))
    Xl = Xs / ell
    Kf = _kernel(Xl, Xl, sf2)
    noise = sn2 / count
    K = Kf.copy()
    K[np.diag_indices_from(K)] += noise
    try:
        L = np.asarray(np.linalg.cholesky(K), dtype=np.float64)
    except np.linalg.LinAlgError:
        return 1e25, np.zeros_like(theta)
    alpha = sla.cho_solve((L, True), ybar, check_finite=False)
    m = len(ybar)
    nll = (
        0.5 * float(ybar @ alpha)
        + float(np.sum(np.log(np.diag(L))))
        + 0.5 * m * _LOG_2PI
        + 0.5 * within_ss / sn2
        + 0.5 * (n_trials - m) * (_LOG_2PI + np.log(sn2))
        + 0.5 * float(np.sum(np.log(count)))
    )
    # Gradient: ½ tr(W dK/dθ), W = (K + D)⁻¹ - α αᵀ (R&W eq. 5.9).
    W = _inverse_from_cholesky(L)
    W -= np.outer(alpha, alpha)
    Mk = W * Kf
    r = Mk.sum(axis=1)
    MX = Mk @ Xl
    # tr(W (Kf ∘ Δ_l²)) = Σ_ij Mk_ij (x_il - x_jl)² = 2 (r·x_l² - x_l·(Mk x_l)).
    g_ell = (r @ (Xl * Xl)) - np.einsum("il,il->l", Xl, MX)  # ½ tr(...) = this
    grad = np.empty_like(theta)
    grad[:d] = g_ell
    grad[d] = 0.5 * float(r.sum())
    grad[d + 1] = 0.5 * float(np.diag(W) @ noise) - 0.5 * within_ss / sn2 + 0.5 * (n_trials - m)
    return float(nll), grad


class GPPredictor:
    """A conditioned GP in predictor form, pure numpy (what a model bundle evaluates).

    Parameters
    ----------
    centres : ndarray, shape (m, d)
        Conditions (exact) or inducing inputs (FITC), mapped by ``(x - x_shift) * x_gain``.
    x_shift, x_gain : ndarray, shape (d,)
        Map from encoded inputs to the kernel's space: standardisation and length scales.
    alpha : ndarray, shape (m,)
        Weights of the mean.
    B : ndarray, shape (m, m), optional
        Symmetric matrix of the variance, ``latent var = σ_f² - k_*ᵀ B k_*``.
    chol : ndarray, optional
        Lower Cholesky factor of the variance conditions' ``K + D``: ``B = (K + D)⁻¹`` is
        formed from it on the first variance request (cross-validation needs only means).
    var_index : ndarray of int, shape (s,), optional
        The variance uses the kernel vector entries of these centres only (a subset of the
        conditions, see :func:`build_predictor`); None: all centres.
    var_centres : ndarray, shape (s, d), optional
        Separate centres of the variance (FITC models: conditions, while ``centres`` are the
        inducing inputs); mapped like ``centres``.
    signal_var, noise_var : float
        ``σ_f²`` and ``σ_n²`` in normalised target units.
    y_mean, y_std : float
        Target normalisation (predictions are ``y_mean + y_std * ...``), s.
    """

    def __init__(
        self,
        *,
        centres: FloatArray,
        x_shift: FloatArray,
        x_gain: FloatArray,
        alpha: FloatArray,
        signal_var: float,
        noise_var: float,
        y_mean: float,
        y_std: float,
        B: FloatArray | None = None,
        chol: FloatArray | None = None,
        var_index: NDArray[np.intp] | None = None,
        var_centres: FloatArray | None = None,
    ) -> None:
        if B is None and chol is None:
            raise ModelError("GPPredictor needs B or chol")
        self.var_index = var_index
        self.var_centres = var_centres
        # a leading subset is read as a slice (no gather)
        self._var_n = (
            len(var_index)
            if var_index is not None and np.array_equal(var_index, np.arange(len(var_index)))
            else None
        )
        self._hv = (
            None
            if var_centres is None
            else np.log(float(signal_var)) - 0.5 * np.einsum("ij,ij->i", var_centres, var_centres)
        )
        self.centres = centres
        self.x_shift = x_shift
        self.x_gain = x_gain
        self.alpha = alpha
        self.signal_var = float(signal_var)
        self.noise_var = float(noise_var)
        self.y_mean = float(y_mean)
        self.y_std = float(y_std)
        self._B = B
        self._chol = chol
        # exp(-½|c - x|²)·σ_f² = exp(c·x + h - ½|x|²) with h = log σ_f² - ½|c|²: the
        # fast path needs one matrix-vector product, one add and one exp per centre set.
        self._h = np.log(self.signal_var) - 0.5 * np.einsum("ij,ij->i", centres, centres)
        self._alpha_s = self.y_std * alpha

    @property
    def B(self) -> FloatArray:
        """The variance matrix (m, m)."""
        if self._B is None:
            assert self._chol is not None
            self._B = _inverse_from_cholesky(self._chol)
            self._chol = None
        return self._B

    @property
    def noise_var_s2(self) -> float:
        """Trial noise variance, s²."""
        return self.noise_var * self.y_std**2

    def map_inputs(self, X: FloatArray) -> FloatArray:
        """Encoded inputs (n, d) to the kernel's space."""
        return (X - self.x_shift) * self.x_gain

    def _chunks(self, n: int) -> list[slice]:
        # rows per block so that a block's kernel matrix stays near 4 M entries (32 MB):
        # predicting 33,500 trials against 3,352 conditions at once would take ~1 GB
        step = max(1, 4_000_000 // max(len(self.centres), 1))
        return [slice(i, min(i + step, n)) for i in range(0, n, step)]

    def predict_mean(self, X: FloatArray) -> FloatArray:
        """Mean (s) for encoded inputs X (n, d), in row blocks."""
        Xm = self.map_inputs(np.atleast_2d(X))
        out = np.empty(len(Xm))
        for sl in self._chunks(len(Xm)):
            out[sl] = _kernel(Xm[sl], self.centres, self.signal_var) @ self.alpha
        return self.y_mean + self.y_std * out

    @property
    def exact_variance(self) -> bool:
        """Whether the variance uses every condition (else a subset: an upper bound)."""
        return self.var_index is None and self.var_centres is None

    def predict(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Mean (s) and latent variance (s²) for encoded inputs X (n, d), in row blocks."""
        X2 = np.atleast_2d(X)
        mean = np.empty(len(X2))
        var = np.empty(len(X2))
        for sl in self._chunks(len(X2)):
            mean[sl], var[sl] = self._predict_block(X2[sl])
        return mean, var

    def _predict_block(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        Xm = self.map_inputs(X)
        Ks = _kernel(Xm, self.centres, self.signal_var)
        mean = self.y_mean + self.y_std * (Ks @ self.alpha)
        if self.var_centres is not None:
            Kv = _kernel(Xm, self.var_centres, self.signal_var)
        elif self._var_n is not None:
            Kv = Ks[:, : self._var_n]
        elif self.var_index is not None:
            Kv = Ks[:, self.var_index]
        else:
            Kv = Ks
        var = self.signal_var - np.einsum("ij,ij->i", Kv @ self.B, Kv)
        np.maximum(var, 0.0, out=var)
        return mean, var * self.y_std**2

    def latent_cov(self, A: FloatArray, B: FloatArray) -> FloatArray:
        """Posterior covariance of the latent delay between encoded inputs A (n, d) and
        B (k, d), s², shape (n, k): ``k(a, b) - k(a, C) (K + D)⁻¹ k(C, b)``.

        What sequential design asks (the variance a planned trial would remove elsewhere
        does not depend on its outcome). Exact models only.

        Raises
        ------
        ModelError
            The variance is conditioned on a subset or is FITC's (an upper bound, not a
            covariance): fit with ``max_variance_conditions=None`` and below
            ``max_exact_conditions``.
        """
        if not self.exact_variance or self.centres.shape[0] != self.B.shape[0]:
            raise ModelError(
                "latent_cov needs the exact posterior: fit the GP with "
                "max_variance_conditions=None and at most max_exact_conditions conditions"
            )
        Am = self.map_inputs(np.atleast_2d(A))
        Bm = self.map_inputs(np.atleast_2d(B))
        Ka = _kernel(Am, self.centres, self.signal_var)
        Kb = _kernel(Bm, self.centres, self.signal_var)
        cov = _kernel(Am, Bm, self.signal_var) - (Ka @ self.B) @ Kb.T
        return np.asarray(cov * self.y_std**2, dtype=np.float64)

    def predict_one(self, x: FloatArray) -> tuple[float, float]:
        """Mean (s) and latent variance (s²) for one encoded input x (d,): the fast path.

        One kernel vector (an (m, d) matrix-vector product and m exponentials), a dot
        product for the mean and an (s, s) matrix-vector product for the variance: about
        ``2·m·d + 2·s²`` flops (s = variance conditions).
        """
        B = self._B if self._B is not None else self.B
        xm = (x - self.x_shift) * self.x_gain
        half_xx = 0.5 * float(xm @ xm)
        z = self.centres @ xm
        z += self._h
        z -= half_xx
        k = np.exp(z, out=z)
        mean = self.y_mean + float(k @ self._alpha_s)
        if self.var_centres is not None:
            assert self._hv is not None
            zv = self.var_centres @ xm
            zv += self._hv
            zv -= half_xx
            kv = np.exp(zv, out=zv)
        elif self._var_n is not None:
            kv = k[: self._var_n]
        elif self.var_index is not None:
            kv = k[self.var_index]
        else:
            kv = k
        var = self.signal_var - float(kv @ (B @ kv))
        return mean, max(var, 0.0) * self.y_std**2


def condition_exact(
    Xs: FloatArray,
    ybar: FloatArray,
    count: FloatArray,
    ell: FloatArray,
    signal_var: float,
    noise_var: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Exact conditioning on the condition means (R&W Alg. 2.1 with noise σ_n²/n_i).

    Returns the centres (inputs divided by the length scales), ``α = (K + D)⁻¹ ȳ`` and
    the lower Cholesky factor ``L`` of ``K + D`` (``B = (K + D)⁻¹ = L⁻ᵀ L⁻¹``).
    """
    import scipy.linalg as sla

    Xl = Xs / ell
    K = _kernel(Xl, Xl, signal_var)
    K[np.diag_indices_from(K)] += noise_var / count
    L = _cholesky(K, "exact GP")
    alpha = sla.cho_solve((L, True), ybar, check_finite=False)
    return Xl, alpha, L


def condition_fitc(
    Xs: FloatArray,
    ybar: FloatArray,
    count: FloatArray,
    Zs: FloatArray,
    ell: FloatArray,
    signal_var: float,
    noise_var: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """FITC conditioning on inducing inputs ``Zs`` (same space as ``Xs``).

    ``Λ = diag(σ_f² - q_ii + σ_n²/n_i)``, ``Σ = (K_mm + K_mn Λ⁻¹ K_nm)⁻¹``;
    mean weights ``α = Σ K_mn Λ⁻¹ ȳ``, variance matrix ``B = K_mm⁻¹ - Σ``.
    Computed through ``V = L_m⁻¹ K_mn`` and ``C = I + V Λ⁻¹ Vᵀ`` for stability.
    """
    import scipy.linalg as sla

    Xl = Xs / ell
    Zl = Zs / ell
    m = len(Zl)
    Kmm = _kernel(Zl, Zl, signal_var)
    Kmm[np.diag_indices_from(Kmm)] += 1e-8 * signal_var
    Lm = _cholesky(Kmm, "FITC inducing kernel")
    Kmn = _kernel(Zl, Xl, signal_var)
    V = sla.solve_triangular(Lm, Kmn, lower=True, check_finite=False)
    q = np.einsum("ij,ij->j", V, V)
    lam = np.maximum(signal_var - q, 0.0) + noise_var / count
    Vl = V / lam
    C = np.eye(m) + Vl @ V.T
    Lc = _cholesky(C, "FITC")
    # α = Lm⁻ᵀ C⁻¹ V Λ⁻¹ ȳ
    beta = sla.cho_solve((Lc, True), Vl @ ybar, check_finite=False)
    alpha = sla.solve_triangular(Lm, beta, lower=True, trans="T", check_finite=False)
    # B = Lm⁻ᵀ (I - C⁻¹) Lm⁻¹
    Cinv = sla.cho_solve((Lc, True), np.eye(m), check_finite=False)
    Lminv = sla.solve_triangular(Lm, np.eye(m), lower=True, check_finite=False)
    B = Lminv.T @ (np.eye(m) - Cinv) @ Lminv
    B = 0.5 * (B + B.T)
    return Zl, alpha, B


def spread_subset(Xl: FloatArray, size: int) -> NDArray[np.intp]:
    """Indices of ``size`` well-spread rows of Xl (greedy farthest-point), deterministic.

    Starts at the row nearest the mean and repeatedly adds the row farthest from those
    chosen (a 2-approximation of the k-centre problem, Gonzalez 1985).
    """
    m = len(Xl)
    if size >= m:
        return np.arange(m)
    first = int(np.argmin(np.sum((Xl - Xl.mean(axis=0)) ** 2, axis=1)))
    chosen = np.empty(size, dtype=np.intp)
    chosen[0] = first
    dist = np.sum((Xl - Xl[first]) ** 2, axis=1)
    for i in range(1, size):
        nxt = int(np.argmax(dist))
        chosen[i] = nxt
        np.minimum(dist, np.sum((Xl - Xl[nxt]) ** 2, axis=1), out=dist)
    return np.sort(chosen)


def build_predictor(
    *,
    X_train: FloatArray,
    y_train: FloatArray,
    counts: FloatArray,
    x_mean: FloatArray,
    x_scale: FloatArray,
    length_scale: FloatArray,
    signal_var: float,
    noise_var: float,
    y_mean: float,
    y_std: float,
    inducing: FloatArray | None = None,
    max_variance_conditions: int | None = None,
) -> GPPredictor:
    """Condition a GP with given hyperparameters on condition means: exact, or FITC on ``inducing``.

    The mean always uses every condition. The latent variance is exact when there are at
    most ``max_variance_conditions`` conditions (and the model is exact); otherwise it is
    the exact posterior variance given a well-spread subset of that many conditions
    (:func:`spread_subset`). Conditioning a GP on fewer observations can only raise its
    posterior variance, so this is an upper bound of the full variance — timing bounds
    built from it stay conservative — and one prediction costs ``O(s²)`` instead of
    ``O(m²)``.

    The one path from sufficient statistics to a predictor, used by
    :meth:`DelayGP.fit <timedexec.learning.DelayGP.fit>` and by model bundles (which store
    the statistics, not the ``M × M`` matrices), so both give the same numbers.

    Parameters
    ----------
    X_train : ndarray, shape (m, d)
        Distinct conditions, encoded inputs.
    y_train, counts : ndarray, shape (m,)
        Mean target (s) and trial count per condition.
    x_mean, x_scale : ndarray, shape (d,)
        Input standardisation.
    length_scale : ndarray, shape (d,)
        Length scales, standardised input units.
    signal_var, noise_var : float
        ``σ_f²``, ``σ_n²`` in normalised target units.
    y_mean, y_std : float
        Target normalisation, s.
    inducing : ndarray, shape (k, d), optional
        FITC inducing inputs (encoded input units); None for exact conditioning.
    max_variance_conditions : int, optional
        Largest number of conditions the variance is conditioned on (None: all).
    """
    Xs = (X_train - x_mean) / x_scale
    ybar = (y_train - y_mean) / y_std
    B: FloatArray | None = None
    chol: FloatArray | None = None
    var_index: NDArray[np.intp] | None = None
    var_centres: FloatArray | None = None
    m = len(ybar)
    subset = max_variance_conditions is not None and m > max_variance_conditions
    if inducing is None:
        if subset:
            assert max_variance_conditions is not None
            # chosen in the standardised inputs, not the GP's length-scale metric: a joint's
            # actuation and response GPs then share the subset (one fused evaluation); the
            # subset goes first, so the variance reads a slice of the kernel vector
            sel = spread_subset(Xs, int(max_variance_conditions))
            order = np.concatenate([sel, np.setdiff1d(np.arange(m), sel)])
            Xs, ybar, counts = Xs[order], ybar[order], counts[order]
            var_index = np.arange(len(sel))
        centres, alpha, chol = condition_exact(
            Xs, ybar, counts, length_scale, signal_var, noise_var
        )
        if var_index is not None:
            _, _, chol = condition_exact(
                Xs[var_index],
                ybar[var_index],
                counts[var_index],
                length_scale,
                signal_var,
                noise_var,
            )
    else:
        Zs = (inducing - x_mean) / x_scale
        centres, alpha, B = condition_fitc(
            Xs, ybar, counts, Zs, length_scale, signal_var, noise_var
        )
        if subset:
            assert max_variance_conditions is not None
            sel = spread_subset(Xs, int(max_variance_conditions))
            var_centres, _, chol = condition_exact(
                Xs[sel], ybar[sel], counts[sel], length_scale, signal_var, noise_var
            )
            B = None
    return GPPredictor(
        centres=centres,
        x_shift=np.asarray(x_mean, dtype=float).copy(),
        x_gain=1.0 / (x_scale * length_scale),
        alpha=alpha,
        B=B,
        chol=chol,
        var_index=var_index,
        var_centres=var_centres,
        signal_var=float(signal_var),
        noise_var=float(noise_var),
        y_mean=float(y_mean),
        y_std=float(y_std),
    )


def predictor_from_arrays(arrays: Mapping[str, NDArray[Any]]) -> GPPredictor:
    """Inverse of :meth:`DelayGP.to_arrays`: the conditioned predictor (pure numpy)."""
    sf2, sn2, y_mean, y_std = (float(v) for v in arrays["scalars"])
    mvc = arrays.get("max_variance_conditions")
    return build_predictor(
        X_train=arrays["X_train"],
        y_train=arrays["y_train"],
        counts=arrays["counts"],
        x_mean=arrays["x_mean"],
        x_scale=arrays["x_scale"],
        length_scale=arrays["length_scale"],
        signal_var=sf2,
        noise_var=sn2,
        y_mean=y_mean,
        y_std=y_std,
        inducing=arrays.get("inducing"),
        max_variance_conditions=None if mvc is None or int(mvc) <= 0 else int(mvc),
    )


class GPPairPredictor:
    """Two GPs on the same conditions (a joint's actuation and response models), fused.

    Both GPs of a joint are conditioned on the same condition inputs with the same
    standardisation (and variance subset); only their hyperparameters differ. With
    ``D = X_train - x_mean`` shared,
    ``c_a·x_a = D·((x - x_mean) ∘ g_a²)`` (``g`` the inverse length scales over the scale),
    so both kernel vectors come from one ``(m, d) @ (d, 2)`` product and one exp, and both
    variances from one batched matrix-vector product: half the numpy calls of two separate
    predictors, the same numbers to rounding. Built by :meth:`from_pair` when the two are
    compatible (same conditions and variance subset, no FITC), else None.
    """

    def __init__(self, a: GPPredictor, b: GPPredictor, D: FloatArray) -> None:
        self.shift = a.x_shift
        self.DT = np.ascontiguousarray(D.T)  # (d, m)
        self.U = np.ascontiguousarray(np.vstack([a.x_gain**2, b.x_gain**2]))  # (2, d)
        self.H = np.ascontiguousarray(np.vstack([a._h, b._h]))  # (2, m)
        self.alpha_a, self.alpha_b = a._alpha_s, b._alpha_s
        self.B_a, self.B_b = a.B, b.B
        self.var_n = a._var_n
        self.a, self.b = a, b

    @classmethod
    def from_pair(cls, a: GPPredictor, b: GPPredictor) -> GPPairPredictor | None:
        """Fuse two predictors conditioned on the same conditions, if they are compatible."""
        if a.var_centres is not None or b.var_centres is not None:
            return None
        if (a._var_n is None) != (b._var_n is None) or a._var_n != b._var_n:
            return None
        if (a.var_index is None) != (b.var_index is None):
            return None
        if a.centres.shape != b.centres.shape or not np.array_equal(a.x_shift, b.x_shift):
            return None
        D = a.centres / a.x_gain  # the shared x - x_mean, in the predictors' order
        if not np.allclose(D * b.x_gain, b.centres, rtol=1e-12, atol=1e-12):
            return None
        return cls(a, b, D)

    def predict_one(self, x: FloatArray) -> tuple[float, float, float, float]:
        """Both GPs for one encoded input x (d,): mean_a, var_a, mean_b, var_b (s, s²)."""
        v = x - self.shift
        W = self.U * v  # (2, d)
        Z = W @ self.DT  # (2, m): c·x per centre, both GPs
        Z += self.H
        half = 0.5 * (W @ v)
        Z[0] -= half[0]
        Z[1] -= half[1]
        K = np.exp(Z, out=Z)
        ka, kb = K[0], K[1]
        a, b = self.a, self.b
        if self.var_n is None:
            va, vb = ka, kb
        else:
            va, vb = ka[: self.var_n], kb[: self.var_n]
        var_a = a.signal_var - float(va @ (self.B_a @ va))
        var_b = b.signal_var - float(vb @ (self.B_b @ vb))
        return (
            a.y_mean + float(ka @ self.alpha_a),
            max(var_a, 0.0) * a.y_std**2,
            b.y_mean + float(kb @ self.alpha_b),
            max(var_b, 0.0) * b.y_std**2,
        )
