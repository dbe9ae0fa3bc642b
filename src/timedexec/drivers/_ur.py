"""Universal Robots driver over the ``ur_rtde`` client (RTDE receive + control interfaces).

State packages come from :class:`rtde_receive.RTDEReceiveInterface`, commands go through
:class:`rtde_control.RTDEControlInterface` (which uploads its control script to the robot).

Fresh-package detection
-----------------------
``ur_rtde`` parses the stream in its own C++ thread and keeps only the latest package; it
offers no callback or blocking read to Python. :meth:`URDriver.read_state` therefore polls
``getTimestamp()`` every ``poll_interval_s`` (default 50 µs) and returns a package as soon
as the controller time stamp changes, stamping it with :func:`time.monotonic` at that
moment. The host stamp is late by the client thread's own polling (it sleeps 100 µs when
the socket is empty), this driver's polling interval and the Python call overhead. Against
the UR twin the stamp follows the simulated send time by a median 0.4-0.6 ms and a 99th
percentile of 1.5-2.5 ms on a two-vCPU VM (``tests/test_ur_driver.py`` asserts a median
below 1 ms); that figure also contains the twin's own sender wake-up (~0.1-0.2 ms), so the
driver's share is a few hundred µs. Packages the caller does not read in time are replaced by
newer ones inside ``ur_rtde``; :attr:`RobotState.sequence` is derived from the controller
time stamp, so such losses show up as gaps.

Watchdog
--------
The control script ``ur_rtde`` uploads re-issues ``speedj(qd, a, t)`` every cycle until
``speedStop``, so the duration ``t`` never stops the arm of a dead host.
:meth:`URDriver.arm_watchdog` calls ``setWatchdog(1 / timeout_s)`` (the script's
``rtde_set_watchdog("input_int_register_0", f, "stop")``): when no input package updates
the command register for ``timeout_s`` the controller stops the program and the arm
decelerates. Every command this driver sends updates that register;
:meth:`URDriver.kick_watchdog` (``kickWatchdog``) does so without motion. The watchdog
stays armed until the program stops; after a trip every command fails with a
:class:`~timedexec.errors.DriverError` saying so, and :meth:`URDriver.arm_watchdog`
re-uploads the script and re-arms (measured against the twin: ~25 ms for the upload and
program start, ~5 ms for ``setWatchdog``; a kick costs ~70 µs median).

Nagle's algorithm
-----------------
``ur_rtde`` 1.6.5 asks for ``TCP_NODELAY`` on its RTDE socket, then connects it with
``boost::asio::connect``, which reopens the socket: the connection runs with Nagle's
algorithm (checked with ``getsockopt`` on its descriptors). A 72-byte command then waits in
the host's kernel until the controller acknowledges the previous one; a controller that
delays its ACK to the next state package (the twin's Linux stack does) takes each command
right after a package leaves, whatever the host's send time, and a cycle-locked sender
cannot place its commands. The driver sets ``TCP_NODELAY`` on those sockets itself at
connect (:attr:`URDriver.no_delay_sockets`). Against the UR10e twin, commands sent
mid-cycle: on the wire (tcpdump) a median 1.35 ms after ``speedJ`` returned, 6 µs after
the next state package; with the option 0.03 ms.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import socket
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.drivers._base import RobotDriver, RobotState
from timedexec.errors import ConfigError, DriverError, DriverTimeout
from timedexec.robots import ROBOT_NAMES, RobotSpec, get_robot, get_robot_entry

__all__ = ["URDriver", "ur_robot_named"]

#: The controller accepts joint accelerations up to this multiple of the spec's planning
#: limit (as the simulated controller does), capped by ur_rtde's own range check.
_ACCELERATION_HEADROOM = 4.0
_UR_RTDE_ACCELERATION_MAX_RAD_S2 = 40.0

#: Outputs the driver asks the receive interface for (fewer fields, less parsing).
DEFAULT_VARIABLES = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "target_q",
    "target_qd",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "runtime_state",
    "speed_scaling",
)


def _set_timer_slack_ns(slack_ns: int) -> None:
    """Set the calling thread's timer slack (Linux ``PR_SET_TIMERSLACK``); no-op elsewhere."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(29, slack_ns, 0, 0, 0)


#: RTDE port of a UR controller (the state stream and the command registers).
RTDE_PORT = 30004


