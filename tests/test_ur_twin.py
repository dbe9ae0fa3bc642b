"""The simulated UR controller (UR twin) against the real ``ur_rtde`` client, and against a
minimal RTDE peer written with the twin's public codec (:class:`RawRTDE`).

The twin runs in its own process (spawned by ``URTwin``) on a private loopback address per
fixture (127.0.0.2x, 127.0.0.3x), because the client's ports are fixed. Timing bands are
wide enough for a loaded two-core CI machine and are justified next to each assert.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from timedexec.effects import EffectSet, default_effects, make_effect
from timedexec.errors import ConfigError, ProtocolError
from timedexec.sim import ControllerSim, default_settings
from timedexec.twins import (
    DASHBOARD_PORT,
    RTDE_HEADER_SIZE,
    RTDE_INPUT_TYPES,
    RTDE_OUTPUT_TYPES,
    RTDE_PORT,
    SCRIPT_PORT,
    UR_CONTROLLER_VERSIONS,
    RTDEPackageType,
    RTDERecipe,
    Twin,
    URTwin,
    decode_rtde_header,
    encode_rtde_package,
    iter_truth_records,
    read_truth,
)

try:
    import rtde_control
    import rtde_receive
except ImportError:  # the tests through the raw codec still run
    rtde_control = rtde_receive = None

needs_ur_rtde = pytest.mark.skipif(
    rtde_receive is None, reason="needs the ur_rtde client (pip install ur_rtde)"
)

#: ur_rtde 1.6.5's default receive recipe for PolyScope 5.11 (every field it asks for).
RECEIVE_DEFAULTS = [
    "timestamp", "target_q", "target_qd", "target_qdd", "target_current", "target_moment",
    "actual_q", "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
    "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
    "actual_digital_input_bits", "joint_temperatures", "actual_execution_time", "robot_mode",
    "joint_mode", "safety_mode", "actual_tool_accelerometer", "speed_scaling",
    "target_speed_fraction", "actual_momentum", "actual_main_voltage", "actual_robot_voltage",
    "actual_robot_current", "actual_joint_voltage", "actual_digital_output_bits",
    "runtime_state", "standard_analog_input0", "standard_analog_input1",
    "standard_analog_output0", "standard_analog_output1", "robot_status_bits",
    "safety_status_bits", "ft_raw_wrench", "payload", "payload_cog", "payload_inertia",
    "output_int_register_2", *[f"output_int_register_{i}" for i in range(12, 20)],
    *[f"output_double_register_{i}" for i in range(12, 20)],
]  # fmt: skip


def collect(recv: object, duration_s: float) -> dict[str, np.ndarray]:
    """Poll a receive interface for ``duration_s``; one row per new controller time stamp."""
    host, stamp, qd, q = [], [], [], []
    last = None
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        ts = recv.getTimestamp()  # type: ignore[attr-defined]
        if ts != last:
            host.append(time.monotonic())
            stamp.append(ts)
            qd.append(recv.getActualQd())  # type: ignore[attr-defined]
            q.append(recv.getActualQ())  # type: ignore[attr-defined]
            last = ts
        time.sleep(50e-6)
    return {
        "host": np.array(host),
        "ts": np.array(stamp),
        "qd": np.array(qd),
        "q": np.array(q),
    }


def wait_fresh(recv: object, timeout_s: float = 1.0) -> tuple[float, float]:
    """Block until a new package arrives; return (host time, controller time)."""
    last = recv.getTimestamp()  # type: ignore[attr-defined]
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        ts = recv.getTimestamp()  # type: ignore[attr-defined]
        if ts != last:
            return time.monotonic(), ts
        time.sleep(50e-6)
    raise TimeoutError("no package")


def command_record(truth_path: Path, kind: str, after_s: float, timeout_s: float = 3.0) -> dict:
    """The truth record of the first ``kind`` command that arrived after ``after_s``,
    once its moved joints have onsets (the twin appends updates as they happen)."""
    end = time.monotonic() + timeout_s
    while True:
        _, commands = read_truth(truth_path)
        hits = [
            r
            for r in commands.values()
            if r["kind"] == kind and r["arrival_s"] is not None and r["arrival_s"] >= after_s
        ]
        if hits:
            rec = min(hits, key=lambda r: r["arrival_s"])
            moved = rec.get("moved_joints") or []
            if rec["reference_start_s"] is not None and all(
                rec["onset_s"][j - 1] is not None for j in moved
            ):
                return rec
        if time.monotonic() > end:
            raise AssertionError(f"no complete truth record of {kind} after {after_s}: {hits}")
        time.sleep(0.05)


class RawRTDE:
    """A minimal RTDE peer built on the twin's public codec (what a user's own client does).

    Negotiates protocol version 2, an output recipe and optionally an input recipe, starts
    the stream and reads state packages in order.
    """

    def __init__(
        self,
        host: str,
        outputs: list[str],
        *,
        frequency_hz: float = 500.0,
        inputs: list[str] | None = None,
    ) -> None:
        self.sock = socket.create_connection((host, RTDE_PORT), timeout=5.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        assert (
            self.request(RTDEPackageType.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
        )
        self.version = struct.unpack(">4I", self.request(RTDEPackageType.GET_URCONTROL_VERSION))
        reply = self.request(
            RTDEPackageType.CONTROL_PACKAGE_SETUP_OUTPUTS,
            struct.pack(">d", frequency_hz) + ",".join(outputs).encode(),
        )
        self.output = RTDERecipe.build(reply[0], outputs, RTDE_OUTPUT_TYPES)
        self.input: RTDERecipe | None = None
        if inputs:
            reply = self.request(
                RTDEPackageType.CONTROL_PACKAGE_SETUP_INPUTS, ",".join(inputs).encode()
            )
            assert reply[0] != 0, reply
            self.input = RTDERecipe.build(reply[0], inputs, RTDE_INPUT_TYPES)
        assert self.request(RTDEPackageType.CONTROL_PACKAGE_START) == b"\x01"

    def _recv_exact(self, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError("the twin closed the connection")
            buf += chunk
        return bytes(buf)

    def read_package(self) -> tuple[int, bytes]:
        size, kind = decode_rtde_header(self._recv_exact(RTDE_HEADER_SIZE))
        return kind, self._recv_exact(size - RTDE_HEADER_SIZE)

    def request(self, kind: RTDEPackageType, payload: bytes = b"") -> bytes:
        """Send a request; return its reply's payload (state packages in between skipped)."""
        self.sock.sendall(encode_rtde_package(kind, payload))
        while True:
            got, body = self.read_package()
            if got == kind:
                return body

    def state(self) -> dict:  # type: ignore[type-arg]
        """The next state package, decoded."""
        while True:
            kind, body = self.read_package()
            if kind == RTDEPackageType.DATA_PACKAGE:
                return self.output.unpack(body)

    def states_until(self, controller_time_s: float, timeout_s: float = 10.0) -> list[dict]:  # type: ignore[type-arg]
        """Every state package up to (and including) the first stamped at or after
        ``controller_time_s``."""
        out = []
        end = time.monotonic() + timeout_s
        while not out or out[-1]["timestamp"] < controller_time_s:
            assert time.monotonic() < end, "the twin did not stream up to the time asked for"
            out.append(self.state())
        return out

    def wait_for(self, field: str, value: object, timeout_s: float = 5.0) -> dict:  # type: ignore[type-arg]
        """Read state packages until ``field`` equals ``value``; return that package."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            state = self.state()
            if state[field] == value:
                return state
        raise AssertionError(f"{field} did not become {value!r} within {timeout_s} s")

    def wait_until(self, test: Callable[[dict], bool], timeout_s: float = 5.0) -> dict:  # type: ignore[type-arg]
        """Read state packages until ``test(package)``; return that package."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            state = self.state()
            if test(state):
                return state
        raise AssertionError(f"no package passed the test within {timeout_s} s")

    def write(self, **values: object) -> None:
        assert self.input is not None
        self.sock.sendall(self.input.pack(values))

    def close(self) -> None:
        self.sock.close()


