"""The delay models shipped with timedexec (``models/`` in the repository, installed as the
data package ``timedexec.models``), found by name from any working folder."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from timedexec.errors import ModelError
from timedexec.robots import ROBOT_NAMES, get_robot_entry

__all__ = ["BUNDLED_MODELS", "bundled_model_dir"]

#: Model bundles shipped with the package, one per robot of the catalog (its entry's
#: ``shipped_model``; trained on the simulated robots by scripts/train_bundled_models.py,
#: see models/README.md); load them by name: ``DelayModel.load("kr5-sim")``.
BUNDLED_MODELS: tuple[str, ...] = tuple(get_robot_entry(n).shipped_model for n in ROBOT_NAMES)


def bundled_model_dir(name: str) -> Path:
    """The folder of the shipped model ``name`` (one of :data:`BUNDLED_MODELS`).

    Raises
    ------
    ModelError
        If ``name`` is not a shipped model.
    """
    if name not in BUNDLED_MODELS:
        raise ModelError(f"{name!r} is not a bundled model; bundled: {', '.join(BUNDLED_MODELS)}")
    # Works in a wheel and in an editable install (pyproject maps models/ to the package).
    return Path(str(importlib.resources.files("timedexec.models") / name))
