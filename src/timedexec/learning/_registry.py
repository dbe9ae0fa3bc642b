"""The registry of delay-model methods: one module per method, listed once, here.

Each module named in ``_MODULES`` ends with ``METHOD = DelayMethod(...)`` (see
:class:`~timedexec.learning.DelayMethod`). To add a method, write its module and add one
line below; ``tests/test_learning_registry.py`` then trains it, round-trips it through a
bundle and checks its fast predictor against its estimator.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

from timedexec.errors import ConfigError
from timedexec.learning._method import DelayMethod, ModelInputs

__all__ = [
    "DEFAULT_METHODS",
    "METHODS",
    "check_methods",
    "describe_methods",
    "get_method",
    "make_estimator",
]

#: The method modules, in the order the tables list them (the paper's first).
_MODULES = (
    "timedexec.learning._median",
    "timedexec.learning._nn",
    "timedexec.learning._tree",
    "timedexec.learning._gp",
    "timedexec.learning._phys",
)


def _load(modules: Sequence[str]) -> Mapping[str, DelayMethod]:
    out: dict[str, DelayMethod] = {}
    for module in modules:
        method = getattr(importlib.import_module(module), "METHOD", None)
        if not isinstance(method, DelayMethod):
            raise ConfigError(f"{module} must define METHOD = DelayMethod(...) to be registered")
        if method.name in out:
            raise ConfigError(f"{module}: method name {method.name!r} is registered twice")
        out[method.name] = method
    return MappingProxyType(out)


_REGISTRY = _load(_MODULES)

#: Every registered method's name, in table order.
METHODS: tuple[str, ...] = tuple(_REGISTRY)
#: The methods trained when none are named: the paper's median, NN, tree and GP.
DEFAULT_METHODS: tuple[str, ...] = tuple(n for n, m in _REGISTRY.items() if m.default)


def get_method(name: str) -> DelayMethod:
    """The registered method ``name``; an unknown name raises ConfigError listing them."""
    method = _REGISTRY.get(name)
    if method is None:
        raise ConfigError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    return method


def check_methods(methods: Sequence[str] | str) -> tuple[str, ...]:
    """Normalise a method list ("median,nn" or a sequence); unknown names raise ConfigError."""
    if isinstance(methods, str):
        methods = [m.strip() for m in methods.split(",") if m.strip()]
    out = tuple(dict.fromkeys(methods))
    bad = [m for m in out if m not in _REGISTRY]
    if bad or not out:
        raise ConfigError(
            f"unknown or no method(s) {', '.join(bad) or '(none)'}; choose from {', '.join(METHODS)}"
        )
    return out


def make_estimator(
    method: str, *, random_state: int | None = None, inputs: ModelInputs | None = None
) -> Any:
    """A fresh research estimator of ``method`` with the defaults used here.

    ``inputs`` says what the encoded input columns mean (robot, joint, columns); the
    methods that compute physical quantities from the pose need it.
    """
    return get_method(method).estimator(inputs, random_state)


def describe_methods() -> str:
    """One line per registered method, ``name  label: description`` (--help, docs)."""
    width = max(len(n) for n in METHODS)
    return "\n".join(
        f"  {m.name:{width}}  {m.label}: {m.description}"
        + ("" if m.default else " (not trained by default)")
        for m in _REGISTRY.values()
    )
