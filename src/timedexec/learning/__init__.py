"""timedexec.learning: delay models, cross-validation as published, model bundles.

Estimators (scikit-learn API) on encoded inputs (:func:`encode_inputs`): the baseline
:class:`MedianDelay`, the Levenberg-Marquardt neural net :class:`LMNeuralNet`, the
linear-leaf regression tree :class:`LinearLeafTree` and the Gaussian process
:class:`DelayGP` (mean and standard deviation, exact on replicate-collapsed data, FITC for
very large sweeps). :func:`train_delay_models` cross-validates them per joint and combined
for both delays (the paper's Tables I/II) and trains a :class:`DelayModel` bundle whose
:meth:`DelayModel.predict` answers in tens of µs without scikit-learn. See docs/models.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from timedexec.learning._bundle import (
    ARRAYS_NAME,
    BUNDLE_FORMAT,
    MANIFEST_NAME,
    DelayModel,
    DelayPrediction,
)
from timedexec.learning._calibrate import gaussian_coverage, std_scale_factor
from timedexec.learning._features import (
    Collapsed,
    collapse_replicates,
    encode_inputs,
    feature_names,
)
from timedexec.learning._gpcore import (
    GPPairPredictor,
    GPPredictor,
    build_predictor,
    condition_exact,
    condition_fitc,
    neg_log_likelihood,
    predictor_from_arrays,
)
from timedexec.learning._shipped import BUNDLED_MODELS, bundled_model_dir
from timedexec.learning._threads import single_threaded_blas
from timedexec.learning._train import (
    DELAYS,
    METHODS,
    PAPER_TABLES,
    CVResult,
    TrainResult,
    check_methods,
    cross_validate,
    fold_of_configuration,
    make_estimator,
    noise_floor,
    paper_family,
    train_delay_models,
)

if TYPE_CHECKING:
    from timedexec.learning._gp import DelayGP
    from timedexec.learning._median import MedianDelay
    from timedexec.learning._nn import LMNeuralNet
    from timedexec.learning._tree import LinearLeafTree

# The estimators load on first use: they subclass scikit-learn's BaseEstimator, and loading
# and querying a bundle (DelayModel) must not need scikit-learn.
_LAZY = {
    "DelayGP": "timedexec.learning._gp",
    "LMNeuralNet": "timedexec.learning._nn",
    "LinearLeafTree": "timedexec.learning._tree",
    "MedianDelay": "timedexec.learning._median",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'timedexec.learning' has no attribute {name!r}")


__all__ = [
    "ARRAYS_NAME",
    "BUNDLED_MODELS",
    "BUNDLE_FORMAT",
    "DELAYS",
    "MANIFEST_NAME",
    "METHODS",
    "PAPER_TABLES",
    "CVResult",
    "Collapsed",
    "DelayGP",
    "DelayModel",
    "DelayPrediction",
    "GPPairPredictor",
    "GPPredictor",
    "LMNeuralNet",
    "LinearLeafTree",
    "MedianDelay",
    "TrainResult",
    "build_predictor",
    "bundled_model_dir",
    "check_methods",
    "collapse_replicates",
    "condition_exact",
    "condition_fitc",
    "cross_validate",
    "encode_inputs",
    "feature_names",
    "fold_of_configuration",
    "gaussian_coverage",
    "make_estimator",
    "neg_log_likelihood",
    "noise_floor",
    "paper_family",
    "predictor_from_arrays",
    "single_threaded_blas",
    "std_scale_factor",
    "train_delay_models",
]
