"""The "nn" method: one hidden layer of tanh units trained with Levenberg-Marquardt (as published)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.learning._base import DelayEstimator, not_fitted
from timedexec.learning._features import check_x, check_xy, collapse_replicates, standardise
from timedexec.learning._method import DelayMethod, MeanPredictor, ModelInputs
from timedexec.learning._threads import single_threaded_blas

# scipy.linalg: imported where the fit factorises (see _gpcore).

__all__ = ["METHOD", "LMNeuralNet"]


SOLVERS = ("marquardt", "scipy-lm")


def nn_forward(
    X: FloatArray,
    W1: FloatArray,
    b1: FloatArray,
    W2: FloatArray,
    b2: float,
) -> FloatArray:
    """Network output for standardised inputs X (n, d): ``W2 · tanh(W1 x + b1) + b2``."""
    return np.tanh(X @ W1.T + b1) @ W2 + b2  # type: ignore[no-any-return]


class _Net:
    """Parameter layout, residuals and Jacobian of the weighted least-squares problem."""

    def __init__(
        self,
        X: FloatArray,
        y: FloatArray,
        count: FloatArray,
        within_ss: float,
        hidden: int,
        decay: float,
    ) -> None:
        self.X, self.y, self.sw = X, y, np.sqrt(count)
        self.n_trials = float(count.sum())
        self.within_ss = within_ss
        self.H = hidden
        self.d = X.shape[1]
        self.P = hidden * self.d + 2 * hidden + 1
        # Weight decay on the weights, not on the biases.
        self.mask = np.zeros(self.P)
        self.mask[: hidden * self.d] = 1.0
        self.mask[hidden * self.d + hidden : hidden * self.d + 2 * hidden] = 1.0
        self.n_weights = float(self.mask.sum())
        self.set_decay(decay)

    def set_decay(self, lam: float) -> None:
        self.lam = lam
        self.decay = lam * self.mask

    def unpack(self, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        H, d = self.H, self.d
        W1 = t[: H * d].reshape(H, d)
        b1 = t[H * d : H * d + H]
        W2 = t[H * d + H : H * d + 2 * H]
        return W1, b1, W2, float(t[-1])

    def residuals(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Weighted data residuals and hidden activations."""
        W1, b1, W2, b2 = self.unpack(t)
        A = np.tanh(self.X @ W1.T + b1)
        return self.sw * (A @ W2 + b2 - self.y), A

    def cost(self, r: FloatArray, t: FloatArray) -> float:
        return 0.5 * float(r @ r) + 0.5 * float(self.decay @ (t * t))

    def jacobian(self, t: FloatArray, A: FloatArray) -> FloatArray:
        H, d = self.H, self.d
        W2 = t[H * d + H : H * d + 2 * H]
        G = (1.0 - A * A) * W2 * self.sw[:, None]  # (n, H)
        J = np.empty((len(self.y), self.P))
        J[:, : H * d] = (G[:, :, None] * self.X[:, None, :]).reshape(len(self.y), H * d)
        J[:, H * d : H * d + H] = G
        J[:, H * d + H : H * d + 2 * H] = A * self.sw[:, None]
        J[:, -1] = self.sw
        return J

    def initial(self, rng: np.random.Generator) -> FloatArray:
        """Nguyen-Widrow-style start: hidden units spread over the standardised input range."""
        H, d = self.H, self.d
        W1 = rng.standard_normal((H, d))
        W1 *= 0.7 * H ** (1.0 / max(d, 1)) / np.linalg.norm(W1, axis=1, keepdims=True)
        b1 = rng.uniform(-1.0, 1.0, H) * np.linalg.norm(W1, axis=1)
        W2 = rng.standard_normal(H) / np.sqrt(H)
        return np.concatenate([W1.ravel(), b1, W2, [0.0]])


