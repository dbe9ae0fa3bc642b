"""The effect registry and the effect set.

Every consumer of the vocabulary iterates :data:`EFFECTS` (the simulator asks each effect of
a set for its physics, the discrepancy workflow scores every registered effect, the CLI
lists the names): adding an effect is one class registered here, by its own module
(:func:`register_effect`) or at run time (an effect built from a fitted term).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from timedexec.effects._base import Effect
from timedexec.errors import ConfigError

__all__ = [
    "EFFECTS",
    "EffectRegistry",
    "EffectSet",
    "effect_type",
    "make_effect",
    "register_effect",
]

_E = TypeVar("_E", bound=type[Effect])


class EffectRegistry(Mapping[str, type[Effect]]):
    """The effect classes by name, in the vocabulary's order (each class's ``order``, then
    the order of registration)."""

    def __init__(self) -> None:
        self._types: dict[str, type[Effect]] = {}
        self._rank: dict[str, int] = {}

    def __getitem__(self, name: str) -> type[Effect]:
        return self._types[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._types)

    def __len__(self) -> int:
        return len(self._types)

    def register(self, cls: _E) -> _E:
        """Add ``cls`` under ``cls.name`` (usable as a class decorator); returns ``cls``.

        Raises
        ------
        ConfigError
            ``cls`` is no :class:`Effect` subclass, has no name, or its name belongs to
            another class already.
        """
        if not (isinstance(cls, type) and issubclass(cls, Effect)):
            raise ConfigError(f"register_effect takes an Effect subclass, got {cls!r}")
        name = cls.name
        if not name or not name.isidentifier():
            raise ConfigError(
                f"effect class {cls.__qualname__} needs a name (a Python identifier such as "
                f"'payload'), got {name!r}"
            )
        if cls.acts_on not in ("actuation_delay", "response_delay"):
            raise ConfigError(
                f"effect {name!r}: acts_on={cls.acts_on!r} must be 'actuation_delay' or "
                "'response_delay'"
            )
        old = self._types.get(name)
        if old is not None and old is not cls:
            raise ConfigError(
                f"effect name {name!r} is taken by {old.__module__}.{old.__qualname__}; "
                "pick another name or unregister it first"
            )
        types: dict[str, type[Effect]] = {**self._types, name: cls}
        seq = list(types)
        ordered = sorted(seq, key=lambda n: (types[n].order, seq.index(n)))
        self._types = {n: types[n] for n in ordered}
        self._rank = {n: k for k, n in enumerate(self._types)}
        return cls

    def unregister(self, name: str) -> None:
        """Remove the effect called ``name`` (an effect registered at run time)."""
        self.get_type(name)
        del self._types[name]
        self._rank = {n: k for k, n in enumerate(self._types)}

    def get_type(self, name: str) -> type[Effect]:
        """The class of the effect called ``name``.

        Raises
        ------
        ConfigError
            Unknown name (the message lists the vocabulary).
        """
        try:
            return self._types[name]
        except KeyError:
            raise ConfigError(
                f"unknown effect {name!r}; the vocabulary is: {', '.join(self._types)}"
            ) from None

    def rank(self, name: str) -> int:
        """Position of ``name`` in the vocabulary's order."""
        return self._rank[name]

    @property
    def vocabulary(self) -> tuple[str, ...]:
        """The names the discrepancy workflow may give, in order: every registered effect
        but the data-driven terms (:attr:`Effect.data_driven`) it found itself."""
        return tuple(n for n, cls in self._types.items() if not cls.data_driven)


#: The registry: every effect of the vocabulary by name, in order.
EFFECTS = EffectRegistry()
register_effect = EFFECTS.register
effect_type = EFFECTS.get_type


def make_effect(name: str, **params: Any) -> Effect:
    """Build the effect called ``name`` with ``params`` (defaults for the rest).

    Raises
    ------
    ConfigError
        Unknown name (the message lists the vocabulary) or an invalid parameter.
    """
    cls = effect_type(name)
    try:
        return cls(**params)
    except TypeError as exc:
        allowed = [f.name for f in dataclasses.fields(cls)]
        raise ConfigError(f"effect {name!r}: {exc}; its parameters are {allowed}") from exc


@dataclass(frozen=True)
class EffectSet:
    """An immutable set of effects, at most one per name, kept in vocabulary order."""

    effects: tuple[Effect, ...] = ()

    def __post_init__(self) -> None:
        seen: dict[str, Effect] = {}
        for e in self.effects:
            if not isinstance(e, Effect) or not e.name:
                raise ConfigError(f"EffectSet holds effects, got {e!r}")
            if e.name in seen:
                raise ConfigError(f"effect {e.name!r} given twice")
            effect_type(e.name)  # registered (else: the vocabulary is listed)
            seen[e.name] = e
        ordered = tuple(sorted(seen.values(), key=lambda e: EFFECTS.rank(e.name)))
        object.__setattr__(self, "effects", ordered)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the effects present."""
        return tuple(e.name for e in self.effects)

    def __contains__(self, name: object) -> bool:
        return name in self.names

    def __iter__(self) -> Iterator[Effect]:
        return iter(self.effects)

    def __len__(self) -> int:
        return len(self.effects)

    def get(self, name: str) -> Effect | None:
        """The effect called ``name``, or None when it is off."""
        for e in self.effects:
            if e.name == name:
                return e
        return None

    def with_effect(self, effect: Effect) -> EffectSet:
        """A copy with ``effect`` added (replacing one of the same name)."""
        return EffectSet((*tuple(e for e in self.effects if e.name != effect.name), effect))

    def without(self, name: str) -> EffectSet:
        """A copy without the effect called ``name``."""
        effect_type(name)  # raises with the vocabulary listed
        return EffectSet(tuple(e for e in self.effects if e.name != name))

    def to_dict(self) -> list[dict[str, Any]]:
        """JSON-safe list of effect dicts."""
        return [e.to_dict() for e in self.effects]

    @classmethod
    def from_dict(cls, data: Iterable[Mapping[str, Any]]) -> EffectSet:
        """Inverse of :meth:`to_dict`."""
        effects = []
        for item in data:
            params = dict(item)
            name = params.pop("name")
            effects.append(make_effect(name, **params))
        return cls(tuple(effects))
