"""The independently written UR peer (tests/independent_ur_peer/) as a cell where remote control
is forbidden: the pendant program holding Universal Robots' External Control URCap node.

What is checked, and against what:

* the dashboard replies UR documents for ``load`` / ``play`` / ``pause`` / ``stop`` (PolyScope
  3.4+ and 5.x), ``get loaded program`` and ``programState``;
* ``play`` fetches the script the way the URCap does (``request_program\\n`` to the PC address
  of its installation; a reply complete at ``# NODE_CONTROL_LOOP_ENDS`` on a connection the PC
  keeps open) and runs it only when it is ur_rtde's control script, with the register offsets
  written in its header; a PC that is deaf, silent, floods or cuts the script off fails ``play``;
* the real ``ur_rtde`` 1.6.5 client through ``URDriver(..., program=...)`` (its script server
  on 0.0.0.0:50002, ``FLAG_USE_EXT_UR_CAP | FLAG_NO_WAIT``): motion, a watchdog trip that stops
  the program, re-playing it (a host process SIGKILLed mid-motion through this program:
  ``test_execution_safety.py::test_killed_or_paused_host_stops_the_independent_peer_arm``).

The peer runs in a subprocess on 127.0.0.198 (no ur_rtde script server involved) or 127.0.0.199
(with one). ur_rtde's script server binds 0.0.0.0:50002, so one such client at a time; drivers
are closed in ``finally``. Times in s, joint positions in rad, velocities in rad/s; controller
time is the peer's ``cycles * period`` clock from its truth log.
"""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from independent_ur_peer import (
    MAX_URCAP_LINE,
    MAX_URCAP_SCRIPT,
    fetch_urcap_script,
    run_peer,
)

HOST = "127.0.0.198"  # dashboard and fetch tests: a fake PC of this test, no ur_rtde
CLIENT_HOST = "127.0.0.199"  # the real ur_rtde client through the External Control program
PROGRAM = "/programs/external_control.urp"
DASHBOARD_PORT = 29999
#: The peer's program-stop deceleration (its --stop-decel default), rad/s².

#: ur_rtde's control script in miniature (written for this test; the same layout as the text
#: ur_rtde 1.6.5 serves, including its register-offset lines whose value stands on the next
#: line), with the upper register range (offset 24).
CONTROL_SCRIPT = """# HEADER_BEGIN
    global reg_offset_float = # float register offset
24    global reg_offset_int = # int register offset
24    global keep_running = True
    def rtde_cmd():
        return read_input_integer_register(0 + reg_offset_int)
    end
    def signal_ready():
        write_output_integer_register(0 + reg_offset_int, 1)
    end
    def process_cmd(cmd):
        return cmd != 255
    end
# HEADER_END

# NODE_CONTROL_LOOP_BEGINS
        signal_ready()
        while keep_running:
            cmd = rtde_cmd()
            keep_running = process_cmd(cmd)
            sync()
        end
# NODE_CONTROL_LOOP_ENDS
"""
#: Marked like ur_rtde's script but something else: a program the peer cannot interpret.
FOREIGN_SCRIPT = """# HEADER_BEGIN
    def wave():
        movej([0, -1.57, 1.57, -1.57, -1.57, 0.3], a=1.0, v=0.5)
    end
# HEADER_END
# NODE_CONTROL_LOOP_BEGINS
        wave()
# NODE_CONTROL_LOOP_ENDS
"""


# ------------------------------------------------------------------------------------------
# Helpers: a dashboard session, a fake PC serving the URCap's request
# ------------------------------------------------------------------------------------------


