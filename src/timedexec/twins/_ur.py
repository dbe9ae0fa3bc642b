"""A simulated Universal Robots controller that the real ``ur_rtde`` client talks to.

The twin serves RTDE (port 30004), the dashboard server (29999) and the script port (30003)
on one loopback address, and drives the stepped simulated controller
(:class:`timedexec.sim.ControllerSim`) one cycle per controller period on a real-time
clock: controller time ``t`` happens at host time ``t0_monotonic_s + t``
(:func:`time.monotonic`, which is shared by every process on the machine).

What it emulates (see ``docs/ur-twin.md``):

* RTDE protocol version 2: version negotiation, controller version (3.15.7 for a CB3 UR10,
  so the client streams at 125 Hz; 5.11.1 for a UR10e, 500 Hz), output recipes with the
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
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import heapq
import importlib
import json
import math
import multiprocessing
import multiprocessing.connection
import os
import queue
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

import numpy as np

from timedexec._realtime import try_realtime
from timedexec.errors import ConfigError, DriverError, ProtocolError

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

#: TCP ports a UR controller serves (fixed by the ``ur_rtde`` client).
RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

#: Controller software version the twin reports per robot: (major, minor, bugfix, build).
UR_CONTROLLER_VERSIONS: dict[str, tuple[int, int, int, int]] = {
    "ur10": (3, 15, 7, 106331),
    "ur10e": (5, 11, 1, 108318),
}
_SERIAL_NUMBERS = {"ur10": "2018300001", "ur10e": "20215000001"}
_MODEL_NAMES = {"ur10": "UR10", "ur10e": "UR10"}

# --------------------------------------------------------------------------------------
# RTDE wire format
# --------------------------------------------------------------------------------------

_HEADER = struct.Struct(">HB")
_RTDE_REQUEST_PROTOCOL_VERSION = ord("V")
_RTDE_GET_URCONTROL_VERSION = ord("v")
_RTDE_TEXT_MESSAGE = ord("M")
_RTDE_DATA_PACKAGE = ord("U")
_RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
_RTDE_CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
_RTDE_CONTROL_PACKAGE_START = ord("S")
_RTDE_CONTROL_PACKAGE_PAUSE = ord("P")

#: struct code and element count per RTDE type name.
_TYPE_CODES: dict[str, tuple[str, int]] = {
    "DOUBLE": ("d", 1),
    "UINT64": ("Q", 1),
    "UINT32": ("I", 1),
    "INT32": ("i", 1),
    "UINT8": ("B", 1),
    "BOOL": ("?", 1),
    "VECTOR3D": ("d", 3),
    "VECTOR6D": ("d", 6),
    "VECTOR6INT32": ("i", 6),
    "VECTOR6UINT32": ("I", 6),
}


def _build_type_table() -> tuple[dict[str, str], dict[str, str]]:
    """Output and input field types of a UR controller (RTDE guide, PolyScope 3.15 / 5.11).

    The client decodes packages with its own table, so these types must match the real
    controller's byte for byte: 6D vectors for joint and TCP quantities, 3D for the tool
    accelerometer, payload CoG and elbow, six int32 for ``joint_mode``, uint64 digital bit
    fields, uint32 status bit fields.
    """
    out: dict[str, str] = {"timestamp": "DOUBLE"}
    for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment",
        "actual_q", "actual_qd", "actual_qdd", "actual_current", "actual_moment",
        "actual_current_window", "actual_current_as_torque", "joint_control_output",
        "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose",
        "target_TCP_speed", "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench",
        "payload_inertia", "external_force_torque",
    ):  # fmt: skip
        out[name] = "VECTOR6D"
    for name in ("actual_tool_accelerometer", "payload_cog", "elbow_position", "elbow_velocity"):
        out[name] = "VECTOR3D"
    for name in (
        "actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
        "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
        "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
        "standard_analog_output1", "io_current", "euromap67_24V_voltage",
        "euromap67_24V_current", "tool_analog_input0", "tool_analog_input1",
        "tool_output_current", "tool_temperature", "tcp_force_scalar", "payload",
        "joint_position_deviation_ratio", "collision_detection_ratio",
    ):  # fmt: skip
        out[name] = "DOUBLE"
    for name in ("robot_mode", "safety_mode", "safety_status", "tool_output_voltage"):
        out[name] = "INT32"
    out["joint_mode"] = "VECTOR6INT32"
    for name in ("actual_digital_input_bits", "actual_digital_output_bits"):
        out[name] = "UINT64"
    for name in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "euromap67_input_bits", "euromap67_output_bits", "tool_mode",
        "tool_analog_input_types", "output_bit_registers0_to_31",
        "output_bit_registers32_to_63", "input_bit_registers0_to_31",
        "input_bit_registers32_to_63", "script_control_line", "time_scale_source",
    ):  # fmt: skip
        out[name] = "UINT32"
    for name in ("tool_output_mode", "tool_digital_output0_mode", "tool_digital_output1_mode"):
        out[name] = "UINT8"
    for i in range(48):
        out[f"output_int_register_{i}"] = "INT32"
        out[f"output_double_register_{i}"] = "DOUBLE"
        out[f"input_int_register_{i}"] = "INT32"
        out[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        out[f"output_bit_register_{i}"] = "BOOL"
        out[f"input_bit_register_{i}"] = "BOOL"

    inp: dict[str, str] = {
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(48):
        inp[f"input_int_register_{i}"] = "INT32"
        inp[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        inp[f"input_bit_register_{i}"] = "BOOL"
    return out, inp


_OUTPUT_TYPES, _INPUT_TYPES = _build_type_table()


@dataclasses.dataclass(frozen=True)
class _Recipe:
    """A negotiated recipe: names, their RTDE types and the packing struct."""

    recipe_id: int
    names: tuple[str, ...]
    counts: tuple[int, ...]
    struct: struct.Struct

    @classmethod
    def build(cls, recipe_id: int, names: Sequence[str], table: Mapping[str, str]) -> _Recipe:
        fmt = ">B"
        counts = []
        for name in names:
            code, count = _TYPE_CODES[table[name]]
            fmt += f"{count}{code}" if count > 1 else code
            counts.append(count)
        return cls(recipe_id, tuple(names), tuple(counts), struct.Struct(fmt))

    def pack(self, values: Mapping[str, Any]) -> bytes:
        args: list[Any] = [self.recipe_id]
        for name, count in zip(self.names, self.counts, strict=True):
            if count == 1:
                args.append(values[name])
            else:
                args.extend(values[name])
        body = self.struct.pack(*args)
        return _HEADER.pack(len(body) + 3, _RTDE_DATA_PACKAGE) + body

    def unpack(self, payload: bytes) -> dict[str, Any]:
        """Decode a data package body (recipe id byte included); short bodies decode the
        fields that fit, as the client sends only the values a command uses."""
        if len(payload) < self.struct.size:
            payload = payload + b"\0" * (self.struct.size - len(payload))
        flat = self.struct.unpack(payload[: self.struct.size])
        out: dict[str, Any] = {}
        i = 1
        for name, count in zip(self.names, self.counts, strict=True):
            out[name] = flat[i] if count == 1 else flat[i : i + count]
            i += count
        return out


def _frame(kind: int, payload: bytes) -> bytes:
    return _HEADER.pack(len(payload) + 3, kind) + payload


def _parse_names(raw: bytes) -> list[str]:
    return [n for n in raw.decode("ascii", errors="replace").strip("\0").split(",") if n]


# --------------------------------------------------------------------------------------
# ur_rtde control script emulation
# --------------------------------------------------------------------------------------

_CMD_NO_CMD = 0
_CMD_MOVEJ = 1
_CMD_SPEEDJ = 9
_CMD_SERVOJ = 11
_CMD_SPEED_STOP = 15
_CMD_SERVO_STOP = 16
_CMD_STOPJ = 34
_CMD_IS_STEADY = 47
_CMD_WATCHDOG = 99
_CMD_STOP_SCRIPT = 255
#: Commands the script processes every cycle and only acknowledges with "ready".
_REALTIME_CMDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, *range(66, 72)})

_SIGNAL_BUSY = 0
_SIGNAL_READY = 1
_SIGNAL_DONE = 2

_RUNTIME_STOPPED = 1
_RUNTIME_PLAYING = 2

#: Deceleration used when the program is stopped while the arm moves, rad/s².
_PROGRAM_STOP_DECELERATION_RAD_S2 = 4.0
#: Delay from the end of a script upload to ``runtime_state == PLAYING``, s.
_PROGRAM_START_DELAY_S = 0.02
#: Joint mode reported for every joint: JOINT_RUNNING_MODE.
_JOINT_RUNNING_MODE = 253


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


def _command_types(sim: object) -> Any:
    """The command classes (SpeedJ, MoveJ ...) that belong to ``sim``'s implementation."""
    module = sys.modules.get(type(sim).__module__)
    if module is not None and hasattr(module, "SpeedJ"):
        return module
    return importlib.import_module("timedexec.sim")


