"""The "rt" method: a regression tree with linear models in the leaves (M5-like)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray, IntArray
from timedexec.errors import ConfigError
from timedexec.learning._base import DelayEstimator, not_fitted
from timedexec.learning._features import check_x, check_xy, collapse_replicates, standardise
from timedexec.learning._method import DelayMethod, MeanPredictor, ModelInputs
from timedexec.learning._threads import single_threaded_blas

__all__ = ["METHOD", "LinearLeafTree"]


def tree_predict(
    Xs: FloatArray,
    feature: IntArray,
    threshold: FloatArray,
    left: IntArray,
    right: IntArray,
    coef: FloatArray,
) -> FloatArray:
    """Evaluate a linear-leaf tree on standardised inputs Xs (n, d).

    ``feature[k] < 0`` marks leaf ``k``; ``coef[k]`` holds ``[intercept, slopes (d)]``.
    Rows descend level by level (vectorised), then each takes its leaf's linear model.
    """
    node = np.zeros(len(Xs), dtype=np.int64)
    rows = np.arange(len(Xs))
    while True:
        f = feature[node]
        inner = f >= 0
        if not inner.any():
            break
        idx = rows[inner]
        go_left = Xs[idx, f[inner]] <= threshold[node[inner]]
        node[idx] = np.where(go_left, left[node[inner]], right[node[inner]])
    c = coef[node]
    return c[:, 0] + np.einsum("ij,ij->i", c[:, 1:], Xs)  # type: ignore[no-any-return]


class _Builder:
    """Grows, prunes and smooths the tree on weighted condition means."""

    def __init__(self, est: LinearLeafTree, X: FloatArray, y: FloatArray, w: FloatArray) -> None:
        self.X, self.y, self.w = X, y, w
        self.max_depth = int(est.max_depth)
        self.min_leaf = int(est.min_samples_leaf)
        self.ridge = float(est.ridge)
        self.smoothing = float(est.smoothing)
        self.feature: list[int] = []
        self.threshold: list[float] = []
        self.left: list[int] = []
        self.right: list[int] = []
        self.coef: list[FloatArray] = []
        self.n: list[int] = []
        self.parent: list[int] = []
        self.mse: list[float] = []

    def linear(self, idx: NDArray[np.intp]) -> tuple[FloatArray, float]:
        """Weighted ridge fit on rows idx with M5's term elimination.

        Starting from all inputs, the term whose removal most lowers the adjusted error
        ``mse · (n + ν)/(n - ν)`` is dropped, while any removal lowers it (Quinlan 1992).
        Returns ``[b0, b]`` (dropped slopes are 0) and the weighted mean squared error.
        """
        X, y = self.X[idx], self.y[idx]
        w = self.w[idx] / self.w[idx].mean()
        n, d = X.shape
        A = np.empty((n, d + 1))
        A[:, 0] = 1.0
        A[:, 1:] = X
        Aw = A * w[:, None]
        G = A.T @ Aw
        G[np.diag_indices_from(G)] += self.ridge
        G[0, 0] -= self.ridge  # no penalty on the intercept
        b = Aw.T @ y
        yy = float(np.sum(w * y * y))
        sw = float(np.sum(w))

        def fit(cols: NDArray[np.intp]) -> tuple[FloatArray, float, float]:
            beta = np.linalg.solve(G[np.ix_(cols, cols)], b[cols])
            # weighted SSE = yᵀWy - 2 βᵀ(AᵀWy) + βᵀ(AᵀWA)β, with the unpenalised Gram matrix
            Gc = G[np.ix_(cols, cols)].copy()
            Gc[np.diag_indices_from(Gc)] -= self.ridge
            Gc[0, 0] += self.ridge if cols[0] == 0 else 0.0
            sse = max(yy - 2.0 * float(beta @ b[cols]) + float(beta @ Gc @ beta), 0.0)
            mse = sse / sw
            nu = len(cols)
            return beta, mse, mse * (n + nu) / max(n - nu, 1)

        cols = np.arange(d + 1)
        beta, mse, adj = fit(cols)
        while len(cols) > 1:
            trials = [fit(np.delete(cols, i)) for i in range(1, len(cols))]
            i = int(np.argmin([t[2] for t in trials]))
            if trials[i][2] > adj:
                break
            cols = np.delete(cols, i + 1)
            beta, mse, adj = trials[i]
        out = np.zeros(d + 1)
        out[cols] = beta
        return out, mse

    def best_split(self, idx: NDArray[np.intp]) -> tuple[int, float, float] | None:
        """The (feature, threshold, SSE reduction) that most reduces the weighted SSE."""
        X, y, w = self.X[idx], self.y[idx], self.w[idx]
        n = len(idx)
        if n < 2 * self.min_leaf:
            return None
        total = float(np.sum(w * y * y) - np.sum(w * y) ** 2 / np.sum(w))
        best: tuple[int, float, float] | None = None
        lo, hi = self.min_leaf, n - self.min_leaf  # left part holds order[:k], k in [lo, hi]
        for j in range(X.shape[1]):
            order = np.argsort(X[:, j], kind="stable")
            xs = X[order, j]
            ws, wys, wyys = (
                np.cumsum(w[order]),
                np.cumsum((w * y)[order]),
                np.cumsum((w * y * y)[order]),
            )
            k = np.arange(lo, hi + 1)
            k = k[xs[k - 1] < xs[np.minimum(k, n - 1)]]  # split between distinct values
            if len(k) == 0:
                continue
            wl, wyl, wyyl = ws[k - 1], wys[k - 1], wyys[k - 1]
            wr, wyr, wyyr = ws[-1] - wl, wys[-1] - wyl, wyys[-1] - wyyl
            sse = (wyyl - wyl**2 / wl) + (wyyr - wyr**2 / wr)
            i = int(np.argmin(sse))
            gain = total - float(sse[i])
            if best is None or gain > best[2]:
                thr = 0.5 * (xs[k[i] - 1] + xs[k[i]])
                best = (j, float(thr), gain)
        if best is None or best[2] <= 1e-12 * max(total, 1e-300):
            return None
        return best

    def grow(self, idx: NDArray[np.intp], depth: int, parent: int) -> int:
        node = len(self.feature)
        beta, mse = self.linear(idx)
        self.mse.append(mse)
        self.feature.append(-1)
        self.threshold.append(0.0)
        self.left.append(-1)
        self.right.append(-1)
        self.coef.append(beta)
        self.n.append(len(idx))
        self.parent.append(parent)
        split = self.best_split(idx) if depth < self.max_depth else None
        if split is not None:
            j, thr, _ = split
            go_left = self.X[idx, j] <= thr
            self.feature[node] = j
            self.threshold[node] = thr
            self.left[node] = self.grow(idx[go_left], depth + 1, node)
            self.right[node] = self.grow(idx[~go_left], depth + 1, node)
        return node

    def prune(self, node: int, idx: NDArray[np.intp]) -> float:
        """M5 pruning (Quinlan 1992) bottom-up; returns the node's adjusted error.

        A node's own linear model has adjusted error ``mse · (n + ν) / (n - ν)`` (``ν``
        parameters, ``n`` conditions); a subtree's is the size-weighted sum of its
        children's. Where the linear model is no worse, the subtree is cut.
        """
        nu = self.X.shape[1] + 1  # every candidate term: the stronger penalty prunes better here
        n = len(idx)
        own = float(self.mse[node] * (n + nu) / max(n - nu, 1))
        if self.feature[node] < 0:
            return own
        go_left = self.X[idx, self.feature[node]] <= self.threshold[node]
        sub = (
            float(
                self.prune(self.left[node], idx[go_left]) * go_left.sum()
                + self.prune(self.right[node], idx[~go_left]) * (~go_left).sum()
            )
            / n
        )
        if own <= sub:
            self.feature[node] = -1
            return own
        return sub

    def smooth(self, node: int, inherited: FloatArray | None) -> None:
        """M5 smoothing: a leaf's model blends with its ancestors', ``(n p + k q) / (n + k)``.

        All models are linear, so the blend is a linear model too; it replaces the leaf's.
        """
        own = self.coef[node]
        if self.feature[node] < 0:
            if inherited is not None and self.smoothing > 0:
                k, n = self.smoothing, self.n[node]
                self.coef[node] = (n * own + k * inherited) / (n + k)
            return
        # What the children inherit: this node's model smoothed by its ancestors.
        mine = own
        if inherited is not None and self.smoothing > 0:
            k, n = self.smoothing, self.n[node]
            mine = (n * own + k * inherited) / (n + k)
        self.smooth(self.left[node], mine)
        self.smooth(self.right[node], mine)

    def compact(self) -> dict[str, NDArray[Any]]:
        """Drop nodes below cut subtrees and renumber."""
        keep: list[int] = []
        stack = [0]
        while stack:
            k = stack.pop()
            keep.append(k)
            if self.feature[k] >= 0:
                stack.extend([self.right[k], self.left[k]])
        new = {old: i for i, old in enumerate(keep)}
        feat = np.array([self.feature[k] for k in keep], dtype=np.int64)
        return {
            "feature": feat,
            "threshold": np.array([self.threshold[k] for k in keep]),
            "left": np.array(
                [new[self.left[k]] if feat[i] >= 0 else -1 for i, k in enumerate(keep)],
                dtype=np.int64,
            ),
            "right": np.array(
                [new[self.right[k]] if feat[i] >= 0 else -1 for i, k in enumerate(keep)],
                dtype=np.int64,
            ),
            "coef": np.array([self.coef[k] for k in keep]),
        }


class LinearLeafTree(DelayEstimator):
    """Regression tree with ridge linear models in its leaves (M5-like, Quinlan 1992).

    Grown by weighted variance reduction (the CART criterion; M5's standard-deviation
    reduction orders splits almost identically) on standardised inputs, to ``max_depth``
    with at least ``min_samples_leaf`` distinct conditions per leaf; every node gets a
    ridge linear model; subtrees whose adjusted error is no better than their root's linear
    model are pruned (M5's ``(n + ν)/(n - ν)`` factor); leaf models are smoothed towards
    their ancestors (M5 smoothing, constant ``smoothing``). Replicates are collapsed first:
    condition means weighted by counts give the same splits and least-squares leaves.

    Parameters
    ----------
    max_depth : int
        Largest depth (root = 0).
    min_samples_leaf : int
        Fewest distinct input rows (conditions, after collapsing replicates) in a leaf.
    ridge : float
        Ridge penalty of the leaf models (standardised inputs, counts normalised to mean 1).
    smoothing : float
        M5 smoothing constant ``k`` (0: none).
    prune : bool
        Apply M5 pruning.
    random_state : None
        Unused (the tree is deterministic); kept for a uniform estimator interface.

    Attributes
    ----------
    feature_, threshold_, left_, right_ : ndarray, shape (n_nodes,)
        Tree structure over standardised active inputs; ``feature_ < 0`` marks a leaf.
    coef_ : ndarray, shape (n_nodes, n_active + 1)
        Leaf models ``[intercept, slopes]`` in normalised target units.
    active_ : ndarray of bool, shape (d,)
        Input columns that vary in the training data.
    n_leaves_ : int
        Leaves after pruning.
    """

    def __init__(
        self,
        *,
        max_depth: int = 6,
        min_samples_leaf: int = 40,
        ridge: float = 1.0,
        smoothing: float = 15.0,
        prune: bool = True,
        random_state: Any = None,
    ) -> None:
        self.max_depth = max_depth
        self.min_samples_leaf = min_samples_leaf
        self.ridge = ridge
        self.smoothing = smoothing
        self.prune = prune
        self.random_state = random_state

    def _check_params(self) -> None:
        for name, low in (("max_depth", 0), ("min_samples_leaf", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
                raise ConfigError(f"LinearLeafTree: {name}={v!r} must be an integer >= {low}")
        for name in ("ridge", "smoothing"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v >= 0):
                raise ConfigError(f"LinearLeafTree: {name}={v!r} must be a finite number >= 0")

    def fit(self, X: ArrayLike, y: ArrayLike) -> LinearLeafTree:
        """Grow, prune and smooth on encoded inputs X (n, d) and delays y (n,), s."""
        self._check_params()
        Xa, ya = check_xy(X, y, "LinearLeafTree.fit")
        col = collapse_replicates(Xa, ya)
        self.n_features_in_ = Xa.shape[1]
        self.x_mean_, self.x_scale_ = standardise(col.X, col.count)
        self.active_ = np.std(col.X, axis=0) > 1e-12
        self.y_mean_ = float(ya.mean())
        self.y_std_ = float(ya.std()) or 1.0
        Xs = ((col.X - self.x_mean_) / self.x_scale_)[:, self.active_]
        ys = (col.mean - self.y_mean_) / self.y_std_
        with single_threaded_blas():
            b = _Builder(self, Xs, ys, col.count)
            idx = np.arange(len(ys))
            b.grow(idx, 0, -1)
            if self.prune:
                b.prune(0, idx)
            b.smooth(0, None)
            arrays = b.compact()
        self.feature_ = arrays["feature"]
        self.threshold_ = arrays["threshold"]
        self.left_ = arrays["left"]
        self.right_ = arrays["right"]
        self.coef_ = arrays["coef"]
        self.n_leaves_ = int(np.sum(self.feature_ < 0))
        return self

    def predict(self, X: ArrayLike) -> FloatArray:
        """Predicted delays (n,), s, for encoded inputs X (n, d)."""
        if not hasattr(self, "coef_"):
            raise not_fitted("LinearLeafTree")
        Xa = check_x(X, self.n_features_in_, "LinearLeafTree.predict")
        Xs = ((Xa - self.x_mean_) / self.x_scale_)[:, self.active_]
        out = tree_predict(Xs, self.feature_, self.threshold_, self.left_, self.right_, self.coef_)
        return self.y_mean_ + self.y_std_ * out

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The fitted tree as named numeric arrays (for a model bundle)."""
        return {
            "feature": self.feature_,
            "threshold": self.threshold_,
            "left": self.left_,
            "right": self.right_,
            "coef": self.coef_,
            "active": self.active_.astype(np.int8),
            "x_mean": self.x_mean_,
            "x_scale": self.x_scale_,
            "scalars": np.array([self.y_mean_, self.y_std_]),
        }


def _predictor(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> MeanPredictor:
    active = arrays["active"].astype(bool)
    x_mean, x_scale = arrays["x_mean"], arrays["x_scale"]
    y_mean, y_std = (float(v) for v in arrays["scalars"])
    parts = (
        arrays["feature"],
        arrays["threshold"],
        arrays["left"],
        arrays["right"],
        arrays["coef"],
    )

    def mean(X: FloatArray) -> FloatArray:
        Xs = ((X - x_mean) / x_scale)[:, active]
        return y_mean + y_std * tree_predict(Xs, *parts)

    return MeanPredictor(mean)


def _check(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> str:
    feature = arrays["feature"]
    inner = feature >= 0
    children = np.concatenate([arrays["left"][inner], arrays["right"][inner]])
    n_active = int(np.count_nonzero(arrays["active"]))
    if np.any(feature[inner] >= n_active) or np.any((children < 0) | (children >= len(feature))):
        return "the tree's node indices point outside its arrays"
    return ""


#: "f" input columns, "a" the active ones, "m" the tree's nodes.
METHOD = DelayMethod(
    name="rt",
    label="regression tree",
    description="partitions of the inputs with a linear model in each leaf, M5-like: ridge "
    "leaves, pruning, smoothing (as published)",
    estimator=lambda inputs, random_state: LinearLeafTree(),
    fit_cost=1.0,
    arrays=(
        ("active", ("f",)),
        ("x_mean", ("f",)),
        ("x_scale", ("f",)),
        ("feature", ("m",)),
        ("threshold", ("m",)),
        ("left", ("m",)),
        ("right", ("m",)),
        ("coef", ("m", "a+1")),
        ("scalars", ("2",)),
    ),
    predictor=_predictor,
    info=lambda est: {"leaves": int(est.n_leaves_)},
    check=_check,
)
