"""The RTDE watchdog of the simulated UR controller (URScript ``rtde_set_watchdog``).

``ur_rtde``'s ``setWatchdog(min_frequency)`` makes its control script call
``rtde_set_watchdog("input_int_register_0", min_frequency, "stop")`` (register 24 with the
upper register range); ``kickWatchdog()`` sends a no-op command that rewrites that register.
UR's documentation: when the watchdog did not receive an input update for the variable within
``1 / min_frequency`` s, the action is taken ("ignore", "pause" or "stop" the program), and
all watchdogs are removed on program stop.

Here an *update* is any RTDE input package that carries the watched variable (whatever its
value: the controller counts packages, not changes), time-stamped when its bytes arrived.
The twin checks the watchdogs at every controller cycle boundary against the updates
applied by then, so a violation is acted on at the first boundary more than
``1 / min_frequency`` s after the last update (within one controller period).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable

from timedexec.errors import ConfigError

#: Actions ``rtde_set_watchdog`` takes.
WATCHDOG_ACTIONS = ("ignore", "pause", "stop")


@dataclasses.dataclass
class Watchdog:
    """One armed watchdog.

    Attributes
    ----------
    variable : str
        RTDE input field watched (e.g. ``"input_int_register_0"``).
    min_frequency_hz : float
        Updates expected at least this often, Hz.
    action : str
        One of :data:`WATCHDOG_ACTIONS`.
    last_update_s : float
        Controller time of the last update (or of arming), s.
    """

    variable: str
    min_frequency_hz: float
    action: str
    last_update_s: float

    @property
    def timeout_s(self) -> float:
        """Longest allowed silence, s."""
        return 1.0 / self.min_frequency_hz


class Watchdogs:
    """The watchdogs of the running program, by watched variable."""

    def __init__(self) -> None:
        self._armed: dict[str, Watchdog] = {}

    def __bool__(self) -> bool:
        return bool(self._armed)

    def arm(self, variable: str, min_frequency_hz: float, action: str, now_s: float) -> Watchdog:
        """Arm (or re-arm) the watchdog of ``variable`` at controller time ``now_s``.

        Raises
        ------
        ConfigError
            A frequency that is not finite and > 0, or an unknown action.
        """
        if not (math.isfinite(min_frequency_hz) and min_frequency_hz > 0):
            raise ConfigError(
                f"rtde_set_watchdog: min_frequency {min_frequency_hz!r} Hz must be finite and > 0"
            )
        if action not in WATCHDOG_ACTIONS:
            raise ConfigError(
                f"rtde_set_watchdog: action {action!r} is not one of {WATCHDOG_ACTIONS}"
            )
        dog = Watchdog(variable, float(min_frequency_hz), action, float(now_s))
        self._armed[variable] = dog
        return dog

    def note(self, names: Iterable[str], arrival_s: float) -> None:
        """An input package carrying ``names`` arrived at controller time ``arrival_s``."""
        if not self._armed:
            return
        for name in names:
            dog = self._armed.get(name)
            if dog is not None and arrival_s > dog.last_update_s:
                dog.last_update_s = arrival_s

    def expired(self, boundary_s: float) -> Watchdog | None:
        """The first watchdog (other than "ignore") whose silence at ``boundary_s`` is
        longer than its timeout, or None."""
        for dog in self._armed.values():
            if dog.action != "ignore" and boundary_s - dog.last_update_s > dog.timeout_s:
                return dog
        return None

    def clear(self) -> None:
        """Remove every watchdog (program stop)."""
        self._armed.clear()
