"""The effect vocabulary: named physical and timing effects.

Each effect is a frozen, keyword-only dataclass with physical parameters. The simulator
applies the effects of an :class:`EffectSet`; the discrepancy workflow scores the same
objects as candidate explanations of what a measurement shows and a simulation lacks. The
names are part of the public interface (DESIGN.md, "Effect vocabulary").

How each effect acts in the simulator (``timedexec.sim``):

``gravity_load``
    Load-dependent friction of the gear: the breakaway (static friction) torque of a joint
    grows by ``friction_per_load`` N·m per N·m of gravity torque it holds at the start pose.
    A joint holding more load needs longer before its velocity loop breaks it free.
``gravity_direction``
    Lifting against gravity needs more breakaway torque than lowering with it: breakaway
    torque changes by ``friction_per_load`` · d · τ_g (d the direction, τ_g the holding torque;
    d · τ_g > 0 means the motion raises the potential energy).
``direction``
    Pose-independent asymmetry of the drive: breakaway torque scales by ``1 + asymmetry_j · d``.
``inertia``
    The joint's true reflected inertia at the start pose is used; without the effect every
    pose has the nominal inertia (the one the velocity loop is tuned for). More inertia means
    a slower rise after breakaway.
``thermal_drift``
    Cold grease: breakaway and kinetic friction start ``cold_excess`` above their warm values
    and relax with ``time_constant_s`` over the sweep.
``joint_offset``
    Each joint's drive applies the setpoint ``offsets_s[j]`` later (drive bus slot, filters).
``response_extra_cycle``
    State sampling and transmission fall in separate controller cycles: every state package
    leaves ``cycles`` periods later.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from timedexec._validation import check_joint_tuple
from timedexec.errors import ConfigError
from timedexec.robots import get_robot_entry

__all__ = [
    "EFFECT_NAMES",
    "Direction",
    "Effect",
    "EffectSet",
    "GravityDirection",
    "GravityLoad",
    "Inertia",
    "JointOffset",
    "ResponseExtraCycle",
    "ThermalDrift",
    "default_effects",
    "make_effect",
    "parse_effects",
]


@dataclass(frozen=True, kw_only=True)
class Effect:
    """Base class of the effects. Subclasses set ``name``, ``meaning`` and ``variable``."""

    name: ClassVar[str] = ""
    #: What the effect means physically (one sentence, for reports).
    meaning: ClassVar[str] = ""
    #: The variable whose value the effect follows (for reports and residual plots).
    variable: ClassVar[str] = ""
    #: Which delay it acts on: "actuation_delay" or "response_delay".
    acts_on: ClassVar[str] = "actuation_delay"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form: ``{"name": ..., **parameters}``."""
        out: dict[str, Any] = {"name": self.name}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    def _check_finite(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            for v in values:
                if not isinstance(v, int | float) or v != v or v in (float("inf"), float("-inf")):
                    raise ConfigError(
                        f"effect {self.name!r}: parameter {f.name}={value!r} must be finite numbers"
                    )


@dataclass(frozen=True, kw_only=True)
class GravityLoad(Effect):
    """Breakaway torque grows with the gravity torque the joint holds.

    Parameters
    ----------
    friction_per_load : float
        Extra breakaway torque per unit holding torque, N·m/N·m (dimensionless), >= 0.
    """

    name: ClassVar[str] = "gravity_load"
    meaning: ClassVar[str] = (
        "actuation delay grows with the gravity torque the actuated joint holds at the start pose"
    )
    variable: ClassVar[str] = "|gravity torque| (N·m)"
    friction_per_load: float = 0.2

    def __post_init__(self) -> None:
        self._check_finite()
        if self.friction_per_load < 0:
            raise ConfigError(
                f"gravity_load: friction_per_load={self.friction_per_load} must be >= 0"
            )


@dataclass(frozen=True, kw_only=True)
class GravityDirection(Effect):
    """Lifting needs more breakaway torque than lowering.

    Parameters
    ----------
    friction_per_load : float
        Breakaway torque change per unit signed holding torque d · τ_g, dimensionless, >= 0.
    """

    name: ClassVar[str] = "gravity_direction"
    meaning: ClassVar[str] = (
        "moving against gravity differs from moving with it (direction x gravity torque sign)"
    )
    variable: ClassVar[str] = "direction x gravity torque (N·m)"
    friction_per_load: float = 0.08

    def __post_init__(self) -> None:
        self._check_finite()
        if self.friction_per_load < 0:
            raise ConfigError(
                f"gravity_direction: friction_per_load={self.friction_per_load} must be >= 0"
            )


@dataclass(frozen=True, kw_only=True)
class Direction(Effect):
    """Pose-independent direction asymmetry of each joint's breakaway torque.

    Parameters
    ----------
    asymmetry : tuple of 6 float
        Breakaway torque is scaled by ``1 + asymmetry[j] * direction``; each in (-0.9, 0.9).
    """

    name: ClassVar[str] = "direction"
    meaning: ClassVar[str] = "a pose-independent asymmetry between positive and negative motion"
    variable: ClassVar[str] = "direction (+1/-1)"
    asymmetry: tuple[float, ...] = (0.2, 0.15, 0.2, 0.2, 0.2, 0.2)

    def __post_init__(self) -> None:
        object.__setattr__(
            self,
            "asymmetry",
            check_joint_tuple(f"effect {self.name!r}", "asymmetry", self.asymmetry),
        )
        self._check_finite()
        if any(abs(a) >= 0.9 for a in self.asymmetry):
            raise ConfigError(f"direction: asymmetry {self.asymmetry} must lie in (-0.9, 0.9)")


@dataclass(frozen=True, kw_only=True)
class Inertia(Effect):
    """The true, pose-dependent reflected inertia acts (instead of the nominal one).

    Parameters
    ----------
    scale : float
        Multiplier on the link part of the inertia (1.0 = the robot spec's values), > 0.
    """

    name: ClassVar[str] = "inertia"
    meaning: ClassVar[str] = (
        "actuation delay grows with the inertia the joint must accelerate (distal joint angles)"
    )
    variable: ClassVar[str] = "reflected inertia (kg·m²)"
    scale: float = 1.0

    def __post_init__(self) -> None:
        self._check_finite()
        if self.scale <= 0:
            raise ConfigError(f"inertia: scale={self.scale} must be > 0")


@dataclass(frozen=True, kw_only=True)
class ThermalDrift(Effect):
    """Friction starts high (cold grease) and relaxes over the sweep.

    Parameters
    ----------
    cold_excess : float
        Relative friction excess at t = 0 (0.3 = 30 % above warm), >= 0.
    time_constant_s : float
        Warm-up time constant, s, > 0.
    """

    name: ClassVar[str] = "thermal_drift"
    meaning: ClassVar[str] = "delays drift with time since the sweep started (warm-up)"
    variable: ClassVar[str] = "time since sweep start (s)"
    cold_excess: float = 0.6
    time_constant_s: float = 3600.0

    def __post_init__(self) -> None:
        self._check_finite()
        if self.cold_excess < 0 or self.time_constant_s <= 0:
            raise ConfigError(
                f"thermal_drift: cold_excess={self.cold_excess} must be >= 0 and "
                f"time_constant_s={self.time_constant_s} > 0"
            )

    def friction_factor(self, t_s: Any) -> Any:
        """Friction multiplier at sweep time ``t_s`` (s); array in, array out."""
        import numpy as np

        return 1.0 + self.cold_excess * np.exp(-np.asarray(t_s, dtype=float) / self.time_constant_s)


@dataclass(frozen=True, kw_only=True)
class JointOffset(Effect):
    """Each joint's drive applies the setpoint a constant time later.

    Parameters
    ----------
    offsets_s : tuple of 6 float
        Extra dead time per joint, s, each in [0, 0.05].
    """

    name: ClassVar[str] = "joint_offset"
    meaning: ClassVar[str] = "each joint has its own constant offset"
    variable: ClassVar[str] = "joint"
    offsets_s: tuple[float, ...] = (0.0, 0.0015, 0.0008, 0.0004, 0.0012, 0.0002)

    def __post_init__(self) -> None:
        object.__setattr__(
            self,
            "offsets_s",
            check_joint_tuple(f"effect {self.name!r}", "offsets_s", self.offsets_s),
        )
        self._check_finite()
        if any(not 0.0 <= o <= 0.05 for o in self.offsets_s):
            raise ConfigError(f"joint_offset: offsets_s {self.offsets_s} must lie in [0, 0.05] s")


@dataclass(frozen=True, kw_only=True)
class ResponseExtraCycle(Effect):
    """State sampling and transmission fall in separate cycles.

    Parameters
    ----------
    cycles : int
        Extra controller periods between sampling and sending, 1 or more.
    """

    name: ClassVar[str] = "response_extra_cycle"
    meaning: ClassVar[str] = (
        "state sampling and transmission fall in separate cycles: one more period of response"
    )
    variable: ClassVar[str] = "controller period"
    acts_on: ClassVar[str] = "response_delay"
    cycles: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.cycles, int) or isinstance(self.cycles, bool) or self.cycles < 1:
            raise ConfigError(f"response_extra_cycle: cycles={self.cycles!r} must be an int >= 1")


