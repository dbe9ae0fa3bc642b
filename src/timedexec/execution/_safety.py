"""The executor's safety against a dead host and its stop: the controller watchdog, rest.

:class:`ControllerWatchdog` arms the driver's controller watchdog
(:meth:`~timedexec.drivers.RobotDriver.arm_watchdog`) when the executor connects and keeps
it fed: every command feeds it, and while idle (no plan, arm at rest) every handled package
kicks it at most once per :data:`KICK_FRACTION` of the timeout. If the caller does not step
the executor for longer than the timeout while idle, the watchdog stops the program: that
is harmless (the arm is at rest) and the next motion re-arms it (the driver restarts the
program; ~25 ms on the UR twin). A trip while streaming is a fault.

:func:`wait_for_rest` is the stop that returns only when the arm is at rest: a zero
``speedj`` on every package (it decelerates at the stop deceleration and feeds the
watchdog) until the reported speed of every joint stays below a threshold for a few
packages, within a timeout derived from the current speed and the deceleration.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable

import numpy as np

from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import DriverError, DriverTimeout

__all__ = [
    "DEFAULT_WATCHDOG_TIMEOUT_S",
    "KICK_FRACTION",
    "REST_PACKAGES",
    "REST_SPEED_RAD_S",
    "STOP_MARGIN_S",
    "ControllerWatchdog",
    "fault_stop",
    "rest_timeout_s",
    "wait_for_rest",
]


#: Default controller watchdog timeout, s: 50 periods at 500 Hz (12.5 at 125 Hz). Longer
#: than any stall the adaptive staleness limits tolerate (their 80 ms ceiling), so the
#: host's own fault stop comes first whenever the host is alive; short enough that a dead
#: host's arm moving at 1 rad/s travels at most 0.1 rad before the program stop begins.
DEFAULT_WATCHDOG_TIMEOUT_S = 0.1
#: While idle, kick at most once per this fraction of the timeout (5 kicks per timeout).
KICK_FRACTION = 0.2
#: A joint below this reported speed counts as at rest, rad/s.
REST_SPEED_RAD_S = 0.01
#: Consecutive packages with every joint at rest before stop() returns.
REST_PACKAGES = 3
#: While stopping, a zero speedj goes out at least this often even without packages, s.
FEED_EVERY_S = 0.02
#: Extra time a stop may take beyond speed / deceleration, s (delays, host jitter).
STOP_MARGIN_S = 0.25


class ControllerWatchdog:
    """The driver's controller watchdog as the executor uses it.

    Parameters
    ----------
    driver : RobotDriver
        The driver (a controller without a watchdog makes every method a no-op).
    timeout_s : float or None
        Timeout to arm, s (validated by
        :class:`~timedexec.execution.ExecutorSettings`); None: never arm.

    Attributes
    ----------
    armed_s : float or None
        The timeout in force, s (None: not armed or not supported).
    kicks : int
        Kicks sent.
    idle_trips : int
        Kicks refused because the watchdog had tripped while idle (harmless, at rest).
    rearm_s : list of float
        Duration of each re-arm after an idle trip, s (the cost of letting it trip).
    """

    def __init__(self, driver: RobotDriver, timeout_s: float | None) -> None:
        self.driver = driver
        self.timeout_s = None if timeout_s is None else float(timeout_s)
        self.armed_s: float | None = None
        self.kicks = 0
        self.idle_trips = 0
        self.rearm_s: list[float] = []
        self._last_feed_s = -math.inf

    def arm(self, now_s: float) -> None:
        """Arm (or re-arm) the watchdog."""
        if self.timeout_s is None:
            return
        self.armed_s = self.driver.arm_watchdog(self.timeout_s)
        self._last_feed_s = now_s

    def fed(self, now_s: float) -> None:
        """A command left at ``now_s`` (it feeds the watchdog)."""
        self._last_feed_s = now_s

    def kick_if_due(self, now_s: float) -> None:
        """While idle: kick when the last feed is older than a fifth of the timeout."""
        armed = self.armed_s
        if armed is not None and now_s - self._last_feed_s >= KICK_FRACTION * armed:
            self._last_feed_s = now_s
            try:
                self.driver.kick_watchdog()
            except DriverError:
                # Tripped while idle at rest (the caller or the stream paused past the
                # timeout): harmless; the next motion re-arms it.
                if not self.tripped():
                    raise
                self.idle_trips += 1
                return
            self.kicks += 1

    def tripped(self) -> bool:
        """Whether the armed watchdog stopped the program."""
        return self.armed_s is not None and self.driver.watchdog_tripped()

    def rearm_if_tripped(self, clock: Callable[[], float]) -> bool:
        """Before a motion from rest: re-arm after an idle trip, else kick at once (the
        caller may not have stepped for a while: planning); returns whether it had
        tripped. A kick refused because the trip landed just now re-arms too."""
        if self.armed_s is None:
            return False
        if not self.tripped():
            try:
                self.driver.kick_watchdog()
                self.kicks += 1
                self._last_feed_s = clock()
                return False
            except DriverError:
                if not self.tripped():
                    raise
        t = time.perf_counter()
        self.arm(clock())
        self.rearm_s.append(time.perf_counter() - t)
        return True


def fault_stop(driver: RobotDriver, deceleration_rad_s2: float, message: str) -> None:
    """Stop the arm after a fault: a zero-speed ``speedj`` at once (a realtime command; the
    drivers' ``stop()`` may first wait for the controller's acknowledgement of the previous
    command: ur_rtde's speedStop, ~30 ms when the stream has stalled), then ``stop()``.

    Raises
    ------
    DriverError
        The controller refused the zero speed (``"<message>; <why>"``): its watchdog had
        already stopped the program (the host was paused past the timeout), which stopped
        the arm.
    """
    try:
        driver.speedj(np.zeros(6), deceleration_rad_s2, 0.0)
    except DriverError as exc:
        raise DriverError(f"{message}; {exc}") from exc
    finally:
        with contextlib.suppress(DriverError):
            driver.stop(deceleration_rad_s2)


def rest_timeout_s(speed_rad_s: float, deceleration_rad_s2: float, period_s: float) -> float:
    """How long a stop from ``speed_rad_s`` may take before it is a failure, s: the ramp
    (speed / deceleration) plus :data:`STOP_MARGIN_S` plus the rest packages."""
    return abs(speed_rad_s) / deceleration_rad_s2 + STOP_MARGIN_S + (REST_PACKAGES + 1) * period_s


def wait_for_rest(
    driver: RobotDriver,
    *,
    deceleration_rad_s2: float,
    hold_s: float,
    period_s: float,
    clock: Callable[[], float],
    speed_rad_s: float,
    timeout_s: float | None = None,
    rest_speed_rad_s: float = REST_SPEED_RAD_S,
    rest_packages: int = REST_PACKAGES,
    on_state: Callable[[RobotState], None] | None = None,
    watchdog: ControllerWatchdog | None = None,
) -> RobotState:
    """Decelerate to rest, end speed mode (the driver's ``stop()``) and return the first
    package of the rest run.

    Parameters
    ----------
    driver : RobotDriver
        The driver.
    deceleration_rad_s2 : float
        Deceleration of the leading joint, rad/s².
    hold_s : float
        Duration of each zero ``speedj``, s.
    period_s : float
        Controller period, s.
    clock : callable
        The host clock the driver stamps with, s.
    speed_rad_s : float
        The fastest joint's current speed (commanded or reported), rad/s: sets the default
        timeout.
    timeout_s : float, optional
        Give up after this long, s (default :func:`rest_timeout_s`).
    rest_speed_rad_s : float
        Every joint's reported speed must stay below this, rad/s.
    rest_packages : int
        For this many consecutive packages.
    on_state : callable, optional
        Called with every package read.
    watchdog : ControllerWatchdog, optional
        Fed by the last zero ``speedj``.

    Raises
    ------
    DriverError
        The arm still moves when the timeout runs out (the message names the speed, the
        joint, the time waited and the deceleration).
    """
    if timeout_s is None:
        timeout_s = rest_timeout_s(speed_rad_s, deceleration_rad_s2, period_s)
    zero = np.zeros(6)
    start = clock()
    deadline = start + timeout_s
    run = 0
    first_at_rest: RobotState | None = None
    worst = math.inf
    worst_joint = 0
    while True:
        driver.speedj(zero, deceleration_rad_s2, hold_s)
        remaining = deadline - clock()
        if remaining <= 0:
            break
        try:
            # Short reads: a stalled stream must not starve the watchdog while stopping
            # (a zero speedj is always safe to repeat).
            state = driver.read_state(timeout_s=min(remaining, max(FEED_EVERY_S, 2 * period_s)))
        except DriverTimeout:
            continue
        if on_state is not None:
            on_state(state)
        qd = np.abs(state.qd)
        worst_joint = int(np.argmax(qd))
        worst = float(qd[worst_joint])
        if worst < rest_speed_rad_s:
            run += 1
            if first_at_rest is None:
                first_at_rest = state
            if run >= rest_packages:
                if watchdog is not None:
                    watchdog.fed(clock())
                driver.stop(deceleration_rad_s2)
                return first_at_rest
        else:
            run = 0
            first_at_rest = None
    if not math.isfinite(worst):
        raise DriverError(
            f"no state package within {timeout_s:.3f} s of the stop at {deceleration_rad_s2:g} "
            "rad/s²: cannot confirm the arm is at rest; check the connection and stop the "
            "robot from the pendant"
        )
    raise DriverError(
        f"the arm did not come to rest: joint {worst_joint + 1} still reports "
        f"{worst:.4g} rad/s (rest: below {rest_speed_rad_s:g} rad/s for {rest_packages} "
        f"packages) {clock() - start:.3f} s after the stop at {deceleration_rad_s2:g} "
        f"rad/s² from {speed_rad_s:.3g} rad/s (allowed {timeout_s:.3f} s); check the "
        "controller (protective stop, speed scaling) and stop the robot from the pendant"
    )
