"""The RTDE wire format of a UR controller, and the server side of one RTDE connection.

The codec (public through :mod:`timedexec.twins`) is what a peer of the UR twin needs to
speak RTDE protocol version 2 without the ``ur_rtde`` client:

* every package is a big-endian header ``>HB`` (total size including the 3 header bytes,
  package type) and a payload (:func:`encode_rtde_package`, :func:`decode_rtde_header`);
* :class:`RTDEPackageType` names the package types;
* :data:`RTDE_OUTPUT_TYPES` / :data:`RTDE_INPUT_TYPES` give the RTDE type of every field a
  UR controller serves (PolyScope 3.15 / 5.11), with the sizes the real controller packs;
* :class:`RTDERecipe` packs and unpacks data packages of a negotiated recipe.

:class:`_RTDEConnection` is one client connection of the twin's server: the handshake
(``V``, ``v``, ``O``, ``I``, ``S``, ``P``) in its own thread, state packages sent by the
twin's clock. See ``docs/ur-twin.md`` and the RTDE guide for the protocol.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import math
import socket
import struct
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from types import MappingProxyType
from typing import Any, Protocol

from timedexec.errors import ProtocolError

__all__ = [
    "RTDE_HEADER_SIZE",
    "RTDE_INPUT_TYPES",
    "RTDE_OUTPUT_TYPES",
    "RTDE_TYPE_CODES",
    "RTDEPackageType",
    "RTDERecipe",
    "decode_rtde_header",
    "enable_receive_stamps",
    "encode_rtde_package",
    "recv_stamped",
]

#: Linux's ``SO_TIMESTAMPNS`` (``SCM_TIMESTAMPNS``, asm-generic/socket.h; the socket module
#: does not name it): the kernel stamps each received segment with its arrival time.
_SO_TIMESTAMPNS = 35
_STAMP_SPACE = socket.CMSG_SPACE(16)


def enable_receive_stamps(sock: socket.socket) -> bool:
    """Ask the kernel to stamp what ``sock`` receives (Linux); False where it cannot."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
    except (OSError, AttributeError):
        return False
    return True


def recv_stamped(sock: socket.socket, n: int) -> tuple[bytes, float]:
    """Read exactly ``n`` bytes and when they arrived: the kernel's receive stamp of the
    first ones (:func:`enable_receive_stamps`), as :func:`time.monotonic` seconds, or the
    time they were read where there is no stamp.

    A controller's intake sees the arrival; a Python reader thread sees its data when it
    gets the interpreter, in the twin after however long the clock thread holds it.
    """
    data, ancillary, _, _ = sock.recvmsg(n, _STAMP_SPACE)
    mono = time.monotonic()
    real = time.time()
    if not data:
        raise ConnectionResetError("client closed the connection")
    arrival = mono
    for level, kind, raw in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(raw) >= 16:
            sec, nsec = struct.unpack("qq", raw[:16])
            # Never after now; never more than a second before it (a wall-clock step
            # between the stamp and now would otherwise move it).
            arrival = min(mono, max(mono - 1.0, sec + nsec * 1e-9 - (real - mono)))
    buf = bytearray(data)
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionResetError("client closed the connection")
        buf += chunk
    return bytes(buf), arrival


_HEADER = struct.Struct(">HB")
#: RTDE protocol versions a UR controller accepts (PolyScope 3.x and 5.x: 1 and 2). Any
#: other request is answered "not accepted" (0), as the controller does; the client may then
#: ask for another. The twin speaks version 2's framing (what ``ur_rtde`` asks for).
RTDE_PROTOCOL_VERSIONS = (1, 2)
#: Bytes of an RTDE package header (uint16 total size, uint8 package type).
RTDE_HEADER_SIZE = _HEADER.size


class RTDEPackageType(enum.IntEnum):
    """RTDE package types (the header's type byte, an ASCII letter)."""

    REQUEST_PROTOCOL_VERSION = ord("V")
    GET_URCONTROL_VERSION = ord("v")
    TEXT_MESSAGE = ord("M")
    DATA_PACKAGE = ord("U")
    CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
    CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
    CONTROL_PACKAGE_START = ord("S")
    CONTROL_PACKAGE_PAUSE = ord("P")


