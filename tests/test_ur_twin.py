"""The simulated UR controller (UR twin) against the real ``ur_rtde`` client.

The twin runs in its own process (spawned by ``URTwin``) on a private loopback address per
fixture (127.0.0.2x), because the client's ports are fixed. Timing bands are wide enough
for a loaded two-core CI machine and are justified next to each assert.
"""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from timedexec.effects import EffectSet, default_effects, make_effect
from timedexec.errors import ConfigError
from timedexec.sim import ControllerSim, SpeedJ, default_settings
from timedexec.twins import UR_CONTROLLER_VERSIONS, URTwin, read_truth
from timedexec.twins._ur import _OUTPUT_TYPES, _Recipe, _split_program, _TwinServer

rtde_receive = pytest.importorskip("rtde_receive")
rtde_control = pytest.importorskip("rtde_control")

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


# --------------------------------------------------------------------------------------
# Offline parts (no sockets)
# --------------------------------------------------------------------------------------


def test_type_table_covers_the_receive_defaults_with_the_client_sizes() -> None:
    """Every field ur_rtde's receive interface asks for by default is served, with the
    byte size the client decodes (it uses its own table: a wrong size shifts every field)."""
    sizes = {"VECTOR6D": 48, "VECTOR3D": 24, "VECTOR6INT32": 24, "DOUBLE": 8, "UINT64": 8,
             "UINT32": 4, "INT32": 4}  # fmt: skip
    for name in RECEIVE_DEFAULTS:
        assert name in _OUTPUT_TYPES, name
    assert _OUTPUT_TYPES["actual_tool_accelerometer"] == "VECTOR3D"
    assert _OUTPUT_TYPES["payload_cog"] == "VECTOR3D"
    assert _OUTPUT_TYPES["joint_mode"] == "VECTOR6INT32"
    assert _OUTPUT_TYPES["actual_digital_input_bits"] == "UINT64"
    assert _OUTPUT_TYPES["robot_mode"] == "INT32"
    assert _OUTPUT_TYPES["runtime_state"] == "UINT32"
    recipe = _Recipe.build(1, RECEIVE_DEFAULTS, _OUTPUT_TYPES)
    expected = 1 + sum(sizes[_OUTPUT_TYPES[n]] for n in RECEIVE_DEFAULTS)
    assert recipe.struct.size == expected


def test_recipe_round_trip_and_short_input_packages() -> None:
    """Input packages decode by the negotiated types; a package shorter than its recipe
    (the client packs only the values a command uses) decodes the fields that fit."""
    from timedexec.twins._ur import _INPUT_TYPES

    names = ["input_int_register_0", *[f"input_double_register_{i}" for i in range(8)],
             "input_int_register_1"]  # fmt: skip
    recipe = _Recipe.build(3, names, _INPUT_TYPES)
    payload = struct.pack(">Bi8di", 3, 9, *range(8), 1)
    values = recipe.unpack(payload)
    assert values["input_int_register_0"] == 9
    assert values["input_double_register_7"] == 7.0
    assert values["input_int_register_1"] == 1
    short = recipe.unpack(struct.pack(">Bid", 3, 15, 2.5))
    assert short["input_int_register_0"] == 15
    assert short["input_double_register_0"] == 2.5
    assert short["input_double_register_1"] == 0.0


def test_split_program_needs_the_closing_end() -> None:
    """A script upload is a program only once its top-level ``end`` line has arrived;
    indented ``end`` lines close inner blocks."""
    part = "def rtde_control():\n  if True:\n    x = 1\n  end\n"
    assert _split_program(part) == (None, part)
    program, rest = _split_program(part + "end\nrtde_control()\n")
    assert program is not None
    assert program.endswith("\nend")
    assert rest == "rtde_control()\n"


@pytest.mark.parametrize("extra", [False, True])
def test_early_package_equals_the_cycle_package(extra: bool) -> None:
    """The package the twin sends before computing a cycle equals the one
    ``ControllerSim.cycle()`` returns afterwards (bit for bit), with and without the
    response_extra_cycle effect, while a command moves the arm."""
    effects = default_effects("ur10e")
    if extra:
        effects = effects.with_effect(make_effect("response_extra_cycle"))
    server = _TwinServer(
        "ur10e", "127.0.0.1", effects=effects, sim_factory=None, log=lambda _m: None
    )
    sim = server.sim
    for k in range(120):
        if k == 10:
            sim.submit(SpeedJ((0.0, 0.3, 0.0, 0.0, 0.0, 0.0), 3.0, 0.0), arrival_s=sim.time_s)
        peeked = server._peek_packet()
        packet = sim.cycle().packet
        server._check_peek(peeked, packet)
    assert server.stats["peek_mismatches"] == 0
    server.close()