#: The input recipe of the command tests: command id, eight double arguments.
COMMAND_INPUTS = ["input_int_register_0", *[f"input_double_register_{i}" for i in range(8)]]
SPEEDJ = 9
SPEED_STOP = 15
SET_WATCHDOG = 35


def closed_within(peer: RawRTDE, timeout_s: float) -> bool:
    """Whether the twin closes ``peer``'s connection within ``timeout_s`` (the packages
    already on their way are read first)."""
    end = time.monotonic() + timeout_s
    try:
        while time.monotonic() < end:
            peer.state()
    except OSError:  # ConnectionResetError: EOF; or a reset
        return True
    return False


def command(cmd: int, *args: float) -> dict[str, float]:
    """Register values for command ``cmd`` with double arguments ``args`` (rest zero)."""
    values: dict[str, float] = {"input_int_register_0": cmd}
    for i in range(8):
        values[f"input_double_register_{i}"] = float(args[i]) if i < len(args) else 0.0
    return values


def upload(host: str, text: str) -> None:
    """Send ``text`` to the script port (a program upload, possibly in parts)."""
    with socket.create_connection((host, SCRIPT_PORT), timeout=5.0) as sock:
        sock.sendall(text.encode())
        time.sleep(0.05)  # the twin reads it before the connection closes


PROGRAM = "def rtde_control():\n  while True:\n    sync()\n  end\nend\n"


def dashboard(host: str, *lines: str) -> list[str]:
    """The dashboard's welcome line and its answer to each of ``lines``."""
    with socket.create_connection((host, DASHBOARD_PORT), timeout=5.0) as sock:
        reader = sock.makefile("r", encoding="utf-8", newline="\n")
        answers = [reader.readline().rstrip("\n")]
        for line in lines:
            sock.sendall(line.encode() + b"\n")
            answers.append(reader.readline().rstrip("\n"))
        return answers


# --------------------------------------------------------------------------------------
# The codec (no sockets)
# --------------------------------------------------------------------------------------


