"""The "median" method: the published baseline, the median delay of the training trials."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.learning._base import DelayEstimator, not_fitted
from timedexec.learning._features import check_x, check_xy
from timedexec.learning._method import DelayMethod, MeanPredictor, ModelInputs

__all__ = ["METHOD", "MedianDelay"]


class MedianDelay(DelayEstimator):
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
            raise not_fitted("MedianDelay")
        Xa = check_x(X, self.n_features_in_, "MedianDelay.predict")
        return np.full(len(Xa), self.median_)

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The fitted model as named numeric arrays (for a model bundle)."""
        return {"scalars": np.array([self.median_])}


def _predictor(arrays: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> MeanPredictor:
    value = float(arrays["scalars"][0])
    return MeanPredictor(lambda X: np.full(len(X), value))


METHOD = DelayMethod(
    name="median",
    label="median baseline",
    description="one delay for every pose, the median of the training trials (the paper's "
    "baseline)",
    estimator=lambda inputs, random_state: MedianDelay(),
    fit_cost=1e-3,
    arrays=(("scalars", ("1",)),),
    predictor=_predictor,
    info=lambda est: {"median_s": float(est.median_)},
)
