"""The built-in robots, one data module each.

Each module here (``ur10.py``, ``kr5.py`` ...) holds everything about one robot as data: a
:class:`~timedexec.robots.RobotEntry` called ``ROBOT`` (its :class:`~timedexec.robots.RobotSpec`
with the sources of every number, its controller timing, twin identity, weld cell, joint
names, calibration ranges, default effects and shipped model). The registry
(:func:`timedexec.robots.get_robot`, :data:`timedexec.robots.ROBOT_NAMES`) is built from the
modules named in :data:`MODULES`, in that order, and everything else in timedexec iterates it.

To add a robot: copy the module of a robot like it, change the numbers (say in
``sources`` which are estimates), add its name to :data:`MODULES`, then train its shipped
model (``scripts/train_bundled_models.py --robots NAME``); ``tests/test_catalog.py`` checks
that every consumer of the registry works for it.

Registration is one explicit line rather than discovery of the package's modules: the
order of :data:`ROBOT_NAMES` is stated, not alphabetical; a half-written or stray module is
not registered by being there; and a missing module fails here, by name.
"""

from __future__ import annotations

__all__ = ["MODULES"]

#: The catalog's modules, one robot each, in the order the registry lists them.
MODULES: tuple[str, ...] = (
    "ur10",
    "ur10e",
    "kr5",
    "ur5e",
)