def test_type_table_covers_the_receive_defaults_with_the_client_sizes() -> None:
    """Every field ur_rtde's receive interface asks for by default is served, with the
    byte size the client decodes (it uses its own table: a wrong size shifts every field)."""
    sizes = {"VECTOR6D": 48, "VECTOR3D": 24, "VECTOR6INT32": 24, "DOUBLE": 8, "UINT64": 8,
             "UINT32": 4, "INT32": 4}  # fmt: skip
    for name in RECEIVE_DEFAULTS:
        assert name in RTDE_OUTPUT_TYPES, name
    assert RTDE_OUTPUT_TYPES["actual_tool_accelerometer"] == "VECTOR3D"
    assert RTDE_OUTPUT_TYPES["payload_cog"] == "VECTOR3D"
    assert RTDE_OUTPUT_TYPES["joint_mode"] == "VECTOR6INT32"
    assert RTDE_OUTPUT_TYPES["actual_digital_input_bits"] == "UINT64"
    assert RTDE_OUTPUT_TYPES["robot_mode"] == "INT32"
    assert RTDE_OUTPUT_TYPES["runtime_state"] == "UINT32"
    recipe = RTDERecipe.build(1, RECEIVE_DEFAULTS, RTDE_OUTPUT_TYPES)
    expected = 1 + sum(sizes[RTDE_OUTPUT_TYPES[n]] for n in RECEIVE_DEFAULTS)
    assert recipe.struct.size == expected
    with pytest.raises(TypeError):
        RTDE_OUTPUT_TYPES["timestamp"] = "INT32"  # type: ignore[index]  # read-only table


def test_recipe_round_trip_and_short_input_packages() -> None:
    """Input packages decode by the negotiated types; a package shorter than its recipe
    (the client packs only the values a command uses) decodes the fields that fit; a
    packed package carries the ``>HB`` header with its own size."""
    names = ["input_int_register_0", *[f"input_double_register_{i}" for i in range(8)],
             "input_int_register_1"]  # fmt: skip
    recipe = RTDERecipe.build(3, names, RTDE_INPUT_TYPES)
    payload = struct.pack(">Bi8di", 3, 9, *range(8), 1)
    values = recipe.unpack(payload)
    assert values["input_int_register_0"] == 9
    assert values["input_double_register_7"] == 7.0
    assert values["input_int_register_1"] == 1
    short = recipe.unpack(struct.pack(">Bid", 3, 15, 2.5))
    assert short["input_int_register_0"] == 15
    assert short["input_double_register_0"] == 2.5
    assert short["input_double_register_1"] == 0.0
    package = recipe.pack(values)
    assert decode_rtde_header(package[:RTDE_HEADER_SIZE]) == (len(package), ord("U"))
    assert package[RTDE_HEADER_SIZE:] == payload
    assert encode_rtde_package(RTDEPackageType.CONTROL_PACKAGE_START, b"") == b"\x00\x03S"


def test_header_smaller_than_itself_is_a_protocol_error() -> None:
    """A declared package size below the 3 header bytes cannot be framed."""
    with pytest.raises(ProtocolError, match="< 3"):
        decode_rtde_header(b"\x00\x02U")


# --------------------------------------------------------------------------------------
# A twin process against the raw codec (no ur_rtde needed)
# --------------------------------------------------------------------------------------

RAW_HOST = "127.0.0.35"


