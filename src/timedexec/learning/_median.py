"""MedianDelay: the published baseline, the median delay of the training trials."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator, RegressorMixin

from timedexec.learning._features import check_x, check_xy

__all__ = ["MedianDelay"]


class MedianDelay(RegressorMixin, BaseEstimator):  # type: ignore[misc]
    """Predict the median training delay for every input (the paper's baseline).

    Attributes
    ----------
    median_ : float
        Median of the training targets (s for delays).
    n_features_in_ : int
        Number of input columns seen in fit.
    """

    def fit(self, X: ArrayLike, y: ArrayLike) -> MedianDelay:
        """Store the median of y (n,); X (n, d) is validated and otherwise ignored."""
        Xa, ya = check_xy(X, y, "MedianDelay.fit")
        self.n_features_in_ = Xa.shape[1]
        self.median_ = float(np.median(ya))
        return self

    def predict(self, X: ArrayLike) -> NDArray[np.float64]:
        """The training median for each row of X (n, d)."""
        if not hasattr(self, "median_"):
            from sklearn.exceptions import NotFittedError

            raise NotFittedError("MedianDelay is not fitted yet; call fit(X, y) first")
        Xa = check_x(X, self.n_features_in_, "MedianDelay.predict")
        return np.full(len(Xa), self.median_)

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The fitted model as named numeric arrays (for a model bundle)."""
        return {"scalars": np.array([self.median_])}
