"""KUKA RSI driver: the PC side of Ethernet RSI XML (UDP server answering every cycle).

The robot controller sends a ``<Rob>`` frame every interpolation cycle (12 ms with
``#IPO``, 4 ms with ``#IPO_FAST``) from an ephemeral source port to this PC's port. A
background thread receives each frame, answers it *at once* with a ``<Sen>`` frame that
echoes the frame's IPOC and carries the current joint correction, and only then publishes
the state to :meth:`KukaRSIDriver.read_state`. An answer that arrives after the controller's
next cycle counts as late on the robot; when its late counter reaches the configured
``Timeout`` (commonly 100) the controller stops RSI ("RSITimeout", KSS29002).

Joint motion (:meth:`~KukaRSIDriver.speedj`, :meth:`~KukaRSIDriver.stop`) is turned into
corrections by integrating a velocity profile in the controller's cycle, one cycle per
received frame: ramp every joint towards the target speed (the leading axis with the given
acceleration, the others scaled so that they arrive together), hold until ``duration_s``
has passed since the command took effect (ramp included, as URScript ``speedj``), then
ramp down to rest with the same acceleration. In ``"absolute"`` mode (``RSI_ON(#ABSOLUTE)``)
each answer carries the total offset from the pose at RSI start; in ``"relative"`` mode the
increment of this cycle (a lost answer then loses that increment, which absolute mode does
not, so absolute is the default).

Conventions and assumptions
---------------------------
* **Start pose.** The first frame of a session defines the pose at RSI start (``ASPos`` if
  sent, else ``AIPos``), and the correction is taken to be zero there: connect the driver
  before the robot program reaches ``RSI_ON``. A session ends when no frame arrives for
  ``session_gap_s`` (default 150 cycles, beyond the controller's default Timeout of 100
  late cycles, after which the robot has certainly stopped RSI); the next frame starts a new
  session with zero correction.
* **Controller time.** ``controller_time_s = (IPOC - IPOC0) * ipoc_tick_s`` where IPOC0 is
  the first IPOC after :meth:`~KukaRSIDriver.connect` (the raw value stays in
  :attr:`RSIState.ipoc`); subtracting it keeps the times small and exact. The tick
  (``ipoc_tick_s``, default ``"auto"``: 1 ms, KR C4, unless the IPOC advances by exactly 1
  per frame, KR C2 / RSI 2.x, then one period) is checked once per session against the frame
  period measured on the host clock, and so is ``period_s``: a mismatch raises
  :class:`~timedexec.errors.DriverError` naming both numbers and the URL parameter that fixes
  it (:mod:`timedexec.drivers._rsi_link`). If the IPOC goes backwards (controller
  restarted), IPOC0 is re-based so that controller time continues one cycle later.
* **Network.** The driver listens on ``host`` (loopback by default; the PC's address on the
  robot's network, or ``0.0.0.0``, for a real robot), answers only the robot (``robot_ip``,
  else the first sender of a valid frame; others are counted in ``ignored_frames`` and
  never answered) and waits ``first_frame_timeout_s`` (default 10 s) for the first frame,
  with a progress line on stderr each second.
* **Velocity.** RSI reports positions only. ``qd`` is the backward difference of
  successive ``AIPos`` over the IPOC time between them; it is the mean velocity over the
  last cycle, i.e. the velocity of half a cycle earlier (a lag of T/2: 6 ms at 12 ms, 2 ms
  at 4 ms) for smooth motion. The first frame of a session reports ``qd = 0`` and
  ``extra["qd_valid"] = 0.0``.
* **One package, once.** States are queued first-in first-out (bounded by
  ``queue_size``; overflow drops the oldest and is counted) and each is returned exactly
  once; :meth:`~KukaRSIDriver.read_state` raises
  :class:`~timedexec.errors.DriverTimeout` when no frame arrives in time, never a stale
  copy.
* **Motion time.** The profile advances one controller cycle per received frame, not by
  wall time: when frames are lost the motion stretches instead of jumping, so a lost frame
  never turns into a position step on the robot.
* **Limits.** Commands beyond the robot spec's speed or acceleration limits are refused
  with :class:`~timedexec.errors.ConfigError`; the integrated correction is kept inside the
  joint position limits and ``max_correction_deg`` (the RSI configuration's correction
  limit), braking at the spec's acceleration limit before it, clamping as a last resort.
* **GIL.** Answers are produced in a Python thread. A client that keeps the interpreter
  busy (pure-Python loops without blocking calls) delays them by up to
  :func:`sys.getswitchinterval` (5 ms by default), so while connected the driver lowers
  the switch interval to an eighth of the period (``tune_gil``, restored on close). Heavy
  work belongs in another process all the same; late answers are counted in
  :meth:`~KukaRSIDriver.stats`.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from timedexec._rsi_xml import MAX_FRAME_BYTES, build_sen, parse_rob
from timedexec._types import FloatArray
from timedexec.drivers._base import RobotDriver
from timedexec.drivers._rsi_intake import AnswerShaping, RSIIntake, probe_intake
from timedexec.drivers._rsi_link import (
    FirstFrameWait,
    IpocClock,
    PeerLock,
    check_first_frame_timeout,
    check_ipoc_tick,
    check_listen_address,
    check_robot_ip,
    format_address,
)
from timedexec.drivers._rsi_profile import SpeedCommand as _Command
from timedexec.drivers._rsi_profile import SpeedProfile as _Profile
from timedexec.drivers._rsi_reach import check_reach, diagnose
from timedexec.drivers._rsi_records import RSICommandRecord, RSIState, RSIStats
from timedexec.errors import ConfigError, DriverError, DriverTimeout, ProtocolError
from timedexec.robots import RobotSpec, get_robot

__all__ = ["KukaRSIDriver", "RSICommandRecord", "RSIIntake", "RSIState", "RSIStats"]

_RECV_POLL_S = 0.05  # how often the receive thread checks for shutdown


class KukaRSIDriver(RobotDriver):
    """PC side of KUKA Ethernet RSI XML: a UDP server that answers every controller cycle.

    Parameters
    ----------
    port : int, optional
        UDP port to bind (the RSI configuration's destination port; 49152 in the common ROS
        configurations). 0 binds an ephemeral port (see :attr:`port`), handy for tests.
    host : str, optional
        IPv4 address to listen on. The default, loopback, serves the simulated controller
        (:class:`timedexec.twins.RSITwin`) only; for a real robot give the PC's address on
        the RSI network (``"192.168.1.5"``) or ``"0.0.0.0"`` (every interface).
    robot_ip : str, optional
        The robot controller's IPv4 address: only its frames are taken (and answered).
        Default None: lock to the first sender of a valid frame. Frames from anyone else are
        counted (:attr:`ignored_frames`) and dropped unparsed.
    robot : str or RobotSpec, optional
        Robot spec (limits, default period); ``"kr5"`` by default.
    period_s : float, optional
        RSI cycle: 0.012 (``#IPO``) or 0.004 (``#IPO_FAST``); ``None`` takes the spec's.
    sen_type : str, optional
        ``Type`` attribute of the answers; must match the configuration's SENTYPE.
    correction_tag : str, optional
        Correction element of the answers (``"AK"``, ``"AKorr"``, ...).
    mode : {"absolute", "relative"}, optional
        Must match ``RSI_ON(#ABSOLUTE)`` / ``RSI_ON(#RELATIVE)``.
    max_correction_deg : float or array_like of 6, optional
        Largest absolute correction per axis, degrees; keep it at or inside the limits of
        the configuration's AXISCORR object (beyond them the robot stops RSI). Default 90.
    ipoc_tick_s : float or "auto", optional
        Seconds per IPOC unit: 0.001 on a KR C4 (millisecond stamps), the period on a
        KR C2 / RSI 2.x (frame counter); ``"auto"`` (default) tells them apart on the second
        frame. Checked against the host clock (``ipoc_check_s``).
    ipoc_check_s : float or None, optional
        After this much host time (and at least 10 frames) of each session, check that IPOC
        step x tick and ``period_s`` both match the measured frame period within 30 %
        (the wrong settings differ by a factor of 3 or more); a mismatch stops motion and
        makes :meth:`read_state` and :meth:`speedj` raise DriverError naming the numbers
        and the fix. Default 1.0; None switches it off (a scripted robot in tests).
    first_frame_timeout_s : float, optional
        How long the first :meth:`read_state` after :meth:`connect` waits for the robot's
        first frame, whatever its own ``timeout_s`` (default 10 s: a KUKA takes seconds
        from ``RSI_ON``). Later reads use their own timeout.
    progress : bool, optional
        While waiting for the first frame, print a line on stderr each second saying what
        is awaited on which address:port; on :meth:`close`, report ignored datagrams there.
    queue_size : int, optional
        Most unread states kept (default 4096: 49 s at 12 ms).
    session_gap_s : float, optional
        Silence after which the next frame starts a new session; default 150 cycles.
    max_frame_bytes : int, optional
        Datagram size limit for the parser.
    tune_gil : bool, optional
        While connected, lower the interpreter's thread switch interval
        (:func:`sys.setswitchinterval`, 5 ms by default) to at most an eighth of the period
        (1.5 ms at 12 ms, 0.5 ms at 4 ms), and restore it on :meth:`close`. Without this, a
        main thread running pure-Python code holds the GIL for up to 5 ms before the answer
        thread gets it: at 4 ms every such frame is answered late. The setting is
        process-wide; pass ``False`` to leave it alone.

    Notes
    -----
    ``packet_callback`` (attribute, default ``None``) is called in the receive thread with
    each new :class:`RSIState` *before* the correction for that frame is computed, so a
    :meth:`speedj` issued from it leaves in the answer to that very frame (the paper's
    "command on arrival of a package"). It must return quickly (well under a cycle).
    """

    def __init__(
        self,
        port: int = 49152,
        *,
        host: str = "127.0.0.1",
        robot_ip: str | None = None,
        robot: str | RobotSpec = "kr5",
        period_s: float | None = 0.012,
        sen_type: str = "ImFree",
        correction_tag: str = "AK",
        mode: Literal["absolute", "relative"] = "absolute",
        max_correction_deg: float | ArrayLike = 90.0,
        ipoc_tick_s: float | str = "auto",
        ipoc_check_s: float | None = 1.0,
        first_frame_timeout_s: float = 10.0,
        progress: bool = True,
        queue_size: int = 4096,
        session_gap_s: float | None = None,
        max_frame_bytes: int = MAX_FRAME_BYTES,
        tune_gil: bool = True,
    ) -> None:
        spec = get_robot(robot) if isinstance(robot, str) else robot
        if not isinstance(spec, RobotSpec):
            raise ConfigError(f"robot must be a robot name or RobotSpec, got {robot!r}")
        if period_s is not None:
            spec = spec.with_period(period_s)
        if spec.vendor != "kuka":
            raise ConfigError(
                f"robot {spec.name!r} is a {spec.vendor} robot; RSI is KUKA's interface "
                "(use robot='kr5' or a KUKA spec)"
            )
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ConfigError(f"port={port!r} must be an integer in 0..65535")
        if mode not in ("absolute", "relative"):
            raise ConfigError(f"mode={mode!r} must be 'absolute' or 'relative' (RSI_ON mode)")
        max_corr = np.broadcast_to(np.asarray(max_correction_deg, dtype=np.float64), (6,)).copy()
        if not np.all(np.isfinite(max_corr)) or np.any(max_corr <= 0):
            raise ConfigError(
                f"max_correction_deg={max_corr.tolist()} must be positive and finite per axis"
            )
        tick = check_ipoc_tick(ipoc_tick_s)
        if ipoc_check_s is not None and not (
            isinstance(ipoc_check_s, (int, float)) and 0.1 <= ipoc_check_s <= 60.0
        ):
            raise ConfigError(
                f"ipoc_check_s={ipoc_check_s!r} must be None (no check) or 0.1 .. 60 s of "
                "frames to measure the period on (default 1.0)"
            )
        if not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError(f"queue_size={queue_size!r} must be a positive integer")
        # Validate the answer settings once by building a frame.
        try:
            build_sen(0, np.zeros(6), sen_type=sen_type, correction_tag=correction_tag)
        except ProtocolError as exc:
            raise ConfigError(str(exc)) from None
        self.robot = spec.name
        self.spec = spec
        self.host = check_listen_address(host)
        self.robot_ip = check_robot_ip(robot_ip)
        self.first_frame_timeout_s = check_first_frame_timeout(first_frame_timeout_s)
        self.progress = bool(progress)
        self._requested_port = port
        self.sen_type = sen_type
        self.correction_tag = correction_tag
        self.mode = mode
        self.max_correction_rad: FloatArray = np.radians(max_corr)
        self.queue_size = queue_size
        period = spec.controller_period_s
        self.session_gap_s = 150 * period if session_gap_s is None else float(session_gap_s)
        if not self.session_gap_s > 0:
            raise ConfigError(f"session_gap_s={session_gap_s!r} must be positive")
        self.max_frame_bytes = int(max_frame_bytes)
        self.tune_gil = bool(tune_gil)
        self._saved_switch_interval: float | None = None
        self.packet_callback: Callable[[RSIState], None] | None = None

        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._cond = threading.Condition()
        self._queue: collections.deque[RSIState] = collections.deque()
        self._error: BaseException | None = None
        self._cmd_lock = threading.Lock()
        self._pending: _Command | None = None
        self._commands: list[RSICommandRecord] = []
        self._profile = _Profile(spec, self.max_correction_rad)
        self._peers = PeerLock(self.robot_ip, self.session_gap_s)
        self._clock = IpocClock(tick, period, ipoc_check_s)
        self._fault: DriverError | None = None  # the time-base check failed
        self._frames_since_connect = 0
        self._mute = False  # test hook: stop answering (the robot then counts late cycles)
        # Thread-owned session state.
        self._last_rx_s = -math.inf
        self._last_ipoc = -1
        self._ipoc_origin = -1
        self._last_q: FloatArray | None = None
        self._sequence = -1
        self._sent_corr = np.zeros(6)
        self._stats: dict[str, Any] = dataclasses.asdict(RSIStats())
        self._shaping = AnswerShaping()  # the intake probe's trials, command placement
        self._latency_sum_s = 0.0

    # ------------------------------------------------------------------ properties

    @property
    def controller_period_s(self) -> float:
        """RSI cycle period, s."""
        return float(self.spec.controller_period_s)

    @property
    def port(self) -> int:
        """The bound UDP port (the requested one, or the ephemeral one for ``port=0``)."""
        if self._sock is None:
            return self._requested_port
        return int(self._sock.getsockname()[1])

    @property
    def connected(self) -> bool:
        """True between :meth:`connect` and :meth:`close`."""
        return self._sock is not None

    @property
    def ipoc_tick_s(self) -> float:
        """Seconds per IPOC unit in use (with ``"auto"``: 1 ms until the second frame)."""
        return self._clock.tick_s

    @property
    def ignored_frames(self) -> int:
        """Datagrams from addresses other than the robot's, dropped without an answer."""
        with self._cond:
            return self._peers.ignored_frames

    @property
    def last_foreign_address(self) -> tuple[str, int] | None:
        """(ip, port) of the last ignored datagram's sender, None if there was none."""
        with self._cond:
            return self._peers.last_foreign

    @property
    def peer_address(self) -> tuple[str, int] | None:
        """(ip, port) of the robot this driver answers (None before its first frame)."""
        with self._cond:
            return self._peers.peer

    # ------------------------------------------------------------------ lifecycle

    def connect(self) -> None:
        """Bind the UDP port and start answering.

        Raises
        ------
        DriverError
            If the address cannot be bound (port in use, address not on this host).
        """
        if self._sock is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self._requested_port))
        except OSError as exc:
            sock.close()
            raise DriverError(
                f"cannot bind UDP {self.host}:{self._requested_port} for RSI ({exc}); "
                "is another RSI server running, or is the address not on this PC?"
            ) from exc
        sock.settimeout(_RECV_POLL_S)
        self._sock = sock
        self._error = None
        self._frames_since_connect = 0
        self._running.set()
        self._thread = threading.Thread(
            target=self._serve, name=f"rsi-answer-{self.port}", daemon=True
        )
        if self.tune_gil:
            current = sys.getswitchinterval()
            wanted = self.controller_period_s / 8.0
            if wanted < current:
                self._saved_switch_interval = current
                sys.setswitchinterval(wanted)
        self._thread.start()

    def close(self) -> None:
        """Ramp motion down while still answering, then stop answering and unbind.

        Idempotent. If frames are flowing and the correction is moving, waits (at most
        2 s) until the commanded velocity is zero, so the robot is not left with a
        correction step. The robot stops RSI with "RSITimeout" once it gets no answers.
        """
        if self._sock is None:
            return
        try:
            if self._active() and float(np.max(np.abs(self._profile.v))) > 0.0:
                self.stop(float(np.min(self.spec.qdd_max_rad_s2)))
                deadline = time.monotonic() + 2.0
                while time.monotonic() < deadline and self._active():
                    if float(np.max(np.abs(self._profile.v))) == 0.0:
                        break
                    time.sleep(self.controller_period_s)
        finally:
            self._running.clear()
            if self._thread is not None:
                self._thread.join(timeout=2.0)
            self._thread = None
            self._sock.close()
            self._sock = None
            if self._saved_switch_interval is not None:
                sys.setswitchinterval(self._saved_switch_interval)
                self._saved_switch_interval = None
            with self._cond:
                self._cond.notify_all()
                ignored = self._peers.ignored_frames
            if ignored and self.progress:
                print(f"KukaRSIDriver: {self._peers.summary()}", file=sys.stderr, flush=True)

    # ------------------------------------------------------------------ state

    def read_state(self, timeout_s: float = 0.1) -> RSIState:
        """Return the oldest unread state package, waiting up to ``timeout_s`` for one.

        Returns
        -------
        RSIState
            ``host_time_s`` (monotonic receive time), ``controller_time_s`` (IPOC minus
            the first IPOC since connect, times ``ipoc_tick_s``), ``q`` (AIPos, rad), ``qd`` (backward difference, rad/s),
            ``raw`` (the datagram), ``sequence`` (controller cycles since connect; a gap
            means lost frames) and the RSI fields.

        Raises
        ------
        DriverTimeout
            If no frame arrives within ``timeout_s`` (the robot is not running RSI, or it
            stopped: "RSITimeout", program end, correction limit).
        DriverError
            If the driver is not connected or its receive thread failed.
        """
        start = time.monotonic()
        wait_s = float(timeout_s)
        first = self._frames_since_connect == 0 and self.first_frame_timeout_s > wait_s
        if first:  # a KUKA takes seconds from RSI_ON to its first frame
            wait_s = self.first_frame_timeout_s
            waiter = FirstFrameWait(
                f"the robot's first RSI frame on UDP {self.host}:{self.port}",
                wait_s,
                enabled=self.progress,
            )
        deadline = start + wait_s
        with self._cond:
            if self._fault is not None:
                raise self._fault
            while not self._queue:
                if self._fault is not None:
                    raise self._fault
                if self._error is not None:
                    raise DriverError(f"RSI receive thread failed: {self._error}")
                if self._sock is None:
                    raise DriverError("KukaRSIDriver is not connected; call connect() first")
                now = time.monotonic()
                remaining = deadline - now
                if remaining <= 0.0:
                    raise DriverTimeout(self._silence_message(wait_s))
                if first and self._frames_since_connect == 0:
                    due = start + (waiter.lines + 1) * waiter.INTERVAL_S
                    if now >= due:
                        waiter.tick(now - start, self._ignored_note())
                        continue
                    remaining = min(remaining, due - now)
                self._cond.wait(remaining)
            return self._queue.popleft()

    def _ignored_note(self) -> str:
        peers = self._peers
        if not peers.ignored_frames:
            return ""
        return (
            f"ignored {peers.ignored_frames} datagram(s) from other senders, last "
            f"{format_address(peers.last_foreign)}"
        )

    def _silence_message(self, timeout_s: float) -> str:
        if self._last_ipoc < 0:
            note = self._ignored_note()
            return (
                f"no RSI frame within {timeout_s:g} s on UDP {self.host}:{self.port}; is the "
                "robot program past RSI_ON, does its RSI configuration send to this "
                "address and port (IP_NUMBER, PORT), and does the firewall let it through?"
                + (f" ({note}; if that is the robot, set ?robot=IP)" if note else "")
            )
        age = time.monotonic() - self._last_rx_s
        return (
            f"no RSI frame for {age:.3f} s (timeout {timeout_s:g} s; last IPOC "
            f"{self._last_ipoc}); the robot stopped RSI (RSITimeout after late answers, a "
            "correction limit, or the program ended) or the network is down"
        )

    def pending_states(self) -> int:
        """Number of received states not yet returned by :meth:`read_state`."""
        with self._cond:
            return len(self._queue)

    def clear_states(self) -> int:
        """Discard unread states; return how many were discarded."""
        with self._cond:
            n = len(self._queue)
            self._queue.clear()
            return n

    def stats(self) -> RSIStats:
        """Snapshot of the answer thread's counters."""
        with self._cond:
            peers = self._peers
            return RSIStats(**{
                **self._stats, "ignored_frames": peers.ignored_frames,
                "last_foreign_address": format_address(peers.last_foreign),
                "peer_address": format_address(peers.peer), "ipoc_tick_s": self._clock.tick_s,
            })  # fmt: skip

    def command_log(self) -> list[RSICommandRecord]:
        """Every motion command since connect, with the time its first answer left."""
        with self._cmd_lock:
            return list(self._commands)

    @property
    def correction_rad(self) -> FloatArray:
        """The absolute correction most recently integrated, rad, shape (6,)."""
        return self._profile.corr.copy()

    def commanded_q_rad(self) -> FloatArray | None:
        """The start pose plus the correction the last answer sent (the placement's lead in
        it), rad (6,): the set-point once taken (absolute mode); None before a session."""
        if self._sock is None or not self._active() or self._frames_since_connect == 0:
            return None
        return np.asarray(self._profile.q_start + self._sent_corr)

    @property
    def start_pose_rad(self) -> FloatArray:
        """Pose at RSI start of the current session (first frame), rad, shape (6,)."""
        return self._profile.q_start.copy()

    # ------------------------------------------------------------------ what RSI can reach

    def reachable_range_rad(self) -> tuple[FloatArray, FloatArray]:
        """The joint positions the correction can reach in this session, rad, (6,) each:
        the pose where RSI started plus or minus ``max_correction_deg``, inside the joint
        limits less 0.5°. Waits for the robot's first frame (``first_frame_timeout_s``)
        when none has arrived yet (and then takes that state off the queue).

        Raises
        ------
        DriverTimeout
            No frame arrived: the robot is not running RSI.
        """
        if self._frames_since_connect == 0:
            self.read_state()
        prof = self._profile
        return prof.q_start + prof.lo, prof.q_start + prof.hi

    def check_reachable(self, q_rad: ArrayLike, *, margin_rad: ArrayLike = 0.0,
                        what: str = "configuration") -> None:  # fmt: skip
        """Refuse configurations the correction cannot reach from the pose where RSI started
        (before anything moves): each of ``q_rad`` (n, 6), rad, widened by ``margin_rad``
        (a trial's excursion, rad, scalar or (6,)), must lie in :meth:`reachable_range_rad`.

        Raises
        ------
        ConfigError
            Naming the first configuration and axis out of reach, the correction it needs,
            the limit (``max_correction_deg`` or the joint limit), how many configurations
            leave the limits and how to fix it.
        """
        lo, hi = self.reachable_range_rad()
        check_reach(q_rad, lo, hi, self._profile.q_start, self.max_correction_rad, self.spec,
                    margin_rad=margin_rad, what=what)  # fmt: skip

    def diagnose_motion(self) -> str | None:
        """What the driver saw that keeps a motion from converging: a correction held at
        its limit (per axis, with the correction and the limit), a time-base fault, RSI
        stopped (no frame for over ten cycles) or the robot's late counter; None if
        nothing."""
        silent = time.monotonic() - self._last_rx_s if self._last_ipoc >= 0 else 0.0
        late = self._stats.get("robot_late_count", -1)
        return diagnose(self._profile, fault=self._fault, silent_s=silent,
                        stopped=silent > max(10 * self.controller_period_s, 0.1),
                        late_count=late if isinstance(late, int) else -1)  # fmt: skip

    def probe_intake(self, *, place_commands: bool = True, **settings: Any) -> RSIIntake:
        """Find where the controller takes an answer, the arm at rest (2-3.5 s at 12 ms;
        ``settings``: ``phases``, ``rounds``, ``fine``, ``offset_rad`` of
        :func:`timedexec.drivers._rsi_intake.probe_intake`, which raises DriverError when
        RSI is not running, the arm moves, the frames lack ``ASPos`` or no clean step
        shows). With ``place_commands`` each later command's speed change is led by how
        much later than 1.5 periods after its call it is taken."""
        fix = probe_intake(self, **settings)
        with self._cmd_lock:
            self._shaping.use(fix, place_commands)
        return fix

    # ------------------------------------------------------------------ commands

    def _active(self) -> bool:
        return self._last_ipoc >= 0 and (
            time.monotonic() - self._last_rx_s < max(10 * self.controller_period_s, 0.1)
        )

    def _require_active(self, what: str) -> None:
        if self._sock is None:
            raise DriverError(f"cannot {what}: KukaRSIDriver is not connected")
        if self._fault is not None:
            raise DriverError(f"cannot {what}: {self._fault}")
        if self._error is not None:
            raise DriverError(f"cannot {what}: RSI receive thread failed: {self._error}")
        if not self._active():
            if self._last_ipoc < 0:
                raise DriverError(
                    f"cannot {what}: no RSI frame received yet; start the robot program "
                    "(RSI_ON / RSI_MOVECORR) first and wait for read_state()"
                )
            age = time.monotonic() - self._last_rx_s
            raise DriverError(
                f"cannot {what}: RSI is not running (last frame {age:.3f} s ago); the robot "
                "stopped RSI"
            )

    def speedj(self, qd_rad_s: ArrayLike, acceleration_rad_s2: float, duration_s: float) -> None:
        """Move joints at constant speed, speedj style, through RSI corrections.

        Parameters
        ----------
        qd_rad_s : array_like, shape (6,)
            Target joint speeds, rad/s; each within the spec's ``qd_max_rad_s``.
        acceleration_rad_s2 : float
            Acceleration of the leading axis (largest speed change), rad/s²; the other
            joints are scaled so that all arrive together. Per joint within
            ``qdd_max_rad_s2``.
        duration_s : float
            Time from the command taking effect until the ramp down starts (ramp-up
            included), s, rounded up to whole controller cycles; ``math.inf`` holds the
            speed until :meth:`stop`.

        Raises
        ------
        ConfigError
            For a wrong shape, non-finite values, or a speed/acceleration beyond the spec
            (the message names the joint, value and limit).
        DriverError
            If RSI is not running (no recent frame).
        """
        qd = np.asarray(qd_rad_s, dtype=np.float64)
        if qd.shape != (6,):
            raise ConfigError(f"qd_rad_s has shape {qd.shape}; expected (6,) (joints 1..6)")
        if not np.all(np.isfinite(qd)):
            raise ConfigError(f"qd_rad_s={qd.tolist()} contains non-finite values")
        accel = float(acceleration_rad_s2)
        if not (math.isfinite(accel) and accel > 0.0):
            raise ConfigError(f"acceleration_rad_s2={acceleration_rad_s2!r} must be > 0")
        duration = float(duration_s)
        if math.isnan(duration) or duration < 0.0:
            raise ConfigError(
                f"duration_s={duration_s!r} must be >= 0 (0 or math.inf: hold until the next "
                "command, as URScript speedj)"
            )
        if duration == 0.0:
            duration = math.inf
        prof = self._profile
        for j in range(6):
            if abs(qd[j]) > prof.qd_max[j]:
                raise ConfigError(
                    f"joint {j + 1}: speed {qd[j]:.4g} rad/s exceeds the {self.robot} limit "
                    f"of {prof.qd_max[j]:.4g} rad/s; reduce qd_rad_s[{j}]"
                )
        self._check_accel(qd - prof.v, accel, "acceleration_rad_s2")
        self._require_active("speedj")
        self._submit(_Command("speedj", qd.copy(), accel, duration, time.monotonic(), -1))

    def stop(self, deceleration_rad_s2: float = 10.0) -> None:
        """Ramp all joints to rest, the leading axis at ``deceleration_rad_s2`` (rad/s²).

        The deceleration is capped at the spec's per-joint limits. A no-op when RSI is not
        running (there is nothing to stop).
        """
        decel = float(deceleration_rad_s2)
        if not (math.isfinite(decel) and decel > 0.0):
            raise ConfigError(f"deceleration_rad_s2={deceleration_rad_s2!r} must be > 0")
        if self._sock is None or not self._active():
            return
        v = self._profile.v.copy()
        lead = float(np.max(np.abs(v)))
        if lead > 0.0:
            # Cap so that no joint exceeds its own limit after leading-axis scaling.
            speed = np.abs(v)
            caps = np.full(6, np.inf)
            np.divide(self._profile.qdd_max * lead, speed, out=caps, where=speed > 0)
            decel = min(decel, float(np.min(caps)))
        self._submit(_Command("stop", np.zeros(6), decel, math.inf, time.monotonic(), -1))

    def _check_accel(self, delta: FloatArray, accel: float, name: str) -> None:
        rates = _Profile._scaled_rates(delta, accel)
        over = rates > self._profile.qdd_max * (1 + 1e-12)
        if np.any(over):
            j = int(np.argmax(over))
            raise ConfigError(
                f"joint {j + 1}: acceleration {rates[j]:.4g} rad/s² exceeds the {self.robot} "
                f"limit of {self._profile.qdd_max[j]:.4g} rad/s²; reduce {name}"
            )

    def _submit(self, cmd: _Command) -> None:
        with self._cmd_lock:
            cmd.index = len(self._commands)
            self._commands.append(
                RSICommandRecord(
                    kind=cmd.kind,
                    qd_rad_s=cmd.qd.copy(),
                    acceleration_rad_s2=cmd.accel,
                    duration_s=cmd.duration_s,
                    call_host_s=cmd.call_host_s,
                )
            )
            self._pending = cmd

    # ------------------------------------------------------------------ receive thread

    def _serve(self) -> None:
        sock = self._sock
        assert sock is not None
        recv = sock.recvfrom
        limit = self.max_frame_bytes + 1
        try:
            while self._running.is_set():
                try:
                    data, addr = recv(max(limit, 8192))
                except TimeoutError:
                    continue
                except ConnectionRefusedError:
                    continue  # ICMP from an earlier answer to a closed robot port
                t_rx = time.monotonic()
                self._handle(data, addr, t_rx)
        except OSError as exc:
            if self._running.is_set():
                self._fail(exc)
        except Exception as exc:  # pragma: no cover - a bug; surface it to the reader
            self._fail(exc)

    def _time_base_fault(self, exc: DriverError, t_rx: float) -> None:
        """The IPOC/period check failed: ramp any motion down (still answering, so the robot
        sees no jump) and make read_state/speedj raise ``exc``."""
        decel = float(np.min(self.spec.qdd_max_rad_s2))
        with self._cmd_lock:
            self._pending = None
        self._profile.apply(_Command("stop", np.zeros(6), decel, math.inf, t_rx, -1))
        with self._cond:
            self._fault = exc
            self._cond.notify_all()

    def _fail(self, exc: BaseException) -> None:
        with self._cond:
            self._error = exc
            self._cond.notify_all()

    def _handle(self, data: bytes, addr: tuple[str, int], t_rx: float) -> None:
        st = self._stats
        with self._cond:
            if not self._peers.admits(addr, t_rx):
                return  # not the robot: neither parsed nor answered (counted)
        try:
            frame = parse_rob(data, max_bytes=self.max_frame_bytes)
        except ProtocolError as exc:
            with self._cond:
                st["protocol_errors"] += 1
                st["last_protocol_error"] = str(exc)
            return
        if frame is None:
            with self._cond:
                st["empty_frames"] += 1
            return
        if frame.aipos_rad is None:
            with self._cond:
                st["protocol_errors"] += 1
                st["last_protocol_error"] = (
                    "Rob frame has no <AIPos>; add AIPos to the RSI configuration's SEND list"
                )
            # Still answer below: the robot must not time out because of our needs.
        with self._cond:
            self._peers.lock(addr, t_rx)  # a valid frame: this sender is the robot
        prof = self._profile
        period = self.controller_period_s
        new_session = (
            self._last_ipoc < 0
            or t_rx - self._last_rx_s > self.session_gap_s
            or frame.ipoc <= self._last_ipoc
        )
        q = frame.aipos_rad
        if new_session:
            self._clock.reset_session()
        try:  # resolves an "auto" tick on the second frame; checks it after ipoc_check_s
            self._clock.observe(frame.ipoc, t_rx, None if new_session else self._last_ipoc)
        except DriverError as exc:
            self._time_base_fault(exc, t_rx)
        tick_s = self._clock.tick_s
        if self._ipoc_origin < 0:
            self._ipoc_origin = frame.ipoc
        elif frame.ipoc <= self._last_ipoc:  # controller restarted: keep time increasing
            one_cycle = max(1, round(period / tick_s))
            self._ipoc_origin = frame.ipoc - (self._last_ipoc - self._ipoc_origin) - one_cycle
        if new_session:
            start = frame.aspos_rad if frame.aspos_rad is not None else q
            with self._cmd_lock:
                self._pending = None
            prof.reset(start if start is not None else np.zeros(6))
            self._sent_corr = np.zeros(6)
            cycles = 1
            qd = np.zeros(6)
            qd_valid = 0.0
            with self._cond:
                st["sessions"] += 1
        else:
            dt_ctrl = (frame.ipoc - self._last_ipoc) * tick_s
            cycles = max(1, round(dt_ctrl / period))
            if q is not None and self._last_q is not None and dt_ctrl > 0:
                qd = (q - self._last_q) / dt_ctrl
                qd_valid = 1.0
            else:
                qd = np.zeros(6)
                qd_valid = 0.0
        self._sequence += cycles
        self._last_ipoc = frame.ipoc
        self._last_rx_s = t_rx
        self._last_q = q
        controller_s = (frame.ipoc - self._ipoc_origin) * tick_s

        state = RSIState(
            host_time_s=t_rx,
            controller_time_s=controller_s,
            q=q if q is not None else np.full(6, np.nan),
            qd=qd,
            raw=bytes(data),
            sequence=self._sequence,
            extra={
                "ipoc": float(frame.ipoc),
                "qd_valid": qd_valid,
                "robot_late_count": float(-1 if frame.delay is None else frame.delay),
            },
            ipoc=frame.ipoc,
            q_setpoint=frame.aspos_rad,
            cartesian=frame.rist,
            robot_late_count=frame.delay,
        )
        callback = self.packet_callback
        if callback is not None and not new_session:
            try:
                callback(state)
            except Exception as exc:  # never let a user callback kill the answer thread
                with self._cond:
                    st["last_protocol_error"] = f"packet_callback raised {exc!r}"

        # ---- correction for this cycle, then answer at once (or when the probe asks)
        with self._cmd_lock:
            cmd = self._pending
            self._pending = None
            probe, self._shaping.request = None if new_session else self._shaping.request, None
            if new_session:
                self._shaping.reset()
        target_before = prof.target.copy()
        if cmd is not None and not new_session:
            prof.apply(cmd)
        clamped = False if new_session else prof.step(period)
        total = self._shaping.total(prof.corr, prof.lo, prof.hi, t_rx, controller_s, probe,
                                    None if new_session else cmd, target_before)  # fmt: skip
        wire = total if self.mode == "absolute" else total - self._sent_corr
        answer = build_sen(
            frame.ipoc, wire, sen_type=self.sen_type, correction_tag=self.correction_tag
        )
        if self._mute:
            t_tx = math.nan
        else:
            sock = self._sock
            if sock is None:
                return
            try:
                sock.sendto(answer, addr)
            except OSError:
                return  # robot port gone; the robot will time out
            t_tx = time.monotonic()
            self._sent_corr = total.copy()
            if probe is not None:
                with self._cmd_lock:
                    self._shaping.sent = (frame.ipoc, controller_s, t_tx)
        if cmd is not None and not math.isnan(t_tx):
            with self._cmd_lock:
                rec = self._commands[cmd.index]
                self._commands[cmd.index] = RSICommandRecord(
                    **{
                        **rec.__dict__,
                        "first_answer_host_s": t_tx,
                        "first_answer_ipoc": frame.ipoc,
                    }
                )

        # ---- bookkeeping and publication (after the answer left)
        state = dataclasses.replace(state, correction=total.copy(), answer_host_time_s=t_tx)
        with self._cond:
            st["frames"] += 1
            self._frames_since_connect += 1
            if not new_session:
                st["missed_cycles"] += cycles - 1
            if clamped:
                st["clamped_cycles"] += 1
            if frame.delay is not None:
                st["robot_late_count"] = frame.delay
            if not math.isnan(t_tx):
                latency = t_tx - t_rx
                st["answers"] += 1
                self._latency_sum_s += latency
                st["mean_answer_latency_s"] = self._latency_sum_s / st["answers"]
                prev_max = st["max_answer_latency_s"]
                st["max_answer_latency_s"] = (
                    latency if math.isnan(prev_max) else max(prev_max, latency)
                )
                if latency > period:
                    st["late_answers"] += 1
            if q is not None:
                if len(self._queue) >= self.queue_size:
                    self._queue.popleft()
                    st["queue_overflows"] += 1
                self._queue.append(state)
                self._cond.notify_all()