@pytest.fixture(scope="module")
def raw_twin(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    truth = tmp_path_factory.mktemp("raw") / "truth.jsonl"
    with URTwin("ur10", RAW_HOST, seed=3, truth_path=truth) as twin:
        yield twin


@contextlib.contextmanager
def playing(outputs: list[str], host: str = RAW_HOST) -> Iterator[RawRTDE]:
    """A raw RTDE peer (125 Hz, the command inputs) with the test program playing."""
    peer = RawRTDE(host, outputs, frequency_hz=125.0, inputs=COMMAND_INPUTS)
    try:
        upload(host, PROGRAM)
        peer.wait_for("runtime_state", 2)
        yield peer
    finally:
        peer.close()


def test_twin_lifecycle_verbs(raw_twin: URTwin) -> None:
    """URTwin is driven like every twin; drop() closes the open connections and the twin
    keeps serving new ones; a negative stall is refused with a message."""
    assert isinstance(raw_twin, Twin)
    assert raw_twin.is_alive
    with pytest.raises(ConfigError, match="must be >= 0"):
        raw_twin.stall(-0.5)
    peer = RawRTDE(RAW_HOST, ["timestamp"], frequency_hz=125.0)
    try:
        peer.state()
        raw_twin.drop()
        assert closed_within(peer, 2.0)
    finally:
        peer.close()
    again = RawRTDE(RAW_HOST, ["timestamp"], frequency_hz=125.0)
    try:
        assert again.state()["timestamp"] > 0
    finally:
        again.close()


def test_dashboard_answers_what_the_client_expects(raw_twin: URTwin) -> None:
    """Dashboard replies the client parses: the welcome line, version with four numbers, a
    numeric serial, remote control on, an unknown command named back; ``quit`` ends the
    session with ``Disconnected``."""
    answers = dashboard(
        RAW_HOST, "PolyscopeVersion", "get serial number", "is in remote control", "frobnicate",
        "quit",
    )  # fmt: skip
    assert answers[0] == "Connected: Universal Robots Dashboard Server"
    assert answers[1].startswith("URSoftware 3.15.7.")
    assert answers[2].isdigit()
    assert answers[3] == "true"
    assert answers[4] == "could not understand: 'frobnicate'"
    assert answers[5] == "Disconnected"


def test_script_upload_starts_the_program_only_once_complete(raw_twin: URTwin) -> None:
    """A script upload is a program only once its top-level ``end`` line has arrived
    (indented ``end`` lines close inner blocks): the runtime state stays STOPPED (1) on a
    partial upload and turns PLAYING (2) with the closing line; dashboard ``stop`` is
    answered exactly ``Stopped`` and stops it again."""
    peer = RawRTDE(RAW_HOST, ["timestamp", "runtime_state"], frequency_hz=125.0)
    try:
        assert dashboard(RAW_HOST, "stop")[1] == "Stopped"
        peer.wait_for("runtime_state", 1)
        with socket.create_connection((RAW_HOST, SCRIPT_PORT), timeout=5.0) as script:
            script.sendall(b"def rtde_control():\n  if True:\n    x = 1\n  end\n")
            t_part = raw_twin.controller_time_s()
            # 0.2 s of controller time: ten times the program start delay (20 ms).
            states = peer.states_until(t_part + 0.2)
            assert {s["runtime_state"] for s in states} == {1}
            script.sendall(b"end\n")
            peer.wait_for("runtime_state", 2)
        assert dashboard(RAW_HOST, "programState", "stop")[1:] == [
            "PLAYING rtde_control",
            "Stopped",
        ]
        peer.wait_for("runtime_state", 1)
    finally:
        peer.close()


def test_truth_records_are_appended_and_read_back(raw_twin: URTwin) -> None:
    """A speedJ written through the raw codec is taken at the first cycle boundary after
    it arrived; the ground truth goes to a JSON-lines file (meta line first, one line per
    new or changed record, flushed) and ``read_truth`` keeps the latest record per
    command id."""
    with playing(["timestamp", "runtime_state", "actual_qd"]) as peer:
        t_cmd = raw_twin.controller_time_s()
        peer.write(**command(SPEEDJ, 0.3, 0, 0, 0, 0, 0, 2.0, 0.0))
        rec = command_record(raw_twin.truth_path, "SpeedJ", t_cmd)
        # 0.1 s after the onset the joint runs at about 0.23 rad/s (2 rad/s² ramp).
        moving = [s["actual_qd"][0] for s in peer.states_until(rec["onset_s"][0] + 0.1)]
        peer.write(**command(SPEED_STOP, 5.0))
    meta, commands = read_truth(raw_twin.truth_path)
    assert meta["robot"] == "ur10"
    assert meta["period_s"] == pytest.approx(0.008)
    assert meta["t0_monotonic_s"] == pytest.approx(raw_twin.t0_monotonic_s)
    assert commands[rec["id"]]["kind"] == "SpeedJ"
    # Wire: after the write (>= 0), within 50 ms on loopback (normally < 1 ms).
    assert 0 <= rec["arrival_s"] - t_cmd < 0.050
    # Intake at the first 8 ms boundary after arrival.
    assert 0 <= rec["intake_s"] - rec["arrival_s"] < 0.008 + 1e-9
    assert rec["intake_s"] / 0.008 == pytest.approx(round(rec["intake_s"] / 0.008), abs=1e-6)
    assert max(moving) > 0.1  # the arm followed the command the client saw
    lines = raw_twin.truth_path.read_text().splitlines()
    assert json.loads(lines[0])["event"] == "meta"
    assert sum('"SpeedJ"' in line for line in lines) >= 2  # first sight + completed


def test_speedj_time_does_not_expire_and_the_watchdog_stops_it(raw_twin: URTwin) -> None:
    """As the uploaded script does: speedj's time argument never ends the motion (the
    speed thread re-issues it), and a watchdog set with command 35 (``rtde_set_watchdog``
    on the command register, action "stop") stops the program once the register is not
    written for 1/f: runtime_state leaves PLAYING and the arm comes to rest. The stop is
    in the ground truth as a ``program_stop`` line."""
    with playing(["timestamp", "runtime_state", "actual_qd"]) as peer:
        t_cmd = raw_twin.controller_time_s()
        peer.write(**command(SPEEDJ, 0.3, 0, 0, 0, 0, 0, 3.0, 0.05))  # t = 50 ms
        # 0.5 s later (controller time) the joint still runs at the commanded speed.
        state = peer.states_until(t_cmd + 0.5)[-1]
        assert state["actual_qd"][0] == pytest.approx(0.3, rel=0.02)
        peer.write(**command(SET_WATCHDOG, 20.0))  # 20 Hz: 50 ms of silence allowed
        stopped = peer.wait_for("runtime_state", 1, timeout_s=2.0)
        rest = peer.states_until(stopped["timestamp"] + 0.3)[-1]
    assert all(v == 0.0 for v in rest["actual_qd"])  # 0.3 rad/s at 4 rad/s²: 75 ms ramp
    stops = [
        r
        for r in iter_truth_records(raw_twin.truth_path)
        if r.get("event") == "program_stop" and r["time_s"] > t_cmd
    ]
    assert [r["reason"] for r in stops] == ["watchdog"]
    # Fired at the first 8 ms boundary after 50 ms without a write of the register.
    assert 0.05 < stops[0]["time_s"] - stops[0]["last_update_s"] <= 0.05 + 0.008 + 1e-9
    # The package sampled at the next boundary is the first to show it.
    assert stopped["timestamp"] == pytest.approx(stops[0]["time_s"] + 0.008, abs=1e-9)


def test_speedj_time_paces_when_the_next_target_is_taken(raw_twin: URTwin) -> None:
    """The speed thread runs ``speedj(target, a, t)``, which returns after ``t``; only then
    does it take the newest target (URScript's speedj; the ur_rtde 1.6.5 script's speed
    thread). A second target written 40 ms into a t = 200 ms call acts 200 ms after the
    first, not at once; with t = one period each target acts at the next boundary."""
    with playing(["timestamp", "runtime_state", "target_qd"]) as peer:
        peer.write(**command(SPEEDJ, 0.2, 0, 0, 0, 0, 0, 10.0, 0.2))
        first = peer.wait_until(lambda st: st["target_qd"][0] > 0.19)["timestamp"]
        time.sleep(0.04)
        peer.write(**command(SPEEDJ, 0.1, 0, 0, 0, 0, 0, 10.0, 0.008))
        slow = peer.wait_until(lambda st: st["target_qd"][0] < 0.11, timeout_s=1.0)
        time.sleep(0.02)
        peer.write(**command(SPEEDJ, 0.05, 0, 0, 0, 0, 0, 10.0, 0.008))
        t_write = raw_twin.controller_time_s()
        slower = peer.wait_until(lambda st: st["target_qd"][0] < 0.06, timeout_s=1.0)
    # 10 rad/s² ramps 0.1 rad/s in 10 ms (2 cycles): the first target was reached one or
    # two cycles after the call began, which returns 0.2 s after it began.
    assert 0.2 - 0.016 - 1e-9 <= slow["timestamp"] - first <= 0.2 + 0.016 + 1e-9
    # With t = 8 ms the thread comes round every cycle: the new target acts within the
    # cycle it arrives in plus the ramp (< 3 cycles; 20 ms allows the write's wire time).
    assert slower["timestamp"] - t_write < 0.024 + 0.02


def test_read_truth_skips_a_line_being_written(tmp_path: Path) -> None:
    """read_truth is a view of the one truth reader: the last meta line, the latest record
    per command id, and a torn last line (read while the twin writes it) skipped."""
    path = tmp_path / "truth.jsonl"
    rows = [
        {"event": "meta", "robot": "ur10", "period_s": 0.008, "t0_monotonic_s": 1.0},
        {"event": "command", "id": 1, "kind": "SpeedJ", "onset_s": [None] * 6},
        {"event": "command", "id": 1, "kind": "SpeedJ", "onset_s": [0.1, *[None] * 5]},
    ]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"event": "comm')
    meta, commands = read_truth(path)
    assert meta == {"robot": "ur10", "period_s": 0.008, "t0_monotonic_s": 1.0}
    assert list(commands) == [1]
    assert commands[1]["onset_s"][0] == 0.1


@pytest.mark.parametrize(("extra", "host"), [(False, "127.0.0.36"), (True, "127.0.0.37")])
def test_early_package_equals_the_cycle_package(extra: bool, host: str) -> None:
    """The package the twin sends before computing a cycle equals the one
    ``ControllerSim.cycle()`` returns afterwards (bit for bit; the twin counts every
    difference), with and without the response_extra_cycle effect, while a command moves
    the arm."""
    effects = default_effects("ur10e")
    if extra:
        effects = effects.with_effect(make_effect("response_extra_cycle"))
    with URTwin("ur10e", host, effects=effects) as twin:
        peer = RawRTDE(host, ["timestamp", "runtime_state", "actual_qd"], inputs=COMMAND_INPUTS)
        try:
            upload(host, PROGRAM)
            peer.wait_for("runtime_state", 2)
            peer.write(**command(SPEEDJ, 0, 0.3, 0, 0, 0, 0, 3.0, 0.0))
            states = peer.states_until(twin.controller_time_s() + 0.3)
            peer.write(**command(SPEED_STOP, 5.0))
        finally:
            peer.close()
        stats = twin.stats()
    assert max(abs(s["actual_qd"][1]) for s in states) > 0.1  # the arm moved
    stamps = np.array([s["timestamp"] for s in states])
    assert np.allclose(np.diff(stamps) / 0.002, np.round(np.diff(stamps) / 0.002), atol=1e-6)
    assert stats["cycles"] > 100
    assert stats["peek_mismatches"] == 0
    # the CPUs kept out of deep idle states while serving, where this process may ask it
    assert stats["fast_wakeup"] == os.access("/dev/cpu_dma_latency", os.W_OK)


def test_bad_robot_name_is_a_config_error() -> None:
    """Only the simulated URs can be served; the message names the choices."""
    with pytest.raises(ConfigError, match="ur10e"):
        URTwin("kr5")


# --------------------------------------------------------------------------------------
# The real client against a twin process
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ur10_twin(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    truth = tmp_path_factory.mktemp("ur10") / "truth.jsonl"
    with URTwin("ur10", "127.0.0.21", seed=3, truth_path=truth) as twin:
        yield twin


@pytest.fixture(scope="module")
def ur10_clients(ur10_twin: URTwin):  # type: ignore[no-untyped-def]
    recv = rtde_receive.RTDEReceiveInterface(ur10_twin.host)
    ctrl = rtde_control.RTDEControlInterface(ur10_twin.host)
    yield recv, ctrl
    ctrl.stopScript()
    ctrl.disconnect()
    recv.disconnect()


@needs_ur_rtde
@pytest.mark.parametrize(
    ("robot", "host", "period_s"),
    [
        ("ur10", "127.0.0.22", 0.008),
        pytest.param("ur10e", "127.0.0.23", 0.002, marks=pytest.mark.realtime_twin),
    ],
)
def test_receive_interface_streams_at_the_controller_rate(
    robot: str, host: str, period_s: float
) -> None:
    """The client asks 125 Hz from a CB3 (3.15.7) and 500 Hz from an e-Series (5.11.1) and
    gets one package per controller cycle, time-stamped on the controller clock."""
    with URTwin(robot, host) as twin:
        recv = rtde_receive.RTDEReceiveInterface(host)
        try:
            data = collect(recv, 2.0)
            assert recv.getRobotMode() == 7
            assert recv.getSafetyMode() == 1
            assert len(recv.getActualTCPPose()) == 6
            assert len(recv.getActualToolAccelerometer()) == 3
            assert recv.getJointMode() == [253] * 6
        finally:
            recv.disconnect()
        stats = twin.stats()
    assert twin.version == UR_CONTROLLER_VERSIONS[robot]
    steps = np.diff(data["ts"])
    # Controller time stamps are exact multiples of the period (no jitter in the stamps).
    assert np.allclose(steps / period_s, np.round(steps / period_s), atol=1e-6)
    # Lost packages (client or our polling too slow under load) show as multiples; most
    # cycles arrive (all on an idle machine; 0.6 allows a loaded two-core CI machine).
    assert len(data["ts"]) >= 0.6 * 2.0 / period_s
    # Host-side mean period: slope of host receipt time against controller time (least
    # squares over ~2 s). A package delayed by a descheduled client (tens of ms on a loaded
    # CI machine) moves the slope by < 0.1 %; the twin's clock is 1:1 with host time.
    slope = np.polyfit(data["ts"], data["host"], 1)[0]
    assert slope * period_s == pytest.approx(period_s, rel=0.01)
    assert stats["peek_mismatches"] == 0


@needs_ur_rtde
def test_control_interface_connects_and_runs_the_script(ur10_clients) -> None:  # type: ignore[no-untyped-def]
    """The control interface finds the program running (runtime_state 2, status bits 3)."""
    recv, ctrl = ur10_clients
    assert ctrl.isConnected()
    assert ctrl.isProgramRunning()
    assert recv.getRuntimeState() == 2
    assert recv.getRobotStatus() == 3


@needs_ur_rtde
def test_speedj_actuation_and_response_delay_match_ground_truth(
    ur10_twin: URTwin, ur10_clients
) -> None:  # type: ignore[no-untyped-def]
    """speedJ on joint 1: the reported speed stays still until the true onset, the first
    package at or after the onset shows the motion, and it reaches the host after its
    simulated send time (sample + packing phase): both delays are visible to the client."""
    recv, ctrl = ur10_clients
    period = 0.008
    threshold = default_settings("ur10").servo.onset_threshold_rad_s
    host_cmd, _ = wait_fresh(recv)
    t_call = time.monotonic()
    assert ctrl.speedJ([0.4, 0, 0, 0, 0, 0], 3.0, 0.0)
    call_s = time.monotonic() - t_call
    data = collect(recv, 0.35)
    assert ctrl.speedStop(5.0)
    # speedJ is a realtime command: it returns once sent (waits only for "ready").
    assert call_s < 0.05  # a few ms normally; 50 ms allows a descheduled client thread
    rec = command_record(ur10_twin.truth_path, "SpeedJ", ur10_twin.controller_time_s(host_cmd))
    arrival, intake, start = rec["arrival_s"], rec["intake_s"], rec["reference_start_s"]
    onset = rec["onset_s"][0]
    assert rec["moved_joints"] == [1]
    # Wire: the bytes arrive after the call (>= 0) and within 50 ms on loopback
    # (typically < 1 ms; the bound allows a descheduled process under CI load).
    assert 0 <= arrival - ur10_twin.controller_time_s(t_call) < 0.050
    # Intake at the first cycle boundary after arrival; pipeline of whole cycles after it.
    assert 0 <= intake - arrival < period + 1e-9
    assert (start - intake) / period == pytest.approx(round((start - intake) / period), abs=1e-6)
    # Actuation delay (arrival -> physical onset): positive, below 150 ms (sim calibration
    # puts the UR10 around tens of ms).
    assert 0 < onset - arrival < 0.150
    ts, qd = data["ts"], data["qd"][:, 0]
    before = ts < onset
    assert before.any()
    assert np.all(np.abs(qd[before]) <= threshold + 1e-9)  # still until the onset
    after = ~before
    assert np.all(np.abs(qd[after]) > threshold)  # accelerating from the onset on
    # The first package sampled at/after the onset is the next cycle boundary.
    first = int(np.flatnonzero(after)[0])
    boundary = np.ceil(onset / period - 1e-9) * period
    if abs(ts[first] - boundary) < 1e-9:  # it was not lost on a loaded machine
        sim = ControllerSim("ur10", seed=3)
        send = ts[first] + sim.packing_phase_s(ts[first])
        lag = data["host"][first] - (ur10_twin.t0_monotonic_s + send)
        # Host receipt after the simulated send time (typically < 1 ms later; 50 ms
        # allows a descheduled client on a loaded two-core CI machine).
        assert -0.2e-3 < lag < 0.050
        # Response delay as the host sees it: from onset to receipt, at least the
        # sampling wait plus the packing phase.
        seen = data["host"][first] - (ur10_twin.t0_monotonic_s + onset)
        assert seen >= (ts[first] - onset) + sim.packing_phase_s(ts[first]) - 0.2e-3


@needs_ur_rtde
def test_speedstop_stops_and_movej_reaches_the_target(ur10_clients) -> None:  # type: ignore[no-untyped-def]
    """speedStop returns once the arm is still; moveJ blocks until the target is reached;
    isSteady reports the rest."""
    recv, ctrl = ur10_clients
    assert ctrl.speedJ([0, 0, 0, 0, 0.3, 0], 2.0, 0.0)
    time.sleep(0.2)
    assert ctrl.speedStop(4.0)
    wait_fresh(recv)
    wait_fresh(recv)
    assert np.allclose(recv.getActualQd(), 0.0, atol=1e-6)  # stuck joints report exactly 0
    target = np.array(recv.getActualQ()) + np.array([0.05, -0.05, 0.05, 0.0, 0.0, 0.1])
    t0 = time.monotonic()
    assert ctrl.moveJ(target.tolist(), 1.0, 2.0)
    took = time.monotonic() - t0
    wait_fresh(recv)
    wait_fresh(recv)
    # Position loop settles to well below a milliradian.
    assert np.allclose(recv.getActualQ(), target, atol=1e-3)
    assert took > 0.1  # 0.1 rad at 2 rad/s² needs ~0.45 s: it did block
    assert ctrl.isSteady()


@needs_ur_rtde
def test_second_control_interface_is_refused(ur10_twin: URTwin, ur10_clients) -> None:  # type: ignore[no-untyped-def]
    """Input registers belong to the first control connection: a second one gets IN_USE
    and the client raises, as against a real controller."""
    with pytest.raises(RuntimeError, match="already in use"):
        rtde_control.RTDEControlInterface(ur10_twin.host)
    _, ctrl = ur10_clients
    assert ctrl.speedStop(5.0)  # the first one still works


@needs_ur_rtde
def test_stall_stops_the_stream_and_it_resumes(ur10_twin: URTwin, ur10_clients) -> None:  # type: ignore[no-untyped-def]
    """A short stall sends nothing (no stale packages are made up) and the stream resumes
    with the controller clock having run on."""
    recv, _ = ur10_clients
    _, before = wait_fresh(recv)
    ur10_twin.stall(0.5)
    time.sleep(0.02)  # let the packages already on their way arrive
    with pytest.raises(TimeoutError):
        wait_fresh(recv, timeout_s=0.3)
    time.sleep(0.3)
    _, after = wait_fresh(recv, timeout_s=0.5)
    assert after - before > 0.45  # the controller clock ran through the stall


@needs_ur_rtde
def test_reconnect_stops_the_old_program_and_uploads_again() -> None:
    """A control interface that reconnects finds the program running, stops it (255 and
    dashboard ``stop``) and uploads its script again."""
    host = "127.0.0.24"
    with URTwin("ur10e", host):
        ctrl = rtde_control.RTDEControlInterface(host)
        ctrl.disconnect()  # leaves the program running
        ctrl = rtde_control.RTDEControlInterface(host)
        try:
            assert ctrl.isProgramRunning()
            assert ctrl.speedJ([0.1, 0, 0, 0, 0, 0], 1.0, 0.0)
            assert ctrl.speedStop(5.0)
        finally:
            ctrl.stopScript()
            ctrl.disconnect()


def test_address_in_use_is_a_config_error(ur10_twin: URTwin) -> None:
    """A second twin on the same address fails with a message that says what to do."""
    with pytest.raises(ConfigError, match="loopback IP"):
        URTwin("ur10", ur10_twin.host).start()


@needs_ur_rtde
@pytest.mark.slow
def test_effects_response_extra_cycle_delays_packages_by_one_period() -> None:
    """With response_extra_cycle the same controller time stamp reaches the host one
    period later than without it (send time = sample + phase + period)."""
    lags = {}
    for extra, host in ((False, "127.0.0.25"), (True, "127.0.0.26")):
        effects: EffectSet = default_effects("ur10e")
        if extra:
            effects = effects.with_effect(make_effect("response_extra_cycle"))
        with URTwin("ur10e", host, effects=effects, seed=1) as twin:
            recv = rtde_receive.RTDEReceiveInterface(host)
            data = collect(recv, 1.0)
            recv.disconnect()
        sim = ControllerSim("ur10e", seed=1, effects=effects)
        send = np.array([t + sim.packing_phase_s(t) for t in data["ts"]])
        lags[extra] = np.median(data["host"] - twin.t0_monotonic_s - data["ts"])
        # Receipt after the simulated send time (phase and extra period included).
        assert np.median(data["host"] - twin.t0_monotonic_s - send) < 0.005
    assert lags[True] - lags[False] == pytest.approx(0.002, abs=0.001)


def _read_gyro(port: str, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Read the gyro twin's 11-byte frames for ``duration_s``: (unwrapped counters, raw)."""
    serial = pytest.importorskip("serial")
    buf = bytearray()
    with serial.Serial(port, timeout=0.05) as link:
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            buf += link.read(4096)
    data = bytes(buf)
    start = data.find(b"\xa5\x5a")
    frames = [data[i : i + 11] for i in range(start, len(data) - 10, 11)]
    frames = [f for f in frames if f[:2] == b"\xa5\x5a"]
    counter = np.array([struct.unpack("<H", f[2:4])[0] for f in frames], dtype=np.int64)
    raw = np.array([struct.unpack("<3h", f[4:10]) for f in frames], dtype=np.float64)
    steps = np.diff(counter) % 65536
    return np.concatenate([[counter[0]], counter[0] + np.cumsum(steps)]), raw


@needs_ur_rtde
@pytest.mark.realtime_twin
@pytest.mark.slow
def test_gyro_twin_measures_the_simulated_flange_rate(tmp_path: Path) -> None:
    """With ``imu_link`` the twin streams the physics' flange rate through the gyro twin:
    a joint 6 speedJ shows on the gyro's z axis at the commanded speed, starting at the
    ground-truth onset (mapped through the gyro's clock and its 0.98 ms filter delay)."""
    pytest.importorskip("serial")  # the gyro twin is read through pyserial
    host = "127.0.0.27"
    link = str(tmp_path / "gyro")
    truth = tmp_path / "truth.jsonl"
    with URTwin("ur10e", host, imu_link=link, truth_path=truth, seed=2) as twin:
        recv = rtde_receive.RTDEReceiveInterface(host)
        ctrl = rtde_control.RTDEControlInterface(host)
        try:
            _read_gyro(link, 0.2)  # drain the backlog
            host_cmd, _ = wait_fresh(recv)
            assert ctrl.speedJ([0, 0, 0, 0, 0, 0.5], 5.0, 0.0)
            counter, raw = _read_gyro(link, 0.6)
            assert ctrl.speedStop(5.0)
        finally:
            ctrl.stopScript()
            ctrl.disconnect()
            recv.disconnect()
        rec = command_record(truth, "SpeedJ", twin.controller_time_s(host_cmd))
    gyro = next(json.loads(line) for line in truth.read_text().splitlines() if '"gyro"' in line)
    rate = np.radians(raw / 65.5)  # ±500 °/s range: 65.5 LSB per °/s
    rate -= rate[:200].mean(axis=0)  # bias from the still start
    # Wrist 3 turns about the tool z axis: |z| reaches the commanded 0.5 rad/s (±5 %:
    # servo overshoot and 0.3 °/s noise), x and y stay near zero.
    assert np.abs(rate[-200:, 2]).mean() == pytest.approx(0.5, rel=0.05)
    assert np.abs(rate[-200:, :2]).max() < 0.05
    # Absolute sample index: the counter wraps every 65536 samples (8.2 s).
    now_k = (time.monotonic() - gyro["start_time_s"]) * gyro["true_rate_hz"]
    counter = counter + 65536 * np.round((now_k - counter[-1]) / 65536)
    content_s = (
        gyro["start_time_s"]
        + counter / gyro["true_rate_hz"]
        - gyro["dlpf_group_delay_s"]
        - twin.t0_monotonic_s
    )
    threshold = default_settings("ur10e").servo.onset_threshold_rad_s  # truth's definition
    moving = np.abs(rate[:, 2]) > threshold
    onset_gyro = content_s[np.flatnonzero(moving)[0]]
    # Same threshold as the truth: equal up to the noise (0.0055 rad/s std against a
    # ramp of >= 5 rad/s² is ~1 ms per sigma; 3 ms is 3 sigma) and the 0.25 ms physics step.
    assert abs(onset_gyro - rec["onset_s"][5]) < 0.003


@needs_ur_rtde
def test_run_ur_twin_serves_until_sigterm() -> None:
    """The blocking entry point (for ``timedexec serve``) serves the client and exits
    cleanly on SIGTERM."""
    import signal
    import subprocess
    import sys

    host = "127.0.0.28"
    code = f"from timedexec.twins import run_ur_twin; run_ur_twin('ur10', {host!r})"
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE)
    try:
        recv = None
        end = time.monotonic() + 20.0
        while recv is None:
            try:
                recv = rtde_receive.RTDEReceiveInterface(host)
            except RuntimeError:
                assert time.monotonic() < end, "run_ur_twin did not start listening"
                time.sleep(0.2)
        _, stamp = wait_fresh(recv)
        assert stamp > 0
        recv.disconnect()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@needs_ur_rtde
def test_upper_range_registers() -> None:
    """With FLAG_UPPER_RANGE_REGISTERS the client uses registers 24+; the twin follows."""
    host = "127.0.0.29"
    flags = (
        rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        | rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
    )
    with URTwin("ur10e", host):
        ctrl = rtde_control.RTDEControlInterface(host, -1.0, flags)
        recv = rtde_receive.RTDEReceiveInterface(host)
        try:
            assert ctrl.speedJ([0.2, 0, 0, 0, 0, 0], 4.0, 0.0)
            time.sleep(0.3)
            assert recv.getActualQd()[0] == pytest.approx(0.2, rel=0.02)  # servo settled
            assert ctrl.speedStop(5.0)
            assert ctrl.isSteady()
        finally:
            ctrl.stopScript()
            ctrl.disconnect()
            recv.disconnect()


def test_rtde_reader_stamps_what_arrived_when_it_arrived() -> None:
    """The twin's RTDE reader takes a package's arrival from the kernel's receive stamp,
    not from when its thread got the interpreter (which the twin's clock thread holds for
    most of each cycle: commands looked up to a cycle late and missed their intake). Bytes
    read 30 ms after they arrived are stamped within 5 ms of their sending (loopback: tens
    of µs; the allowance is for a loaded machine), the read itself 30 ms later."""
    from timedexec.twins import enable_receive_stamps, recv_stamped

    server = socket.create_server(("127.0.0.1", 0))
    with server, socket.create_connection(server.getsockname()) as client:
        conn, _ = server.accept()
        with conn:
            if not enable_receive_stamps(conn):
                pytest.skip("no kernel receive stamps on this platform")
            sent = time.monotonic()
            client.sendall(b"\x00\x07V\x01\x02\x03\x04")
            time.sleep(0.03)
            data, arrival = recv_stamped(conn, 7)
            read = time.monotonic()
    assert data == b"\x00\x07V\x01\x02\x03\x04"
    assert sent - 1e-3 <= arrival <= sent + 5e-3, arrival - sent
    assert read - arrival >= 0.03 - 1e-3