def _finite(value: Any) -> bool:
    return value is not None and not (isinstance(value, float) and math.isnan(value))


def _json_safe(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return [_json_safe(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _tuple6(value: Any) -> tuple[float, ...]:
    return tuple(float(v) for v in value)


#: Ground-truth records still open (onsets pending) are rewritten for this long, s.
_TRUTH_OPEN_S = 10.0
#: A package later than this counts as a late send, s.
_LATE_S = 0.5e-3
#: SCHED_FIFO priority of the twin's clock and sender threads (None: normal scheduling).
_DEFAULT_RT_PRIORITY = 10
#: Grid on which the gyro twin is handed the flange rate (its nominal sample rate), Hz.
_GYRO_GRID_HZ = 8000.0
#: Interpreter switch interval in the twin process: bounds how long the physics thread
#: can delay the sender thread, s.
_SWITCH_INTERVAL_S = 0.2e-3


def _truth_complete(record: Mapping[str, Any]) -> bool:
    """Whether a truth record can no longer change."""
    if record.get("superseded"):
        return record.get("intake_s") is None or record.get("reference_start_s") is not None
    if record.get("intake_s") is None or record.get("reference_start_s") is None:
        return False
    onset = record.get("onset_s") or []
    moved = record.get("moved_joints")
    if moved is None:
        return all(v is not None for v in onset)
    return all(onset[j - 1] is not None for j in moved)


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


class _RTDEConnection:
    """One RTDE client connection: handshake in its own thread, data sent by the clock."""

    def __init__(self, server: _TwinServer, sock: socket.socket, conn_id: int) -> None:
        self.server = server
        self.sock = sock
        self.conn_id = conn_id
        self.send_lock = threading.Lock()
        self.output_recipe: _Recipe | None = None
        self.input_recipes: dict[int, _Recipe] = {}
        self.decimation = 1
        self.stalled_until = -math.inf
        self.started = False
        self.closed = False
        self.thread = threading.Thread(target=self._run, name=f"rtde-{conn_id}", daemon=True)

    # -- sending ---------------------------------------------------------------------
    def reply(self, kind: int, payload: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(_frame(kind, payload))

    def send_state(self, cycle: int, values: Mapping[str, Any]) -> None:
        recipe = self.output_recipe
        if not self.started or recipe is None or cycle % self.decimation:
            return
        data = recipe.pack(values)
        with self.send_lock:
            try:
                sent = self.sock.send(data, socket.MSG_DONTWAIT)
            except BlockingIOError:
                sent = 0
            except OSError:
                self.close()
                return
        if sent != len(data):
            # The client stopped reading (its buffer is full): a partial package would
            # desynchronise the stream, so drop the connection as a controller would.
            self.server.log(f"RTDE client {self.conn_id} is not reading; closing it")
            self.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.started = False
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self.sock.close()

    # -- receiving -------------------------------------------------------------------
    def _recv_exact(self, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError("client closed the connection")
            buf += chunk
        return bytes(buf)

    def _run(self) -> None:
        try:
            while not self.closed:
                size, kind = _HEADER.unpack(self._recv_exact(3))
                if size < 3:
                    raise ProtocolError(f"RTDE package size {size} < 3 (header)")
                payload = self._recv_exact(size - 3)
                arrival_s = time.monotonic() - self.server.t0
                self._handle(kind, payload, arrival_s)
        except (OSError, ProtocolError, struct.error) as exc:
            if not self.closed and not isinstance(exc, ConnectionResetError):
                self.server.log(f"RTDE connection {self.conn_id}: {exc}")
        finally:
            self.close()
            self.server.connection_closed(self)

    def _handle(self, kind: int, payload: bytes, arrival_s: float) -> None:
        server = self.server
        if kind == _RTDE_REQUEST_PROTOCOL_VERSION:
            self.reply(kind, b"\x01")
        elif kind == _RTDE_GET_URCONTROL_VERSION:
            self.reply(kind, struct.pack(">4I", *server.version))
        elif kind == _RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
            (frequency_hz,) = struct.unpack(">d", payload[:8])
            names = _parse_names(payload[8:])
            types = [_OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            if "NOT_FOUND" in types or not names:
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            recipe_id = 1 if self.output_recipe is None else self.output_recipe.recipe_id + 1
            self.output_recipe = _Recipe.build(recipe_id, names, _OUTPUT_TYPES)
            rate_hz = 1.0 / server.period_s
            self.decimation = max(1, round(rate_hz / frequency_hz)) if frequency_hz > 0 else 1
            self.reply(kind, bytes([recipe_id]) + ",".join(types).encode())
        elif kind == _RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            names = _parse_names(payload)
            types = [_INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            if "NOT_FOUND" in types or not names:
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            in_use = server.claim_inputs(self.conn_id, names)
            if in_use:
                types = ["IN_USE" if n in in_use else t for n, t in zip(names, types, strict=True)]
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            recipe_id = len(self.input_recipes) + 1
            self.input_recipes[recipe_id] = _Recipe.build(recipe_id, names, _INPUT_TYPES)
            if recipe_id == 1 and names[0] in ("input_int_register_0", "input_int_register_24"):
                # ur_rtde's first recipe starts with the command register: 24 means the
                # client uses the upper register range (FLAG_UPPER_RANGE_REGISTERS).
                server.set_register_offset(int(names[0].rsplit("_", 1)[1]))
            self.reply(kind, bytes([recipe_id]) + ",".join(types).encode())
        elif kind == _RTDE_CONTROL_PACKAGE_START:
            self.started = self.output_recipe is not None
            self.reply(kind, b"\x01" if self.started else b"\x00")
        elif kind == _RTDE_CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.reply(kind, b"\x01")
        elif kind == _RTDE_DATA_PACKAGE:
            if not payload:
                raise ProtocolError("RTDE data package without recipe id")
            recipe = self.input_recipes.get(payload[0])
            if recipe is None:
                server.log(f"RTDE connection {self.conn_id}: data for unknown recipe {payload[0]}")
                return
            server.write_inputs(arrival_s, recipe.unpack(payload))
        else:
            server.log(f"RTDE connection {self.conn_id}: ignoring package type {kind}")


# --------------------------------------------------------------------------------------
# The server (runs inside the twin process)
# --------------------------------------------------------------------------------------


def _set_timer_slack_ns(slack_ns: int) -> None:
    """Tighten this thread's sleep precision (Linux PR_SET_TIMERSLACK); no-op elsewhere."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(29, slack_ns, 0, 0, 0)


def _check_robot(robot: str) -> None:
    if robot not in UR_CONTROLLER_VERSIONS:
        raise ConfigError(
            f"robot={robot!r} is not a simulated UR; use one of {sorted(UR_CONTROLLER_VERSIONS)}"
        )


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
        log: Callable[[str], None] | None = None,
    ) -> None:
        _check_robot(robot)
        self.robot = robot
        self.host = host
        self.rt_priority = rt_priority
        self.version = UR_CONTROLLER_VERSIONS[robot]
        self._log = log or (lambda msg: print(f"[ur-twin {host}] {msg}", file=sys.stderr))
        self._seed = seed
        if sim_factory is None:
            self.sim = _default_sim_factory(
                robot, effects=effects, q0_rad=q0_rad, seed=seed, physics_rate_hz=physics_rate_hz
            )
        else:
            factory = _resolve_factory(sim_factory)
            self.sim = factory(robot, effects=effects, q0_rad=q0_rad, seed=seed)
        self.commands = _command_types(self.sim)
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
        self._inputs: dict[str, Any] = dict.fromkeys(_INPUT_TYPES, 0)
        for name, kind in _INPUT_TYPES.items():
            if kind == "DOUBLE":
                self._inputs[name] = 0.0
            elif kind == "VECTOR6D":
                self._inputs[name] = (0.0,) * 6
        # control-script state (touched by the clock thread, or under _lock)
        self.runtime_state = _RUNTIME_STOPPED
        self._program_start_s = math.inf
        self._out_int = [0] * 48
        self._out_double = [0.0] * 48
        self._register_offset = 0
        self._pending_op: tuple[int, int] | None = None  # (command id, sim command id)
        self._async_op: int | None = None
        self._async_op_counter = 0
        self._prev_target_qd: tuple[float, ...] = (0.0,) * 6
        self._prev_actual_qd: tuple[float, ...] = (0.0,) * 6
        self._static = self._static_values()
        # ground truth
        self._truth_file = open(truth_path, "a", encoding="utf-8") if truth_path else None  # noqa: SIM115
        self._truth_written: dict[int, str] = {}
        self._truth_open: dict[int, Any] = {}
        self._truth_last_id = 0
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
            "peek_mismatches": 0,
            "max_cycle_lag_s": 0.0,
        }
        self._send_queue: queue.Queue[_Send | None] = queue.Queue()

    def log(self, message: str) -> None:
        self._log(message)

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
            self._register_offset = offset

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
        cmd = line.strip()
        low = cmd.lower()
        major, minor, bugfix, build = self.version
        if low == "polyscopeversion":
            return f"URSoftware {major}.{minor}.{bugfix}.{build} (Oct 18 2022)"
        if low == "get serial number":
            return _SERIAL_NUMBERS[self.robot]
        if low == "get robot model":
            return _MODEL_NAMES[self.robot]
        if low == "is in remote control":
            return "true"
        if low == "stop":
            self._request_program_stop()
            return "Stopped"
        if low == "play":
            return "Starting program"
        if low == "pause":
            return "Pausing program"
        if low == "robotmode":
            return "Robotmode: RUNNING"
        if low == "safetymode":
            return "Safetymode: NORMAL"
        if low == "safetystatus":
            return "Safetystatus: NORMAL"
        if low == "programstate":
            playing = self.runtime_state == _RUNTIME_PLAYING
            return "PLAYING rtde_control" if playing else "STOPPED <unnamed>"
        if low == "running":
            return f"Program running: {str(self.runtime_state == _RUNTIME_PLAYING).lower()}"
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
        if low == "get loaded program":
            return "No program loaded"
        if low == "quit":
            return None
        return f"could not understand: '{cmd}'"

    def _dashboard_loop(self, client: socket.socket) -> None:
        try:
            client.sendall(b"Connected: Universal Robots Dashboard Server\n")
            buf = b""
            while not self.stop_event.is_set():
                chunk = client.recv(4096)
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf:
                    raw, buf = buf.split(b"\n", 1)
                    answer = self._dashboard_reply(raw.decode("utf-8", errors="replace"))
                    if answer is None:
                        client.sendall(b"Disconnected\n")
                        return
                    client.sendall(answer.encode() + b"\n")
        except OSError:
            return
        finally:
            self._forget(client)

    def _script_loop(self, client: socket.socket) -> None:
        text = ""
        try:
            while not self.stop_event.is_set():
                chunk = client.recv(65536)
                if not chunk:
                    return
                text += chunk.decode("utf-8", errors="replace")
                while True:
                    program, rest = _split_program(text)
                    if program is None:
                        break
                    text = rest
                    self._program_uploaded(program)
        except OSError:
            return
        finally:
            self._forget(client)

    def _program_uploaded(self, program: str) -> None:
        with self._lock:
            self._program_start_s = time.monotonic() - self.t0 + _PROGRAM_START_DELAY_S
        self.log(f"program uploaded ({len(program)} characters); starting it")

    def _request_program_stop(self) -> None:
        with self._lock:
            self._write_counter += 1
            write = _Write(time.monotonic() - self.t0, self._write_counter, {}, stop_program=True)
            heapq.heappush(self._writes, write)

    # -- the controller clock --------------------------------------------------------------
    def _static_values(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for name, kind in _OUTPUT_TYPES.items():
            code, count = _TYPE_CODES[kind]
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
                self._inputs.update(write.values)
                if f"input_int_register_{self._register_offset}" in write.values:
                    latest = write
            if self._program_start_s <= boundary_s:
                self._program_start_s = math.inf
                self.runtime_state = _RUNTIME_PLAYING
                self._out_int[0] = _SIGNAL_READY
                self._pending_op = None
        return latest, disconnected, stop_program

    def _reg_d(self, i: int) -> float:
        return float(self._inputs[f"input_double_register_{i + self._register_offset}"])

    def _reg_i(self, i: int) -> int:
        return int(self._inputs[f"input_int_register_{i + self._register_offset}"])

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
        if not self.sim.is_steady():
            self._submit("StopJ", arrival_s, deceleration_rad_s2=_PROGRAM_STOP_DECELERATION_RAD_S2)

    def _script_step(
        self, boundary_s: float, write: _Write | None, disconnected: bool, stop_program: bool
    ) -> None:
        """One iteration of the ur_rtde control script's main loop at this cycle boundary."""
        if stop_program or (disconnected and write is None):
            arrival = boundary_s
            if stop_program:
                self.runtime_state = _RUNTIME_STOPPED
                self._pending_op = None
                self._out_int[0] = _SIGNAL_BUSY
            self._stop_motion(arrival)
            if stop_program:
                return
        if self.runtime_state != _RUNTIME_PLAYING:
            return
        if write is None:
            return
        arrival = write.arrival_s
        cmd = self._reg_i(0)
        if cmd in (_CMD_NO_CMD, _CMD_WATCHDOG):
            if self._pending_op is None:
                self._out_int[0] = _SIGNAL_READY
            return
        if cmd == _CMD_STOP_SCRIPT:
            self.runtime_state = _RUNTIME_STOPPED
            self._pending_op = None
            self._out_int[0] = _SIGNAL_BUSY
            self._stop_motion(arrival)
            return
        q = tuple(self._reg_d(i) for i in range(6))
        if cmd == _CMD_SPEEDJ:
            self._pending_op = None
            self._submit(
                "SpeedJ",
                arrival,
                qd_rad_s=np.array(q),
                acceleration_rad_s2=self._reg_d(6),
                duration_s=self._reg_d(7),
            )
            self._out_int[0] = _SIGNAL_READY
        elif cmd == _CMD_SERVOJ:
            self._pending_op = None
            self._submit(
                "ServoJ",
                arrival,
                q_rad=np.array(q),
                time_s=self._reg_d(8),
                lookahead_s=self._reg_d(9),
                gain=self._reg_d(10),
            )
            self._out_int[0] = _SIGNAL_READY
        elif cmd == _CMD_MOVEJ:
            sim_id = self._submit(
                "MoveJ",
                arrival,
                q_rad=np.array(q),
                speed_rad_s=self._reg_d(6),
                acceleration_rad_s2=self._reg_d(7),
            )
            self._finish_or_wait(cmd, sim_id, asynchronous=self._reg_i(1) != 0)
        elif cmd in (_CMD_SPEED_STOP, _CMD_SERVO_STOP, _CMD_STOPJ):
            deceleration = self._reg_d(0)
            if cmd == _CMD_SPEED_STOP:
                sim_id = self._submit("SpeedStop", arrival, deceleration_rad_s2=deceleration)
            else:
                sim_id = self._submit("StopJ", arrival, deceleration_rad_s2=deceleration)
            self._finish_or_wait(
                cmd, sim_id, asynchronous=cmd == _CMD_STOPJ and self._reg_i(1) != 0
            )
        elif cmd == _CMD_IS_STEADY:
            self._out_int[1] = 1 if self.sim.is_steady() else 0
            self._out_int[0] = _SIGNAL_DONE
        elif cmd in _REALTIME_CMDS:
            self.log(f"realtime command {cmd} is not simulated; acknowledged without motion")
            self._out_int[0] = _SIGNAL_READY
        else:
            self.log(f"command {cmd} is not simulated; acknowledged as done without motion")
            self._out_int[0] = _SIGNAL_DONE

    def _finish_or_wait(self, cmd: int, sim_id: int | None, *, asynchronous: bool) -> None:
        if sim_id is None:
            self._pending_op = None
            self._out_int[0] = _SIGNAL_DONE
        elif asynchronous:
            self._pending_op = None
            self._async_op = sim_id
            self._async_op_counter += 1
            self._out_int[0] = _SIGNAL_DONE
        else:
            self._pending_op = (cmd, sim_id)
            self._out_int[0] = _SIGNAL_BUSY

    def _op_finished(self, sim_id: int) -> bool:
        """A blocking command is done once its reference has started and the arm is still."""
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

    def _after_cycle(self) -> None:
        if self._pending_op is not None and self._op_finished(self._pending_op[1]):
            self._pending_op = None
            self._out_int[0] = _SIGNAL_DONE
        if self._async_op is not None:
            running = not self._op_finished(self._async_op)
            op_id = self._async_op_counter & 0xFF
            self._out_int[2] = (op_id << 24) | ((1 << 15) if running else 0)
            if not running:
                self._async_op = None

    def _packet_values(self, packet: Any) -> dict[str, Any]:
        values = dict(self._static)
        q = _tuple6(packet.q_rad)
        qd = _tuple6(packet.qd_rad_s)
        tq = _tuple6(packet.q_target_rad)
        tqd = _tuple6(packet.qd_target_rad_s)
        period = self.period_s
        values["timestamp"] = float(packet.sample_time_s)
        values["actual_q"] = q
        values["actual_qd"] = qd
        values["target_q"] = tq
        values["target_qd"] = tqd
        values["target_qdd"] = tuple(
            (a - b) / period for a, b in zip(tqd, self._prev_target_qd, strict=True)
        )
        values["actual_qdd"] = tuple(
            (a - b) / period for a, b in zip(qd, self._prev_actual_qd, strict=True)
        )
        self._prev_target_qd = tqd
        self._prev_actual_qd = qd
        playing = self.runtime_state == _RUNTIME_PLAYING
        values["runtime_state"] = self.runtime_state
        values["robot_status_bits"] = 3 if playing else 1
        values["actual_execution_time"] = 0.4e-3
        for i in range(3):
            values[f"output_int_register_{i + self._register_offset}"] = self._out_int[i]
        for i in range(6):
            values[f"output_double_register_{i + self._register_offset}"] = self._out_double[i]
        return values

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
        if self._truth_file is None:
            return
        truth = getattr(self.sim, "truth", None)
        if truth is None:
            events: list[Any] = self.sim.truth_records()
            fresh = [e for e in events if int(e["id"]) > self._truth_last_id]
        else:
            fresh = []
            for event in reversed(truth):
                if int(_field(event, "id")) <= self._truth_last_id:
                    break
                fresh.append(event)
            fresh.reverse()
        for event in fresh:
            self._truth_open[int(_field(event, "id"))] = event
            self._truth_last_id = max(self._truth_last_id, int(_field(event, "id")))
        horizon_s = float(self.sim.time_s) - _TRUTH_OPEN_S
        for key, event in list(self._truth_open.items()):
            record = _json_safe(_as_record(event))
            line = json.dumps({"event": "command", **record}, sort_keys=True)
            if self._truth_written.get(key) != line:
                self._truth_written[key] = line
                self._truth_file.write(line + "\n")
                self._truth_file.flush()
            if _truth_complete(record) or float(record.get("arrival_s") or 0.0) < horizon_s:
                del self._truth_open[key]
                del self._truth_written[key]

    def _write_meta(self) -> None:
        if self._truth_file is None:
            return
        meta = {
            "event": "meta",
            "robot": self.robot,
            "host": self.host,
            "version": ".".join(map(str, self.version)),
            "period_s": self.period_s,
            "t0_monotonic_s": self.t0,
            "pid": os.getpid(),
        }
        self._truth_file.write(json.dumps(meta, sort_keys=True) + "\n")
        self._truth_file.flush()

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
        if self._truth_file is not None:
            meta = {
                "event": "gyro",
                "link_path": self._imu_link,
                "slave_path": gyro.slave_path,
                "start_time_s": gyro.start_time_s,
                "true_rate_hz": gyro.true_rate_hz,
                "clock_error_ppm": gyro.clock_error_ppm,
                "dlpf_group_delay_s": gyro.source.dlpf_group_delay_s,
            }
            self._truth_file.write(json.dumps(meta, sort_keys=True) + "\n")
            self._truth_file.flush()

    def serve(self, *, ready: Callable[[dict[str, Any]], None] | None = None) -> None:
        """Run until :attr:`stop_event` is set (bind first)."""
        if not self._listeners:
            self.bind()
        # Real-time priority for this thread before any other starts: threads inherit it,
        # so no normal-priority thread can hold the GIL while preempted (priority inversion).
        self.stats["realtime"] = try_realtime(self.rt_priority)
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
            and np.array_equal(peeked.q_rad, packet.q_rad)
            and np.array_equal(peeked.qd_rad_s, packet.qd_rad_s)
            and np.array_equal(peeked.q_target_rad, packet.q_target_rad)
            and np.array_equal(peeked.qd_target_rad_s, packet.qd_target_rad_s)
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
        while True:
            item = self._send_queue.get()
            if item is None:
                return
            target = self.t0 + item.send_time_s
            _sleep_until(target)
            lateness = time.monotonic() - target
            if lateness > _LATE_S:
                self.stats["late_sends"] += 1
            self.stats["max_lateness_s"] = max(self.stats["max_lateness_s"], lateness)
            now = time.monotonic()
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
                write, disconnected, stop_program = self._apply_writes(boundary_s)
                self._script_step(boundary_s, write, disconnected, stop_program)
                result = sim.cycle()
                lag_s = time.monotonic() - self.t0 - float(sim.time_s)
                self.stats["max_cycle_lag_s"] = max(self.stats["max_cycle_lag_s"], lag_s)
                self._check_peek(peeked, result.packet)
                self._after_cycle()
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
        if self._truth_file is not None:
            with contextlib.suppress(OSError, ValueError):
                self._truth_file.close()


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


def _split_program(text: str) -> tuple[str | None, str]:
    """Split off the first complete top-level ``def``/``sec`` ... ``end`` block."""
    lines = text.split("\n")
    start = None
    for i, line in enumerate(lines):
        if start is None:
            if line.startswith(("def ", "sec ")):
                start = i
            continue
        if line.rstrip() == "end" and i < len(lines) - 1:
            return "\n".join(lines[start : i + 1]), "\n".join(lines[i + 1 :])
    return None, text


# --------------------------------------------------------------------------------------
# Process management
# --------------------------------------------------------------------------------------


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
) -> None:
    """Serve a simulated UR controller until stopped (blocking; for ``timedexec serve``).

    Parameters
    ----------
    robot : {"ur10", "ur10e"}
        Simulated robot; reports controller version 3.15.7 (CB3, 125 Hz, 8 ms cycle) or
        5.11.1 (e-Series, 500 Hz, 2 ms cycle).
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
            conn.send(("ok", dict(server.stats)))

    def ready(info: dict[str, Any]) -> None:
        conn.send(("ready", info))
        threading.Thread(target=control, name="twin-control", daemon=True).start()

    server.serve(ready=ready)
    with contextlib.suppress(OSError, BrokenPipeError):
        conn.send(("stopped", dict(server.stats)))


class URTwin:
    """A simulated UR controller in its own process, as a context manager.

    Parameters
    ----------
    robot : {"ur10", "ur10e"}
        Simulated robot (controller version 3.15.7 / 5.11.1; 8 ms / 2 ms cycle).
    host : str
        Loopback address to serve on; ports are fixed by the client (30004, 29999, 30003),
        so run one twin per address (127.0.0.2, 127.0.0.3, ... for parallel twins).
    seed, effects, q0_rad, truth_path, imu_link, sim_factory, physics_rate_hz, rt_priority
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
        """
        if not seconds >= 0:
            raise ConfigError(f"stall seconds={seconds!r} must be >= 0")
        self._request(("stall", float(seconds)))

    def drop_connections(self) -> None:
        """Close every client connection (RTDE, dashboard, script); keep listening."""
        self._request(("drop",))

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

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()


def read_truth(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[int, dict[str, Any]]]:
    """Read a twin's ground-truth file.

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
    from timedexec.twins._truth import iter_truth_records

    meta: dict[str, Any] = {}
    commands: dict[int, dict[str, Any]] = {}
    for record in iter_truth_records(path):
        if record.get("event") == "meta":
            meta = record
        elif record.get("event") == "command":
            commands[int(record["id"])] = record
    return meta, commands
