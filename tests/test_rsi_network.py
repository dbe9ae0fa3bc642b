"""KUKA RSI on a real network (issue 15, item 4): what the loopback-only tests never saw.

Against a public RSI simulator and a real cell the driver failed four ways; each has a test
here, mostly against :mod:`independent_rsi_peer` (a robot side written from KUKA's
documentation, sharing no code with the driver or the twin) and, where physics or a gyro is
needed, the RSI twin:

* a robot that needs seconds for its first frame (the driver gave it 0.5 s);
* a listen address other than loopback (a real KUKA cannot reach 127.0.0.1);
* frames from other senders (a spoofed frame moved the reported state by 1.57 rad);
* an IPOC time base or period other than assumed (a 12-ms-per-unit IPOC read as 1 ms
  reported 2.4 rad/s for 0.2 commanded).

Plus the twin's answer rule (an answer echoing an older IPOC than the latest frame is late,
as on KSS) and the safety case: a host process that dies or hangs mid-motion leaves the arm
at rest through the robot's own late-answer stop.
"""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from independent_rsi_peer import IndependentRSIPeer
from timedexec._rsi_xml import build_sen, parse_rob
from timedexec.drivers import KukaRSIDriver, open_driver
from timedexec.errors import ConfigError, DriverError, DriverTimeout
from timedexec.recording import SweepProtocol
from timedexec.robots import get_robot
from timedexec.sim import default_settings
from timedexec.twins import RSITwin, free_udp_port, read_rsi_truth

KR5 = get_robot("kr5")
T12 = 0.012
Q0 = np.array([0.0, -1.2, 1.4, 0.0, 0.6, 0.0])
Q0_DEG = tuple(math.degrees(x) for x in Q0)
PIPELINE_S = default_settings("kr5").timing.pipeline_cycles * T12  # 72 ms


