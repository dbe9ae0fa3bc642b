"""The simulated UR controller's server: sockets, the real-time clock and the ground truth.

Runs inside the twin's process (:class:`~timedexec.twins.URTwin` spawns it;
:func:`~timedexec.twins.run_ur_twin` runs it in the calling process). :class:`_TwinServer`
listens on the RTDE (30004), dashboard (29999) and script (30003) ports of one address,
steps the simulated controller (:class:`timedexec.sim.ControllerSim`) once per controller
period on a real-time clock (controller time ``t`` happens at host time ``t0 + t``,
:func:`time.monotonic`), puts each state package on the wire at the simulated send time and
appends the ground truth to a JSON-lines file (:mod:`timedexec.twins._ur_truthlog`). The
RTDE protocol is in :mod:`timedexec.twins._rtde`, the control script and the dashboard in
:mod:`timedexec.twins._urscript` (its Cartesian motions in :mod:`timedexec.twins._cartesian`,
its RTDE watchdog in :mod:`timedexec.twins._watchdog`).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import heapq
import importlib
import math
import os
import queue
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

try:  # Unix: the readers' unread bytes at a boundary
    import fcntl
    import termios
except ImportError:  # pragma: no cover
    fcntl = termios = None  # type: ignore[assignment]

from timedexec._realtime import GcPauses, fast_wakeup, quiet_gc, try_realtime
from timedexec.errors import ConfigError, ProtocolError
from timedexec.robots import ROBOT_NAMES, TwinIdentity, get_robot_entry
from timedexec.twins._cartesian import tcp_values
from timedexec.twins._rtde import RTDE_OUTPUT_TYPES, RTDE_TYPE_CODES, _RTDEConnection
from timedexec.twins._ur_truthlog import TruthLog, json_safe
from timedexec.twins._urprograms import EXTERNAL_CONTROL_PORT, ProgramStore
from timedexec.twins._urscript import (
    _PROGRAM_START_DELAY_S,
    DASHBOARD_MAX_LINE_BYTES,
    _ControlScript,
    _dashboard_reply,
    _LineReader,
    _ScriptReader,
    _SimLike,
)

__all__ = [
    "DASHBOARD_PORT",
    "DEFAULT_PHYSICS_RATE_HZ",
    "RTDE_PORT",
    "SCRIPT_PORT",
    "UR_CONTROLLER_VERSIONS",
]

#: TCP ports a UR controller serves (fixed by the ``ur_rtde`` client).
RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003


def _version(identity: TwinIdentity) -> tuple[int, int, int, int]:
    major, minor, bugfix, build = identity.controller_version  # four for a UR (checked)
    return major, minor, bugfix, build


#: The robots the UR twin simulates (the catalog's ``ur_rtde`` robots) and the controller
#: software version it reports for each: (major, minor, bugfix, build).
UR_CONTROLLER_VERSIONS: dict[str, tuple[int, int, int, int]] = {
    name: _version(get_robot_entry(name).twin)
    for name in ROBOT_NAMES
    if get_robot_entry(name).twin.interface == "ur_rtde"
}
#: Joint mode reported for every joint: JOINT_RUNNING_MODE.
_JOINT_RUNNING_MODE = 253

#: Physics rate of the default simulated controller in the twin, Hz: 4 kHz keeps one
#: e-Series cycle well inside its 2 ms (8 kHz costs about 1.2 ms of CPU per cycle).
DEFAULT_PHYSICS_RATE_HZ = 4000.0


def _default_sim_factory(
    robot: str,
    *,
    effects: Any,
    q0_rad: Any,
    seed: int,
    physics_rate_hz: float | None = DEFAULT_PHYSICS_RATE_HZ,
) -> _SimLike:
    from timedexec.sim import ControllerSim

    sim: _SimLike = ControllerSim(
        robot, effects=effects, q0_rad=q0_rad, seed=seed, physics_rate_hz=physics_rate_hz
    )
    return sim


def _resolve_factory(factory: str | Callable[..., _SimLike] | None) -> Callable[..., _SimLike]:
    if factory is None:
        return _default_sim_factory
    if callable(factory):
        return factory
    module_name, _, attr = factory.partition(":")
    if not attr:
        raise ConfigError(
            f"sim_factory={factory!r}: expected 'module:callable', e.g. "
            "'timedexec.sim:ControllerSim'"
        )
    result: Callable[..., _SimLike] = getattr(importlib.import_module(module_name), attr)
    return result


def _tuple6(value: Any) -> tuple[float, ...]:
    return tuple(np.asarray(value, dtype=np.float64).tolist())


def _same_array(a: Any, b: Any) -> bool:
    """Bit-for-bit equality of two float arrays (cheaper than ``np.array_equal``)."""
    return bool(
        np.asarray(a, dtype=np.float64).tobytes() == np.asarray(b, dtype=np.float64).tobytes()
    )


#: A package later than this counts as a late send, s.
_LATE_S = 0.5e-3
#: SCHED_FIFO priority of the twin's clock and sender threads (None: normal scheduling).
_DEFAULT_RT_PRIORITY = 10
#: Grid on which the gyro twin is handed the flange rate (its nominal sample rate), Hz.
_GYRO_GRID_HZ = 8000.0
#: Longest wait at a boundary for the RTDE readers to hand over what has arrived, s.
_DRAIN_S = 3e-4


def _unread(sock: socket.socket) -> int:
    """Bytes waiting in ``sock``'s receive queue (0 if it cannot say)."""
    if fcntl is None:
        return 0
    try:
        raw = fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0")
    except (OSError, ValueError):
        return 0
    return int.from_bytes(raw, sys.byteorder, signed=True)


