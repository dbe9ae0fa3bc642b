"""The cycle-locked sender: each command leaves at a fixed phase of the controller's cycle.

The controller samples its command register once per cycle, at the cycle boundary. A
command that reaches it right at a boundary makes that cycle or the next by chance (host
jitter of a few hundred µs decides): one cycle then gets two commands (the first never
acts) and the next none. Sending as soon as the state package arrives puts the commands
exactly there, because the package leaves the controller right after a boundary and the
command needs about the same round trip back.

The host sees the controller's cycle boundaries through the state stream: the lower
envelope of arrival minus controller time (:class:`~timedexec.execution._state.StateTracker`,
the same clock model as the gyro's clock fit) gives the earliest arrival of each cycle's
package, i.e. the boundary plus the shortest publish-and-wire time. :class:`SendPhase` aims
every command at the middle of the intake window: it leaves at that earliest arrival plus
half a period minus the round trip the command and the package need together (the
shortest publish + wire time up, wire time down; ``round_trip_s``, default
:data:`DEFAULT_ROUND_TRIP_S` as measured on the loopback twin). The command's content is
computed for the instant it leaves. :func:`wait_until` sleeps to just before the target and
spins the rest (``time.sleep`` alone overshoots by 50-100 µs).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from timedexec.errors import ConfigError

__all__ = ["DEFAULT_ROUND_TRIP_S", "SPIN_S", "SendPhase", "wait_until"]

#: Shortest publish + wire-up + wire-down time of the loopback UR twin, s: the earliest
#: package arrival lies this much after the cycle boundary a command sent at once would
#: reach. Measure it for a real cell (the twin's truth gives it; see docs/execution.md).
DEFAULT_ROUND_TRIP_S = 4e-4
#: The last part of a wait is spun, s.
SPIN_S = 1.5e-4


class SendPhase:
    """When, in host time, the command of a controller cycle leaves.

    Parameters
    ----------
    period_s : float
        Controller period, s.
    round_trip_s : float
        Shortest time from a cycle boundary, through the package's arrival, back to the
        controller for a command sent at that arrival, s (>= 0, below one period).
    fraction : float
        Where in the intake window to land, as a fraction of the period (0.5: middle).

    Attributes
    ----------
    offset_s : float
        The send time after the cycle's earliest package arrival, s.
    """

    def __init__(
        self, period_s: float, round_trip_s: float = DEFAULT_ROUND_TRIP_S, fraction: float = 0.5
    ) -> None:
        if not 0 <= round_trip_s < period_s:
            raise ConfigError(
                f"round_trip_s={round_trip_s!r} outside [0, {period_s:g}) s (one controller "
                "period); measure it against the controller or keep the default"
            )
        if not 0 < fraction < 1:
            raise ConfigError(f"fraction={fraction!r} outside (0, 1); 0.5 is mid-cycle")
        self.period_s = float(period_s)
        self.round_trip_s = float(round_trip_s)
        self.fraction = float(fraction)
        self.offset_s = (fraction * period_s - round_trip_s) % period_s

    def target_s(self, earliest_arrival_s: float) -> float:
        """Host send time of the command answering the package whose earliest possible
        arrival is ``earliest_arrival_s``, s."""
        return earliest_arrival_s + self.offset_s


def wait_until(t_s: float, clock: Callable[[], float] = time.monotonic) -> float:
    """Sleep, then spin, until ``clock()`` reaches ``t_s``; return the clock then."""
    now = clock()
    rest = t_s - now - SPIN_S
    if rest > 0:
        time.sleep(rest)
    now = clock()
    while now < t_s:
        now = clock()
    return now