def _alias_available(ip: str) -> bool:
    """Whether this host can send from the loopback alias ``ip`` (Linux: all of 127/8)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((ip, 0))
        except OSError:
            return False
    return True


def _read_n(drv: KukaRSIDriver, n: int, timeout_s: float = 1.0) -> list:
    return [drv.read_state(timeout_s) for _ in range(n)]


# ------------------------------------------------------------------ URL


def test_rsi_url_options_and_their_errors() -> None:
    """rsi:// takes the listen address before the port or as ?listen=, the robot's IP, the
    IPOC tick in ms (or auto) and the first-frame wait; bad values name value and fix."""
    drv = open_driver("rsi://0.0.0.0:49152")
    assert (drv.host, drv.port, drv.robot_ip) == ("0.0.0.0", 49152, None)
    assert drv.first_frame_timeout_s >= 5.0  # a KUKA needs seconds for its first frame
    drv = open_driver(
        "rsi://49152?listen=192.168.1.5&robot=192.168.1.10&ipoc_tick_ms=12"
        "&first_frame_timeout_s=30&period=0.004"
    )
    assert (drv.host, drv.robot_ip, drv.first_frame_timeout_s) == (
        "192.168.1.5",
        "192.168.1.10",
        30.0,
    )
    assert drv.ipoc_tick_s == pytest.approx(0.012)
    assert drv.controller_period_s == 0.004
    assert open_driver("rsi://49152").host == "127.0.0.1"  # loopback unless asked
    assert open_driver("rsi://49152?ipoc_tick_ms=auto").stats().ipoc_tick_s == 0.001
    cases = {
        "rsi://1.2.3.4:5?listen=1.2.3.5": r"listen address is given twice",
        "rsi://49152?listen=eth0": r"'eth0' is not an IPv4 address.*0\.0\.0\.0",
        "rsi://49152?robot=0.0.0.0": r"robot_ip='0.0.0.0' is not a robot.*192\.168",
        "rsi://49152?ipoc_tick_ms=0": r"ipoc_tick_ms='0' must be auto or .*\(0, 1000\]",
        "rsi://49152?first_frame_timeout_s=-1": r"first_frame_timeout_s='-1'.*0 \.\. 3600",
        "rsi://host:49152": r"host='host' is not an IPv4 address",
        "rsi://49152?bogus=1": r"unknown parameter 'bogus'.*listen, robot, ipoc_tick_ms",
    }
    for url, message in cases.items():
        with pytest.raises(ConfigError, match=message):
            open_driver(url)


# ------------------------------------------------------------------ first frame


def test_first_read_waits_for_a_slow_robot_and_says_so(capfd: pytest.CaptureFixture) -> None:
    """The first read_state after connect waits first_frame_timeout_s for the robot's first
    frame (here 1.5 s late) whatever its own timeout, printing a line each second on
    stderr naming the address:port; later reads use their own timeout."""
    port = free_udp_port()
    with (
        open_driver(f"rsi://{port}?first_frame_timeout_s=5") as drv,
        IndependentRSIPeer(("127.0.0.1", port), first_frame_delay_s=1.5, q_deg=Q0_DEG) as peer,
    ):
        t = time.monotonic()
        state = drv.read_state(timeout_s=0.1)
        waited = time.monotonic() - t
        np.testing.assert_allclose(state.q, np.radians(np.round(Q0_DEG, 4)), atol=1e-9)
        assert peer.answers_in_time >= 0
    # Band: the peer's 1.5 s delay (measured from its thread's start, just after connect)
    # up to 0.5 s of thread start-up and scheduling on a loaded machine.
    assert 1.4 <= waited < 2.0
    err = capfd.readouterr().err
    assert f"waiting for the robot's first RSI frame on UDP 127.0.0.1:{port} (1 s of 5 s" in err


def test_no_robot_times_out_after_the_first_frame_wait() -> None:
    """Nobody sending: DriverTimeout after first_frame_timeout_s, with the checklist
    (RSI_ON, IP_NUMBER/PORT, firewall) in the message."""
    drv = KukaRSIDriver(0, first_frame_timeout_s=0.6, progress=False)
    with drv:
        t = time.monotonic()
        with pytest.raises(DriverTimeout, match=r"within 0.6 s .*IP_NUMBER, PORT.*firewall"):
            drv.read_state(0.05)
        # Band: not before 0.6 s; 0.4 s for a loaded machine.
        assert 0.6 <= time.monotonic() - t < 1.0


# ------------------------------------------------------------------ listen address


def test_listen_on_every_interface() -> None:
    """rsi://0.0.0.0:PORT binds every interface; a robot sending to 127.0.0.1 reaches it
    and gets its answers."""
    port = free_udp_port()
    try:
        drv = open_driver(f"rsi://0.0.0.0:{port}?first_frame_timeout_s=5")
        drv.connect()
    except DriverError as exc:  # a sandbox that forbids binding the wildcard address
        pytest.skip(f"cannot listen on 0.0.0.0 here: {exc}")
    try:
        with IndependentRSIPeer(("127.0.0.1", port), q_deg=Q0_DEG) as peer:
            _read_n(drv, 10)
            time.sleep(0.1)  # the answers are in (late ones too, on a loaded machine)
        assert drv.stats().answers >= 10
        assert peer.answers_total >= 10
        assert drv.peer_address == peer.address
    finally:
        drv.close()


# ------------------------------------------------------------------ peer lock


def test_frames_from_other_senders_are_ignored_and_reported(
    capfd: pytest.CaptureFixture,
) -> None:
    """Without ?robot=: the first sender of a valid frame is the robot; frames from another
    (ip, port) with a pose 1.57 rad away are neither parsed nor answered, never move the
    reported state, and are counted, with the last foreign address, and reported on close."""
    port = free_udp_port()
    drv = open_driver(f"rsi://{port}?first_frame_timeout_s=5")
    with drv, IndependentRSIPeer(("127.0.0.1", port), q_deg=Q0_DEG) as robot:
        first = drv.read_state(2.0)
        spoofed = list(Q0_DEG)
        spoofed[0] += 90.0  # the 1.57 rad jump
        with IndependentRSIPeer(("127.0.0.1", port), q_deg=spoofed, max_frames=30) as spoofer:
            states = _read_n(drv, 40)
            spoofer.close()
        assert spoofer.frames_sent == 30
        assert spoofer.answers_total == 0  # never answered
        time.sleep(0.05)  # the last spoofed datagrams are in
        assert drv.ignored_frames == 30
        assert drv.last_foreign_address == spoofer.address
        assert drv.peer_address == robot.address
        qs = np.array([s.q for s in [first, *states]])
        assert np.ptp(qs, axis=0).max() < 1e-9  # the reported state never jumped
        assert drv.stats().sessions == 1
    err = capfd.readouterr().err
    assert "ignored 30 RSI datagram(s)" in err
    assert f"last from {spoofer.address[0]}:{spoofer.address[1]}" in err


def test_robot_ip_refuses_a_sender_that_comes_first() -> None:
    """?robot=IP: a spoofer from another IP that starts sending before the robot cannot
    take the lock (without ?robot= it would: the first sender wins)."""
    if not _alias_available("127.0.0.2"):
        pytest.skip("cannot send from the loopback alias 127.0.0.2 here")
    port = free_udp_port()
    spoofed = list(Q0_DEG)
    spoofed[0] += 90.0
    drv = open_driver(f"rsi://{port}?robot=127.0.0.1&first_frame_timeout_s=5")
    with (
        drv,
        IndependentRSIPeer(("127.0.0.1", port), source_host="127.0.0.2", q_deg=spoofed) as spoof,
        IndependentRSIPeer(("127.0.0.1", port), first_frame_delay_s=0.3, q_deg=Q0_DEG) as robot,
    ):
        states = _read_n(drv, 20, timeout_s=2.0)
        assert drv.peer_address == robot.address
        assert drv.ignored_frames >= 20  # 0.3 s head start at 12 ms, then one per cycle
        assert drv.last_foreign_address == spoof.address
        assert spoof.answers_total == 0
    assert all(abs(s.q[0] - Q0[0]) < 1e-6 for s in states)


# ------------------------------------------------------------------ IPOC time base


def test_ipoc_time_base_is_checked_against_the_frame_period() -> None:
    """Three robots at once, each ~1 s: (a) an IPOC counting frames (+1 per 12 ms) read
    with ?ipoc_tick_ms=1 -> DriverError naming both periods and ?ipoc_tick_ms=12; (b) the
    same with auto -> a 12 ms tick, speeds right; (c) a 4 ms robot with the driver at the
    default 12 ms -> DriverError naming ?period=0.004."""
    ports = [free_udp_port() for _ in range(3)]
    wrong = open_driver(f"rsi://{ports[0]}?ipoc_tick_ms=1&first_frame_timeout_s=5")
    auto = open_driver(f"rsi://{ports[1]}?first_frame_timeout_s=5")
    fast = open_driver(f"rsi://{ports[2]}?first_frame_timeout_s=5")
    turning = (math.degrees(0.2), 0, 0, 0, 0, 0)  # joint 1 at 0.2 rad/s
    with wrong, auto, fast:
        # No RSITimeout here: this is about the time base, and on a loaded machine the
        # three drivers' answers are late now and then.
        patient = {"timeout_packets": 10**9}
        peers = [
            IndependentRSIPeer(("127.0.0.1", ports[0]), ipoc_step=1, q_deg=Q0_DEG, **patient),
            IndependentRSIPeer(("127.0.0.1", ports[1]), ipoc_step=1, qd_deg_s=turning, **patient),
            IndependentRSIPeer(("127.0.0.1", ports[2]), period_s=0.004, ipoc_step=4, **patient),
        ]
        for p in peers:
            p.__enter__()
        try:
            auto_states = _read_n(auto, 10, timeout_s=2.0)
            errors = {}
            end = time.monotonic() + 5.0
            while len(errors) < 2 and time.monotonic() < end:
                for name, drv in (("wrong", wrong), ("fast", fast)):
                    if name not in errors:
                        try:
                            drv.read_state(0.5)
                        except DriverTimeout:
                            continue  # the peer's thread was not scheduled in time
                        except DriverError as exc:
                            errors[name] = str(exc)
            auto_states += _read_n(auto, 100)  # > 1 s: past the check, no error
            with pytest.raises(DriverError, match=r"cannot speedj: RSI IPOC time base"):
                wrong.speedj(np.zeros(6), 1.0, 1.0)
        finally:
            for p in peers:
                p.close()
    assert errors["wrong"].startswith("RSI IPOC time base: the IPOC advances by 1 per frame")
    assert "ipoc_tick_ms=1 (1 ms per IPOC unit) makes 1.00 ms per frame" in errors["wrong"]
    assert "?ipoc_tick_ms=12" in errors["wrong"]
    arrive = re.search(r"frames arrive every (\d+\.\d+) ms", errors["wrong"])
    assert arrive is not None
    assert 11.0 < float(arrive.group(1)) < 12.0 * 2.5  # 12 ms, more on a loaded machine
    assert errors["fast"].startswith("RSI period: the IPOC advances by 4 per frame")
    assert "the driver's period is 12 ms" in errors["fast"]
    assert "?period=0.004" in errors["fast"]
    assert auto.ipoc_tick_s == pytest.approx(T12)
    steps = np.diff([s.controller_time_s for s in auto_states[:10]])
    np.testing.assert_allclose(steps, T12, rtol=0, atol=1e-12)
    # The peer turns joint 1 by 0.2 rad/s x 12 ms per frame: the driver reports 0.2 rad/s
    # (not the 2.4), to the wire's 1e-4 deg rounding over a 12 ms difference.
    qd = [s.qd[0] for s in auto_states[2:10]]
    np.testing.assert_allclose(qd, 0.2, atol=math.radians(2e-4) / T12)


# ------------------------------------------------------------------ the twin's answer rule


def test_twin_counts_answers_with_a_stale_ipoc_late() -> None:
    """A PC that answers each frame with the *previous* frame's IPOC (in time, but stale)
    gets every cycle counted late by the twin, as on KSS, and none of its corrections
    applied: RSI stops with RSITimeout after Timeout (20) cycles, the robot never moved.
    The independent peer, written from KUKA's documentation, counts the same answers late."""
    pc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    pc.bind(("127.0.0.1", 0))
    pc.settimeout(0.5)
    port = pc.getsockname()[1]
    correction = np.full(6, math.radians(1.0))  # would move every axis by 1 degree
    with RSITwin(port, timeout_packets=20, q0_rad=Q0) as twin:
        previous = None
        answered = 0
        while twin.status().running and answered < 200:
            try:
                data, addr = pc.recvfrom(4096)
            except TimeoutError:
                break
            frame = parse_rob(data)
            assert frame is not None
            if previous is not None:
                pc.sendto(build_sen(previous, correction), addr)
                answered += 1
            previous = frame.ipoc
        status = twin.wait_stopped(10.0)
        answers, frames = twin.answers(), twin.frames()
    twin_truth = twin.truth()
    assert status.reason == "RSITimeout"
    assert status.late_count == 20
    # A twin that fell behind real time sends frames late or back to back; an answer to
    # the earlier frame is then not held against the PC (a real controller is never late),
    # so up to that many stale answers may pass. On time (the usual case): none.
    lenient = status.late_sends  # frames that left over 1 ms late
    burst = math.ceil(status.max_send_lateness_s / T12)
    assert status.answers_in_time <= lenient
    # One late cycle per frame (+ those in flight, + the answers let through).
    assert status.frames_sent <= 22 + burst + status.answers_in_time
    if status.answers_in_time == 0:
        # No correction ever reached the controller (only the brake at the RSI stop).
        assert [r["kind"] for r in twin_truth] in ([], ["StopJ"])
    # The answers that came within their frame's period (which the twin used to take: the
    # issue's ~11 %) are now refused because a newer frame had left: counted late at once.
    # The others ran out their period first (counted late on expiry).
    left = {f["ipoc"]: twin.t0_host_s + f["sent_s"] for f in frames if f["sent_s"] is not None}
    quick = [a for a in answers if a["arrival_host_s"] <= left[a["ipoc"]] + T12]
    assert sum(not a["stale_ipoc"] for a in quick) <= lenient
    print(f"\nstale answers within their period: {len(quick)} of {len(answers)}, all late")
    pc.close()
    # The independent peer: the same stale answers are late there too.
    pc2 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    pc2.bind(("127.0.0.1", 0))
    pc2.settimeout(0.5)
    with IndependentRSIPeer(pc2.getsockname(), timeout_packets=20) as peer:
        previous = None
        while peer.reason == "running":
            try:
                data, addr = pc2.recvfrom(4096)
            except TimeoutError:
                break
            ipoc = int(data.split(b"<IPOC>")[1].split(b"<")[0])
            if previous is not None:
                pc2.sendto(build_sen(previous, correction), addr)
            previous = ipoc
        assert peer.reason == "RSITimeout"
        assert peer.answers_in_time == 0
    pc2.close()