#: Interpreter switch interval in the twin process: bounds how long the physics thread
#: can delay the sender thread, s.
_SWITCH_INTERVAL_S = 0.2e-3


@dataclasses.dataclass(frozen=True)
class _PeekedPacket:
    cycle: int
    sample_time_s: float
    send_time_s: float
    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    q_target_rad: np.ndarray
    qd_target_rad_s: np.ndarray


@dataclasses.dataclass
class _Write:
    """Input registers written by one data package, time-stamped at arrival."""

    arrival_s: float
    sequence: int
    values: dict[str, Any]
    disconnect: bool = False
    stop_program: bool = False

    def __lt__(self, other: _Write) -> bool:
        return (self.arrival_s, self.sequence) < (other.arrival_s, other.sequence)


@dataclasses.dataclass
class _Send:
    """A sampled state package waiting for its send time."""

    send_time_s: float
    sequence: int
    cycle: int
    values: dict[str, Any]

    def __lt__(self, other: _Send) -> bool:
        return (self.send_time_s, self.sequence) < (other.send_time_s, other.sequence)


def _set_timer_slack_ns(slack_ns: int) -> None:
    """Tighten this thread's sleep precision (Linux PR_SET_TIMERSLACK); no-op elsewhere."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(29, slack_ns, 0, 0, 0)


def _check_robot(robot: str) -> TwinIdentity:
    """The identity the twin reports for ``robot``; ConfigError for a robot it cannot be."""
    if robot not in UR_CONTROLLER_VERSIONS:
        raise ConfigError(
            f"robot={robot!r} is not a simulated UR; use one of {sorted(UR_CONTROLLER_VERSIONS)}"
        )
    return get_robot_entry(robot).twin


def _sleep_until(deadline: float) -> None:
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            return
        time.sleep(remaining)


class _TwinServer:
    """The simulated UR controller: sockets, the control script and the real-time clock."""

    def __init__(
        self,
        robot: str,
        host: str,
        *,
        seed: int = 0,
        effects: Any = None,
        q0_rad: Any = None,
        truth_path: str | os.PathLike[str] | None = None,
        imu_link: str | None = None,
        sim_factory: str | Callable[..., _SimLike] | None = None,
        physics_rate_hz: float | None = DEFAULT_PHYSICS_RATE_HZ,
        rt_priority: int | None = _DEFAULT_RT_PRIORITY,
        external_control: tuple[str, int] = ("127.0.0.1", EXTERNAL_CONTROL_PORT),
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.identity = _check_robot(robot)
        self.robot = robot
        self.host = host
        self.rt_priority = rt_priority
        self.version = UR_CONTROLLER_VERSIONS[robot]
        self._log = log or (lambda msg: print(f"[ur-twin {host}] {msg}", file=sys.stderr))
        self._abuse_logged_s = -math.inf
        self._abuse_suppressed = 0
        self._seed = seed
        if sim_factory is None:
            self.sim = _default_sim_factory(
                robot, effects=effects, q0_rad=q0_rad, seed=seed, physics_rate_hz=physics_rate_hz
            )
        else:
            factory = _resolve_factory(sim_factory)
            self.sim = factory(robot, effects=effects, q0_rad=q0_rad, seed=seed)
        self.script = _ControlScript(self.sim, self.log)
        self.script.track_truth = truth_path is not None
        self.programs = ProgramStore(
            external_control,
            start_program=self._program_uploaded,
            request_stop=self._request_program_stop,
            log=self.log,
        )
        self._tcp_wanted = False
        self.period_s = float(self.sim.period_s)
        self.t0 = 0.0
        self.stop_event = threading.Event()
        self._lock = threading.Lock()
        self._listeners: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._rtde: list[_RTDEConnection] = []
        self._others: list[socket.socket] = []
        self._conn_counter = 0
        self._write_counter = 0
        self._writes: list[_Write] = []
        self._owners: dict[str, int] = {}
        self._prev_target_qd: tuple[float, ...] = (0.0,) * 6
        self._prev_actual_qd: tuple[float, ...] = (0.0,) * 6
        self._static = self._static_values()
        # ground truth
        self._truth = TruthLog(truth_path)
        # gyro twin
        self._imu_link = imu_link
        self._gyro: Any = None
        self._rates_ready = threading.Condition()
        self._rates_upto_s = -math.inf
        self._rate_t: list[np.ndarray] = []
        self._rate_w: list[np.ndarray] = []
        self._send_seq = 0
        self.stats: dict[str, Any] = {
            "cycles": 0,
            "late_sends": 0,
            "max_lateness_s": 0.0,
            "drain_timeouts": 0,
            "peek_mismatches": 0,
            "max_cycle_lag_s": 0.0,
            "max_send_gap_s": 0.0,
            "program_stops": [],
        }
        self._send_queue: queue.Queue[_Send | None] = queue.Queue()
        self._gc_quiet = contextlib.ExitStack()
        self._gc_pauses = GcPauses()

    def stats_now(self) -> dict[str, Any]:
        """:attr:`stats` with the longest garbage collection since serving began, s."""
        return dict(self.stats, gc_max_pause_s=self._gc_pauses.max_s)

    def log(self, message: str) -> None:
        self._log(message)

    def log_abuse(self, message: str) -> None:
        """Log a connection closed for breaking an input limit, at most once a second (a
        client that reconnects and offends again in a loop must not flood the log)."""
        now = time.monotonic()
        with self._lock:
            if now - self._abuse_logged_s < 1.0:
                self._abuse_suppressed += 1
                return
            suppressed, self._abuse_suppressed = self._abuse_suppressed, 0
            self._abuse_logged_s = now
        more = f" ({suppressed} more such connections closed meanwhile)" if suppressed else ""
        self._log(message + more)

    # -- sockets -------------------------------------------------------------------------
    def bind(self) -> None:
        """Open the three listening sockets; raise ConfigError if the address is taken."""
        for port, handler in (
            (RTDE_PORT, self._accept_rtde),
            (DASHBOARD_PORT, self._accept_dashboard),
            (SCRIPT_PORT, self._accept_script),
        ):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((self.host, port))
            except OSError as exc:
                sock.close()
                self.close()
                raise ConfigError(
                    f"UR twin cannot listen on {self.host}:{port} ({exc}); another twin or "
                    "robot server uses this address: give each twin its own loopback IP "
                    "(host='127.0.0.2', '127.0.0.3', ...)"
                ) from exc
            sock.listen(8)
            sock.settimeout(0.2)
            self._listeners.append(sock)
            self._threads.append(
                threading.Thread(target=self._accept_loop, args=(sock, handler), daemon=True)
            )

    def _accept_loop(self, sock: socket.socket, handler: Callable[[socket.socket], None]) -> None:
        while not self.stop_event.is_set():
            try:
                client, _ = sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            client.settimeout(None)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            handler(client)

    def _accept_rtde(self, client: socket.socket) -> None:
        with self._lock:
            self._conn_counter += 1
            conn = _RTDEConnection(self, client, self._conn_counter)
            self._rtde.append(conn)
        conn.thread.start()

    def _accept_dashboard(self, client: socket.socket) -> None:
        with self._lock:
            self._others.append(client)
        threading.Thread(target=self._dashboard_loop, args=(client,), daemon=True).start()

    def _accept_script(self, client: socket.socket) -> None:
        with self._lock:
            self._others.append(client)
        threading.Thread(target=self._script_loop, args=(client,), daemon=True).start()

    def _forget(self, client: socket.socket) -> None:
        with self._lock, contextlib.suppress(ValueError):
            self._others.remove(client)
        with contextlib.suppress(OSError):
            client.close()

    def connection_closed(self, conn: _RTDEConnection) -> None:
        with self._lock:
            if conn in self._rtde:
                self._rtde.remove(conn)
            self._tcp_wanted = any(c.wants_tcp for c in self._rtde)
            owned = [n for n, owner in self._owners.items() if owner == conn.conn_id]
            for name in owned:
                del self._owners[name]
            if owned:
                # The writer of the command registers is gone: stop the arm (like the
                # controller's RTDE watchdog) and leave the program running.
                self._write_counter += 1
                heapq.heappush(
                    self._writes,
                    _Write(time.monotonic() - self.t0, self._write_counter, {}, disconnect=True),
                )

    def claim_inputs(self, conn_id: int, names: Iterable[str]) -> set[str]:
        """Take ownership of input fields; return the names another connection owns."""
        with self._lock:
            taken = {n for n in names if self._owners.get(n, conn_id) != conn_id}
            if not taken:
                for n in names:
                    self._owners[n] = conn_id
            return taken

    def set_register_offset(self, offset: int) -> None:
        """Command registers at ``offset`` (0, or 24 for the upper range)."""
        with self._lock:
            self.script.register_offset = offset

    def write_inputs(self, arrival_s: float, values: dict[str, Any]) -> None:
        with self._lock:
            self._write_counter += 1
            heapq.heappush(self._writes, _Write(arrival_s, self._write_counter, values))

    def drop_connections(self) -> None:
        """Close every client connection (RTDE, dashboard, script); keep listening."""
        with self._lock:
            conns = list(self._rtde)
            others = list(self._others)
        for conn in conns:
            conn.close()
        for sock in others:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                sock.close()

    def stall(self, seconds: float) -> None:
        """Stop streaming state packages on the open connections for ``seconds``.

        The controller keeps running; connections opened during the stall stream normally
        (a client that reconnects after its 2.5 s timeout finds a working controller).
        """
        until = time.monotonic() + float(seconds)
        with self._lock:
            for conn in self._rtde:
                conn.stalled_until = until

    # -- dashboard and script port --------------------------------------------------------
    def _dashboard_reply(self, line: str) -> str | None:
        playing = self.script.playing
        answer = self.programs.reply(line.strip(), playing)
        if answer is not None:
            return answer
        return _dashboard_reply(
            line,
            version=self.version,
            serial_number=self.identity.serial_number,
            model=self.identity.model_name,
            playing=playing,
        )

    def _dashboard_loop(self, client: socket.socket) -> None:
        reader = _LineReader(DASHBOARD_MAX_LINE_BYTES, "dashboard")
        try:
            client.sendall(b"Connected: Universal Robots Dashboard Server\n")
            while not self.stop_event.is_set():
                chunk = client.recv(65536)
                if not chunk:
                    return
                for line in reader.feed(chunk):
                    answer = self._dashboard_reply(line)
                    if answer is None:
                        client.sendall(b"Disconnected\n")
                        return
                    client.sendall(answer.encode() + b"\n")
        except ProtocolError as exc:  # a line over the limit: this client only
            self.log_abuse(str(exc))
        except OSError:
            return
        finally:
            self._forget(client)

    def _script_loop(self, client: socket.socket) -> None:
        reader = _ScriptReader()
        try:
            while not self.stop_event.is_set():
                chunk = client.recv(65536)
                if not chunk:
                    return
                for program in reader.feed(chunk):
                    self.programs.script_uploaded()
                    self._program_uploaded(program)
        except ProtocolError as exc:  # a line or program over the limits: this client only
            self.log_abuse(str(exc))
        except OSError:
            return
        finally:
            self._forget(client)

    def _program_uploaded(self, program: str) -> None:
        with self._lock:
            self.script.program_start_s = time.monotonic() - self.t0 + _PROGRAM_START_DELAY_S
        self.log(f"program uploaded ({len(program)} characters); starting it")

    def _request_program_stop(self) -> None:
        with self._lock:
            self._write_counter += 1
            write = _Write(time.monotonic() - self.t0, self._write_counter, {}, stop_program=True)
            heapq.heappush(self._writes, write)

    # -- the controller clock --------------------------------------------------------------
    def _static_values(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for name, kind in RTDE_OUTPUT_TYPES.items():
            code, count = RTDE_TYPE_CODES[kind]
            zero: Any = 0.0 if code == "d" else (False if code == "?" else 0)
            values[name] = zero if count == 1 else (zero,) * count
        values.update(
            robot_mode=7,
            safety_mode=1,
            safety_status=1,
            safety_status_bits=1,
            joint_mode=(_JOINT_RUNNING_MODE,) * 6,
            speed_scaling=1.0,
            target_speed_fraction=1.0,
            joint_temperatures=(32.0,) * 6,
            actual_main_voltage=48.0,
            actual_robot_voltage=48.0,
            actual_joint_voltage=(47.5,) * 6,
            actual_tool_accelerometer=(0.0, 0.0, 9.81),
            tool_temperature=30.0,
        )
        return values

    def _drain_inputs(self) -> None:
        """Let the RTDE readers hand over what reached the socket before this boundary.

        A controller's intake reads the register as the network left it; here a reader
        thread must first get the interpreter, which the clock thread holds for much of
        its cycle: a command that arrived (kernel stamp) just before the boundary could be
        taken a cycle late. Waits while a reader holds a package or a socket holds unread
        bytes, at most :data:`_DRAIN_S`."""
        deadline = time.monotonic() + _DRAIN_S
        while True:
            with self._lock:
                conns = list(self._rtde)
            if not any(c.handling or _unread(c.sock) for c in conns):
                return
            if time.monotonic() >= deadline:
                self.stats["drain_timeouts"] += 1
                return
            time.sleep(2e-5)

    def _apply_writes(self, boundary_s: float) -> tuple[_Write | None, bool, bool]:
        """Apply the register writes that arrived before this boundary.

        Returns the latest command write (or None), whether a register owner disconnected,
        and whether a program stop was requested.
        """
        latest: _Write | None = None
        disconnected = False
        stop_program = False
        with self._lock:
            while self._writes and self._writes[0].arrival_s <= boundary_s:
                write = heapq.heappop(self._writes)
                if write.disconnect:
                    disconnected = True
                    continue
                if write.stop_program:
                    stop_program = True
                    continue
                self.script.inputs.update(write.values)
                self.script.watchdogs.note(write.values, write.arrival_s)
                if self.script.command_register in write.values:
                    latest = write
            self.script.start_if_due(boundary_s)
        return latest, disconnected, stop_program

    def _packet_values(self, packet: Any) -> dict[str, Any]:
        values = dict(self._static)
        q = _tuple6(packet.q_rad)
        qd = _tuple6(packet.qd_rad_s)
        tq = _tuple6(packet.q_target_rad)
        tqd = _tuple6(packet.qd_target_rad_s)
        rate = 1.0 / self.period_s
        values["timestamp"] = float(packet.sample_time_s)
        values["actual_q"] = q
        values["actual_qd"] = qd
        values["target_q"] = tq
        values["target_qd"] = tqd
        values["target_qdd"] = tuple(
            [(a - b) * rate for a, b in zip(tqd, self._prev_target_qd, strict=True)]
        )
        values["actual_qdd"] = tuple(
            [(a - b) * rate for a, b in zip(qd, self._prev_actual_qd, strict=True)]
        )
        self._prev_target_qd = tqd
        self._prev_actual_qd = qd
        script = self.script
        playing = script.playing
        values["runtime_state"] = script.runtime_state
        values["robot_status_bits"] = 3 if playing else 1
        values["actual_execution_time"] = 0.4e-3
        values.update(script.output_registers())
        if self._tcp_wanted and script.kin is not None:
            values.update(tcp_values(script.kin, packet))
        return values

    def output_recipe_set(self) -> None:
        """A connection set up its output recipe: compute the TCP fields only while a
        connection asks for them (a pose and a Jacobian per cycle)."""
        with self._lock:
            self._tcp_wanted = any(c.wants_tcp for c in self._rtde)

    def _program_stopped(self) -> None:
        """Report the program stops of this cycle: stats and ground truth."""
        for stop in self.script.events:
            record = json_safe({"event": "program_stop", **stop})
            self.stats["program_stops"].append(record)
            self._truth.line(record)
        self.script.events.clear()

    def _record_rates(self, result: Any) -> None:
        """Keep the flange rate of the physics substeps for the gyro twin (last second)."""
        if self._gyro is None:
            return
        t = getattr(result, "substep_time_s", None)
        w = getattr(result, "flange_rate_rad_s", None)
        if t is None or w is None:
            return
        with self._rates_ready:
            self._rate_t.append(np.asarray(t, dtype=np.float64))
            self._rate_w.append(np.asarray(w, dtype=np.float64))
            keep = max(4, int(1.0 / self.period_s))
            if len(self._rate_t) > keep:
                del self._rate_t[:-keep]
                del self._rate_w[:-keep]
            self._rates_upto_s = float(self.sim.time_s)
            self._rates_ready.notify_all()

    def flange_rate(self, times_s: Any) -> np.ndarray:
        """Physical flange angular rate at controller times ``times_s``, shape (n, 3), rad/s.

        Linear interpolation between physics substeps; before the first recorded substep
        and after the last the end values are held. Waits (at most two controller periods)
        until the simulation has computed the requested times: a cycle computes its whole
        period at once, shortly after the period starts.
        """
        times = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        latest = float(times.max()) if times.size else -math.inf
        with self._rates_ready:
            self._rates_ready.wait_for(
                lambda: self._rates_upto_s >= latest or self.stop_event.is_set(),
                timeout=2 * self.period_s,
            )
            if not self._rate_t:
                return np.zeros((times.size, 3))
            t = np.concatenate(self._rate_t)
            w = np.concatenate(self._rate_w)
        return np.stack([np.interp(times, t, w[:, i]) for i in range(3)], axis=1)

    def _write_truth(self) -> None:
        """Append new and changed ground-truth records (one JSON line each, flushed)."""
        self._truth.commands(self.sim, self.script.silent_ids, self.script.truth_kinds)

    def _write_meta(self) -> None:
        self._truth.line(
            {
                "event": "meta",
                "robot": self.robot,
                "host": self.host,
                "version": ".".join(map(str, self.version)),
                "period_s": self.period_s,
                "t0_monotonic_s": self.t0,
                "pid": os.getpid(),
            }
        )

    def _start_gyro(self) -> None:
        """Start the gyro twin (``timedexec.twins._gyro``) fed by the flange rate."""
        if self._imu_link is None:
            return
        from timedexec.twins import _gyro as gyro_mod

        server = self

        def rate_source(t0_s: float, t1_s: float) -> np.ndarray:
            # The gyro asks on its own time base (s since its start_time_s, host clock) for
            # a grid of k values on [t0_s, t1_s); one per 8 kHz sample is exact.
            k = max(1, math.ceil((t1_s - t0_s) * _GYRO_GRID_HZ - 1e-9))
            base = gyro.start_time_s - server.t0
            grid = base + t0_s + np.arange(k) * ((t1_s - t0_s) / k)
            return server.flange_rate(grid)

        self._gyro = True  # record rates from the first cycle on
        gyro = gyro_mod.GyroTwin(rate_source, link_path=self._imu_link, seed=self._seed)
        gyro.start()
        self._gyro = gyro
        self._truth.line(
            {
                "event": "gyro",
                "link_path": self._imu_link,
                "slave_path": gyro.slave_path,
                "start_time_s": gyro.start_time_s,
                "true_rate_hz": gyro.true_rate_hz,
                "clock_error_ppm": gyro.clock_error_ppm,
                "dlpf_group_delay_s": gyro.source.dlpf_group_delay_s,
            }
        )

    def serve(self, *, ready: Callable[[dict[str, Any]], None] | None = None) -> None:
        """Run until :attr:`stop_event` is set (bind first)."""
        if not self._listeners:
            self.bind()
        # Real-time priority for this thread before any other starts: threads inherit it,
        # so no normal-priority thread can hold the GIL while preempted (priority inversion).
        self.stats["realtime"] = try_realtime(self.rt_priority)
        # Full collections walk only what was made since (see quiet_gc): 10-35 ms each
        # otherwise, every few tens of seconds, 5-17 missed cycles.
        self._gc_pauses = self._gc_quiet.enter_context(quiet_gc())
        # A controller's CPU never sleeps deeply; an idle VM's does, and wakes the cycle
        # late by milliseconds (see fast_wakeup).
        self.stats["fast_wakeup"] = self._gc_quiet.enter_context(fast_wakeup())
        self.t0 = time.monotonic() + 0.005
        self._write_meta()
        self._start_gyro()
        for thread in self._threads:
            thread.start()
        if ready is not None:
            ready(
                {
                    "t0_monotonic_s": self.t0,
                    "period_s": self.period_s,
                    "version": list(self.version),
                    "host": self.host,
                    "pid": os.getpid(),
                }
            )
        try:
            self._clock_loop()
        finally:
            self.close()

    def _peek_packet(self) -> Any:
        """The state package of the current cycle boundary, before the cycle is computed.

        ``ControllerSim.cycle()`` returns the package sampled at its start only after it
        has computed the whole period's physics (about 0.7 ms for a 2 ms e-Series cycle,
        3.6 ms for 8 ms), but the package must go on the wire as early as 0.04 ms after the
        boundary. The package depends only on the state at the boundary, so it is read
        here; :meth:`_clock_loop` checks it against what ``cycle()`` returns.
        """
        sim = self.sim
        peek = getattr(sim, "peek_packet", None)
        if callable(peek):
            return peek()
        t_s = float(sim.time_s)
        extra = None
        effects = getattr(sim, "effects", None)
        if effects is not None and hasattr(effects, "get"):
            extra = effects.get("response_extra_cycle")
        extra_s = self.period_s * float(getattr(extra, "cycles", 0)) if extra is not None else 0.0
        q = np.array(sim.q_rad, dtype=np.float64)
        qd = np.array(sim.qd_rad_s, dtype=np.float64)
        return _PeekedPacket(
            cycle=int(getattr(sim, "cycle_index", round(t_s / self.period_s))),
            sample_time_s=t_s,
            send_time_s=t_s + float(sim.packing_phase_s(t_s)) + extra_s,
            q_rad=q,
            qd_rad_s=qd,
            q_target_rad=np.array(getattr(sim, "_ref_q", q), dtype=float),
            qd_target_rad_s=np.array(getattr(sim, "_ref_v", qd), dtype=float),
        )

    def _check_peek(self, peeked: Any, packet: Any) -> None:
        same = (
            int(peeked.cycle) == int(packet.cycle)
            and abs(float(peeked.send_time_s) - float(packet.send_time_s)) < 1e-9
            and _same_array(peeked.q_rad, packet.q_rad)
            and _same_array(peeked.qd_rad_s, packet.qd_rad_s)
            and _same_array(peeked.q_target_rad, packet.q_target_rad)
            and _same_array(peeked.qd_target_rad_s, packet.qd_target_rad_s)
        )
        if not same:
            self.stats["peek_mismatches"] += 1
            if self.stats["peek_mismatches"] == 1:
                self.log(
                    f"cycle {packet.cycle}: the package sent early differs from the one "
                    "ControllerSim.cycle() returned; state on the wire may be off by a cycle"
                )

    def _sender_loop(self) -> None:
        """Put each package on the wire at its send time (own thread, so a long cycle
        computation does not delay it beyond the interpreter's switch interval)."""
        _set_timer_slack_ns(1000)
        stats = self.stats
        last_send = math.nan
        while True:
            item = self._send_queue.get()
            if item is None:
                return
            target = self.t0 + item.send_time_s
            _sleep_until(target)
            now = time.monotonic()
            lateness = now - target
            if lateness > _LATE_S:
                stats["late_sends"] += 1
            stats["max_lateness_s"] = max(stats["max_lateness_s"], lateness)
            # Worst stall: the largest gap between two consecutive packages put on the wire.
            if now - last_send > stats["max_send_gap_s"]:
                stats["max_send_gap_s"] = now - last_send
            last_send = now
            with self._lock:
                conns = [c for c in self._rtde if c.stalled_until <= now]
            for conn in conns:
                conn.send_state(item.cycle, item.values)

    def _schedule(self, packet: Any) -> None:
        self._send_seq += 1
        values = self._packet_values(packet)
        self._send_queue.put(
            _Send(float(packet.send_time_s), self._send_seq, int(packet.cycle), values)
        )

    def _clock_loop(self) -> None:
        """Real-time loop: one ``ControllerSim.cycle()`` per controller period.

        At boundary k the register writes that arrived before it are handed to the
        simulation, then ``cycle()`` computes the period k -> k+1. Package k+1 is read
        right after (:meth:`_peek_packet`) and queued for the sender thread, which puts it
        on the wire at its send time.
        """
        _set_timer_slack_ns(1000)
        sim = self.sim
        truth_every = max(1, round(0.01 / self.period_s))
        sender = threading.Thread(target=self._sender_loop, name="twin-sender", daemon=True)
        sender.start()
        try:
            peeked = self._peek_packet()
            self._schedule(peeked)
            while not self.stop_event.is_set():
                boundary_s = float(sim.time_s)
                _sleep_until(self.t0 + boundary_s)
                self._drain_inputs()
                write, disconnected, stop_program = self._apply_writes(boundary_s)
                self.script.step(
                    boundary_s,
                    None if write is None else write.arrival_s,
                    disconnected,
                    stop_program,
                )
                if self.script.events:
                    self._program_stopped()
                result = sim.cycle()
                lag_s = time.monotonic() - self.t0 - float(sim.time_s)
                if lag_s > self.stats["max_cycle_lag_s"]:
                    self.stats["max_cycle_lag_s"] = lag_s
                    self.stats["max_cycle_lag_at_s"] = boundary_s
                self._check_peek(peeked, result.packet)
                self.script.after_cycle()
                self._record_rates(result)
                self.stats["cycles"] += 1
                if self.stats["cycles"] % truth_every == 0:
                    self._write_truth()
                peeked = self._peek_packet()
                self._schedule(peeked)
        finally:
            self._send_queue.put(None)
            sender.join(1.0)
            self._write_truth()

    def close(self) -> None:
        self.stop_event.set()
        self._gc_quiet.close()
        for sock in self._listeners:
            with contextlib.suppress(OSError):
                sock.close()
        self._listeners.clear()
        self.drop_connections()
        gyro, self._gyro = self._gyro, None
        with self._rates_ready:
            self._rates_ready.notify_all()
        if gyro is not None and gyro is not True:
            with contextlib.suppress(Exception):
                gyro.close()
        self._truth.close()
