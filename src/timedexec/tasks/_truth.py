"""The simulator's physical joint angles, where the driver has them: the truth a task measures."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from timedexec._types import FloatArray
from timedexec.execution import TimedExecutor

__all__ = ["physical_probe"]


def physical_probe(executor: TimedExecutor) -> Callable[[], tuple[float, FloatArray]] | None:
    """``() -> (host time, physical q (6,), rad)`` of a simulated driver's controller (an
    in-process ``sim://`` driver in virtual time), else None (a real robot or a twin: only
    the executor's estimate, or the twin's own truth)."""
    driver: Any = executor.driver
    if not hasattr(driver, "controller") or not getattr(driver, "virtual", False):
        return None

    def probe() -> tuple[float, FloatArray]:
        sim = driver.controller
        return float(sim.time_s), np.asarray(sim.q_rad, dtype=float)

    return probe