# ------------------------------------------------------------------ calibration


@pytest.mark.slow
def test_calibration_through_rsi_with_a_slow_robot_and_a_spoofer(
    tmp_path: Path, capfd: pytest.CaptureFixture
) -> None:
    """Two calibration trials through ``rsi://PORT`` (the calibration API, the RSI twin
    with its gyro) against a robot that sends its first frame 3 s after the driver is up,
    while a spoofer on the same host sends plausible frames (pose 1.57 rad away) to the
    same port from another source port: the calibration succeeds, the driver waited with
    a progress line per second, and it ignored (and reports) every spoofed frame."""
    from timedexec._realtime import realtime
    from timedexec.calibration import run_calibration
    from timedexec.recording import SweepPlan
    from timedexec.sensors import open_gyro
    from timedexec.twins import publish_controller_origin, rsi_gyro_factory

    plan = SweepPlan.generate("kr5", 2, seed=5)
    link, out = str(tmp_path / "gyro"), tmp_path / "cal.h5"
    port = free_udp_port()
    twin = RSITwin(
        port,
        seed=5,
        q0_rad=plan.q_start_rad[0],
        controller_factory=rsi_gyro_factory(link),
        first_frame_delay_s=3.0,
        # This test is about the first frame and the spoofer, not the late-answer stop
        # (test_rsi.py covers it): a loaded CI machine must not end the run with it.
        timeout_packets=2000,
    )
    spoofed = [math.degrees(x) for x in plan.q_start_rad[0]]
    spoofed[0] += 90.0
    with twin:
        publish_controller_origin(link, twin.t0_host_s)
        first_frame_at = twin.t0_host_s  # frame 0 leaves at t0 + its packing phase
        robot = open_driver(f"rsi://{port}")  # the default first-frame wait (10 s)
        # As tests/test_live_twins.py: the client's threads at SCHED_FIFO 5 (below the
        # twin's 10) where allowed, or the shared machine delays its answers and reads.
        with realtime(5), robot, open_gyro(link, read_period_s=0.002) as gyro:
            # The spoofer, in its own process (another machine), starts once the robot's
            # first frame has locked the driver: 300 frames at 12 ms, 3.6 s.
            spoofer = subprocess.Popen(
                [
                    sys.executable,
                    str(Path(__file__).with_name("independent_rsi_peer.py")),
                    f"--port={port}",
                    f"--delay={max(0.0, first_frame_at - time.monotonic()) + 0.5}",
                    "--frames=300",
                    "--q-deg",
                    *(f"{x:.4f}" for x in spoofed),
                ],
                stdout=subprocess.PIPE,
                text=True,
            )
            host, _, source_port = _readline(spoofer, 30.0).strip().partition(":")
            t_start = time.monotonic()
            # No pre-flight: its gyro-peak check is the calibration layer's (test_preflight,
            # test_live_twins) and fails when an overloaded machine slows the twin to a
            # fraction of real time; the trials are the same either way.
            result = run_calibration(
                robot,
                gyro,
                plan,
                out,
                protocol=SweepProtocol.for_robot("kr5"),
                progress=False,
                source="rsi://",
                preflight=False,
            )
            assert result.summary()["recorded_now"] == 2
            sent, answered, _late, reason = spoofer.communicate(timeout=30.0)[0].split()
            assert reason == "done"
            time.sleep(0.05)
            ignored = robot.ignored_frames
            assert ignored == int(sent) == 300
            assert int(answered) == 0  # the spoofer never got an answer
            assert robot.last_foreign_address == (host, int(source_port))
            assert robot.stats().sessions == 1
        status = twin.stop()
    assert status.reason == "stopped"
    waited = first_frame_at - t_start
    err = capfd.readouterr().err
    # 3 s after the twin started, minus what opening driver and gyro took: 2-3 lines.
    assert waited > 2.0
    lines = err.count(f"waiting for the robot's first RSI frame on UDP 127.0.0.1:{port}")
    assert math.floor(waited) - 1 <= lines <= math.ceil(waited)
    assert f"ignored {ignored} RSI datagram(s)" in err
    print(f"\nfirst-frame wait {waited:.2f} s ({lines} progress lines); ignored {ignored}")


