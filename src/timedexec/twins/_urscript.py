"""The program side of the simulated UR controller: the ``ur_rtde`` control script, script
uploads on port 30003 and the dashboard server's replies.

The ``ur_rtde`` control interface uploads a URScript program and then drives it through
RTDE registers. The twin does not interpret the script text; it recognises a complete
upload (:class:`_ScriptReader`) and emulates the script's main loop
(:class:`_ControlScript`): command id in ``input_int_register_0`` (24 with upper-range
registers), arguments in the double registers, acknowledgement in
``output_int_register_0`` (1 ready, 2 done), ``IS_STEADY`` in ``output_int_register_1``,
async progress in ``output_int_register_2``. Registers are sampled once per controller
cycle, not queued.

Input from the script and dashboard ports is read line by line with per-connection limits
(:class:`_LineReader`): a line longer than the limit, or a program larger than its limit,
is a :class:`~timedexec.errors.ProtocolError` and the server closes that connection. Each
byte is looked at once, so a client that sends megabytes without a newline costs the twin
no more CPU than one that sends the same bytes as lines (the unbounded buffer it replaced
rescanned everything on every read and starved the RTDE stream of the other clients).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import sys
import threading
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from timedexec.errors import ConfigError, ProtocolError
from timedexec.robots import RobotSpec
from timedexec.twins._cartesian import Kinematics, LinearMove, ToolSpeed, servo_target
from timedexec.twins._rtde import RTDE_INPUT_TYPES
from timedexec.twins._watchdog import Watchdogs

_CMD_NO_CMD = 0
_CMD_MOVEJ = 1
_CMD_MOVEL = 3
_CMD_SPEEDJ = 9
_CMD_SPEEDL = 10
_CMD_SERVOJ = 11
_CMD_SPEED_STOP = 15
_CMD_SERVO_STOP = 16
_CMD_SERVOL = 24
_CMD_STOPL = 33
_CMD_STOPJ = 34
_CMD_SET_WATCHDOG = 35
_CMD_IS_STEADY = 47
_CMD_WATCHDOG = 99
_CMD_STOP_SCRIPT = 255
#: Commands the script processes every cycle and only acknowledges with "ready".
_REALTIME_CMDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, *range(66, 72)})
#: Motion commands and stops: each ends what the script's motion threads were doing.
_MOTION_CMDS = frozenset(
    {
        _CMD_MOVEJ,
        _CMD_MOVEL,
        _CMD_SPEEDJ,
        _CMD_SPEEDL,
        _CMD_SERVOJ,
        _CMD_SERVOL,
        _CMD_SPEED_STOP,
        _CMD_SERVO_STOP,
        _CMD_STOPL,
        _CMD_STOPJ,
    }
)
#: Stands for the sim command id of a moveL that is still sending setpoints.
_MOTION_RUNNING = -1
#: Time over which a moveL's final position setpoint is reached, s.
_MOVEL_SETTLE_S = 0.02

_SIGNAL_BUSY = 0
_SIGNAL_READY = 1
_SIGNAL_DONE = 2

_RUNTIME_STOPPED = 1
_RUNTIME_PLAYING = 2
_RUNTIME_PAUSED = 3

#: Deceleration used when the program is stopped while the arm moves, rad/s².
_PROGRAM_STOP_DECELERATION_RAD_S2 = 4.0
#: Delay from the end of a script upload to ``runtime_state == PLAYING``, s.
_PROGRAM_START_DELAY_S = 0.02

#: Longest line the dashboard server takes, bytes. Its commands are short (``load
#: /programs/x.urp``, ``popup <text>``, ``addToLog <message>``): 64 KiB is generous.
DASHBOARD_MAX_LINE_BYTES = 64 * 2**10
#: Longest line of an uploaded script, bytes (URScript lines are short).
SCRIPT_MAX_LINE_BYTES = 64 * 2**10
#: Largest program the script port collects, characters (``ur_rtde`` 1.6.5 uploads a
#: control script of 38,543: a hundred times that is room for any real program).
SCRIPT_MAX_PROGRAM_BYTES = 4 * 2**20


class _SimLike(Protocol):
    """The part of :class:`timedexec.sim.ControllerSim` the twin uses."""

    period_s: float
    time_s: float

    @property
    def q_rad(self) -> Any: ...

    @property
    def qd_rad_s(self) -> Any: ...

    def packing_phase_s(self, t_s: float) -> float: ...

    def submit(self, command: Any, *, arrival_s: float | None = None) -> int: ...

    def cycle(self) -> Any: ...

    def is_steady(self) -> bool: ...

    def truth_records(self) -> list[dict[str, Any]]: ...


def _command_types(sim: object) -> Any:
    """The command classes (SpeedJ, MoveJ ...) that belong to ``sim``'s implementation."""
    module = sys.modules.get(type(sim).__module__)
    if module is not None and hasattr(module, "SpeedJ"):
        return module
    return importlib.import_module("timedexec.sim")


