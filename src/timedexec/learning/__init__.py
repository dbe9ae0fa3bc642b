"""timedexec.learning: delay models, cross-validation as published, model bundles.

Methods are a registry (:data:`METHODS`, :func:`get_method`): each is one module declaring
a :class:`DelayMethod` (name, description, research estimator, fit cost, bundle arrays,
fast predictor, model info). The paper's four are the default (:data:`DEFAULT_METHODS`):
the baseline :class:`MedianDelay`, the Levenberg-Marquardt neural net
:class:`LMNeuralNet`, the linear-leaf regression tree :class:`LinearLeafTree` and the
Gaussian process :class:`DelayGP` (mean and standard deviation, exact on
replicate-collapsed data, FITC for very large sweeps). Beside them, on request,
:class:`PhysicalLinearModel` ("phys": Bayesian linear regression on the gravity torque and
inertia of the start pose, mean and standard deviation). All take encoded inputs
(:func:`encode_inputs`) and follow scikit-learn's estimator contract.
:func:`train_delay_models` cross-validates them per joint and combined for both delays
(the paper's Tables I/II) and trains a :class:`DelayModel` bundle whose
:meth:`DelayModel.predict` answers in tens of µs without scikit-learn. See docs/models.md.
"""

from __future__ import annotations

from timedexec.learning._bundle import (
    ARRAYS_NAME,
    BUNDLE_FORMAT,
    MANIFEST_NAME,
    DelayModel,
    DelayPrediction,
)
from timedexec.learning._calibrate import (
    DelayBounds,
    bound_quantile,
    gaussian_coverage,
    std_scale_factor,
)
from timedexec.learning._features import (
    Collapsed,
    collapse_replicates,
    encode_inputs,
    feature_names,
)
from timedexec.learning._gp import DelayGP
from timedexec.learning._gpcore import (
    GPPairPredictor,
    GPPredictor,
    build_predictor,
    condition_exact,
    condition_fitc,
    neg_log_likelihood,
    predictor_from_arrays,
)
from timedexec.learning._median import MedianDelay
from timedexec.learning._method import DelayMethod, MeanPredictor, ModelInputs, Predictor
from timedexec.learning._nn import LMNeuralNet
from timedexec.learning._phys import PhysicalLinearModel
from timedexec.learning._registry import (
    DEFAULT_METHODS,
    METHODS,
    check_methods,
    describe_methods,
    get_method,
    make_estimator,
)
from timedexec.learning._shipped import BUNDLED_MODELS, bundled_model_dir
from timedexec.learning._thermal import (
    THERMAL_MARGIN_S,
    WARM_AFTER_S,
    thermal_mismatch,
    thermal_state,
)
from timedexec.learning._threads import single_threaded_blas
from timedexec.learning._train import (
    DELAYS,
    PAPER_TABLES,
    CVResult,
    TrainResult,
    cross_validate,
    fold_of_configuration,
    noise_floor,
    paper_family,
    train_delay_models,
)
from timedexec.learning._tree import LinearLeafTree

__all__ = [
    "ARRAYS_NAME",
    "BUNDLED_MODELS",
    "BUNDLE_FORMAT",
    "DEFAULT_METHODS",
    "DELAYS",
    "MANIFEST_NAME",
    "METHODS",
    "PAPER_TABLES",
    "THERMAL_MARGIN_S",
    "WARM_AFTER_S",
    "CVResult",
    "Collapsed",
    "DelayBounds",
    "DelayGP",
    "DelayMethod",
    "DelayModel",
    "DelayPrediction",
    "GPPairPredictor",
    "GPPredictor",
    "LMNeuralNet",
    "LinearLeafTree",
    "MeanPredictor",
    "MedianDelay",
    "ModelInputs",
    "PhysicalLinearModel",
    "Predictor",
    "TrainResult",
    "bound_quantile",
    "build_predictor",
    "bundled_model_dir",
    "check_methods",
    "collapse_replicates",
    "condition_exact",
    "condition_fitc",
    "cross_validate",
    "describe_methods",
    "encode_inputs",
    "feature_names",
    "fold_of_configuration",
    "gaussian_coverage",
    "get_method",
    "make_estimator",
    "neg_log_likelihood",
    "noise_floor",
    "paper_family",
    "predictor_from_arrays",
    "single_threaded_blas",
    "std_scale_factor",
    "thermal_mismatch",
    "thermal_state",
    "train_delay_models",
]
