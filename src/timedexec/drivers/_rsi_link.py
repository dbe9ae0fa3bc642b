"""The network side of the KUKA RSI driver: who may talk to it and on which time base.

:class:`~timedexec.drivers._rsi.KukaRSIDriver` binds a UDP port and answers whoever sends
it a ``<Rob>`` frame. Three things here make that safe on a real network:

* **Listen address** (:func:`check_listen_address`): loopback by default; the robot's
  interface (``192.168.1.5``) or every interface (``0.0.0.0``) only when asked for.
* **Peer lock** (:class:`PeerLock`): the first sender of a valid frame, or the one IP the
  user named (``robot_ip``), is the robot. Datagrams from any other (ip, port) are counted
  and dropped unparsed: a spoofed frame can neither move the reported state nor receive
  an answer. The lock is released only after the robot has been silent for a whole RSI
  session gap (it stopped RSI; its next run may use another ephemeral source port).
* **IPOC time base** (:class:`IpocClock`): the IPOC tick (1 ms on a KR C4, one cycle on
  a KR C2 / RSI 2.x) is given or found from the IPOC step (``"auto"``), and checked once per
  session against the frame period measured on the host clock: a wrong tick would scale
  every controller time and speed, a wrong period every commanded speed.

Plus :class:`FirstFrameWait`, the patience of the first :meth:`read_state` after connect
(a KUKA takes seconds from ``RSI_ON`` to its first frame) with a progress line per second.
"""

from __future__ import annotations

import ipaddress
import math
import sys
from typing import TextIO

from timedexec.errors import ConfigError, DriverError

__all__ = [
    "IPOC_CHECK_TOLERANCE",
    "FirstFrameWait",
    "IpocClock",
    "PeerLock",
    "check_first_frame_timeout",
    "check_ipoc_tick",
    "check_listen_address",
    "check_robot_ip",
    "format_address",
]

#: Accepted relative difference between the IPOC's frame period (IPOC step x tick) and the
#: driver's ``period_s``: both are exact numbers, so any mismatch is a setting (4 vs 12 ms
#: periods, 1 vs 4 or 12 ms ticks differ by a factor of 3 or more).
IPOC_CHECK_TOLERANCE = 0.3
#: Accepted ratio of the frame period measured on the host to the IPOC's frame period.
#: Above 1: a sender behind real time stretches it (the RSI twin on a two-core machine
#: running four test suites sent its 12 ms frames every 24.6 ms); 2.5 still tells a
#: 12 ms robot from a driver set to 4 ms (3) and every wrong tick (4 or 12). Below 1 only
#: by the first frame's lateness over the 1 s window (a few %); 1/1.5 leaves room.
HOST_PERIOD_RATIO = (1 / 1.5, 2.5)
#: IPOC ticks that ``"auto"`` chooses between: a millisecond stamp (KR C4) unless the IPOC
#: advances by exactly one per frame (KR C2 / RSI 2.x frame counter: one tick per cycle).
_KRC4_TICK_S = 0.001
#: The ticks a KUKA uses, ms: KR C4 stamps, a KR C2 counting 4 or 12 ms frames.
_KUKA_TICKS_MS = (1.0, 4.0, 12.0)


def format_address(addr: tuple[str, int] | None) -> str:
    """``ip:port`` (``"-"`` for None)."""
    return "-" if addr is None else f"{addr[0]}:{addr[1]}"


def check_listen_address(host: object, what: str = "host") -> str:
    """``host`` as an IPv4 listen address (``127.0.0.1``, ``0.0.0.0``, an interface's IP).

    Raises
    ------
    ConfigError
        Not an IPv4 address; the message names the value and the fix.
    """
    try:
        return str(ipaddress.IPv4Address(str(host).strip()))
    except ValueError:
        raise ConfigError(
            f"{what}={host!r} is not an IPv4 address; give the PC's address on the robot's "
            "network (e.g. 192.168.1.5), 0.0.0.0 for every interface, or 127.0.0.1 "
            "(loopback, the default) for a twin on this PC"
        ) from None


def check_robot_ip(ip: object) -> str | None:
    """``ip`` as the robot controller's IPv4 address (None: lock to the first sender).

    Raises
    ------
    ConfigError
        Not a single host's IPv4 address.
    """
    if ip is None:
        return None
    try:
        addr = ipaddress.IPv4Address(str(ip).strip())
    except ValueError:
        addr = None
    if addr is None or addr.is_unspecified or addr.is_multicast:
        raise ConfigError(
            f"robot_ip={ip!r} is not a robot controller's IPv4 address; give the address its "
            "RSI frames come from (the KLI/RSI network address of the KR C4, e.g. "
            "192.168.1.10), or leave it out to lock to the first sender"
        )
    return str(addr)