def _no_delay_sockets(host: str, port: int = RTDE_PORT) -> int | None:
    """Set ``TCP_NODELAY`` on this process's TCP sockets connected to ``host:port``;
    return how many (None where the process's descriptors cannot be listed: not Linux).
    Why: the module notes ("Nagle's algorithm"). Options belong to the socket, so setting
    them through a duplicate of the descriptor reaches ``ur_rtde``'s own."""
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return None
    try:
        peers = {info[4][0] for info in socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)}
    except OSError:
        return 0
    done: set[Any] = set()
    for name in fds:
        try:
            if not os.readlink(f"/proc/self/fd/{name}").startswith("socket:"):
                continue
            dup = os.dup(int(name))
        except (OSError, ValueError):
            continue  # closed meanwhile, or not a descriptor
        sock = socket.socket(fileno=dup)
        try:
            if sock.family not in (socket.AF_INET, socket.AF_INET6):
                continue
            if sock.type != socket.SOCK_STREAM:
                continue
            peer = sock.getpeername()
            if peer[1] == port and peer[0] in peers:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                done.add(sock.getsockname())  # a socket may hold several descriptors
        except OSError:
            continue  # not connected
        finally:
            sock.close()  # closes the duplicate only
    return len(done)


def _hint(host: str) -> str:
    return (
        f"check that the UR controller at {host} is powered on and reachable, that remote "
        "control is enabled (e-Series), that no other program owns the RTDE input registers "
        "(another RTDEControlInterface, EtherNet/IP, PROFINET, MODBUS) and that ports 30004, "
        "29999 and 30003 are open"
    )


def ur_robot_named(model: str, major: int) -> str | None:
    """The catalog's UR robot whose controller reports ``model`` (the dashboard's robot
    model, case-insensitive) with software major version ``major``, or None.

    The e-Series reports the same model name as its CB3 namesake ("UR10" on a UR10e);
    PolyScope 5 and later (major >= 5) tells them apart. Matched against each robot's
    catalog identity (``RobotEntry.twin``), which the UR twin reports.
    """
    for name in ROBOT_NAMES:
        twin = get_robot_entry(name).twin
        if (
            twin.interface == "ur_rtde"
            and twin.model_name.lower() == model.strip().lower()
            and (twin.controller_version[0] >= 5) == (major >= 5)
        ):
            return name
    return None