def _finite(value: Any) -> bool:
    return value is not None and not (isinstance(value, float) and math.isnan(value))


def _field(event: Any, name: str) -> Any:
    return event[name] if isinstance(event, Mapping) else getattr(event, name)


def _as_record(event: Any) -> dict[str, Any]:
    if isinstance(event, Mapping):
        return dict(event)
    to_dict = getattr(event, "to_dict", None)
    if callable(to_dict):
        record: dict[str, Any] = to_dict()
        return record
    if dataclasses.is_dataclass(event) and not isinstance(event, type):
        return {f.name: getattr(event, f.name) for f in dataclasses.fields(event)}
    return dict(vars(event))


class _LineReader:
    """Complete lines of a byte stream, each byte looked at once, lines of bounded length.

    Parameters
    ----------
    max_line_bytes : int
        Longest line accepted (without its newline).
    what : str
        Names the stream in the error message.
    """

    def __init__(self, max_line_bytes: int, what: str) -> None:
        self.max_line_bytes = max_line_bytes
        self.what = what
        self._partial = bytearray()

    def feed(self, data: bytes) -> list[str]:
        """The lines that ``data`` completes (decoded as UTF-8, bad bytes replaced).

        Raises
        ------
        ProtocolError
            A line is longer than ``max_line_bytes``.
        """
        lines: list[str] = []
        start = 0
        while (end := data.find(b"\n", start)) >= 0:
            if self._partial:
                self._partial += data[start:end]
                raw = bytes(self._partial)
                self._partial.clear()
            else:
                raw = data[start:end]
            self._check(len(raw))
            lines.append(raw.decode("utf-8", errors="replace"))
            start = end + 1
        self._partial += data[start:]
        self._check(len(self._partial))
        return lines

    def _check(self, n: int) -> None:
        if n > self.max_line_bytes:
            raise ProtocolError(
                f"{self.what}: a line of more than {self.max_line_bytes} bytes; closing the "
                "connection"
            )


class _ScriptReader:
    """Programs uploaded to the script port: complete top-level ``def``/``sec`` ... ``end``
    blocks, in order; text outside them is ignored (as the controller's interpreter does).

    Indented ``end`` lines close inner blocks; the top-level ``end`` completes the program
    once its newline has arrived.
    """

    def __init__(
        self,
        *,
        max_line_bytes: int = SCRIPT_MAX_LINE_BYTES,
        max_program_bytes: int = SCRIPT_MAX_PROGRAM_BYTES,
    ) -> None:
        self._lines = _LineReader(max_line_bytes, "script port")
        self.max_program_bytes = max_program_bytes
        self._program: list[str] | None = None
        self._program_bytes = 0

    def feed(self, data: bytes) -> list[str]:
        """The programs that ``data`` completes.

        Raises
        ------
        ProtocolError
            A line or a program longer than the limits.
        """
        programs = []
        for line in self._lines.feed(data):
            if self._program is None:
                if line.startswith(("def ", "sec ")):
                    self._program, self._program_bytes = [line], len(line) + 1
                continue
            self._program.append(line)
            self._program_bytes += len(line) + 1
            if self._program_bytes > self.max_program_bytes:
                raise ProtocolError(
                    f"script port: a program of more than {self.max_program_bytes} bytes "
                    "without its closing 'end'; closing the connection"
                )
            if line.rstrip() == "end":
                programs.append("\n".join(self._program))
                self._program = None
        return programs