class PeerLock:
    """Accept RSI frames from one robot only.

    Parameters
    ----------
    robot_ip : str or None
        Only frames from this IP are ever accepted (any source port, as the robot's is
        ephemeral); None: the first sender of a valid frame.
    release_after_s : float
        Silence of the locked peer after which another (ip, port) may take over, s (the
        driver's RSI session gap).
    """

    def __init__(self, robot_ip: str | None, release_after_s: float) -> None:
        self.robot_ip = robot_ip
        self.release_after_s = float(release_after_s)
        self.peer: tuple[str, int] | None = None
        self.last_peer_rx_s = -math.inf
        self.ignored_frames = 0
        self.last_foreign: tuple[str, int] | None = None

    def reset(self) -> None:
        """Forget the peer and the counters (a new connection)."""
        self.peer = None
        self.last_peer_rx_s = -math.inf
        self.ignored_frames = 0
        self.last_foreign = None

    def admits(self, addr: tuple[str, int], t_rx: float) -> bool:
        """Whether a datagram from ``addr`` may be parsed; counts it as ignored if not.

        Call :meth:`lock` once a frame from ``addr`` parsed as a valid ``<Rob>`` frame.
        """
        addr = (str(addr[0]), int(addr[1]))
        if self.robot_ip is not None and addr[0] != self.robot_ip:
            return self._ignore(addr)
        if self.peer is None or addr == self.peer:
            return True
        if t_rx - self.last_peer_rx_s > self.release_after_s:
            return True  # the robot went quiet for a session gap: a new run may take over
        return self._ignore(addr)

    def lock(self, addr: tuple[str, int], t_rx: float) -> bool:
        """Make ``addr`` the peer (after a valid frame); True if the peer changed."""
        addr = (str(addr[0]), int(addr[1]))
        changed = addr != self.peer
        self.peer = addr
        self.last_peer_rx_s = t_rx
        return changed

    def _ignore(self, addr: tuple[str, int]) -> bool:
        self.ignored_frames += 1
        self.last_foreign = addr
        return False

    def summary(self) -> str:
        """One line for the log: how many datagrams were ignored and the last sender."""
        who = f"robot {self.robot_ip}" if self.robot_ip else f"peer {format_address(self.peer)}"
        return (
            f"ignored {self.ignored_frames} RSI datagram(s) from address(es) other than the "
            f"{who} (last from {format_address(self.last_foreign)}); if that was the robot, "
            "set ?robot=IP to its address, else find who else sends to this port"
        )