class URDriver(RobotDriver):
    """A Universal Robots arm (CB3 or e-Series) through ``ur_rtde``.

    Parameters
    ----------
    host : str
        Controller address, e.g. ``"192.168.1.10"`` or a UR twin's ``"127.0.0.2"``.
    frequency_hz : float, optional
        RTDE stream frequency; default: what ``ur_rtde`` picks (125 Hz for a CB3, 500 Hz
        for an e-Series).
    robot : str, optional
        A UR robot of the catalog, for its limits and controller period; default: inferred
        from the dashboard server's model and PolyScope version (:func:`ur_robot_named`).
    control : bool
        Also open the control interface (commands); False gives a read-only driver.
    variables : sequence of str, optional
        RTDE outputs to stream (default :data:`DEFAULT_VARIABLES`); must include
        ``timestamp``, ``actual_q`` and ``actual_qd``.
    poll_interval_s : float
        Sleep between polls of the receive interface in :meth:`read_state`, s.
    tight_timer_slack : bool
        On Linux, set the calling thread's timer slack to 1 µs before the ``ur_rtde``
        threads are created (they inherit it): their 100 µs polling sleeps and this
        driver's polling then wake on time instead of up to 50 µs late.
    external_control : bool
        Run the control script through Universal Robots' External Control URCap instead of
        uploading it (a cell without remote control): ``ur_rtde`` serves the script on
        ``ur_cap_port`` of this PC (``FLAG_USE_EXT_UR_CAP``) and the pendant program holding
        the External Control node fetches it when it starts. Implied by ``program``.
    ur_cap_port : int
        Port the URCap's installation points at (its default, 50002).
    program : str, optional
        Pendant program holding the External Control node (e.g.
        ``"/programs/external_control.urp"``): loaded and played through the dashboard
        server on connect and after a watchdog trip. None: someone presses play on the
        pendant (the driver waits ``program_timeout_s`` and says so every 5 s).
    program_timeout_s : float
        How long to wait for the External Control program to run, s.

    Attributes
    ----------
    no_delay_sockets : int or None
        How many of this process's connections to the controller's RTDE port got
        ``TCP_NODELAY`` at connect (``ur_rtde`` 1.6.5 loses its own; without it each
        command waits for the controller's acknowledgement of the previous one: see the
        module notes). None where it cannot be set (not Linux).

    Examples
    --------
    >>> with URDriver("127.0.0.2") as drv:                      # doctest: +SKIP
    ...     state = drv.read_state(timeout_s=0.1)
    ...     drv.speedj([0, 0.2, 0, 0, 0, 0], 2.0, 0.5)
    """

    #: The control script's speed thread takes a new target when the previous ``speedj``
    #: returns, after its ``t`` (see :class:`~timedexec.drivers.RobotDriver`).
    speedj_duration_paces_updates = True
    #: ``target_qd`` shows which cycle took a command: the executor probes the intake at
    #: connect and locks its sends to it by default.
    cycle_lock_default = True

    def __init__(
        self,
        host: str,
        *,
        frequency_hz: float | None = None,
        robot: str | None = None,
        control: bool = True,
        variables: Sequence[str] | None = None,
        poll_interval_s: float = 50e-6,
        tight_timer_slack: bool = True,
        external_control: bool = False,
        ur_cap_port: int = 50002,
        program: str | None = None,
        program_timeout_s: float = 60.0,
    ) -> None:
        if frequency_hz is not None and not 0 < frequency_hz <= 500:
            raise ConfigError(
                f"frequency_hz={frequency_hz!r} outside (0, 500]; use 125 (CB3) or 500 (e-Series)"
            )
        if not 0 <= poll_interval_s <= 0.01:
            raise ConfigError(f"poll_interval_s={poll_interval_s!r} outside [0, 0.01] s")
        self.host = host
        self.frequency_hz = frequency_hz
        self._robot_arg = robot
        self._spec: RobotSpec | None = get_robot(robot) if robot is not None else None
        self.robot = robot or ""
        self.control = control
        self.variables = tuple(variables) if variables is not None else DEFAULT_VARIABLES
        missing = {"timestamp", "actual_q", "actual_qd"} - set(self.variables)
        if missing:
            raise ConfigError(f"variables must include {sorted(missing)} (read_state needs them)")
        self._streams_target_qd = "target_qd" in self.variables
        self.poll_interval_s = float(poll_interval_s)
        self.tight_timer_slack = tight_timer_slack
        if isinstance(ur_cap_port, bool) or not (
            isinstance(ur_cap_port, int) and 1 <= ur_cap_port <= 65535
        ):
            raise ConfigError(
                f"ur_cap_port={ur_cap_port!r} outside 1..65535; use the port the External "
                "Control URCap's installation names (default 50002)"
            )
        if program is not None and not (isinstance(program, str) and program.endswith(".urp")):
            raise ConfigError(
                f"program={program!r} is not a pendant program; give the .urp path that holds "
                "the External Control node, e.g. '/programs/external_control.urp'"
            )
        if not (isinstance(program_timeout_s, int | float) and 0 < program_timeout_s <= 3600):
            raise ConfigError(f"program_timeout_s={program_timeout_s!r} outside (0, 3600] s")
        self.external_control = bool(external_control) or program is not None
        self.ur_cap_port = int(ur_cap_port)
        self.program = program
        self.program_timeout_s = float(program_timeout_s)
        self.controller_version: tuple[int, ...] = ()
        self._recv: Any = None
        self._ctrl: Any = None
        self._last_ts: float | None = None
        self._first_ts: float | None = None
        self._stream_period_s = math.nan
        self._link_lost = False
        self._watchdog_s: float | None = None
        self.no_delay_sockets: int | None = None

    # ------------------------------------------------------------------ connection
    @property
    def spec(self) -> RobotSpec:
        """The robot's spec (limits, period); known after :meth:`connect`."""
        if self._spec is None:
            raise DriverError(f"URDriver({self.host!r}): robot unknown until connect()")
        return self._spec

    @property
    def controller_period_s(self) -> float:
        """Controller cycle period, s (0.008 CB3, 0.002 e-Series)."""
        return float(self.spec.controller_period_s)

    @property
    def stream_period_s(self) -> float:
        """Period of the RTDE stream, s (1 / frequency)."""
        return self._stream_period_s

    @property
    def is_connected(self) -> bool:
        """Whether the receive interface still has its connection."""
        return self._recv is not None and bool(self._recv.isConnected())

    def _infer_robot(self) -> str:
        import dashboard_client

        try:
            dash = dashboard_client.DashboardClient(self.host)
            dash.connect()
            try:
                version = str(dash.polyscopeVersion())
                model = str(dash.getRobotModel()).strip().lower()
            finally:
                dash.disconnect()
        except RuntimeError as exc:
            raise DriverError(
                f"cannot ask the UR dashboard server at {self.host}:29999 for the robot "
                f"model ({exc}); {_hint(self.host)}, or pass robot='ur10'/'ur10e'"
            ) from exc
        parts = [int(p) for p in version.replace("-", ".").split(".") if p.isdigit()]
        self.controller_version = tuple(parts)
        name = ur_robot_named(model, parts[0] if parts else 0)
        if name is None:
            raise ConfigError(
                f"robot model {model!r} with PolyScope {version!r} at {self.host} has no spec "
                f"in the catalog; pass robot= explicitly, e.g. URDriver(host, robot='ur10e')"
            )
        return name

    def connect(self) -> None:
        """Open the receive (and control) interfaces; raise DriverError on failure."""
        if self._recv is not None:
            return
        import rtde_control
        import rtde_receive

        if self._spec is None:
            self.robot = self._infer_robot()
            self._spec = get_robot(self.robot)
        frequency = -1.0 if self.frequency_hz is None else float(self.frequency_hz)
        if self.tight_timer_slack:
            _set_timer_slack_ns(1000)
        try:
            self._recv = rtde_receive.RTDEReceiveInterface(
                self.host, frequency, list(self.variables)
            )
        except RuntimeError as exc:
            raise DriverError(
                f"cannot open the RTDE receive interface of {self.host}:30004 ({exc}); "
                f"{_hint(self.host)}"
            ) from exc
        if self.control:
            iface = rtde_control.RTDEControlInterface
            try:
                if self.external_control:
                    # NO_WAIT: the constructor would wait for the program holding the GIL.
                    flags = iface.FLAG_USE_EXT_UR_CAP | iface.FLAG_NO_WAIT
                    self._ctrl = iface(self.host, frequency, flags, self.ur_cap_port)
                else:
                    self._ctrl = iface(self.host, frequency)
            except RuntimeError as exc:
                self._close_receive()
                raise DriverError(
                    f"cannot open the RTDE control interface of {self.host} ({exc}); "
                    f"{_hint(self.host)}"
                ) from exc
            if self.external_control:
                try:
                    self._start_external_program()
                except DriverError:
                    self.close()
                    raise
        if self.frequency_hz is not None:
            rate_hz = float(self.frequency_hz)
        else:
            rate_hz = 500.0 if self.controller_period_s < 0.005 else 125.0
        self._stream_period_s = 1.0 / rate_hz
        # ur_rtde's own TCP_NODELAY does not survive its connect (see _no_delay_sockets).
        self.no_delay_sockets = _no_delay_sockets(self.host)
        self._last_ts = float(self._recv.getTimestamp())
        self._first_ts = None
        self._link_lost = False
        self._watchdog_s = None

    def _close_receive(self) -> None:
        recv, self._recv = self._recv, None
        if recv is not None:
            with contextlib.suppress(RuntimeError):
                recv.disconnect()

    def close(self) -> None:
        """Stop motion, stop the control script and disconnect; idempotent.

        After a lost link no command is sent: ``ur_rtde`` would try to reconnect first.
        """
        ctrl, self._ctrl = self._ctrl, None
        if ctrl is not None:
            if not self._link_lost and self.is_connected:
                with contextlib.suppress(RuntimeError):
                    if ctrl.isConnected():
                        ctrl.speedStop(self._default_deceleration())
                        ctrl.stopScript()
            with contextlib.suppress(RuntimeError):
                ctrl.disconnect()
        self._watchdog_s = None
        self._close_receive()

    # ------------------------------------------------------------------ state
    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        """Block until a package with a new controller time stamp arrives; return it.

        Raises
        ------
        DriverTimeout
            No new package within ``timeout_s`` (the stream stalled), or the client lost
            its connection (``ur_rtde`` drops it after 2.5 s without data).
        """
        recv = self._recv
        if recv is None:
            raise DriverError(f"URDriver({self.host!r}) is not connected; call connect() first")
        deadline = time.monotonic() + timeout_s
        poll = self.poll_interval_s
        last = self._last_ts
        while True:
            ts = recv.getTimestamp()
            if ts != last:
                host_time_s = time.monotonic()
                q = recv.getActualQ()
                qd = recv.getActualQd()
                # outputs without target_qd: None (the executor cannot probe the intake)
                target_qd = recv.getTargetQd() if self._streams_target_qd else None
                ts_after = recv.getTimestamp()
                if ts_after != ts:
                    continue  # a newer package landed while reading: take that one
                return self._state(host_time_s, ts, q, qd, target_qd)
            if time.monotonic() > deadline:
                if not recv.isConnected():
                    self._link_lost = True
                    raise DriverTimeout(
                        f"the RTDE connection to the UR controller at {self.host} is lost (the "
                        "controller closed it, or ur_rtde dropped it after a 2.5 s stall); "
                        f"{_hint(self.host)}, then close() and connect() again"
                    )
                raise DriverTimeout(
                    f"no new RTDE package from {self.host} within {timeout_s} s (last controller "
                    f"time {last}); the stream stalled: check the network and the controller load"
                )
            if poll > 0:
                time.sleep(poll)

    def _state(
        self, host_time_s: float, ts: float, q: Any, qd: Any, target_qd: Any = None
    ) -> RobotState:
        self._last_ts = ts
        if self._first_ts is None:
            self._first_ts = ts
        sequence = round((ts - self._first_ts) / self._stream_period_s)
        return RobotState(
            host_time_s=host_time_s,
            controller_time_s=float(ts),
            q=np.asarray(q, dtype=float),
            qd=np.asarray(qd, dtype=float),
            sequence=int(sequence),
            target_qd=None if target_qd is None else np.asarray(target_qd, dtype=float),
        )

    # ------------------------------------------------------------------ commands
    def _control(self) -> Any:
        if self._link_lost or (self._recv is not None and not self._recv.isConnected()):
            self._link_lost = True
            raise DriverError(
                f"URDriver({self.host!r}) lost its RTDE connection; {_hint(self.host)}, then "
                "close() and connect() again"
            )
        if self._ctrl is None:
            what = "opened with control=False" if self._recv is not None else "not connected"
            raise DriverError(f"URDriver({self.host!r}) cannot command the robot: {what}")
        return self._ctrl

    def _acceleration_limit(self) -> float:
        return min(
            max(self.spec.qdd_max_rad_s2) * _ACCELERATION_HEADROOM,
            _UR_RTDE_ACCELERATION_MAX_RAD_S2,
        )

    def _default_deceleration(self) -> float:
        return min(10.0, self._acceleration_limit())

    def _check_acceleration(self, what: str, value: float) -> float:
        limit = self._acceleration_limit()
        value = float(value)
        if not 0 < value <= limit:
            raise ConfigError(
                f"{what}: acceleration {value!r} rad/s² outside (0, {limit:.4g}] for "
                f"{self.spec.name}; choose a value in that range"
            )
        return value

    def _check_q(self, what: str, q: ArrayLike) -> list[float]:
        arr = np.asarray(q, dtype=float)
        if arr.shape != (6,):
            raise ConfigError(f"{what}: incorrect vector length: expected 6, got {arr.size}")
        lo, hi = np.asarray(self.spec.q_min_rad), np.asarray(self.spec.q_max_rad)
        for j in range(6):
            if not lo[j] <= arr[j] <= hi[j]:
                raise ConfigError(
                    f"{what}: joint {j + 1} position {arr[j]:.4g} rad outside "
                    f"[{lo[j]:.4g}, {hi[j]:.4g}] rad of {self.spec.name}"
                )
        return [float(v) for v in arr]

    def _check_speeds(self, what: str, qd: ArrayLike) -> list[float]:
        arr = np.asarray(qd, dtype=float)
        if arr.shape != (6,):
            raise ConfigError(f"{what}: incorrect vector length: expected 6, got {arr.size}")
        limits = self.spec.qd_max_rad_s
        for j in range(6):
            if not abs(arr[j]) <= limits[j]:
                raise ConfigError(
                    f"{what}: joint {j + 1} speed {arr[j]:.4g} rad/s exceeds the limit "
                    f"±{limits[j]:.4g} rad/s of {self.spec.name}; command a lower speed"
                )
        return [float(v) for v in arr]

    def _call(self, what: str, fn: Any, *args: Any) -> Any:
        try:
            ok = fn(*args)
        except RuntimeError as exc:
            raise DriverError(
                f"{what} on the UR controller at {self.host} failed ({exc}); {_hint(self.host)}"
            ) from exc
        if ok is False:
            if self.watchdog_tripped():
                raise DriverError(self._watchdog_message(what))
            raise DriverError(
                f"the UR controller at {self.host} did not accept {what}: the control script "
                "is not running or the robot is protective/emergency stopped; check the "
                "teach pendant and reconnect"
            )
        return ok

    def commanded_q_rad(self) -> FloatArray | None:
        """The controller's ``target_q`` in the newest package, rad (6,), or None when the
        outputs leave it out or the driver is not connected."""
        recv = self._recv
        if recv is None or "target_q" not in self.variables or self._link_lost:
            return None
        return np.asarray(recv.getTargetQ(), dtype=float)

    def speedj(
        self, qd_rad_s: FloatArray | Sequence[float], acceleration_rad_s2: float, duration_s: float
    ) -> None:
        """``speedJ(qd, a, t)``: joint speeds (rad/s), leading-axis acceleration (rad/s²),
        duration (s; 0 holds the speed until the next command). Returns once the command is
        sent (realtime command: ``ur_rtde`` waits only for the script's "ready")."""
        qd = self._check_speeds("speedj", qd_rad_s)
        a = self._check_acceleration("speedj", acceleration_rad_s2)
        if not duration_s >= 0:
            raise ConfigError(f"speedj: duration_s={duration_s!r} must be >= 0")
        self._call("speedJ", self._control().speedJ, qd, a, float(duration_s))

    def stop(self, deceleration_rad_s2: float = 10.0) -> None:
        """``speedStop(a)``: decelerate all joints to rest; returns when the arm is still."""
        a = self._check_acceleration("stop", deceleration_rad_s2)
        self._call("speedStop", self._control().speedStop, a)

    # ------------------------------------------------------------------ watchdog
    def _watchdog_message(self, what: str) -> str:
        timeout = self._watchdog_s or math.nan
        return (
            f"the UR controller at {self.host} did not accept {what}: its watchdog stopped "
            f"the control program because no command reached it for more than "
            f"{timeout * 1e3:.0f} ms (setWatchdog({1.0 / timeout:g} Hz)); the program stop "
            "decelerated the arm. Recover with TimedExecutor.recover() or "
            f"URDriver.arm_watchdog({timeout:g}) (re-uploads the control script and re-arms), "
            "or close() and connect() again"
        )

    def _start_external_program(self) -> None:
        """Play :attr:`program` through the dashboard (if given) and wait until the program
        with the External Control node runs (it fetches ``ur_rtde``'s script from us)."""
        import dashboard_client

        ctrl = self._control()
        where = f"this PC, port {self.ur_cap_port}"
        if self.program is not None and not ctrl.isProgramRunning():
            try:
                dash = dashboard_client.DashboardClient(self.host)
                dash.connect()
                try:
                    dash.loadURP(self.program)
                    dash.play()
                finally:
                    dash.disconnect()
            except RuntimeError as exc:
                raise DriverError(
                    f"the dashboard server of {self.host} did not play {self.program!r} "
                    f"(it answered {str(exc)!r}); check the path on the pendant and that its "
                    f"External Control node points at {where}"
                ) from exc
        start = time.monotonic()
        note = start + 5.0
        while not ctrl.isProgramRunning():
            now = time.monotonic()
            if now - start > self.program_timeout_s:
                raise DriverError(
                    f"the External Control program on {self.host} did not run within "
                    f"{self.program_timeout_s:g} s; press play on the pendant (or pass "
                    f"program='/programs/....urp'), and check that its External Control node "
                    f"points at {where}"
                )
            if self.program is None and now >= note:
                print(
                    f"waiting for the program with the External Control node on {self.host} "
                    f"({now - start:.0f} s of {self.program_timeout_s:g}): press play on the "
                    "pendant",
                    file=sys.stderr,
                )
                note += 5.0
            time.sleep(0.01)

    def _restart_program(self, timeout_s: float = 5.0) -> None:
        ctrl = self._control()
        if ctrl.isProgramRunning():
            return
        if self.external_control:
            self._start_external_program()
            return
        self._call("reuploadScript", ctrl.reuploadScript)
        deadline = time.monotonic() + timeout_s
        while not ctrl.isProgramRunning():
            if time.monotonic() > deadline:
                raise DriverError(
                    f"the control script re-uploaded to the UR controller at {self.host} did "
                    f"not start within {timeout_s:g} s; check the teach pendant (protective "
                    "stop, remote control) and reconnect"
                )
            time.sleep(0.001)

    def arm_watchdog(self, timeout_s: float) -> float:
        """``setWatchdog(1 / timeout_s)``: the controller stops the program (the arm
        decelerates) when no command or kick updates the command register for
        ``timeout_s`` (s, at least two controller periods, at most 10 s). Stays armed until
        the program stops. After a trip this re-uploads the control script first."""
        period = self.controller_period_s
        if not 2 * period <= timeout_s <= 10.0:
            raise ConfigError(
                f"watchdog timeout_s={timeout_s!r} outside [{2 * period:g}, 10] s (at least two "
                f"controller periods of {period * 1e3:g} ms); e.g. 0.1"
            )
        self._restart_program()
        self.no_delay_sockets = _no_delay_sockets(self.host)  # in case ur_rtde reconnected
        self._watchdog_s = None
        try:
            self._call("setWatchdog", self._control().setWatchdog, 1.0 / float(timeout_s))
        except DriverError:
            # A connect right after another session's close can find that session's
            # program still running and see it stop between the check and the call: the
            # script refuses; start ours and try once more (a real refusal raises again).
            try:
                running = self._control().isProgramRunning()
            except RuntimeError:
                running = True  # the connection itself is gone: report the refusal
            if running:
                raise
            self._restart_program()
            self._call("setWatchdog", self._control().setWatchdog, 1.0 / float(timeout_s))
        self._watchdog_s = float(timeout_s)
        return self._watchdog_s

    def kick_watchdog(self) -> None:
        """``kickWatchdog()``: feed the watchdog without motion (no-op when not armed)."""
        if self._watchdog_s is not None:
            self._call("kickWatchdog", self._control().kickWatchdog)

    def watchdog_tripped(self) -> bool:
        """Whether the armed watchdog stopped the control program."""
        ctrl = self._ctrl
        if self._watchdog_s is None or ctrl is None:
            return False
        try:
            return not bool(ctrl.isProgramRunning())
        except RuntimeError:
            return False

    def servoj(
        self,
        q_rad: FloatArray | Sequence[float],
        *,
        time_s: float = 0.008,
        lookahead_s: float = 0.1,
        gain: float = 300.0,
    ) -> None:
        """``servoJ(q, 0, 0, time, lookahead, gain)``: joint position setpoint (rad)."""
        q = self._check_q("servoj", q_rad)
        if not time_s > 0:
            raise ConfigError(f"servoj: time_s={time_s!r} must be > 0")
        if not 0.03 <= lookahead_s <= 0.2:
            raise ConfigError(f"servoj: lookahead_s={lookahead_s!r} outside [0.03, 0.2] s")
        if not 100 <= gain <= 2000:
            raise ConfigError(f"servoj: gain={gain!r} outside [100, 2000]")
        args = (q, 0.0, 0.0, float(time_s), float(lookahead_s), float(gain))
        self._call("servoJ", self._control().servoJ, *args)

    def movej(
        self,
        q_rad: FloatArray | Sequence[float],
        speed_rad_s: float = 1.05,
        acceleration_rad_s2: float = 1.4,
        *,
        asynchronous: bool = False,
    ) -> None:
        """``moveJ(q, speed, a, async)``: joint move; blocks until the motion ends unless
        ``asynchronous``."""
        q = self._check_q("movej", q_rad)
        limit = max(self.spec.qd_max_rad_s)
        if not 0 < speed_rad_s <= limit:
            raise ConfigError(
                f"movej: speed {speed_rad_s!r} rad/s outside (0, {limit:.4g}] for {self.spec.name}"
            )
        a = self._check_acceleration("movej", acceleration_rad_s2)
        self._call("moveJ", self._control().moveJ, q, float(speed_rad_s), a, bool(asynchronous))