# ------------------------------------------------------------------ host death


_DRIVER_PROCESS = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from timedexec.drivers import open_driver

    drv = open_driver(f"rsi://{sys.argv[1]}?first_frame_timeout_s=20")
    drv.connect()
    drv.read_state(20.0)
    end = time.monotonic() + 0.1
    while time.monotonic() < end:
        drv.read_state(1.0)
    drv.speedj(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0]), 2.0, 0.0)  # hold until stopped
    while True:
        state = drv.read_state(1.0)
        if drv.correction_rad[1] > 0.06:  # 0.15 s ramp, then 0.1 s at 0.3 rad/s
            print("moving", state.host_time_s, flush=True)
            break
    while True:
        drv.read_state(1.0)
    """
)


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGKILL", "SIGSTOP"])
def test_host_death_mid_motion_leaves_the_arm_at_rest(sig: str, tmp_path: Path) -> None:
    """The driver runs speedj (joint 2 at 0.3 rad/s, held) in its own process; it is killed
    (SIGKILL) or frozen (SIGSTOP) mid-motion. The robot's own safety takes over: without
    answers the correction stays at its last value (absolute mode), so the set-point stops,
    and after Timeout (100) late cycles RSI stops and the robot brakes. From the twin's
    truth: the arm is at rest within Timeout x cycle + the stop ramp of the signal."""
    port = free_udp_port()
    truth_path = tmp_path / "truth.jsonl"
    script = tmp_path / "driver.py"
    script.write_text(_DRIVER_PROCESS)
    with RSITwin(port, q0_rad=Q0, wait_for_pc=True, truth_path=truth_path) as twin:
        proc = subprocess.Popen(
            [sys.executable, str(script), str(port)],
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            line = _readline(proc, 60.0)
            assert line.startswith("moving"), line
            t_signal = time.monotonic()
            os.kill(proc.pid, getattr(signal, sig))
            status = twin.wait_stopped(20.0)
        finally:
            if sig == "SIGSTOP":
                os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
            proc.wait(10.0)
        frames = twin.frames()
    answers = twin.answers()
    data = read_rsi_truth(truth_path)["rsi"]
    # The host's last sign of life in the robot's (controller) time: the arrival of its
    # last answer. Controller time, not the host clock: on an overloaded machine the twin
    # falls behind real time, and its physics runs in controller time.
    t_last = max(a["arrival_s"] for a in answers if a["in_time"])
    # The arm was moving then: joint 2's speed over the last five frames sampled before.
    before = [f for f in frames if f["sample_time_s"] <= t_last]
    v_then = (before[-1]["q_rad"][1] - before[-6]["q_rad"][1]) / (
        before[-1]["sample_time_s"] - before[-6]["sample_time_s"]
    )
    assert v_then > 0.1  # commanded 0.3 rad/s (the 5-frame mean lags on a loaded machine)
    assert status.reason == "RSITimeout"
    assert status.late_count == 100
    rest_s = data["last_motion_s"] - t_last
    stop_s = frames[-1]["sample_time_s"] - t_last  # the last frame sent before RSI stopped
    timeout_s = 100 * T12
    # RSI stopped after Timeout late cycles: 100 frames after the last answer (fewer if some
    # were late before the signal on a loaded machine; +1 for the cycle in progress).
    assert stop_s <= timeout_s + T12
    # The bound (docs/rsi.md): Timeout x cycle until RSI stops, then the brake ramp: the
    # 72 ms pipeline, 0.3 rad/s down at the twin's stop deceleration, two cycles for where
    # the signal fell in its cycle and the rest threshold's own cycle.
    ramp_s = PIPELINE_S + 0.3 / float(np.max(KR5.qdd_max_rad_s2)) + 2 * T12
    assert 0.0 < rest_s <= timeout_s + ramp_s
    print(
        f"\n{sig}: at rest {rest_s * 1e3:.0f} ms after the last answer, RSI stopped "
        f"{stop_s * 1e3:.0f} ms after it (bound {(timeout_s + ramp_s) * 1e3:.0f} ms); "
        f"signal sent at host time {t_signal:.3f}"
    )


def _readline(proc: subprocess.Popen, timeout_s: float) -> str:
    """The child's next stdout line (empty if it ended or timed out)."""
    box: list[str] = []
    reader = threading.Thread(target=lambda: box.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    return box[0] if box else ""