class IpocClock:
    """The IPOC time base of one connection: tick, and its check against the host clock.

    Parameters
    ----------
    tick_s : float or "auto"
        Seconds per IPOC unit; ``"auto"`` decides on the session's second frame: one period
        if the IPOC advanced by exactly 1 (KR C2 / RSI 2.x frame counter), else 1 ms (KR C4).
    period_s : float
        The driver's RSI cycle, s.
    check_after_s : float or None
        Host time over which the first frames of each session are measured before the check
        (needs at least 10 frames); None: never check.
    """

    def __init__(self, tick_s: float | str, period_s: float, check_after_s: float | None) -> None:
        self.auto = tick_s == "auto"
        self.configured = "auto" if self.auto else float(tick_s)
        self.period_s = float(period_s)
        self.check_after_s = check_after_s
        self.tick_s = _KRC4_TICK_S if self.auto else float(tick_s)
        self.resolved = not self.auto
        self.reset_session()

    def reset_session(self) -> None:
        """Start measuring again (a new RSI session)."""
        self._first: tuple[int, float] | None = None
        self._min_step = 0
        self._frames = 0
        self.checked = self.check_after_s is None

    def observe(self, ipoc: int, t_rx: float, prev_ipoc: int | None) -> None:
        """Take a frame of the current session (``prev_ipoc``: the previous one's IPOC).

        Raises
        ------
        DriverError
            When the check fails (once per session, after ``check_after_s``): the message
            names the numbers and the URL parameter that fixes it.
        """
        if prev_ipoc is not None and ipoc > prev_ipoc:
            step = ipoc - prev_ipoc
            self._min_step = step if self._min_step == 0 else min(self._min_step, step)
            if not self.resolved:
                self.tick_s = self.period_s if step == 1 else _KRC4_TICK_S
                self.resolved = True
        if self._first is None:
            self._first = (ipoc, t_rx)
        self._frames += 1
        if self.checked or self.check_after_s is None:
            return
        span_s = t_rx - self._first[1]
        if span_s < self.check_after_s or self._frames < 10 or self._min_step <= 0:
            return
        self.checked = True
        self.check(ipoc - self._first[0], span_s, self._frames)

    def check(self, ipoc_span: int, host_span_s: float, frames: int) -> None:
        """Compare the IPOC's frame period with ``period_s`` and with the host's measured
        one; raise DriverError naming the numbers and the fix if they disagree."""
        step = self._min_step
        measured_s = host_span_s / (ipoc_span / step)
        implied_s = step * self.tick_s
        ratio = measured_s / implied_s
        host_ok = HOST_PERIOD_RATIO[0] <= ratio <= HOST_PERIOD_RATIO[1]
        period_ok = abs(implied_s / self.period_s - 1.0) <= IPOC_CHECK_TOLERANCE
        # A millisecond IPOC (step > 1) states the period itself: then the host clock only
        # decides which setting the message blames (a sender far behind real time, such as
        # a twin on an overloaded machine, is no error). A frame counter (step 1) says
        # nothing about time, so there the host's period must agree.
        if period_ok and (host_ok or step > 1):
            return
        tick = "auto" if self.auto else f"{self.tick_s * 1e3:g}"
        facts = (
            f"the IPOC advances by {step} per frame, which with ipoc_tick_ms={tick} "
            f"({self.tick_s * 1e3:g} ms per IPOC unit) makes {implied_s * 1e3:.2f} ms per "
            f"frame; frames arrive every {measured_s * 1e3:.2f} ms (measured over {frames} "
            f"frames, {host_span_s:.2f} s of host time)"
        )
        if host_ok:  # the time base agrees with the host clock: the period setting is off
            raise DriverError(
                f"RSI period: {facts}, but the driver's period is {self.period_s * 1e3:g} ms; "
                f"set the period the robot program uses: ?period={_nearest_period(implied_s)} "
                "(#IPO 0.012, #IPO_FAST 0.004)"
            )
        per_unit_ms = measured_s / step * 1e3
        fix_ms = min(_KUKA_TICKS_MS, key=lambda t: abs(math.log(per_unit_ms / t)))
        raise DriverError(
            f"RSI IPOC time base: {facts}; set ?ipoc_tick_ms={fix_ms:g} (1 on a KR C4; "
            "on a KR C2 / RSI 2.x counting frames the tick is the period, so check ?period= "
            "too)"
        )


def _nearest_period(measured_s: float) -> str:
    return "0.004" if abs(measured_s - 0.004) < abs(measured_s - 0.012) else "0.012"


class FirstFrameWait:
    """Progress of the wait for the robot's first frame: one line a second on ``stream``.

    Parameters
    ----------
    what : str
        What is awaited, e.g. ``"the robot's first RSI frame on UDP 127.0.0.1:49152"``.
    total_s : float
        How long the wait may last, s.
    stream : text file or None
        Where lines go (default ``sys.stderr``); None with ``enabled=False``.
    """

    INTERVAL_S = 1.0

    def __init__(
        self, what: str, total_s: float, *, enabled: bool = True, stream: TextIO | None = None
    ) -> None:
        self.what = what
        self.total_s = total_s
        self.enabled = enabled
        self.stream = stream
        self.lines = 0

    def tick(self, waited_s: float, extra: str = "") -> None:
        """Print where the wait stands."""
        self.lines += 1
        if not self.enabled:
            return
        stream = self.stream if self.stream is not None else sys.stderr
        note = f"; {extra}" if extra else ""
        print(
            f"KukaRSIDriver: waiting for {self.what} ({waited_s:.0f} s of {self.total_s:g} s"
            f"{note})",
            file=stream,
            flush=True,
        )


def check_first_frame_timeout(value: object) -> float:
    """``value`` as the first-frame wait, s (0 .. 3600).

    Raises
    ------
    ConfigError
        Not a finite number in range.
    """
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        out = math.nan
    if not (math.isfinite(out) and 0.0 <= out <= 3600.0):
        raise ConfigError(
            f"first_frame_timeout_s={value!r} must be a number of s in 0 .. 3600 (how long "
            "the first read_state waits for the robot's first frame; a KUKA needs seconds "
            "from RSI_ON, default 10)"
        )
    return out


def check_ipoc_tick(value: object) -> float | str:
    """``value`` as an IPOC tick in s, or ``"auto"``.

    Raises
    ------
    ConfigError
        Neither ``"auto"`` nor a positive finite number of s up to 1.
    """
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        out = math.nan
    if not (math.isfinite(out) and 0.0 < out <= 1.0):
        raise ConfigError(
            f"ipoc_tick_s={value!r} must be 'auto' or the seconds per IPOC unit in (0, 1] "
            "(0.001 on a KR C4; the period, 0.012 or 0.004, on a KR C2 / RSI 2.x)"
        )
    return out
