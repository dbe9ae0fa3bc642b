"""DelayEstimator: scikit-learn's estimator contract without importing scikit-learn.

Every delay-model method is one module (:class:`~timedexec.learning.DelayMethod`) holding
its research estimator *and* the numpy predictor a deployed bundle uses; a bundle loads
those modules, and loading a bundle must not import scikit-learn (tens of MB and ~1 s).
So the estimators implement the contract themselves, as scikit-learn's ``BaseEstimator``
and ``RegressorMixin`` do: parameters are the keyword arguments of ``__init__`` (stored
unchanged, validated in ``fit``), ``get_params``/``set_params`` read and write them, and
``sklearn.base.clone`` works (it needs only ``get_params`` and a constructor that stores
its arguments).
"""

from __future__ import annotations

import inspect
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike

from timedexec.errors import ConfigError

__all__ = ["DelayEstimator", "not_fitted"]


def not_fitted(who: str) -> Exception:
    """scikit-learn's ``NotFittedError`` (a ValueError and AttributeError) for ``who``.

    Imported only on this error path, which needs scikit-learn installed (training does).
    """
    from sklearn.exceptions import NotFittedError

    error: Exception = NotFittedError(f"{who} is not fitted yet; call fit(X, y) first")
    return error


class DelayEstimator:
    """Base of the delay estimators: ``get_params``, ``set_params``, ``score``, ``repr``.

    Subclasses take keyword-only parameters in ``__init__`` and store each under its own
    name (as scikit-learn requires), validate them in ``fit``, and name learned state
    with a trailing underscore.
    """

    _estimator_type = "regressor"

    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return sorted(
            p.name
            for p in sig.parameters.values()
            if p.name != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
        )

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor parameters, ``{name: value}`` (``deep`` as scikit-learn's)."""
        out: dict[str, Any] = {}
        for name in self._param_names():
            value = getattr(self, name)
            if deep and hasattr(value, "get_params") and not isinstance(value, type):
                out.update((f"{name}__{k}", v) for k, v in value.get_params().items())
            out[name] = value
        return out

    def set_params(self, **params: Any) -> Self:
        """Set constructor parameters by name; an unknown name raises ConfigError."""
        names = self._param_names()
        for name, value in params.items():
            if name not in names:
                raise ConfigError(
                    f"{type(self).__name__}: no parameter {name!r}; "
                    f"its parameters are {', '.join(names)}"
                )
            setattr(self, name, value)
        return self

    def score(self, X: ArrayLike, y: ArrayLike) -> float:
        """Coefficient of determination R² of ``predict(X)`` against y (as scikit-learn's)."""
        ya = np.asarray(y, dtype=np.float64)
        predict: Any = getattr(self, "predict")  # noqa: B009  (every subclass defines it)
        resid = ya - np.asarray(predict(X), dtype=np.float64)
        total = float(np.sum((ya - ya.mean()) ** 2))
        return 1.0 - float(resid @ resid) / total if total > 0 else float("nan")

    def __repr__(self) -> str:
        defaults = {
            p.name: p.default
            for p in inspect.signature(type(self).__init__).parameters.values()
            if p.default is not p.empty
        }
        changed = [
            f"{k}={v!r}"
            for k, v in self.get_params(deep=False).items()
            if k not in defaults or not _same(v, defaults[k])
        ]
        return f"{type(self).__name__}({', '.join(changed)})"


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(a is b or a == b)
    except (TypeError, ValueError):  # arrays and the like: compare by identity only
        return False