_EFFECT_TYPES: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (
        GravityLoad,
        GravityDirection,
        Direction,
        Inertia,
        ThermalDrift,
        JointOffset,
        ResponseExtraCycle,
    )
}

#: The vocabulary, in the order DESIGN.md lists it.
EFFECT_NAMES: tuple[str, ...] = tuple(_EFFECT_TYPES)


def make_effect(name: str, **params: Any) -> Effect:
    """Build the effect called ``name`` with ``params`` (defaults for the rest).

    Raises
    ------
    ConfigError
        Unknown name (the message lists the vocabulary) or an invalid parameter.
    """
    try:
        cls = _EFFECT_TYPES[name]
    except KeyError:
        raise ConfigError(
            f"unknown effect {name!r}; the vocabulary is: {', '.join(EFFECT_NAMES)}"
        ) from None
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
            seen[e.name] = e
        ordered = tuple(seen[n] for n in EFFECT_NAMES if n in seen)
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
        if name not in _EFFECT_TYPES:
            make_effect(name)  # raises with the vocabulary listed
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


def default_effects(robot: str) -> EffectSet:
    """The robot's default effect set: what the simulated robot has unless told otherwise.

    The names come from the robot's catalog entry (``RobotEntry.default_effects``), each
    effect with its default parameters. UR robots: every effect but
    ``response_extra_cycle`` (RTDE samples and sends in one cycle). KUKA KR 5: all effects;
    the paper found its response delay above one period.

    Raises
    ------
    ConfigError
        For a robot the catalog does not hold, or an effect name outside the vocabulary.
    """
    return EffectSet(tuple(make_effect(name) for name in get_robot_entry(robot).default_effects))


def parse_effects(spec: str, robot: str) -> EffectSet:
    """Parse a command-line effect set: ``base``, ``default`` or ``name,name,...``.

    ``base`` is no effect at all (the simulator's base timing only); ``default`` the robot's
    default set; a list names effects with their default parameters.
    """
    text = spec.strip()
    if text == "base":
        return EffectSet()
    if text == "default":
        return default_effects(robot)
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ConfigError(
            f"empty effect list {spec!r}; give base, default or names from: {', '.join(EFFECT_NAMES)}"
        )
    return EffectSet(tuple(make_effect(n) for n in names))
