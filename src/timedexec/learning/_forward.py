"""Forward passes of the neural net and the linear-leaf tree (numpy only: bundles use them)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["nn_forward", "tree_predict"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def nn_forward(
    X: FloatArray,
    W1: FloatArray,
    b1: FloatArray,
    W2: FloatArray,
    b2: float,
) -> FloatArray:
    """Network output for standardised inputs X (n, d): ``W2 · tanh(W1 x + b1) + b2``."""
    return np.tanh(X @ W1.T + b1) @ W2 + b2  # type: ignore[no-any-return]


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