def _evidence(
    net: _Net, JtJ: FloatArray, r: FloatArray, t: FloatArray, *, log_evidence: bool = False
) -> tuple[float, float]:
    """MacKay's evidence framework at the current weights (MacKay 1992; Foresee & Hagan 1997).

    Returns the re-estimated decay ``λ = α/β`` and (with ``log_evidence``) the log evidence
    at the new ``α, β`` (else NaN). ``β`` is the noise precision of a *trial*: the misfit
    counts every trial, ``S_within + Σ n_i r_i²``, so the replicates pin ``β`` down; ``γ``
    is the number of well-determined weights, ``P_w - λ tr((JᵀJ + λM)⁻¹ M)``.
    """
    import scipy.linalg as sla

    sse = net.within_ss + float(r @ r)
    w2 = float(net.mask @ (t * t))
    H = JtJ.copy()
    H[np.diag_indices_from(H)] += net.decay
    try:
        c = sla.cho_factor(H, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return net.lam, -np.inf
    Hinv_diag = np.diag(sla.cho_solve(c, np.eye(net.P), check_finite=False))
    gamma = float(net.n_weights - net.lam * (net.mask @ Hinv_diag))
    gamma = min(max(gamma, 1e-3), net.n_weights)
    n_bias = net.P - net.n_weights
    beta = max(net.n_trials - gamma - n_bias, 1.0) / max(sse, 1e-300)
    alpha = gamma / max(w2, 1e-300)
    lam = alpha / beta
    if not log_evidence:
        return lam, float("nan")
    H = JtJ.copy()
    H[np.diag_indices_from(H)] += lam * net.mask
    try:
        c = sla.cho_factor(H, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return lam, -np.inf
    # log det(β JᵀJ + α M) = P log β + log det(JᵀJ + λ M)
    logdet = net.P * np.log(beta) + 2.0 * float(np.sum(np.log(np.abs(np.diag(c[0])))))
    log_ev = (
        -0.5 * beta * sse
        - 0.5 * alpha * w2
        - 0.5 * logdet
        + 0.5 * net.n_weights * np.log(alpha)
        + 0.5 * net.n_trials * np.log(beta)
    )
    return lam, float(log_ev)


def _marquardt(
    net: _Net,
    t: FloatArray,
    *,
    max_iter: int,
    tol: float,
    auto: bool,
    val: _Net | None = None,
    max_fail: int = 6,
) -> tuple[FloatArray, float, int]:
    """Levenberg-Marquardt on the damped normal equations (Marquardt 1963; MATLAB trainlm).

    Step ``(JᵀJ + Λ + μI) δ = -(Jᵀr + Λθ)`` with weight decay ``Λ``; ``μ`` shrinks by 10
    after a step that lowers the cost and grows by 10 after one that does not. Stops when
    the relative cost reduction of an accepted step falls below ``tol`` (twice in a row),
    the gradient vanishes, ``μ`` exceeds 1e10, or after ``max_iter`` accepted steps. With
    ``auto`` the decay is re-estimated after every accepted step by the evidence framework
    (MATLAB trainbr). With a validation set ``val`` the iteration stops after ``max_fail``
    accepted steps without a lower validation error and returns the weights of the lowest
    (MATLAB trainlm's early stopping). Returns the weights, a score to choose among restarts
    (lower is better: the validation error, else minus the log evidence with ``auto``,
    else the cost) and the iterations.
    """
    import scipy.linalg as sla

    r, A = net.residuals(t)
    cost = net.cost(r, t)
    mu = 1e-3
    small = 0
    it = 0
    eye = np.eye(net.P)
    best_val = np.inf
    best_t = t
    fails = 0
    if val is not None:
        rv, _ = val.residuals(t)
        best_val = float(rv @ rv)
    while it < max_iter:
        J = net.jacobian(t, A)
        JtJ = J.T @ J
        if auto and it > 0:
            lam, _ = _evidence(net, JtJ, r, t)
            net.set_decay(lam)
            cost = net.cost(r, t)
        g = J.T @ r + net.decay * t
        if float(np.max(np.abs(g))) < 1e-12:
            break
        JtJ[np.diag_indices_from(JtJ)] += net.decay
        accepted = False
        while mu <= 1e10:
            try:
                c = sla.cho_factor(JtJ + mu * eye, lower=True, check_finite=False)
                step = -sla.cho_solve(c, g, check_finite=False)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            t_new = t + step
            r_new, A_new = net.residuals(t_new)
            cost_new = net.cost(r_new, t_new)
            if cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                t, r, A, cost = t_new, r_new, A_new, cost_new
                mu = max(mu / 10.0, 1e-12)
                accepted = True
                small = small + 1 if rel < tol else 0
                break
            mu *= 10.0
        it += 1
        if val is not None and accepted:
            rv, _ = val.residuals(t)
            e_val = float(rv @ rv)
            if e_val < best_val:
                best_val, best_t, fails = e_val, t, 0
            else:
                fails += 1
                if fails >= max_fail:
                    break
        if not accepted or small >= 2:
            break
    if val is not None:
        return best_t, best_val, it
    if auto:
        J = net.jacobian(t, A)
        _, log_ev = _evidence(net, J.T @ J, r, t, log_evidence=True)
        return t, -log_ev, it
    return t, cost, it


def _scipy_lm(
    net: _Net, t: FloatArray, *, max_iter: int, tol: float, auto: bool
) -> tuple[FloatArray, float, int]:
    """The same problem through MINPACK (``scipy.optimize.least_squares(method="lm")``)."""
    from scipy.optimize import least_squares

    sq = np.sqrt(net.decay)
    keep = sq > 0

    def fun(p: FloatArray) -> FloatArray:
        r, _ = net.residuals(p)
        return np.concatenate([r, (sq * p)[keep]])

    def jac(p: FloatArray) -> FloatArray:
        _, A = net.residuals(p)
        return np.vstack([net.jacobian(p, A), np.diag(sq)[keep]])

    res = least_squares(fun, t, jac=jac, method="lm", ftol=tol, xtol=tol, max_nfev=max_iter)
    r, _ = net.residuals(res.x)
    return np.asarray(res.x, dtype=float), net.cost(r, res.x), int(res.nfev)


class LMNeuralNet(DelayEstimator):
    """One hidden layer of tanh units, trained with Levenberg-Marquardt.

    As in the paper: a feed-forward net with one hidden layer (30 units by default) and a
    linear output, trained by Levenberg-Marquardt on the squared error. Inputs are
    standardised, the target normalised. Replicates are collapsed first (condition means
    weighted by their counts give the same least-squares problem, about 10x smaller).
    Two guards keep the 30-unit net from fitting the replicate noise, as in MATLAB's
    ``trainlm`` defaults the paper's authors most likely used: early stopping on a
    held-out 15 % of the conditions (stop after ``max_fail`` steps without a lower
    validation error, keep the best weights), and a small weight decay on the weights (not
    the biases): the objective is ``½ Σ_i n_i (ȳ_i - f(x_i))² + ½ λ ||w||²`` in normalised
    units with ``λ = alpha · N`` (N trials). ``alpha="auto"`` instead re-estimates ``λ``
    by MacKay's evidence framework (MATLAB's ``trainbr``); on simulated sweeps it was
    slower and no more accurate. By default the ``n_restarts`` = 2 nets form a committee
    (their average; each has its own validation split), which halves the variance a net
    picks up from noisy means — on a joint without pose signal a single net lost to the
    median, the committee did not; a member that does not beat the training mean on its
    validation conditions is replaced by that mean.

    Parameters
    ----------
    hidden_units : int
        Hidden tanh units.
    alpha : float or "auto"
        A number >= 0: fixed decay per trial (default 1e-2); "auto": Bayesian
        regularisation (evidence framework).
    validation_fraction : float
        Share of the conditions held out for early stopping (MATLAB's default split gives
        15 %); 0 trains on all conditions until convergence.
    max_fail : int
        Accepted LM steps without a lower validation error before stopping (MATLAB: 6).
    committee : bool
        True: average the ``n_restarts`` nets, each early-stopped on its own random
        validation split (the average of K nets of H units is one net of K·H units); False:
        keep the one with the lowest validation error.
    n_restarts : int
        Random starts (>= 1).
    max_iter : int
        Largest number of LM iterations per start.
    tol : float
        Relative cost reduction below which the iteration stops.
    solver : {"marquardt", "scipy-lm"}
        "marquardt": damped normal equations with BLAS (fast, default); "scipy-lm":
        MINPACK through ``scipy.optimize.least_squares(method="lm")`` — same objective,
        10-20x slower at these sizes (a QR per iteration without BLAS), kept for
        cross-checking.
    random_state : int, Generator or None
        Initial weights.

    Attributes
    ----------
    W1_, b1_, W2_, b2_ : ndarray, float
        Weights on standardised inputs (active columns only) and normalised target.
    active_ : ndarray of bool, shape (d,)
        Input columns that vary in the training data (constant columns are dropped).
    x_mean_, x_scale_ : ndarray, shape (d,)
        Input standardisation.
    y_mean_, y_std_ : float
        Target normalisation.
    n_iter_ : int
        LM iterations of the kept start.
    objective_ : float
        Score of the kept start: minus the log evidence (``auto``) or the objective.
    decay_ : float
        Final ``λ`` (normalised units).
    constant_ : bool
        True when no net beat the training mean on the validation conditions and the mean
        was kept (the delay showed no dependence on the inputs).
    """

    def __init__(
        self,
        *,
        hidden_units: int = 30,
        alpha: float | str = 1e-2,
        n_restarts: int = 2,
        max_iter: int = 150,
        tol: float = 1e-5,
        validation_fraction: float = 0.15,
        max_fail: int = 6,
        committee: bool = True,
        solver: str = "marquardt",
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.hidden_units = hidden_units
        self.alpha = alpha
        self.n_restarts = n_restarts
        self.max_iter = max_iter
        self.tol = tol
        self.validation_fraction = validation_fraction
        self.max_fail = max_fail
        self.committee = committee
        self.solver = solver
        self.random_state = random_state

    def _check_params(self) -> None:
        for name in ("hidden_units", "n_restarts", "max_iter", "max_fail"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise ConfigError(f"LMNeuralNet: {name}={v!r} must be an integer >= 1")
        if self.alpha != "auto" and not (
            isinstance(self.alpha, int | float) and np.isfinite(self.alpha) and self.alpha >= 0
        ):
            raise ConfigError(
                f"LMNeuralNet: alpha={self.alpha!r} must be 'auto' or a finite number >= 0"
            )
        vf = self.validation_fraction
        if not (isinstance(vf, int | float) and 0 <= vf < 1):
            raise ConfigError(f"LMNeuralNet: validation_fraction={vf!r} must lie in [0, 1)")
        if not (np.isfinite(self.tol) and self.tol > 0):
            raise ConfigError(f"LMNeuralNet: tol={self.tol!r} must be > 0")
        if self.solver not in SOLVERS:
            raise ConfigError(
                f"LMNeuralNet: solver={self.solver!r}; choose one of {', '.join(SOLVERS)}"
            )

    def fit(self, X: ArrayLike, y: ArrayLike) -> LMNeuralNet:
        """Train on encoded inputs X (n, d) and delays y (n,), s."""
        self._check_params()
        Xa, ya = check_xy(X, y, "LMNeuralNet.fit")
        rng = np.random.default_rng(self.random_state)
        col = collapse_replicates(Xa, ya)
        self.n_features_in_ = Xa.shape[1]
        x_mean, x_scale = standardise(col.X, col.count)
        self.active_ = np.std(col.X, axis=0) > 1e-12
        self.x_mean_, self.x_scale_ = x_mean, x_scale
        self.y_mean_ = float(ya.mean())
        self.y_std_ = float(ya.std()) or 1.0
        Xs = ((col.X - x_mean) / x_scale)[:, self.active_]
        ys = (col.mean - self.y_mean_) / self.y_std_
        auto = self.alpha == "auto"
        decay = 1.0 if auto else float(self.alpha) * col.n
        wss = col.within_ss / self.y_std_**2
        H = int(self.hidden_units)
        vf = float(self.validation_fraction)
        use_val = vf > 0 and len(ys) >= 10

        def split() -> tuple[_Net, _Net | None]:
            if not use_val:
                return _Net(Xs, ys, col.count, wss, H, decay), None
            is_val = np.zeros(len(ys), dtype=bool)
            is_val[rng.choice(len(ys), size=max(1, round(vf * len(ys))), replace=False)] = True
            tr = ~is_val
            wss_tr = wss * float(col.count[tr].sum() / col.n)  # pro rata; only used by auto
            return (
                _Net(Xs[tr], ys[tr], col.count[tr], wss_tr, H, decay),
                _Net(Xs[is_val], ys[is_val], col.count[is_val], 0.0, H, 0.0),
            )

        def train(net: _Net, val: _Net | None) -> tuple[FloatArray, float, int]:
            if self.solver == "marquardt":
                return _marquardt(
                    net,
                    net.initial(rng),
                    max_iter=int(self.max_iter),
                    tol=float(self.tol),
                    auto=auto,
                    val=val,
                    max_fail=int(self.max_fail),
                )
            return _scipy_lm(
                net, net.initial(rng), max_iter=int(self.max_iter), tol=float(self.tol), auto=auto
            )

        def keep_or_constant(
            net: _Net, val: _Net | None, theta: FloatArray, score: float
        ) -> tuple[FloatArray, bool]:
            # A net that does not beat the training mean on the held-out conditions has
            # found no dependence on the inputs: keep the mean instead.
            if val is None:
                return theta, False
            c = float(np.average(net.y, weights=net.sw**2))
            if float(np.sum(val.sw**2 * (c - val.y) ** 2)) > score:
                return theta, False
            theta = theta.copy()
            theta[H * net.d + H : H * net.d + 2 * H] = 0.0
            theta[-1] = c
            return theta, True

        members: list[tuple[float, FloatArray, int, float, bool]] = []
        with single_threaded_blas():
            shared = split()
            for _ in range(int(self.n_restarts)):
                net, val = split() if self.committee else shared
                theta, score, it = train(net, val)
                theta, const = keep_or_constant(net, val, theta, score)
                members.append((score, theta, it, net.lam, const))
        proto = _Net(Xs[:1], ys[:1], col.count[:1], 0.0, H, 0.0)
        if self.committee:
            # The average of K nets of H units is one net of K·H units.
            parts = [proto.unpack(m[1]) for m in members]
            K = len(parts)
            self.W1_ = np.vstack([p[0] for p in parts])
            self.b1_ = np.concatenate([p[1] for p in parts])
            self.W2_ = np.concatenate([p[2] for p in parts]) / K
            self.b2_ = float(np.mean([p[3] for p in parts]))
            self.objective_ = float(np.mean([m[0] for m in members]))
            self.n_iter_ = int(sum(m[2] for m in members))
            self.decay_ = float(np.mean([m[3] for m in members]))
            self.constant_ = all(m[4] for m in members)
        else:
            score, theta, it, lam, const = min(members, key=lambda m: m[0])
            W1, b1, W2, b2 = proto.unpack(theta)
            self.W1_, self.b1_, self.W2_, self.b2_ = W1.copy(), b1.copy(), W2.copy(), b2
            self.objective_, self.n_iter_, self.decay_, self.constant_ = score, it, lam, const
        return self

    def predict(self, X: ArrayLike) -> FloatArray:
        """Predicted delays (n,), s, for encoded inputs X (n, d)."""
        if not hasattr(self, "W1_"):
            raise not_fitted("LMNeuralNet")
        Xa = check_x(X, self.n_features_in_, "LMNeuralNet.predict")
        Xs = ((Xa - self.x_mean_) / self.x_scale_)[:, self.active_]
        return self.y_mean_ + self.y_std_ * nn_forward(Xs, self.W1_, self.b1_, self.W2_, self.b2_)

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The fitted net as named numeric arrays (for a model bundle)."""
        return {
            "W1": self.W1_,
            "b1": self.b1_,
            "W2": self.W2_,
            "active": self.active_.astype(np.int8),
            "x_mean": self.x_mean_,
            "x_scale": self.x_scale_,
            "scalars": np.array([self.b2_, self.y_mean_, self.y_std_]),
        }


def _predictor(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> MeanPredictor:
    active = arrays["active"].astype(bool)
    x_mean, x_scale = arrays["x_mean"], arrays["x_scale"]
    W1, b1, W2 = arrays["W1"], arrays["b1"], arrays["W2"]
    b2, y_mean, y_std = (float(v) for v in arrays["scalars"])

    def mean(X: FloatArray) -> FloatArray:
        Xs = ((X - x_mean) / x_scale)[:, active]
        return y_mean + y_std * nn_forward(Xs, W1, b1, W2, b2)

    return MeanPredictor(mean)


#: "f" input columns, "a" the active ones, "h" hidden units.
METHOD = DelayMethod(
    name="nn",
    label="LM neural net",
    description="one hidden layer of 30 tanh units trained by Levenberg-Marquardt, early "
    "stopping, a committee of two (as published)",
    estimator=lambda inputs, random_state: LMNeuralNet(random_state=random_state),
    fit_cost=6.0,
    arrays=(
        ("active", ("f",)),
        ("x_mean", ("f",)),
        ("x_scale", ("f",)),
        ("W1", ("h", "a")),
        ("b1", ("h",)),
        ("W2", ("h",)),
        ("scalars", ("3",)),
    ),
    predictor=_predictor,
    info=lambda est: {"iterations": int(est.n_iter_), "decay": float(est.decay_)},
)