#: struct code and element count per RTDE type name.
RTDE_TYPE_CODES: Mapping[str, tuple[str, int]] = MappingProxyType(
    {
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
)


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


_output_types, _input_types = _build_type_table()
#: RTDE type name of every output field the controller serves (read-only).
RTDE_OUTPUT_TYPES: Mapping[str, str] = MappingProxyType(_output_types)
#: RTDE type name of every input field a client may write (read-only).
RTDE_INPUT_TYPES: Mapping[str, str] = MappingProxyType(_input_types)


def encode_rtde_package(kind: int, payload: bytes) -> bytes:
    """One RTDE package: the ``>HB`` header (size including the header, type) and payload.

    Parameters
    ----------
    kind : int or RTDEPackageType
        Package type byte.
    payload : bytes
        Package body, at most 65532 bytes.
    """
    return _HEADER.pack(len(payload) + RTDE_HEADER_SIZE, kind) + payload


def decode_rtde_header(header: bytes) -> tuple[int, int]:
    """Decode a package header.

    Parameters
    ----------
    header : bytes
        The first :data:`RTDE_HEADER_SIZE` (3) bytes of a package.

    Returns
    -------
    size : int
        Total package size in bytes, header included.
    kind : int
        Package type byte (compare with :class:`RTDEPackageType`).

    Raises
    ------
    ProtocolError
        If the declared size is smaller than the header itself.
    """
    size, kind = _HEADER.unpack(header)
    if size < RTDE_HEADER_SIZE:
        raise ProtocolError(f"RTDE package size {size} < 3 (header)")
    return int(size), int(kind)


@dataclasses.dataclass(frozen=True)
class RTDERecipe:
    """A negotiated recipe: its id, field names, element counts and the packing struct.

    Attributes
    ----------
    recipe_id : int
        Id the controller gave the recipe (1, 2, ... per connection and direction).
    names : tuple of str
        Field names in recipe order.
    counts : tuple of int
        Elements per field (1, 3 or 6).
    struct : struct.Struct
        Big-endian layout of a data package body, recipe id byte included.
    """

    recipe_id: int
    names: tuple[str, ...]
    counts: tuple[int, ...]
    struct: struct.Struct

    @classmethod
    def build(cls, recipe_id: int, names: Sequence[str], table: Mapping[str, str]) -> RTDERecipe:
        """The recipe of ``names`` typed by ``table`` (:data:`RTDE_OUTPUT_TYPES` or
        :data:`RTDE_INPUT_TYPES`); a name missing from ``table`` raises KeyError."""
        fmt = ">B"
        counts = []
        for name in names:
            code, count = RTDE_TYPE_CODES[table[name]]
            fmt += f"{count}{code}" if count > 1 else code
            counts.append(count)
        return cls(recipe_id, tuple(names), tuple(counts), struct.Struct(fmt))

    def pack(self, values: Mapping[str, Any]) -> bytes:
        """A complete data package (header included) carrying ``values`` (every name of
        the recipe; vectors as sequences)."""
        args: list[Any] = [self.recipe_id]
        for name, count in zip(self.names, self.counts, strict=True):
            if count == 1:
                args.append(values[name])
            else:
                args.extend(values[name])
        body = self.struct.pack(*args)
        return _HEADER.pack(len(body) + 3, RTDEPackageType.DATA_PACKAGE) + body

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


#: Output fields computed from the kinematics (only while a connection asks for one).
_TCP_FIELDS = frozenset(
    {"actual_TCP_pose", "actual_TCP_speed", "target_TCP_pose", "target_TCP_speed"}
)


def _parse_names(raw: bytes) -> list[str]:
    return [n for n in raw.decode("ascii", errors="replace").strip("\0").split(",") if n]


# --------------------------------------------------------------------------------------
# One client connection of the twin's server
# --------------------------------------------------------------------------------------


class _RTDEServer(Protocol):
    """What an RTDE connection needs of the twin's server (``_ur_server._TwinServer``)."""

    version: tuple[int, int, int, int]
    period_s: float
    t0: float

    def log(self, message: str) -> None: ...

    def claim_inputs(self, conn_id: int, names: Iterable[str]) -> set[str]: ...

    def set_register_offset(self, offset: int) -> None: ...

    def write_inputs(self, arrival_s: float, values: dict[str, Any]) -> None: ...

    def connection_closed(self, conn: _RTDEConnection) -> None: ...

    def output_recipe_set(self) -> None: ...


class _RTDEConnection:
    """One RTDE client connection: handshake in its own thread, data sent by the clock."""

    def __init__(self, server: _RTDEServer, sock: socket.socket, conn_id: int) -> None:
        self.server = server
        self.sock = sock
        self.conn_id = conn_id
        self.send_lock = threading.Lock()
        self.output_recipe: RTDERecipe | None = None
        self.input_recipes: dict[int, RTDERecipe] = {}
        self.decimation = 1
        #: Whether the output recipe asks for a TCP pose or speed.
        self.wants_tcp = False
        self.stalled_until = -math.inf
        self.started = False
        self.closed = False
        #: A package read but not yet handed to the server (the clock's drain waits).
        self.handling = False
        enable_receive_stamps(sock)
        self.thread = threading.Thread(target=self._run, name=f"rtde-{conn_id}", daemon=True)

    # -- sending ---------------------------------------------------------------------
    def reply(self, kind: int, payload: bytes) -> None:
        with self.send_lock:
            self.sock.sendall(encode_rtde_package(kind, payload))

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
    def _run(self) -> None:
        try:
            while not self.closed:
                self.handling = False
                header, arrival = recv_stamped(self.sock, RTDE_HEADER_SIZE)
                self.handling = True
                size, kind = decode_rtde_header(header)
                payload = (
                    recv_stamped(self.sock, size - RTDE_HEADER_SIZE)[0]
                    if size > RTDE_HEADER_SIZE
                    else b""
                )
                self._handle(kind, payload, arrival - self.server.t0)
        except (OSError, ProtocolError, struct.error) as exc:
            if not self.closed and not isinstance(exc, ConnectionResetError):
                self.server.log(f"RTDE connection {self.conn_id}: {exc}")
        finally:
            self.close()
            self.server.connection_closed(self)

    def _handle(self, kind: int, payload: bytes, arrival_s: float) -> None:
        server = self.server
        if kind == RTDEPackageType.REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload)[0] if len(payload) == 2 else None
            accepted = version in RTDE_PROTOCOL_VERSIONS
            if not accepted:
                server.log(
                    f"RTDE connection {self.conn_id}: protocol version "
                    f"{version if version is not None else payload!r} not accepted"
                )
            self.reply(kind, b"\x01" if accepted else b"\x00")
        elif kind == RTDEPackageType.GET_URCONTROL_VERSION:
            self.reply(kind, struct.pack(">4I", *server.version))
        elif kind == RTDEPackageType.CONTROL_PACKAGE_SETUP_OUTPUTS:
            (frequency_hz,) = struct.unpack(">d", payload[:8])
            names = _parse_names(payload[8:])
            types = [RTDE_OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            if "NOT_FOUND" in types or not names:
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            rate_hz = 1.0 / server.period_s
            if not frequency_hz <= rate_hz * (1.0 + 1e-9):  # NaN too
                # Above the controller's cycle rate (CB3 125 Hz, e-Series 500 Hz): refused,
                # not served at another rate. The reply carries recipe id 0 (failed); the
                # recipe is not set, so the following start request is refused too, which
                # every client sees (docs/ur-twin.md, "Output frequency").
                server.log(
                    f"RTDE connection {self.conn_id}: output frequency {frequency_hz} Hz "
                    f"refused; this controller serves at most {rate_hz:g} Hz"
                )
                self.output_recipe = None
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            recipe_id = 1 if self.output_recipe is None else self.output_recipe.recipe_id + 1
            self.output_recipe = RTDERecipe.build(recipe_id, names, RTDE_OUTPUT_TYPES)
            self.decimation = max(1, round(rate_hz / frequency_hz)) if frequency_hz > 0 else 1
            self.wants_tcp = not _TCP_FIELDS.isdisjoint(names)
            server.output_recipe_set()
            self.reply(kind, bytes([recipe_id]) + ",".join(types).encode())
        elif kind == RTDEPackageType.CONTROL_PACKAGE_SETUP_INPUTS:
            names = _parse_names(payload)
            types = [RTDE_INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            if "NOT_FOUND" in types or not names:
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            in_use = server.claim_inputs(self.conn_id, names)
            if in_use:
                types = ["IN_USE" if n in in_use else t for n, t in zip(names, types, strict=True)]
                self.reply(kind, b"\x00" + ",".join(types).encode())
                return
            recipe_id = len(self.input_recipes) + 1
            self.input_recipes[recipe_id] = RTDERecipe.build(recipe_id, names, RTDE_INPUT_TYPES)
            if recipe_id == 1 and names[0] in ("input_int_register_0", "input_int_register_24"):
                # ur_rtde's first recipe starts with the command register: 24 means the
                # client uses the upper register range (FLAG_UPPER_RANGE_REGISTERS).
                server.set_register_offset(int(names[0].rsplit("_", 1)[1]))
            self.reply(kind, bytes([recipe_id]) + ",".join(types).encode())
        elif kind == RTDEPackageType.CONTROL_PACKAGE_START:
            self.started = self.output_recipe is not None
            self.reply(kind, b"\x01" if self.started else b"\x00")
        elif kind == RTDEPackageType.CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.reply(kind, b"\x01")
        elif kind == RTDEPackageType.DATA_PACKAGE:
            if not payload:
                raise ProtocolError("RTDE data package without recipe id")
            recipe = self.input_recipes.get(payload[0])
            if recipe is None:
                server.log(f"RTDE connection {self.conn_id}: data for unknown recipe {payload[0]}")
                return
            server.write_inputs(arrival_s, recipe.unpack(payload))
        else:
            server.log(f"RTDE connection {self.conn_id}: ignoring package type {kind}")
