"""DelayMethod: everything about one delay-model method, declared once, in its own module.

A method (the paper's median, neural net, regression tree and Gaussian process, and any
added after them) is one module of :mod:`timedexec.learning` that defines its research
estimator and its deployed predictor and ends with ``METHOD = DelayMethod(...)``; one line
in the registry (``_registry._MODULES``) lists the module. Training and cross-validation,
the model bundle (which arrays it holds, their shapes, the fast predictor), the
``--methods`` option of ``timedexec train`` and ``timedexec fleet``, the reports and the
docs all read the method from the registry; nothing else names it.

Numpy only: a deployed bundle imports the method modules to predict, so neither this
module nor a method module may import scikit-learn at import time (the estimators follow
its contract through :class:`~timedexec.learning._base.DelayEstimator`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.learning._features import feature_names

__all__ = ["ArraySpec", "DelayMethod", "MeanPredictor", "ModelInputs", "Predictor"]


#: ``((array name, shape), ...)``: see :attr:`DelayMethod.arrays`.
ArraySpec = tuple[tuple[str, tuple[str, ...]], ...]

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True, kw_only=True)
class ModelInputs:
    """What the input columns of one model mean.

    Every estimator gets encoded inputs (:func:`~timedexec.learning.encode_inputs`); most
    need nothing else. A method that uses the robot itself (its gravity torque, its
    inertia) learns here which robot, which joint and which columns.

    Attributes
    ----------
    robot : str
        Robot name (:func:`timedexec.robots.get_robot`).
    joint : int or None
        The actuated joint of a per-joint model (1-based); None for the combined model.
    joints : tuple of int
        Every joint the bundle models: the combined model's one-hot columns, in order.
    time_input : bool
        Whether the sweep time in hours is the last column.
    """

    robot: str
    joint: int | None
    joints: tuple[int, ...]
    time_input: bool = False

    @property
    def key(self) -> str:
        """The model's name in a bundle: the joint ("2") or "combined"."""
        return "combined" if self.joint is None else str(self.joint)

    def feature_names(self) -> tuple[str, ...]:
        """The input columns, in order (:func:`~timedexec.learning.feature_names`)."""
        return feature_names(self.joints if self.joint is None else None, self.time_input)

    @classmethod
    def of(cls, robot: str, key: str, joints: tuple[int, ...], time_input: bool) -> ModelInputs:
        """The inputs of the model ``key`` ("combined" or a joint number as text)."""
        return cls(
            robot=robot,
            joint=None if key == "combined" else int(key),
            joints=tuple(joints),
            time_input=time_input,
        )


class Predictor(Protocol):
    """A deployed model: numpy only, built from a bundle's arrays.

    ``predict(X)`` takes encoded inputs (n, d) and returns ``(mean, var)``: the mean delay,
    s, and for a method with a variance (:attr:`DelayMethod.variance`) the variance of the
    mean at X, s² (its uncertainty without the trial scatter), else None. A predictor with
    a variance also has ``noise_var_s2`` (the trial noise variance, s²) and
    ``predict_one(x)`` for one encoded input (d,), returning ``(mean, var)`` as floats:
    :meth:`~timedexec.learning.DelayModel.predict` calls it once per control cycle.
    """

    def predict(self, X: FloatArray) -> tuple[FloatArray, FloatArray | None]: ...


class MeanPredictor:
    """A predictor of the mean only; the bundle reports the model's CV error as its std."""

    def __init__(self, mean: Callable[[FloatArray], FloatArray]) -> None:
        self.mean = mean

    def predict(self, X: FloatArray) -> tuple[FloatArray, None]:
        """``(mean (n,), None)`` for encoded inputs X (n, d)."""
        return self.mean(X), None


