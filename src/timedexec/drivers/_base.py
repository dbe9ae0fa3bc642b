"""The one robot-driver interface every backend implements.

A driver is a context manager. Between ``connect()`` and ``close()`` it publishes the
controller's state packages (``read_state``) and accepts joint-velocity commands in the
``speedj`` style (target joint speeds, acceleration of the leading axis, duration) and stops.
Times: ``host_time_s`` is :func:`time.monotonic` on arrival of the package (or the
simulator's virtual host clock); ``controller_time_s`` is the controller's own clock
(RTDE ``timestamp``, RSI ``IPOC`` converted to seconds).

Controller watchdog: :meth:`RobotDriver.arm_watchdog` asks the controller to stop the
program (and so decelerate the arm) when no command or kick reaches it for ``timeout_s``:
the only protection against a host that dies, hangs or is paused mid-motion when the
controller keeps executing the last speed command (the UR control script re-issues
``speedj`` until ``speedStop``). Every command feeds it; :meth:`RobotDriver.kick_watchdog`
feeds it without moving. A controller without one returns None (the default).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self

from timedexec._types import FloatArray

__all__ = ["RobotDriver", "RobotState"]


@dataclass(frozen=True, kw_only=True)
class RobotState:
    """One state package as received by the host.

    Attributes
    ----------
    host_time_s : float
        Host receive time, s (``time.monotonic()`` or the virtual host clock).
    controller_time_s : float
        Controller time stamp of the package, s.
    q : ndarray, shape (6,)
        Reported joint positions, rad.
    qd : ndarray, shape (6,)
        Reported joint velocities, rad/s (differentiated by the driver where the protocol
        reports positions only, as RSI does).
    raw : bytes
        The package's raw bytes as received (empty for the in-process simulator).
    sequence : int
        Package counter since connect, 0-based; a gap means a package was lost.
    target_qd : ndarray, shape (6,), or None
        The controller's target joint velocities, rad/s, where the protocol reports them
        (UR RTDE ``target_qd``; None otherwise): the command the controller took, which is
        how the cycle lock finds the controller's intake (:mod:`timedexec.execution._intake`).
    """

    host_time_s: float
    controller_time_s: float
    q: FloatArray
    qd: FloatArray
    raw: bytes = b""
    sequence: int = 0
    extra: dict[str, float] = field(default_factory=dict)
    target_qd: FloatArray | None = None

    def __iter__(self):  # type: ignore[no-untyped-def]
        """Unpack as ``host_time_s, controller_time_s, q, qd``."""
        return iter((self.host_time_s, self.controller_time_s, self.q, self.qd))


class RobotDriver(abc.ABC):
    """Common interface of the UR, KUKA RSI and simulator drivers."""

    #: Robot spec name this driver talks to (one of ``timedexec.robots.ROBOT_NAMES``).
    robot: str
    #: Whether ``speedj``'s duration paces the controller's updates rather than holding the
    #: command as a dead-man: URScript ``speedj(qd, a, t)`` returns after ``t``, and the
    #: UR control script's speed thread then re-issues it with the newest target, so a new
    #: target acts only once the previous call's ``t`` has passed. A stream then sends
    #: ``t`` = one period (as ur_rtde's own examples do).
    speedj_duration_paces_updates: bool = False
    #: Whether :class:`~timedexec.execution.TimedExecutor` locks its commands to this
    #: controller's cycle and coasts over late packages unless told otherwise
    #: (``ExecutorSettings(cycle_lock=None, coast=None)``, the defaults): True where the
    #: controller's state lets the executor probe its command intake (a UR's ``target_qd``).
    cycle_lock_default: bool = False

    @property
    @abc.abstractmethod
    def controller_period_s(self) -> float:
        """Controller cycle period, s (0.008 CB3, 0.002 e-Series, 0.012/0.004 RSI)."""

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the connection; raise :class:`~timedexec.errors.DriverError` on failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop any motion and release the connection. Idempotent."""

    @abc.abstractmethod
    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        """Block until the next state package arrives and return it.

        Never returns a package twice. Raises :class:`~timedexec.errors.DriverTimeout` if
        none arrives within ``timeout_s`` (no stale data is handed out as fresh).
        """

    @abc.abstractmethod
    def speedj(self, qd_rad_s: FloatArray, acceleration_rad_s2: float, duration_s: float) -> None:
        """Command joint speeds (rad/s) with the leading axis' acceleration (rad/s²) for
        ``duration_s`` (s; see :attr:`speedj_duration_paces_updates` for what a UR does
        with it); returns as soon as the command is sent (non-blocking)."""

    @abc.abstractmethod
    def stop(self, deceleration_rad_s2: float = 10.0) -> None:
        """Decelerate all joints to rest."""

    def commanded_q_rad(self) -> FloatArray | None:
        """The joint position the controller is commanded to, rad (6,): its set-point, as
        far as the driver can tell, or None where it cannot (the default).

        At rest it differs from the reported position by what the position loop leaves
        (friction, gravity, a gear's backlash) and from a streamed plan's end by what the
        speed stream lost (a command taken a cycle late holds a speed one period too long);
        a motion that must start exactly where a plan says checks it (the conveyor weld).
        """
        return None

    # ------------------------------------------------------------------ watchdog
    def arm_watchdog(self, timeout_s: float) -> float | None:
        """Ask the controller to stop the program when no command or kick reaches it for
        ``timeout_s`` (s); once armed it stays armed until the program stops. Re-arming
        after a trip restarts the program first (the arm is at rest then).

        Returns
        -------
        float or None
            The timeout in force, s; None when the controller has no such watchdog (the
            default: nothing is armed, :meth:`kick_watchdog` does nothing).
        """
        return None

    def kick_watchdog(self) -> None:
        """Feed the armed watchdog without commanding motion (no-op by default).

        Raises
        ------
        DriverError
            The watchdog already stopped the program (the message says how to recover).
        """
        return None

    def watchdog_tripped(self) -> bool:
        """Whether an armed watchdog has stopped the program (False by default)."""
        return False

    def diagnose_motion(self) -> str | None:
        """What the driver saw that keeps a commanded motion from converging (a correction
        held at its limit, a fault, a stopped program), for a message; None if nothing.
        The default reports a tripped watchdog."""
        if self.watchdog_tripped():
            return "the controller's watchdog stopped the program"
        return None

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
