"""Argument checks shared by every layer (one copy; messages name the value and the fix).

Plain functions on values, in the manner of ``sklearn.utils.validation``: settings
dataclasses call them from ``__post_init__``, public functions at their boundary.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError

__all__ = [
    "N_JOINTS",
    "DictMixin",
    "check_joint_array",
    "check_joint_tuple",
    "check_known_keys",
    "check_non_negative",
    "check_positive",
]

#: Joints of every supported arm.
N_JOINTS = 6


def check_positive(owner: str, **values: float) -> None:
    """Raise :class:`ConfigError` unless every value is > 0 (NaN fails)."""
    for name, value in values.items():
        if not value > 0:
            raise ConfigError(f"{owner}: {name}={value!r} must be > 0")


def check_non_negative(owner: str, **values: float) -> None:
    """Raise :class:`ConfigError` unless every value is >= 0 (NaN fails)."""
    for name, value in values.items():
        if not value >= 0:
            raise ConfigError(f"{owner}: {name}={value!r} must be >= 0")


def check_counts(**values: tuple[Any, int]) -> None:
    """Each ``name=(value, low)`` must be an integer (not a bool) >= ``low``; the first
    that is not raises :class:`ConfigError` naming it."""
    for name, (value, low) in values.items():
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            raise ConfigError(f"{name}={value!r} must be an integer >= {low}")


def check_joint_tuple(owner: str, name: str, value: Iterable[float]) -> tuple[float, ...]:
    """``value`` as a tuple of 6 floats (one per joint), for frozen settings."""
    out = tuple(float(v) for v in value)
    if len(out) != N_JOINTS:
        raise ConfigError(
            f"{owner}: {name} needs {N_JOINTS} values (one per joint), got {len(out)}"
        )
    return out


def check_joint_array(name: str, value: ArrayLike) -> NDArray[np.float64]:
    """``value`` as a finite float array of shape (6,) (a joint vector)."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (N_JOINTS,):
        raise ConfigError(f"{name}: incorrect vector length: expected {N_JOINTS}, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name}: values must be finite, got {arr.tolist()}")
    return arr


def check_known_keys(cls: type, data: Iterable[str]) -> None:
    """Raise :class:`ConfigError` when ``data`` (a mapping's keys) names a field the
    dataclass ``cls`` does not have (a misspelt setting in a dict or JSON file)."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"unknown {cls.__name__} keys {unknown}; expected some of {sorted(names)}"
        )


class DictMixin:
    """``to_dict`` for frozen settings dataclasses: JSON-safe, nested settings as dicts."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (tuples become lists)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            if dataclasses.is_dataclass(v) and not isinstance(v, type):
                out[f.name] = v.to_dict()  # type: ignore[attr-defined]
            elif isinstance(v, tuple):
                out[f.name] = list(v)
            else:
                out[f.name] = v
        return out