class Dashboard:
    """One dashboard session: ``ask`` sends a command line and returns the answer line."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, DASHBOARD_PORT), timeout=10.0)
        self.stream = self.sock.makefile("rwb")
        self.welcome = self.stream.readline().decode().strip()

    def ask(self, command: str) -> str:
        self.stream.write(command.encode() + b"\n")
        self.stream.flush()
        return self.stream.readline().decode().strip()

    def close(self) -> None:
        self.stream.close()
        self.sock.close()


@contextlib.contextmanager
def dashboard(host: str) -> Iterator[Dashboard]:
    d = Dashboard(host)
    try:
        yield d
    finally:
        d.close()


class FakePC:
    """A PC on 127.0.0.1 (a free port) answering each URCap request with ``reply`` (changeable
    between requests), then keeping the connection open (as ur_rtde's script server does) or
    closing it. ``requests`` holds the first line of each request."""

    def __init__(self, reply: bytes = b"", close_after: bool = False) -> None:
        self.reply = reply
        self.close_after = close_after
        self.requests: list[bytes] = []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(0.1)
        self.port = int(self.server.getsockname()[1])
        self.open: list[socket.socket] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with contextlib.suppress(OSError):
                conn.settimeout(2.0)
                self.requests.append(conn.makefile("rb").readline())
                conn.sendall(self.reply)
            if self.close_after:
                conn.close()
            else:
                self.open.append(conn)

    def __enter__(self) -> FakePC:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.server.close()
        for conn in self.open:
            conn.close()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on (bound, then released)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_for(pred, timeout: float = 2.0) -> bool:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


# ------------------------------------------------------------------------------------------
# Dashboard replies
# ------------------------------------------------------------------------------------------


def test_dashboard_replies_and_play_fails_when_nobody_serves_the_script() -> None:
    """Nothing loaded: ``play`` fails; an unknown path is not found; the installed program
    loads and is reported; with nobody listening at the URCap's PC address ``play`` fails and
    the program stays STOPPED (truth log included), with the failed connect logged."""
    port = free_port()
    extra = ("--urcap", f"127.0.0.1:{port}", "--external-control-program", PROGRAM)
    with run_peer(HOST, extra_args=extra) as peer, dashboard(HOST) as dash:
        assert dash.welcome == "Connected: Universal Robots Dashboard Server"
        assert dash.ask("get loaded program") == "No program loaded"
        assert dash.ask("programState") == "STOPPED <unnamed>"
        assert dash.ask("play") == "Failed to execute: play"
        assert dash.ask("load /programs/other.urp") == "File not found: /programs/other.urp"
        assert dash.ask("get loaded program") == "No program loaded"
        assert dash.ask(f"load {PROGRAM}") == f"Loading program: {PROGRAM}"
        assert dash.ask("get loaded program") == f"Loaded program: {PROGRAM}"
        assert dash.ask("programState") == "STOPPED external_control.urp"
        t_play = peer.to_peer_time(time.monotonic())
        assert dash.ask("play") == "Failed to execute: play"
        assert dash.ask("programState") == "STOPPED external_control.urp"
        assert dash.ask("running") == "Program running: false"
        assert dash.ask("stop") == "Failed to execute: stop"
        failed = peer.wait_event("urcap_fetch_failed", timeout=2.0)
        assert failed.fields["pc"] == f"127.0.0.1:{port}"
        assert failed.fields["reason"].startswith("connect_failed"), failed.fields
        assert peer.wait_event("play_failed", timeout=2.0).fields["path"] == PROGRAM
        # 0.3 s of controller time after the play: a program that started anyway would show
        # runtime_state 2 after the peer's 0.1 s start delay.
        truth = peer.wait_truth_until(t_play + 0.3)
        assert np.all(truth.runtime_state == 1)
        assert not peer.events("program_started")
        assert not peer.events("program_received")


def test_play_runs_a_complete_control_script_and_refuses_cut_or_foreign_ones() -> None:
    """A fake PC at the URCap's address: a script cut off before ``# NODE_CONTROL_LOOP_ENDS``
    (connection closed) fails ``play``; a marked script that is not ur_rtde's is received but
    not run as the control script; ur_rtde's layout (connection left open) starts at once with
    its register offsets (24); pause / play resume without a new request; stop stops."""
    cut = CONTROL_SCRIPT.split("# NODE_CONTROL_LOOP_BEGINS")[0] + "# NODE_CONTROL_LOOP_BEGINS\n"
    with FakePC(cut.encode(), close_after=True) as pc:
        extra = ("--urcap", f"127.0.0.1:{pc.port}")
        with run_peer(HOST, extra_args=extra) as peer, dashboard(HOST) as dash:
            assert dash.ask(f"load {PROGRAM}") == f"Loading program: {PROGRAM}"
            # (1) cut off: incomplete, not started
            assert dash.ask("play") == "Failed to execute: play"
            assert peer.wait_event("urcap_fetch_failed").fields["reason"] == "incomplete"
            assert dash.ask("programState") == "STOPPED external_control.urp"
            # (2) foreign: fetched and "played", but not run with the control-script semantics
            pc.reply, pc.close_after = FOREIGN_SCRIPT.encode(), False
            assert dash.ask("play") == "Starting program"
            ignored = peer.wait_event("foreign_program_ignored", timeout=2.0)
            peer.wait_event("program_stopped", timeout=2.0, after=ignored.time_s - 1e-6)
            assert not peer.events("program_started")
            # (3) ur_rtde's layout on a connection left open: complete at the end marker, so
            # play answers in far less than the peer's 3 s fetch timeout (loopback: ms; 1 s
            # leaves room for a loaded machine and still fails a reader waiting for the close)
            pc.reply = CONTROL_SCRIPT.encode()
            t = time.monotonic()
            assert dash.ask("play") == "Starting program"
            assert time.monotonic() - t < 1.0
            started = peer.wait_event("program_started", timeout=2.0)
            assert started.fields == {
                "offset_int": "24",
                "offset_float": "24",
                "source": "external_control",
            }
            assert wait_for(lambda: dash.ask("programState") == "PLAYING external_control.urp")
            assert dash.ask("running") == "Program running: true"
            assert dash.ask(f"load {PROGRAM}") == f"Error while loading program: {PROGRAM}"
            assert dash.ask("pause") == "Pausing program"
            assert dash.ask("programState") == "PAUSED external_control.urp"
            assert dash.ask("play") == "Starting program"  # resumes
            assert dash.ask("programState") == "PLAYING external_control.urp"
            assert dash.ask("stop") == "Stopped"
            assert dash.ask("programState") == "STOPPED external_control.urp"
            assert peer.events("program_resumed")
            # three fetches (cut, foreign, control); the resume asked for nothing
            assert pc.requests == [b"request_program\n"] * 3


def test_fetch_is_bounded_in_time_and_size() -> None:
    """The URCap-side fetch fails cleanly on a PC that is silent (timeout), floods one line or
    the whole text, closes at once or is not there; a plain script the PC closes after is
    accepted whole. Timeouts here are 0.3 s; the upper bound 1.5 s allows a loaded machine."""
    with FakePC(b"") as silent:
        t = time.monotonic()
        assert fetch_urcap_script(("127.0.0.1", silent.port), timeout_s=0.3) == (None, "timeout")
        assert 0.3 <= time.monotonic() - t <= 1.5
    with FakePC(b"x" * (MAX_URCAP_LINE + 100)) as flood_line:
        assert fetch_urcap_script(("127.0.0.1", flood_line.port)) == (None, "line_too_long")
    big = (b"    textmsg(1)\n" * (MAX_URCAP_SCRIPT // 15 + 100))[: MAX_URCAP_SCRIPT + 1000]
    with FakePC(b"# HEADER_BEGIN\n" + big) as flood_text:
        assert fetch_urcap_script(("127.0.0.1", flood_text.port)) == (None, "too_large")
    with FakePC(b"", close_after=True) as empty:
        assert fetch_urcap_script(("127.0.0.1", empty.port)) == (None, "empty")
    text, reason = fetch_urcap_script(("127.0.0.1", free_port()), timeout_s=1.0)
    assert text is None
    assert reason.startswith("connect_failed"), reason
    plain = "def prog():\n  textmsg(1)\nend\n"
    with FakePC(plain.encode(), close_after=True) as closing:
        assert fetch_urcap_script(("127.0.0.1", closing.port)) == (plain, "ok")
    with FakePC(CONTROL_SCRIPT.encode() + b"# trailing, after the end marker\n") as keeps_open:
        assert fetch_urcap_script(("127.0.0.1", keeps_open.port), timeout_s=1.0) == (
            CONTROL_SCRIPT,
            "ok",
        )


# ------------------------------------------------------------------------------------------
# The real ur_rtde client through the External Control program
# ------------------------------------------------------------------------------------------

SPEED = 0.2  # rad/s on joint 0
ACCEL = 2.0  # rad/s²: the speed is reached in 0.1 s


def test_urdriver_runs_through_the_external_control_program() -> None:
    """URDriver(program=...) loads and plays the program; the peer runs ur_rtde's fetched
    script; speedj moves only joint 0 by ~SPEED x the time between the two commands and the
    arm comes to rest; with the watchdog armed, 0.4 s of silence trips it and stops the
    program; arming again re-plays the program (a second fetch) which then takes commands."""
    pytest.importorskip("rtde_control")
    from timedexec.drivers import URDriver

    extra = ("--urcap", "127.0.0.1:50002", "--external-control-program", PROGRAM)
    with run_peer(CLIENT_HOST, model="UR10", version="5.11.1", extra_args=extra) as peer:
        drv = URDriver(CLIENT_HOST, robot="ur10e", program=PROGRAM)
        try:
            drv.connect()
            started = peer.wait_event("program_started", timeout=2.0)
            assert started.fields["source"] == "external_control"
            assert started.fields["offset_int"] == "0"
            received = peer.events("urcap_script_received")
            assert len(received) == 1
            assert received[0].fields["marked"] == "True"
            q0 = drv.read_state().q
            t_first = time.monotonic()
            drv.speedj([SPEED, 0, 0, 0, 0, 0], ACCEL, 0.1)
            t_first_sent = time.monotonic()
            time.sleep(0.5)
            t_second = time.monotonic()
            drv.speedj([0.0] * 6, ACCEL, 0.1)
            t_second_sent = time.monotonic()
            time.sleep(0.3)  # the 0.1 s ramp down, the 3-cycle pipeline, and margin
            state = drv.read_state()
            moved = state.q - q0
            # The ramps up and down (0.1 s each, symmetric) cancel, so the move is SPEED x the
            # time between the peer taking the two commands. That time lies between the calls'
            # nearest and farthest ends; 0.02 rad (100 ms at SPEED) for a late peer cycle or a
            # late package on a loaded machine.
            low = SPEED * (t_second - t_first_sent) - 0.02
            high = SPEED * (t_second_sent - t_first) + 0.02
            assert low <= moved[0] <= high, (low, moved[0], high)
            assert np.all(np.abs(moved[1:]) < 1e-9), moved
            assert np.all(state.qd == 0.0), state.qd
            # The watchdog stops the program 0.1 s after the last command.
            drv.arm_watchdog(0.1)
            time.sleep(0.4)
            assert drv.watchdog_tripped()
            trip = peer.wait_event("watchdog_trip", timeout=1.0)
            stop = peer.wait_event("program_stopped", timeout=1.0, after=trip.time_s - 1e-6)
            assert stop.fields["reason"] == "watchdog"
            # Arming again plays the program again: the node fetches the script once more.
            drv.arm_watchdog(0.1)
            assert not drv.watchdog_tripped()
            assert len(peer.events("urcap_request")) == 2
            assert len(peer.events("program_started")) == 2
            for _ in range(15):  # 0.3 s of kicks every 20 ms: the replayed program takes them
                drv.kick_watchdog()
                time.sleep(0.02)
            assert not drv.watchdog_tripped()
            assert len(peer.events("watchdog_trip")) == 1
        finally:
            drv.close()