def _input_defaults() -> dict[str, Any]:
    """Input registers at power-on: zero of each field's type."""
    inputs: dict[str, Any] = dict.fromkeys(RTDE_INPUT_TYPES, 0)
    for name, kind in RTDE_INPUT_TYPES.items():
        if kind == "DOUBLE":
            inputs[name] = 0.0
        elif kind == "VECTOR6D":
            inputs[name] = (0.0,) * 6
    return inputs


class _ControlScript:
    """The ``ur_rtde`` control script's main loop, run on the simulated controller.

    Follows what the uploaded script does (``ur_rtde`` 1.6.5): ``speedj`` / ``speedl`` are
    re-issued by the script's speed thread with the latest target until a stop, another
    motion command or a program stop (their time argument never ends the motion: it is how
    long each call runs before the thread takes the next target); ``servoj``
    is re-issued to the last target (the arm converges and stays); ``moveL`` follows a
    straight TCP line (:mod:`timedexec.twins._cartesian`); ``setWatchdog`` arms an RTDE
    watchdog that stops the program (:mod:`timedexec.twins._watchdog`).

    State touched by the server's clock thread, or under the server's lock: the runtime
    state, the input registers the RTDE writes landed in, the output registers.
    """

    def __init__(self, sim: _SimLike, log: Callable[[str], None]) -> None:
        self.sim = sim
        self.commands = _command_types(sim)
        self.log = log
        self.period_s = float(sim.period_s)
        spec = getattr(sim, "spec", None)
        #: Kinematics of the simulated robot (None: a custom simulator without a spec; then
        #: TCP values stay zero and Cartesian commands are acknowledged without motion).
        self.kin = Kinematics(spec) if isinstance(spec, RobotSpec) else None
        self._accel_limit_rad_s2 = (
            4.0 * max(spec.qdd_max_rad_s2) if isinstance(spec, RobotSpec) else 40.0
        )
        self.runtime_state = _RUNTIME_STOPPED
        self.program_start_s = math.inf
        self.inputs = _input_defaults()
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.register_offset = 0
        self.pending_op: tuple[int, int | None] | None = None  # (command id, sim command id)
        self.async_op: int | None = None
        self.async_op_counter = 0
        self.watchdogs = Watchdogs()
        #: The Cartesian motion the script's threads run (moveL, speedL), if any.
        self.motion: LinearMove | ToolSpeed | None = None
        self._motion_ids = 0  # sim commands the motion has submitted
        self._last_motion_id: int | None = None
        self._planning: _Planning | None = None
        self._servo_q: np.ndarray | None = None  # last servoL target, rad
        #: The speed thread of speedj: when its running ``speedj(target, a, t)`` returns
        #: (controller time, s; None: no speedj thread), and the newest target the main
        #: loop put in its globals (speeds, acceleration, t, arrival), issued at that return.
        self._speedj_returns_s: float | None = None
        self._speedj_target: tuple[tuple[float, ...], float, float, float] | None = None
        self._speedj_issued: tuple[tuple[float, ...], float, float, float] | None = None
        #: Program stops not yet reported to the server: dicts with time_s, reason, ...
        self.events: list[dict[str, Any]] = []
        #: Whether the server writes ground truth (then the two maps below are kept).
        self.track_truth = False
        #: Sim command ids the script submits on its own each cycle (a Cartesian motion's
        #: setpoints after the first): not written to the ground truth.
        self.silent_ids: set[int] = set()
        #: Kind to report for a sim command id in the ground truth ("MoveL", "SpeedL", ...).
        self.truth_kinds: dict[int, str] = {}

    @property
    def playing(self) -> bool:
        """Whether the program runs (``runtime_state == PLAYING``)."""
        return self.runtime_state == _RUNTIME_PLAYING

    @property
    def command_register(self) -> str:
        """Name of the input register holding the command id."""
        return f"input_int_register_{self.register_offset}"

    def start_if_due(self, boundary_s: float) -> None:
        """Start an uploaded program once its start time is reached (controller time, s)."""
        if self.program_start_s <= boundary_s:
            self.program_start_s = math.inf
            self.runtime_state = _RUNTIME_PLAYING
            self.out_int[0] = _SIGNAL_READY
            self.pending_op = None

    def _reg_d(self, i: int) -> float:
        return float(self.inputs[f"input_double_register_{i + self.register_offset}"])

    def _reg_i(self, i: int) -> int:
        return int(self.inputs[f"input_int_register_{i + self.register_offset}"])

    def _submit(self, kind: str, arrival_s: float, **fields: Any) -> int | None:
        command = getattr(self.commands, kind)(**fields)
        try:
            return int(self.sim.submit(command, arrival_s=arrival_s))
        except (ConfigError, ValueError) as exc:
            # A real controller raises a protective stop / script error; the twin refuses
            # the command and reports it, leaving the arm as it was.
            self.log(f"refused {kind}: {exc}")
            return None

    def _stop_motion(self, arrival_s: float) -> None:
        self._cancel_motion()
        if not self.sim.is_steady():
            self._submit("StopJ", arrival_s, deceleration_rad_s2=_PROGRAM_STOP_DECELERATION_RAD_S2)

    def _cancel_motion(self) -> None:
        """End the Cartesian motion (and a moveL still being planned) and the speedj thread:
        the script kills the thread that runs it when another command or a stop comes."""
        self.motion = None
        self._planning = None
        self._speedj_returns_s = None
        self._speedj_target = None

    def _issue_speedj(self, boundary_s: float) -> None:
        """The speed thread's ``speedj(target, a, t)`` with the newest target, from this
        boundary: it returns after ``t`` (rounded up to whole cycles, at least one), or
        with ``t`` = 0 once the target speed is reached (the leading joint's ramp at
        ``a``)."""
        target = self._speedj_target
        assert target is not None
        qd, accel, t_s, arrival = target
        if t_s > 0:
            span = t_s
        else:
            ref = np.asarray(getattr(self.sim, "_ref_v", np.zeros(6)), dtype=float)
            span = float(np.max(np.abs(np.asarray(qd) - ref))) / max(accel, 1e-9)
        cycles = max(1, math.ceil(span / self.period_s - 1e-9))
        self._speedj_returns_s = boundary_s + cycles * self.period_s
        if self._speedj_issued is not target:
            self._speedj_issued = target
            self._submit("SpeedJ", arrival, qd_rad_s=np.array(qd), acceleration_rad_s2=accel)

    def stop_program(self, time_s: float, reason: str, **details: Any) -> None:
        """Stop the program at controller time ``time_s``: runtime state STOPPED, the arm
        decelerates to rest (program-stop ramp), every watchdog removed; the stop is
        reported in :attr:`events`."""
        self.runtime_state = _RUNTIME_STOPPED
        self.pending_op = None
        self.out_int[0] = _SIGNAL_BUSY
        self.watchdogs.clear()
        self._servo_q = None
        self._stop_motion(time_s)
        self.events.append({"time_s": time_s, "reason": reason, **details})

    def step(
        self,
        boundary_s: float,
        write_arrival_s: float | None,
        disconnected: bool,
        stop_program: bool,
    ) -> None:
        """One iteration of the main loop at this cycle boundary (controller time, s).

        ``write_arrival_s`` is the arrival time of the latest write of the command register
        before the boundary (None: no new command), ``disconnected`` whether the register
        owner went away, ``stop_program`` whether the dashboard asked to stop.
        """
        if stop_program:
            self.stop_program(boundary_s, "dashboard stop")
            return
        if self.playing and self.watchdogs:
            dog = self.watchdogs.expired(boundary_s)
            if dog is not None:
                self.log(
                    f"RTDE watchdog: no update of {dog.variable} for more than "
                    f"{dog.timeout_s * 1e3:.0f} ms; action {dog.action!r}"
                )
                self.stop_program(
                    boundary_s,
                    "watchdog",
                    variable=dog.variable,
                    min_frequency_hz=dog.min_frequency_hz,
                    last_update_s=dog.last_update_s,
                )
                if dog.action == "pause":
                    self.runtime_state = _RUNTIME_PAUSED
                return
        if disconnected and write_arrival_s is None:
            self._stop_motion(boundary_s)
        if not self.playing:
            return
        if write_arrival_s is not None:
            self._command(write_arrival_s, boundary_s)
        self._tick(boundary_s)

    def _command(self, arrival: float, boundary_s: float) -> None:
        """Process the command in the registers (written at controller time ``arrival``)."""
        cmd = self._reg_i(0)
        if cmd in (_CMD_NO_CMD, _CMD_WATCHDOG):
            if self.pending_op is None:
                self.out_int[0] = _SIGNAL_READY
            return
        if cmd == _CMD_STOP_SCRIPT:
            self.stop_program(arrival, "stopScript")
            return
        if cmd == _CMD_IS_STEADY:
            self.out_int[1] = 1 if self.sim.is_steady() else 0
            self.out_int[0] = _SIGNAL_DONE
            return
        if cmd == _CMD_SET_WATCHDOG:
            self._set_watchdog(arrival)
            return
        q = tuple(self._reg_d(i) for i in range(6))
        if cmd == _CMD_SPEEDL:
            if self.kin is None:
                self.log("speedL needs the robot's kinematics; acknowledged without motion")
            else:
                self._speedl(q)
            self.out_int[0] = _SIGNAL_READY
            return
        if cmd not in _MOTION_CMDS:
            if cmd in _REALTIME_CMDS:
                self.log(f"realtime command {cmd} is not simulated; acknowledged without motion")
                self.out_int[0] = _SIGNAL_READY
            else:
                self.log(f"command {cmd} is not simulated; acknowledged as done without motion")
                self.out_int[0] = _SIGNAL_DONE
            return
        if cmd == _CMD_SPEEDJ:
            # The main loop puts the target in the speed thread's globals; the thread takes
            # it when its running speedj(target, a, t) returns, t after it began, and
            # re-issues speedj with it (t never ends the motion: only a stop or another
            # motion command does). A new thread starts at once.
            if self._speedj_returns_s is None:
                self._cancel_motion()
                self.pending_op = None
                self._servo_q = None
            self._speedj_target = (q, self._reg_d(6), self._reg_d(7), arrival)
            if self._speedj_returns_s is None or boundary_s >= self._speedj_returns_s - 1e-9:
                self._issue_speedj(boundary_s)
            self.out_int[0] = _SIGNAL_READY
            return
        # Every other motion command or stop ends what the script's threads were doing.
        self._cancel_motion()
        self.pending_op = None
        if cmd != _CMD_SERVOL:
            self._servo_q = None
        if cmd == _CMD_SERVOJ:
            self._submit(
                "ServoJ",
                arrival,
                q_rad=np.array(q),
                time_s=self._reg_d(8),
                lookahead_s=self._reg_d(9),
                gain=self._reg_d(10),
            )
            self.out_int[0] = _SIGNAL_READY
        elif cmd == _CMD_SERVOL:
            self._servol(q, arrival)
            self.out_int[0] = _SIGNAL_READY
        elif cmd == _CMD_MOVEJ:
            sim_id = self._submit(
                "MoveJ",
                arrival,
                q_rad=np.array(q),
                speed_rad_s=self._reg_d(6),
                acceleration_rad_s2=self._reg_d(7),
            )
            self._finish_or_wait(cmd, sim_id, asynchronous=self._reg_i(1) != 0)
        elif cmd == _CMD_MOVEL:
            self._plan_movel(q, arrival, asynchronous=self._reg_i(1) != 0)
        else:  # SPEED_STOP, SERVO_STOP, STOPL, STOPJ
            deceleration = self._reg_d(0)
            if cmd == _CMD_SPEED_STOP:
                sim_id = self._submit("SpeedStop", arrival, deceleration_rad_s2=deceleration)
            else:
                # stopl decelerates along the path in the real controller; the twin stops
                # the joints with the same number (rad/s²).
                sim_id = self._submit("StopJ", arrival, deceleration_rad_s2=deceleration)
            asynchronous = cmd in (_CMD_STOPJ, _CMD_STOPL) and self._reg_i(1) != 0
            self._finish_or_wait(cmd, sim_id, asynchronous=asynchronous)

    def _set_watchdog(self, arrival: float) -> None:
        """``rtde_set_watchdog(<command register>, min_frequency, "stop")``."""
        frequency_hz = self._reg_d(0)
        try:
            self.watchdogs.arm(self.command_register, frequency_hz, "stop", arrival)
        except ConfigError as exc:
            self.log(f"refused set_watchdog: {exc}")
        self.out_int[0] = _SIGNAL_DONE

    def _reference_q(self) -> np.ndarray:
        """Joint positions the reference holds now (the physical ones if unknown), rad."""
        peek = getattr(self.sim, "peek_packet", None)
        if callable(peek):
            return np.array(peek().q_target_rad, dtype=float)
        return np.array(self.sim.q_rad, dtype=float)

    def _speedl(self, xd: tuple[float, ...]) -> None:
        """``speedl(xd, a, t)``: the speed thread's target changes; it keeps running."""
        assert self.kin is not None
        accel = self._reg_d(6)
        current = self.motion if isinstance(self.motion, ToolSpeed) else None
        if current is None:
            _, start_speed = self.kin.tcp(self.sim.q_rad, self.sim.qd_rad_s)
        try:
            if current is not None:
                motion = ToolSpeed(self.kin, xd, accel, current.speed)
                motion.qd = current.qd
            else:
                self._cancel_motion()
                self._servo_q = None
                motion = ToolSpeed(self.kin, xd, accel, start_speed)
        except ConfigError as exc:
            self.log(f"refused SpeedL: {exc}")
            return
        self.pending_op = None
        if current is None:
            self._motion_started(motion)
        else:
            self.motion = motion

    def _servol(self, pose: tuple[float, ...], arrival: float) -> None:
        """``servoL(pose, v, a, t, lookahead, gain)``: an IK target fed to servoj."""
        if self.kin is None:
            self.log("servoL needs the robot's kinematics; acknowledged without motion")
            return
        seed = self._servo_q if self._servo_q is not None else self._reference_q()
        try:
            q = servo_target(self.kin, pose, seed)
        except ConfigError as exc:
            self.log(f"refused ServoL: {exc}")
            return
        sim_id = self._submit(
            "ServoJ",
            arrival,
            q_rad=q,
            time_s=self._reg_d(8),
            lookahead_s=self._reg_d(9),
            gain=self._reg_d(10),
        )
        if sim_id is not None:
            self._servo_q = q
            if self.track_truth:
                self.truth_kinds[sim_id] = "ServoL"

    def _plan_movel(self, pose: tuple[float, ...], arrival: float, *, asynchronous: bool) -> None:
        """Check the straight path of a moveL off the clock thread; :meth:`_tick` starts
        the motion once the check is done (a real controller plans before it moves)."""
        if self.kin is None:
            self.log("moveL needs the robot's kinematics; acknowledged as done without motion")
            self.out_int[0] = _SIGNAL_DONE
            return
        planning = _Planning(
            self.kin,
            self._reference_q(),
            pose,
            self._reg_d(6),
            self._reg_d(7),
            asynchronous=asynchronous,
            arrival_s=arrival,
        )
        self._planning = planning
        self.pending_op = (_CMD_MOVEL, None)
        self.out_int[0] = _SIGNAL_BUSY
        planning.start()

    def _motion_started(self, motion: LinearMove | ToolSpeed) -> None:
        self.motion = motion
        self._motion_ids = 0
        self._last_motion_id = None

    def _tick(self, boundary_s: float) -> None:
        """The threads' work for this cycle: re-issue speedj when its call returns; start
        a planned moveL, then hand the controller the joint command of the coming cycle."""
        returns = self._speedj_returns_s
        if returns is not None and boundary_s >= returns - 1e-9:
            self._issue_speedj(boundary_s)
        planning = self._planning
        if planning is not None and planning.done:
            self._planning = None
            if planning.error is not None:
                self.log(f"refused MoveL: {planning.error}")
                self.pending_op = None
                self.out_int[0] = _SIGNAL_DONE
            else:
                move = planning.move
                assert move is not None
                move.start_s = boundary_s
                self._motion_started(move)
                if planning.asynchronous:
                    self.pending_op = None
                    self.async_op = _MOTION_RUNNING
                    self.async_op_counter += 1
                    self.out_int[0] = _SIGNAL_DONE
        motion = self.motion
        if motion is None:
            return
        if isinstance(motion, LinearMove):
            qd, accel = motion.joint_speeds(boundary_s, self.period_s)
        else:
            qd, accel = motion.joint_speeds(self.sim.q_rad, self.period_s)
        accel = min(max(accel, 0.1), self._accel_limit_rad_s2)
        sim_id = self._submit("SpeedJ", boundary_s, qd_rad_s=qd, acceleration_rad_s2=accel)
        if sim_id is not None and isinstance(motion, LinearMove) and motion.finished:
            # The end of a moveL: the goal's joints as a position setpoint (the speed loops
            # lose a little on the way), reached over a few cycles.
            sim_id = self._submit(
                "ServoJ",
                boundary_s + 1e-9,
                q_rad=motion.q,
                time_s=_MOVEL_SETTLE_S,
                lookahead_s=0.1,
                gain=300.0,
            )
        if sim_id is None:  # the controller refused a setpoint: stop there
            self._stop_motion(boundary_s)
            self._motion_done(None)
            return
        if self.track_truth:
            if self._motion_ids == 0:
                self.truth_kinds[sim_id] = motion.kind
            else:
                self.silent_ids.add(sim_id)
        self._motion_ids += 1
        self._last_motion_id = sim_id
        if motion.finished:
            self.motion = None
            self._motion_done(sim_id)

    def _motion_done(self, sim_id: int | None) -> None:
        """A moveL has sent its last setpoint: a blocking or async moveL is done once that
        setpoint is reached and the arm is steady (refused: at once)."""
        if self.pending_op is not None and self.pending_op[0] == _CMD_MOVEL:
            if sim_id is None:
                self.pending_op = None
                self.out_int[0] = _SIGNAL_DONE
            else:
                self.pending_op = (_CMD_MOVEL, sim_id)
        if self.async_op == _MOTION_RUNNING:
            self.async_op = sim_id

    def _finish_or_wait(self, cmd: int, sim_id: int | None, *, asynchronous: bool) -> None:
        if sim_id is None:
            self.pending_op = None
            self.out_int[0] = _SIGNAL_DONE
        elif asynchronous:
            self.pending_op = None
            self.async_op = sim_id
            self.async_op_counter += 1
            self.out_int[0] = _SIGNAL_DONE
        else:
            self.pending_op = (cmd, sim_id)
            self.out_int[0] = _SIGNAL_BUSY

    def _op_finished(self, sim_id: int | None) -> bool:
        """A blocking command is done once its reference has started and the arm is still
        (a moveL still sending setpoints, ``None`` or :data:`_MOTION_RUNNING`, is not)."""
        if sim_id is None or sim_id == _MOTION_RUNNING:
            return False
        record = self._truth_record(sim_id)
        if record is None:
            return False
        start = record.get("reference_start_s")
        if start is None or not _finite(start) or self.sim.time_s < float(start):
            return False
        return bool(self.sim.is_steady())

    def _truth_record(self, sim_id: int) -> dict[str, Any] | None:
        truth = getattr(self.sim, "truth", None)
        if truth is not None:
            for event in reversed(truth):
                if int(_field(event, "id")) == sim_id:
                    return _as_record(event)
            return None
        for record in reversed(self.sim.truth_records()):
            if int(record["id"]) == sim_id:
                return dict(record)
        return None

    def after_cycle(self) -> None:
        """Signal blocking commands done and async progress once the cycle is computed."""
        if self.pending_op is not None and self._op_finished(self.pending_op[1]):
            self.pending_op = None
            self.out_int[0] = _SIGNAL_DONE
        if self.async_op is not None:
            running = not self._op_finished(self.async_op)
            op_id = self.async_op_counter & 0xFF
            self.out_int[2] = (op_id << 24) | ((1 << 15) if running else 0)
            if not running:
                self.async_op = None

    def output_registers(self) -> dict[str, Any]:
        """The output registers a state package carries (ints 0-2, doubles 0-5)."""
        values: dict[str, Any] = {}
        for i in range(3):
            values[f"output_int_register_{i + self.register_offset}"] = self.out_int[i]
        for i in range(6):
            values[f"output_double_register_{i + self.register_offset}"] = self.out_double[i]
        return values


