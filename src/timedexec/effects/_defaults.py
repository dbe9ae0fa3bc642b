"""The robots' default effect sets and the command line's effect-set syntax."""

from __future__ import annotations

from timedexec.effects._registry import EFFECTS, EffectSet, make_effect
from timedexec.errors import ConfigError
from timedexec.robots import get_robot_entry

__all__ = ["default_effects", "parse_effects"]


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
    default set; a list names effects with their default parameters (``default,NAME,...``:
    the default set plus those named).
    """
    text = spec.strip()
    if text == "base":
        return EffectSet()
    if text == "default":
        return default_effects(robot)
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ConfigError(
            f"empty effect list {spec!r}; give base, default or names from: {', '.join(EFFECTS)}"
        )
    out = default_effects(robot) if names[0] == "default" else EffectSet()
    for n in names[1:] if names[0] in ("base", "default") else names:
        out = out.with_effect(make_effect(n))
    return out
