"""The executor's hold on a driver: connect, identify the robot, pin BLAS, close."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from timedexec.drivers import RobotDriver, RobotState
from timedexec.execution._model import DelayPredictor, check_model_robot
from timedexec.robots import RobotSpec, get_robot

__all__ = ["DriverSession"]


def _driver_spec(driver: RobotDriver, robot: str, period_s: float) -> RobotSpec:
    """The connected driver's robot spec (its own when it has one)."""
    spec = getattr(driver, "spec", None)
    if isinstance(spec, RobotSpec):
        return spec
    settings = getattr(driver, "settings", None)
    if isinstance(getattr(settings, "spec", None), RobotSpec):
        return settings.spec  # type: ignore[union-attr,no-any-return]
    return get_robot(robot, period_s=period_s)


class DriverSession:
    """A driver connected for a delay model.

    Parameters
    ----------
    driver : RobotDriver
        The driver; connected by :meth:`open` (and then closed by :meth:`close`).
    model : DelayPredictor
        The delay model: checked against the connected robot and controller period; a
        model with a BLAS pin (``model.pinned()``, :class:`timedexec.learning.DelayModel`)
        keeps BLAS on one thread while connected, so queries during the loop skip the
        per-call pin and its thread wake-ups.

    Attributes
    ----------
    spec : RobotSpec or None
        The connected robot's spec; None while not connected.
    period_s : float
        Controller period, s (NaN before the first connection).
    """

    def __init__(self, driver: RobotDriver, model: DelayPredictor) -> None:
        self.driver = driver
        self.model = model
        self.spec: RobotSpec | None = None
        self.period_s = math.nan
        self._connected_here = False
        self._pin: Any = None

    def open(self, first_state: Callable[[RobotState], None]) -> None:
        """Connect (no-op when connected), check the model against the robot, and hand a
        first package to ``first_state``; on any failure the driver is closed again."""
        if self.spec is not None:
            return
        self.driver.connect()
        self._connected_here = True
        try:
            robot = str(self.driver.robot)
            period = float(self.driver.controller_period_s)
            check_model_robot(self.model, robot, period)
            self.spec = _driver_spec(self.driver, robot, period)
            self.period_s = period
            first_state(self.driver.read_state(timeout_s=max(1.0, 10 * period)))
        except BaseException:
            self.spec = None
            self.driver.close()
            raise
        pinned = getattr(self.model, "pinned", None)
        if callable(pinned) and self._pin is None:
            self._pin = pinned()
            self._pin.__enter__()

    def close(self, stop: Callable[[], None] | None = None) -> None:
        """Call ``stop`` (bring the arm to rest) if given and connected, release the BLAS
        pin and close the driver if :meth:`open` connected it."""
        try:
            if self.spec is not None and stop is not None:
                stop()
        finally:
            self.spec = None
            if self._pin is not None:
                pin, self._pin = self._pin, None
                pin.__exit__(None, None, None)
            if self._connected_here:
                self.driver.close()
