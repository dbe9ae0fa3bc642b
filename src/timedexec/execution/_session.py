"""The executor's hold on a driver: connect, identify the robot, pin BLAS, hold the real-time
policies (SCHED_FIFO, a quiet garbage collector, prompt wake-ups) while connected, close."""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import ExitStack
from typing import Any

from timedexec._realtime import GcPauses, fast_wakeup, quiet_gc, realtime
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
    realtime : bool
        Whether the connecting thread got SCHED_FIFO (:meth:`open`'s ``realtime_priority``)
        while connected.
    fast_wakeup : bool
        Whether the CPUs are kept out of deep idle states while connected (real-time
        drivers: ``/dev/cpu_dma_latency`` held at 0 µs; root or a udev rule).
    gc_pauses : GcPauses or None
        With a real-time driver: the garbage collections while connected. Everything alive
        at connect is frozen (``gc.freeze``) until close, so a collection only walks what
        the loop made since (a full one stalled a cycle by 10-35 ms).
    """

    def __init__(self, driver: RobotDriver, model: DelayPredictor) -> None:
        self.driver = driver
        self.model = model
        self.spec: RobotSpec | None = None
        self.period_s = math.nan
        self._connected_here = False
        self._pin: Any = None
        self.realtime = self.fast_wakeup = False
        self.gc_pauses: GcPauses | None = None
        self._rt = ExitStack()

    def open(
        self,
        first_state: Callable[[RobotState], None],
        *,
        realtime_priority: int | None = None,
        real_time: bool = False,
    ) -> None:
        """Connect (no-op when connected), check the model against the robot, and hand a
        first package to ``first_state``; on any failure the driver is closed again.

        Before connecting (so the driver's threads inherit it) the thread asks for
        SCHED_FIFO ``realtime_priority``; with ``real_time`` (a driver on the host's clock,
        not a virtual one) the garbage collector is quieted and the CPUs kept awake, until
        :meth:`close`."""
        if self.spec is not None:
            return
        self.realtime = self._rt.enter_context(realtime(realtime_priority))
        if real_time:
            self.gc_pauses = self._rt.enter_context(quiet_gc())
            self.fast_wakeup = self._rt.enter_context(fast_wakeup())
        try:
            self.driver.connect()
        except BaseException:
            self._release()
            raise
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
            self._release()
            raise
        pinned = getattr(self.model, "pinned", None)
        if callable(pinned) and self._pin is None:
            self._pin = pinned()
            self._pin.__enter__()

    def close(self, stop: Callable[[], object] | None = None) -> None:
        """Call ``stop`` (bring the arm to rest) if given and connected, release the BLAS
        pin, close the driver if :meth:`open` connected it and end the real-time
        policies."""
        try:
            if self.spec is not None and stop is not None:
                stop()
        finally:
            self.spec = None
            try:
                if self._pin is not None:
                    pin, self._pin = self._pin, None
                    pin.__exit__(None, None, None)
                if self._connected_here:
                    self.driver.close()
            finally:
                self._release()

    def _release(self) -> None:
        """End the real-time policies :meth:`open` took."""
        self._rt.close()
        self.realtime = self.fast_wakeup = False