class _Planning:
    """A moveL's path check, run in its own thread (a few milliseconds of kinematics that
    must not hold up the controller clock). :attr:`done` once finished; then either
    :attr:`move` or :attr:`error` is set."""

    def __init__(
        self,
        kin: Kinematics,
        q_start_rad: np.ndarray,
        pose: tuple[float, ...],
        speed_m_s: float,
        acceleration_m_s2: float,
        *,
        asynchronous: bool,
        arrival_s: float,
    ) -> None:
        self.asynchronous = asynchronous
        self.move: LinearMove | None = None
        self.error: str | None = None
        self.done = False
        self._args = (kin, q_start_rad, pose, speed_m_s, acceleration_m_s2, arrival_s)

    def start(self) -> None:
        threading.Thread(target=self._run, name="twin-movel-plan", daemon=True).start()

    def _run(self) -> None:
        try:
            move = LinearMove(*self._args)
            move.check()
            self.move = move
        except ConfigError as exc:
            self.error = str(exc)
        except Exception as exc:  # a bug must not leave the client waiting 300 s
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.done = True


def _dashboard_reply(
    line: str,
    *,
    version: tuple[int, int, int, int],
    serial_number: str,
    model: str,
    playing: bool,
) -> str | None:
    """The dashboard server's answer to one command line (None: ``quit``, disconnect).

    Program commands (``load``, ``play``, ``pause``, ``stop``, ``programState``, ``get
    loaded program``) are answered by :class:`timedexec.twins._urprograms.ProgramStore`
    before this is asked."""
    cmd = line.strip()
    low = cmd.lower()
    major, minor, bugfix, build = version
    if low == "polyscopeversion":
        return f"URSoftware {major}.{minor}.{bugfix}.{build} (Oct 18 2022)"
    if low == "get serial number":
        return serial_number
    if low == "get robot model":
        return model
    if low == "is in remote control":
        return "true"
    if low == "robotmode":
        return "Robotmode: RUNNING"
    if low == "safetymode":
        return "Safetymode: NORMAL"
    if low == "safetystatus":
        return "Safetystatus: NORMAL"
    if low == "running":
        return f"Program running: {str(playing).lower()}"
    if low == "power on":
        return "Powering on"
    if low == "power off":
        return "Powering off"
    if low == "brake release":
        return "Brake releasing"
    if low == "unlock protective stop":
        return "Protective stop releasing"
    if low in ("close popup", "close safety popup"):
        return "closing popup" if low == "close popup" else "closing safety popup"
    if low == "quit":
        return None
    return f"could not understand: '{cmd}'"
