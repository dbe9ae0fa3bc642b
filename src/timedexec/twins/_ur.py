"""A simulated Universal Robots controller that the real ``ur_rtde`` client talks to.

The twin serves RTDE (port 30004), the dashboard server (29999) and the script port (30003)
on one loopback address, and drives the stepped simulated controller
(:class:`timedexec.sim.ControllerSim`) one cycle per controller period on a real-time
clock: controller time ``t`` happens at host time ``t0_monotonic_s + t``
(:func:`time.monotonic`, which is shared by every process on the machine).

What it emulates (see ``docs/ur-twin.md``):

* RTDE protocol version 2: version negotiation, controller version (the robot's catalog
  identity: 3.15.7 for a CB3 UR10, so the client streams at 125 Hz; 5.11.1 for an
  e-Series, 500 Hz), output recipes with the
  real controller's types (``NOT_FOUND`` for unknown names), input recipes numbered per
  connection, input ownership (a second writer gets ``IN_USE``; released on disconnect),
  start/pause, data packages both ways.
* The ``ur_rtde`` control script's main loop (the script text itself is not interpreted):
  command id in ``input_int_register_0`` (or 24 with upper-range registers), arguments in
  the double registers, acknowledgement in ``output_int_register_0`` (1 ready, 2 done),
  ``IS_STEADY`` in ``output_int_register_1``; registers are sampled once per controller
  cycle, not queued, so two commands inside one cycle are seen as the last one.
* The dashboard commands the client sends (``PolyscopeVersion``, ``get serial number``,
  ``is in remote control``, ``stop`` -> ``Stopped`` ...).

Each state package is sampled at a controller cycle boundary and put on the wire at the
simulated controller's send time, so the simulated response delay reaches the client.

The server must run in its own process (the ``ur_rtde`` constructors hold the GIL while
they wait for the server): :class:`URTwin` is a context manager that starts it in a
``multiprocessing`` spawn process; :func:`run_ur_twin` is the blocking entry point used by
``timedexec serve``.

Modules: :mod:`timedexec.twins._rtde` (the RTDE wire format and one client connection),
:mod:`timedexec.twins._urscript` (the control script and the dashboard),
:mod:`timedexec.twins._ur_server` (the server inside the twin's process) and this one (the
process around it and the truth reader).
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Self

from timedexec.errors import ConfigError, DriverError
from timedexec.twins._lifecycle import Twin
from timedexec.twins._ur_server import (
    _DEFAULT_RT_PRIORITY,
    _SWITCH_INTERVAL_S,
    DASHBOARD_PORT,
    DEFAULT_PHYSICS_RATE_HZ,
    RTDE_PORT,
    SCRIPT_PORT,
    UR_CONTROLLER_VERSIONS,
    _check_robot,
    _TwinServer,
)
from timedexec.twins._urprograms import EXTERNAL_CONTROL_PORT

__all__ = [
    "DASHBOARD_PORT",
    "DEFAULT_PHYSICS_RATE_HZ",
    "RTDE_PORT",
    "SCRIPT_PORT",
    "UR_CONTROLLER_VERSIONS",
    "URTwin",
    "read_truth",
    "run_ur_twin",
]


def run_ur_twin(
    robot: str = "ur10",
    host: str = "127.0.0.1",
    *,
    seed: int = 0,
    effects: Any = None,
    q0_rad: Any = None,
    truth_path: str | os.PathLike[str] | None = None,
    imu_link: str | None = None,
    stop_event: threading.Event | Any | None = None,
    ready: Callable[[dict[str, Any]], None] | None = None,
    sim_factory: str | Callable[..., Any] | None = None,
    physics_rate_hz: float | None = DEFAULT_PHYSICS_RATE_HZ,
    rt_priority: int | None = _DEFAULT_RT_PRIORITY,
    external_control: tuple[str, int] = ("127.0.0.1", EXTERNAL_CONTROL_PORT),
) -> None:
    """Serve a simulated UR controller until stopped (blocking; for ``timedexec serve``).

    Parameters
    ----------
    robot : str
        Simulated robot, a key of :data:`UR_CONTROLLER_VERSIONS` (the catalog's UR robots);
        reports its catalog identity: e.g. controller version 3.15.7 (CB3, 125 Hz, 8 ms
        cycle) for the ur10, 5.11.1 (e-Series, 500 Hz, 2 ms cycle) for the ur10e.
    host : str
        Address to listen on (RTDE 30004, dashboard 29999, script 30003).
    seed : int
        Seed of the simulated controller.
    effects : EffectSet, optional
        Effects of the simulated controller (default: the robot's default set).
    q0_rad : array_like, shape (6,), optional
        Start configuration, rad.
    truth_path : path, optional
        JSON-lines file the ground truth is appended to (see :func:`read_truth`).
    imu_link : str, optional
        Path of a pseudo-terminal link for the simulated gyro (``timedexec.twins._gyro``).
    stop_event : threading.Event or multiprocessing.Event, optional
        Stops the server when set. SIGTERM and SIGINT also stop it when this runs in the
        main thread.
    ready : callable, optional
        Called once the server listens, with a dict holding ``t0_monotonic_s`` (host time
        of controller time 0), ``period_s`` and ``version``.
    sim_factory : callable or "module:callable", optional
        Builds the simulated controller (default :class:`timedexec.sim.ControllerSim`);
        called as ``factory(robot, effects=..., q0_rad=..., seed=...)``.
    physics_rate_hz : float or None
        Physics integration rate of the default simulated controller, Hz (None: the gyro's
        8 kHz). 4 kHz keeps a 2 ms e-Series cycle at about a quarter of a core.
    rt_priority : int or None
        SCHED_FIFO priority for the twin's clock and sender threads when the OS allows it
        (Linux as root or with CAP_SYS_NICE; silently normal scheduling otherwise). A real
        controller's cycle runs at real-time priority; on a loaded machine this keeps the
        twin on time. None: never ask.
    external_control : (host, port)
        Where the installed program :data:`EXTERNAL_CONTROL_URP` (an External Control URCap
        node) asks for its script when the dashboard plays it: the PC running ``ur_rtde``
        with ``FLAG_USE_EXT_UR_CAP`` (see :mod:`timedexec.twins._urprograms`).
    """
    server = _TwinServer(
        robot,
        host,
        seed=seed,
        effects=effects,
        q0_rad=q0_rad,
        truth_path=truth_path,
        imu_link=imu_link,
        sim_factory=sim_factory,
        physics_rate_hz=physics_rate_hz,
        rt_priority=rt_priority,
        external_control=(str(external_control[0]), int(external_control[1])),
    )
    server.bind()
    sys.setswitchinterval(_SWITCH_INTERVAL_S)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, lambda *_: server.stop_event.set())
    watcher: threading.Thread | None = None
    if stop_event is not None:

        def watch() -> None:
            while not server.stop_event.is_set():
                if stop_event.wait(0.1):
                    server.stop_event.set()

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
    try:
        server.serve(ready=ready)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _child_main(conn: multiprocessing.connection.Connection, kwargs: dict[str, Any]) -> None:
    """Entry point of the twin process: serve and obey the parent's control pipe."""
    sys.setswitchinterval(_SWITCH_INTERVAL_S)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us through the pipe
    try:
        server = _TwinServer(**kwargs)
        server.bind()
    except Exception as exc:  # report any start failure to the parent, then exit
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    signal.signal(signal.SIGTERM, lambda *_: server.stop_event.set())

    def control() -> None:
        while not server.stop_event.is_set():
            try:
                if not conn.poll(0.1):
                    continue
                message = conn.recv()
            except (EOFError, OSError):
                server.stop_event.set()  # the parent is gone
                return
            kind = message[0]
            if kind == "stop":
                server.stop_event.set()
                return
            if kind == "stall":
                server.stall(message[1])
            elif kind == "drop":
                server.drop_connections()
            elif kind == "stats":
                pass
            conn.send(("ok", server.stats_now()))

    def ready(info: dict[str, Any]) -> None:
        conn.send(("ready", info))
        threading.Thread(target=control, name="twin-control", daemon=True).start()

    server.serve(ready=ready)
    with contextlib.suppress(OSError, BrokenPipeError):
        conn.send(("stopped", server.stats_now()))


class URTwin(Twin):
    """A simulated UR controller in its own process, as a context manager.

    Driven by the verbs every twin shares (:class:`~timedexec.twins.Twin`): ``start``,
    ``stop``, ``kill``, ``stall`` (no state packages for a while) and ``drop`` (close the
    client connections).

    Parameters
    ----------
    robot : str
        Simulated robot, a key of :data:`UR_CONTROLLER_VERSIONS` (ur10: controller version
        3.15.7, 8 ms cycle; the e-Series robots: 5.11.1, 2 ms).
    host : str
        Loopback address to serve on; ports are fixed by the client (30004, 29999, 30003),
        so run one twin per address (127.0.0.2, 127.0.0.3, ... for parallel twins).
    seed, effects, q0_rad, truth_path, imu_link, sim_factory, physics_rate_hz, rt_priority,
    external_control
        See :func:`run_ur_twin`. ``effects`` and ``sim_factory`` must be picklable.
    start_timeout_s : float
        How long to wait for the process to listen, s.

    Attributes
    ----------
    t0_monotonic_s : float
        :func:`time.monotonic` value of controller time 0 (valid in every process).
    period_s : float
        Controller cycle period, s.
    version : tuple of int
        Reported controller version.

    Examples
    --------
    >>> with URTwin("ur10e", "127.0.0.2") as twin:            # doctest: +SKIP
    ...     rtde_r = rtde_receive.RTDEReceiveInterface("127.0.0.2")
    """

    def __init__(
        self,
        robot: str = "ur10",
        host: str = "127.0.0.1",
        *,
        seed: int = 0,
        effects: Any = None,
        q0_rad: Any = None,
        truth_path: str | os.PathLike[str] | None = None,
        imu_link: str | None = None,
        sim_factory: str | Callable[..., Any] | None = None,
        physics_rate_hz: float | None = DEFAULT_PHYSICS_RATE_HZ,
        rt_priority: int | None = _DEFAULT_RT_PRIORITY,
        external_control: tuple[str, int] = ("127.0.0.1", EXTERNAL_CONTROL_PORT),
        start_timeout_s: float = 20.0,
    ) -> None:
        _check_robot(robot)
        self.robot = robot
        self.host = host
        self.truth_path = Path(truth_path) if truth_path is not None else None
        self._kwargs: dict[str, Any] = {
            "robot": robot,
            "host": host,
            "seed": seed,
            "effects": effects,
            "q0_rad": None if q0_rad is None else [float(v) for v in q0_rad],
            "truth_path": None if truth_path is None else str(truth_path),
            "imu_link": imu_link,
            "sim_factory": sim_factory,
            "physics_rate_hz": physics_rate_hz,
            "rt_priority": rt_priority,
            "external_control": (str(external_control[0]), int(external_control[1])),
        }
        self.start_timeout_s = float(start_timeout_s)
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._pipe_lock = threading.Lock()
        self.t0_monotonic_s = math.nan
        self.period_s = math.nan
        self.version = UR_CONTROLLER_VERSIONS[robot]
        self.final_stats: dict[str, Any] = {}

    @property
    def pid(self) -> int | None:
        """Process id of the twin (None before start)."""
        return None if self._process is None else self._process.pid

    @property
    def is_alive(self) -> bool:
        """Whether the twin process runs."""
        return self._process is not None and self._process.is_alive()

    def start(self) -> Self:
        """Start the twin process and wait until it listens."""
        if self._process is not None:
            return self
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        process = ctx.Process(
            target=_child_main, args=(child, self._kwargs), name=f"ur-twin-{self.host}", daemon=True
        )
        process.start()
        child.close()
        self._process, self._conn = process, parent
        deadline = time.monotonic() + self.start_timeout_s
        while True:
            if parent.poll(0.05):
                try:
                    kind, info = parent.recv()
                except EOFError:
                    kind, info = "error", "the twin process exited during start"
                if kind == "ready":
                    self.t0_monotonic_s = float(info["t0_monotonic_s"])
                    self.period_s = float(info["period_s"])
                    return self
                self._reap()
                if "ConfigError" in str(info):
                    raise ConfigError(str(info))
                raise DriverError(f"UR twin on {self.host} failed to start: {info}")
            if not process.is_alive() or time.monotonic() > deadline:
                self._reap()
                raise DriverError(
                    f"UR twin on {self.host} did not start within {self.start_timeout_s} s "
                    "(check that the address is a local loopback address and the ports "
                    "30004/29999/30003 are free)"
                )

    def _request(self, message: tuple[Any, ...], timeout_s: float = 5.0) -> dict[str, Any]:
        if self._conn is None or not self.is_alive:
            raise DriverError(f"UR twin on {self.host} is not running; start it first")
        with self._pipe_lock:
            self._conn.send(message)
            if not self._conn.poll(timeout_s):
                raise DriverError(f"UR twin on {self.host} did not answer {message[0]!r}")
            _, info = self._conn.recv()
        result: dict[str, Any] = info
        return result

    def stall(self, seconds: float) -> None:
        """Stop streaming state packages for ``seconds`` (the controller clock keeps going).

        A stall over 2.5 s makes the ``ur_rtde`` client drop its connection.

        Raises
        ------
        ConfigError
            If ``seconds`` is negative or NaN.
        """
        super().stall(seconds)

    def _stall(self, seconds: float) -> None:
        self._request(("stall", seconds))

    def drop(self) -> None:
        """Close every client connection (RTDE, dashboard, script); keep listening."""
        self._request(("drop",))

    def drop_connections(self) -> None:
        """Close every client connection (RTDE, dashboard, script); keep listening
        (the same as :meth:`drop`)."""
        self.drop()

    def stats(self) -> dict[str, Any]:
        """Clock statistics of the twin: cycles run, late sends, maximum lateness (s)."""
        return self._request(("stats",))

    def kill(self) -> None:
        """Kill the twin process abruptly (SIGKILL), as a crashed controller."""
        if self._process is not None and self._process.is_alive():
            self._process.kill()
        self._reap()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the twin cleanly (closes every connection); idempotent."""
        process, conn = self._process, self._conn
        if process is None:
            return
        if conn is not None and process.is_alive():
            with contextlib.suppress(OSError, BrokenPipeError), self._pipe_lock:
                conn.send(("stop",))
            deadline = time.monotonic() + timeout_s
            while process.is_alive() and time.monotonic() < deadline:
                with contextlib.suppress(OSError, EOFError):
                    if conn.poll(0.05):
                        kind, info = conn.recv()
                        if kind == "stopped":
                            self.final_stats = info
        process.join(max(0.0, timeout_s))
        if process.is_alive():
            process.terminate()
            process.join(2.0)
        self._reap()

    def _reap(self) -> None:
        process, conn = self._process, self._conn
        self._process = self._conn = None
        if process is not None:
            process.join(2.0)
            if process.is_alive():
                process.kill()
                process.join(2.0)
        if conn is not None:
            conn.close()

    def controller_time_s(self, host_time_s: float | None = None) -> float:
        """Controller time at host time ``host_time_s`` (default: now), s."""
        now = time.monotonic() if host_time_s is None else host_time_s
        return now - self.t0_monotonic_s


def read_truth(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[int, dict[str, Any]]]:
    """Read a UR twin's ground-truth file (a view of :func:`~timedexec.twins.read_twin_truth`).

    A line still being written while the twin runs is skipped.

    Returns
    -------
    meta : dict
        The last ``meta`` line: robot, period_s, version and ``t0_monotonic_s`` (host
        :func:`time.monotonic` of controller time 0).
    commands : dict of int to dict
        Latest record per command id (``ControllerSim.truth_records()`` fields: kind,
        arrival_s, intake_s, reference_start_s, onset_s per joint with None for "not yet";
        all in controller time, s).
    """
    from timedexec.twins._truth import read_twin_truth

    truth = read_twin_truth(path)
    return truth["meta"], truth["commands"]