@dataclass(frozen=True, kw_only=True)
class DelayMethod:
    """One delay-model method: what training, the bundle and the CLI need to know of it.

    Attributes
    ----------
    name : str
        Short name: ``--methods``, CV tables and JSON, ``method=`` of
        :meth:`~timedexec.learning.DelayModel.predict`, the bundle's array prefix. Lower
        case letters, digits and ``_``.
    label : str
        What it is, in a few words ("Gaussian process").
    description : str
        One sentence for ``--help`` and the docs: what it models and why it is here.
    estimator : callable
        ``estimator(inputs, random_state)`` -> a new, unfitted research estimator with
        scikit-learn's contract (``__init__`` stores its arguments, ``fit(X, y)``
        validates and returns self, learned state ends in ``_``), fitted on encoded inputs
        X (n, d) and delays y (n,), s. ``inputs`` (:class:`ModelInputs`) says what the
        columns mean (None where unknown, e.g. :func:`make_estimator` without inputs);
        ``random_state`` seeds it (methods without randomness ignore it). The fitted
        estimator's ``predict(X)`` gives the mean delay, s, and with :attr:`variance`
        ``predict(X, return_std=True)`` gives ``(mean, std)`` with the std of a single
        trial (latent and noise). Its ``to_arrays()`` exports it: a dict of numeric arrays
        holding at least those of :attr:`arrays` (no pickle, ever).
    fit_cost : float
        Relative CPU time of one fit on 1,000 trials (about 100 conditions); a fit on ``n``
        trials costs ``fit_cost·(n/1000)^1.5``. Only orders the fits (the biggest first).
    arrays : tuple of (str, tuple of str)
        The arrays a bundle must hold for one model, with their shapes: each dimension a
        number, or a letter that must be the same wherever it appears in the model's
        arrays. Reserved letters: ``f`` the number of input columns, ``a`` the number of
        nonzero entries of the array ``active`` (``a+1`` one more). A bundle whose arrays
        do not fit is refused at load.
    predictor : callable
        ``predictor(arrays, inputs)`` -> the deployed :class:`Predictor`, numpy only, from
        the arrays of one model (those ``to_arrays`` wrote) and its :class:`ModelInputs`.
        It must predict what the estimator predicts (to rounding).
    info : callable
        ``info(estimator)`` -> a JSON-safe summary of a fitted estimator for the bundle's
        manifest (``model_info``): hyperparameters, iterations, size.
    variance : bool
        The method predicts a variance of its mean (the GP); otherwise the bundle's std
        is the model's cross-validated RMS error.
    pair : callable, optional
        ``pair(actuation, response)`` -> one object whose ``predict_one(x)`` returns
        ``(act mean, act var, resp mean, resp var)`` from both predictors of a joint at
        once, or None where they cannot be fused. Methods with a variance only.
    check : callable, optional
        ``check(arrays, inputs)`` -> "" or what is wrong with a model's arrays beyond
        their shapes (e.g. tree node indices that point outside the tree).
    default : bool
        Trained when no ``--methods`` is given (the paper's four are).
    """

    name: str
    label: str
    description: str
    estimator: Callable[[ModelInputs | None, int | None], Any]
    fit_cost: float
    arrays: ArraySpec
    predictor: Callable[[Mapping[str, NDArray[Any]], ModelInputs], Predictor]
    info: Callable[[Any], dict[str, Any]]
    variance: bool = False
    pair: Callable[[Any, Any], Any] | None = None
    check: Callable[[Mapping[str, NDArray[Any]], ModelInputs], str] | None = None
    default: bool = True

    def __post_init__(self) -> None:
        if not _NAME.match(self.name):
            raise ConfigError(
                f"DelayMethod name {self.name!r} must be lower case letters, digits and '_', "
                "starting with a letter (it prefixes bundle arrays and goes in comma lists)"
            )
        if not (self.label and self.description):
            raise ConfigError(f"DelayMethod {self.name!r}: give a label and a description")
        if not (np.isfinite(self.fit_cost) and self.fit_cost > 0):
            raise ConfigError(f"DelayMethod {self.name!r}: fit_cost={self.fit_cost!r} must be > 0")
        names = [a for a, _ in self.arrays]
        if not names or len(set(names)) != len(names) or any("." in a for a in names):
            raise ConfigError(
                f"DelayMethod {self.name!r}: arrays {names} must be distinct names without '.'"
            )
        if self.pair is not None and not self.variance:
            raise ConfigError(f"DelayMethod {self.name!r}: a pair predictor needs a variance")

    def cost(self, n_trials: int) -> float:
        """Relative cost of one fit on ``n_trials`` trials (to schedule the big fits first)."""
        conditions = n_trials / 10.0  # a sweep repeats each condition about ten times
        return float(self.fit_cost * (conditions / 100.0) ** 1.5)

    def check_arrays(self, group: Mapping[str, NDArray[Any]], inputs: ModelInputs) -> str:
        """ "" if one model's arrays are what :attr:`arrays` declares, else what is wrong."""
        sizes: dict[str, int] = {"f": len(inputs.feature_names())}
        if "active" in group and group["active"].ndim == 1:
            sizes["a"] = int(np.count_nonzero(group["active"]))
        for name, dims in self.arrays:
            arr = group.get(name)
            if arr is None:
                return f"array {name!r} is missing"
            if arr.dtype.kind not in "biuf":
                return f"array {name!r} holds {arr.dtype} values, not numbers"
            if arr.ndim != len(dims):
                return f"array {name!r} has shape {arr.shape}, expected {len(dims)} dimension(s)"
            for axis, dim in enumerate(dims):
                if dim.isdigit():
                    want: int | None = int(dim)
                elif dim == "a+1":
                    want = sizes["a"] + 1 if "a" in sizes else None
                else:
                    want = sizes.setdefault(dim, arr.shape[axis])
                if want is not None and arr.shape[axis] != want:
                    return f"array {name!r} has shape {arr.shape}; axis {axis} should be {want}"
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                return f"array {name!r} holds NaN or infinite values"
        if any(size < 1 for dim, size in sizes.items() if dim not in ("f", "a")):
            return "a model array is empty"
        return self.check(group, inputs) if self.check is not None else ""