def test_truth_records_are_appended_and_read_back(tmp_path: Path) -> None:
    """Ground truth goes to a JSON-lines file (meta line first, one line per new or changed
    record, flushed); ``read_truth`` keeps the latest record per command id."""
    path = tmp_path / "truth.jsonl"
    server = _TwinServer("ur10", "127.0.0.1", truth_path=path, log=lambda _m: None)
    server._write_meta()
    sim = server.sim
    sim.submit(SpeedJ((0.3, 0.0, 0.0, 0.0, 0.0, 0.0), 2.0, 0.0), arrival_s=0.0105)
    for _ in range(40):
        sim.cycle()
        server._write_truth()
    meta, commands = read_truth(path)
    assert meta["robot"] == "ur10"
    assert meta["period_s"] == pytest.approx(0.008)
    (record,) = commands.values()
    assert record["kind"] == "SpeedJ"
    assert record["intake_s"] == pytest.approx(0.016)  # first boundary after 10.5 ms
    assert record["onset_s"][0] is not None
    assert len(path.read_text().splitlines()) >= 3  # meta + first sight + completed
    server.close()


def test_bad_robot_name_is_a_config_error() -> None:
    """Only the simulated URs can be served; the message names the choices."""
    with pytest.raises(ConfigError, match="ur10e"):
        URTwin("kr5")


def test_dashboard_answers_what_the_client_expects() -> None:
    """Dashboard replies the client parses: version with four numbers, a numeric serial,
    remote control on, ``stop`` answered exactly ``Stopped``."""
    server = _TwinServer("ur10e", "127.0.0.1", log=lambda _m: None)
    assert server._dashboard_reply("PolyscopeVersion").startswith("URSoftware 5.11.1.")
    assert server._dashboard_reply("get serial number").isdigit()
    assert server._dashboard_reply("is in remote control") == "true"
    assert server._dashboard_reply("stop") == "Stopped"
    assert server._dashboard_reply("frobnicate").startswith("could not understand")
    server.close()


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


@pytest.mark.parametrize(
    ("robot", "host", "period_s"), [("ur10", "127.0.0.22", 0.008), ("ur10e", "127.0.0.23", 0.002)]
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


def test_control_interface_connects_and_runs_the_script(ur10_clients) -> None:  # type: ignore[no-untyped-def]
    """The control interface finds the program running (runtime_state 2, status bits 3)."""
    recv, ctrl = ur10_clients
    assert ctrl.isConnected()
    assert ctrl.isProgramRunning()
    assert recv.getRuntimeState() == 2
    assert recv.getRobotStatus() == 3


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


def test_second_control_interface_is_refused(ur10_twin: URTwin, ur10_clients) -> None:  # type: ignore[no-untyped-def]
    """Input registers belong to the first control connection: a second one gets IN_USE
    and the client raises, as against a real controller."""
    with pytest.raises(RuntimeError, match="already in use"):
        rtde_control.RTDEControlInterface(ur10_twin.host)
    _, ctrl = ur10_clients
    assert ctrl.speedStop(5.0)  # the first one still works


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


@pytest.mark.slow
def test_gyro_twin_measures_the_simulated_flange_rate(tmp_path: Path) -> None:
    """With ``imu_link`` the twin streams the physics' flange rate through the gyro twin:
    a joint 6 speedJ shows on the gyro's z axis at the commanded speed, starting at the
    ground-truth onset (mapped through the gyro's clock and its 0.98 ms filter delay)."""
    pytest.importorskip("timedexec.twins._gyro")
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


def test_run_ur_twin_serves_until_sigterm() -> None:
    """The blocking entry point (for ``timedexec serve``) serves the client and exits
    cleanly on SIGTERM."""
    import signal
    import subprocess
    import sys

    host = "127.0.0.28"
    code = f"from timedexec.twins._ur import run_ur_twin; run_ur_twin('ur10', {host!r})"
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
