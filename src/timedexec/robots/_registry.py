"""The robot registry: the catalog's robots by name (:func:`get_robot`, :func:`get_robot_entry`,
:data:`ROBOT_NAMES`).

Built once, at import, from the modules named in
:data:`timedexec.robots.catalog.MODULES` (one data module per robot, each defining
``ROBOT``, a :class:`~timedexec.robots.RobotEntry`); every other layer iterates
:data:`ROBOT_NAMES` or looks a robot up here, so a robot is added in one place.
"""

from __future__ import annotations

import importlib
from types import MappingProxyType

from timedexec.errors import ConfigError
from timedexec.robots._entry import RobotEntry
from timedexec.robots._spec import RobotSpec
from timedexec.robots.catalog import MODULES

__all__ = ["ROBOT_NAMES", "get_robot", "get_robot_entry"]


def _load(modules: tuple[str, ...]) -> MappingProxyType[str, RobotEntry]:
    """Import the catalog's modules and check that each defines its robot."""
    entries: dict[str, RobotEntry] = {}
    for module_name in modules:
        where = f"timedexec/robots/catalog/{module_name}.py"
        module = importlib.import_module(f"timedexec.robots.catalog.{module_name}")
        entry = getattr(module, "ROBOT", None)
        if not isinstance(entry, RobotEntry):
            raise ConfigError(f"{where} must define ROBOT, a RobotEntry; got {entry!r:.60}")
        if entry.name != module_name or entry.name in entries:
            raise ConfigError(
                f"{where} defines robot {entry.name!r}: a robot's name must be its module's "
                "name, once in the catalog"
            )
        entries[entry.name] = entry
    return MappingProxyType(entries)


_ENTRIES = _load(MODULES)

#: Names accepted by :func:`get_robot`, in the catalog's order.
ROBOT_NAMES: tuple[str, ...] = tuple(_ENTRIES)


def get_robot_entry(name: str) -> RobotEntry:
    """Return everything the catalog holds about a robot.

    Parameters
    ----------
    name : str
        One of :data:`ROBOT_NAMES`; case- and space-insensitive.

    Raises
    ------
    ConfigError
        For an unknown name; the message lists the robots.
    """
    key = name.strip().lower() if isinstance(name, str) else None
    entry = _ENTRIES.get(key) if key is not None else None
    if entry is None:
        raise ConfigError(f"unknown robot {name!r}; choose one of {', '.join(ROBOT_NAMES)}")
    return entry


def get_robot(name: str, *, period_s: float | None = None) -> RobotSpec:
    """Return the built-in spec of a robot.

    Parameters
    ----------
    name : str
        One of :data:`ROBOT_NAMES`; case- and space-insensitive.
    period_s : float, optional
        Controller period, s; default: the robot's default period (see
        :meth:`RobotSpec.with_period`).

    Raises
    ------
    ConfigError
        For an unknown name or a period the controller does not offer.
    """
    spec = get_robot_entry(name).spec
    return spec if period_s is None else spec.with_period(period_s)
