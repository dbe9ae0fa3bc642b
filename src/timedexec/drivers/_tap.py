"""A driver decorator that logs the host arrival time of every state package.

A recording keeps host times relative to each trial's trigger package; the absolute host
time of that package (the session's clock origin) is not stored. :class:`HostTimeTap` wraps
the driver given to the calibration runner and logs the absolute host time of every package
by controller time, which anchors each trial to a protocol twin's ground truth
(:func:`timedexec.twins.twin_truth_table`) or to any external clock.
"""

from __future__ import annotations

import threading
from typing import Any

from timedexec._types import FloatArray
from timedexec.drivers._base import RobotDriver, RobotState

__all__ = ["HostTimeTap"]


class HostTimeTap(RobotDriver):
    """A driver that forwards everything to ``driver`` and logs each package's host time.

    The log maps the package's ``controller_time_s`` to its ``host_time_s``
    (:func:`time.monotonic` on arrival), which anchors the recording's trial-relative host
    times to the twin's clock. Attributes the wrapped driver has beyond the interface
    (``last_send_s``, ``clock``, ``port`` ...) are forwarded, so the runner sees the same
    driver.

    Parameters
    ----------
    driver : RobotDriver
        The driver to wrap (connected or not).
    """

    def __init__(self, driver: RobotDriver) -> None:
        self.driver = driver
        self._times: dict[float, float] = {}
        self._lock = threading.Lock()

    def __getattr__(self, name: str) -> Any:
        if name == "driver":  # not set yet (during unpickling or __init__)
            raise AttributeError(name)
        return getattr(self.driver, name)

    @property
    def robot(self) -> str:
        """The wrapped driver's robot name."""
        return str(self.driver.robot)

    @robot.setter
    def robot(self, value: str) -> None:
        self.driver.robot = value

    @property
    def controller_period_s(self) -> float:
        return self.driver.controller_period_s

    def connect(self) -> None:
        self.driver.connect()

    def close(self) -> None:
        self.driver.close()

    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        state = self.driver.read_state(timeout_s=timeout_s)
        with self._lock:
            self._times[float(state.controller_time_s)] = float(state.host_time_s)
        return state

    def speedj(self, qd_rad_s: FloatArray, acceleration_rad_s2: float, duration_s: float) -> None:
        self.driver.speedj(qd_rad_s, acceleration_rad_s2, duration_s)

    def stop(self, deceleration_rad_s2: float = 10.0) -> None:
        self.driver.stop(deceleration_rad_s2)

    @property
    def host_times(self) -> dict[float, float]:
        """Copy of the log: controller time (s) -> host arrival time (s)."""
        with self._lock:
            return dict(self._times)
