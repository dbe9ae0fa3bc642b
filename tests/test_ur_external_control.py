"""ur_rtde through Universal Robots' External Control URCap: the UR twin's pendant program
(``load`` / ``play`` / ``pause`` / ``stop`` on the dashboard, replies as the dashboard
server's documentation gives them), the node's script request, and ``URDriver`` with
``FLAG_USE_EXT_UR_CAP`` (a cell without remote control).

The twin (a CB3 UR10: 125 Hz, cheap enough for any CI machine) runs on its own loopback
address; ``ur_rtde``'s script server listens on 0.0.0.0:50002, so the tests that use it run
one at a time (as the whole suite does).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from timedexec.drivers import URDriver, open_driver
from timedexec.errors import ConfigError, DriverError, ProtocolError
from timedexec.twins import (
    DASHBOARD_PORT,
    EXTERNAL_CONTROL_URP,
    URTwin,
    fetch_external_control_script,
)

pytest.importorskip("rtde_control")

HOST = "127.0.0.96"
#: A twin whose External Control node points at a port nobody listens on.
DEAF_HOST = "127.0.0.97"


def dashboard(host: str, *commands: str) -> list[str]:
    """The welcome line and one answer per command, over one dashboard session."""
    with socket.create_connection((host, DASHBOARD_PORT), timeout=10.0) as sock:
        stream = sock.makefile("rwb")
        answers = [stream.readline().decode().strip()]
        for command in commands:
            stream.write(command.encode() + b"\n")
            stream.flush()
            answers.append(stream.readline().decode().strip())
        return answers


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture(scope="module")
def twin() -> Iterator[URTwin]:
    with URTwin("ur10", HOST, seed=5) as t:
        yield t


def test_program_commands_answer_as_documented_and_a_deaf_pc_fails_play() -> None:
    """No program loaded: ``play`` fails, ``get loaded program`` says so; an unknown file is
    ``File not found``; the installed one loads and ``programState`` names it STOPPED;
    ``pause`` with nothing running fails; ``play`` whose node cannot fetch its script (no
    PC on the port) fails and the program stays STOPPED."""
    port = free_tcp_port()  # bound and released: nobody listens there
    with URTwin("ur10", DEAF_HOST, seed=5, external_control=("127.0.0.1", port)):
        answers = dashboard(
            DEAF_HOST,
            "get loaded program",
            "play",
            "load /programs/nope.urp",
            f"load {EXTERNAL_CONTROL_URP}",
            "get loaded program",
            "programState",
            "pause",
            "play",
            "programState",
            "running",
        )
    assert answers[1:] == [
        "No program loaded",
        "Failed to execute: play",
        "File not found: /programs/nope.urp",
        f"Loading program: {EXTERNAL_CONTROL_URP}",
        f"Loaded program: {EXTERNAL_CONTROL_URP}",
        "STOPPED external_control.urp",
        "Failed to execute: pause",
        "Failed to execute: play",
        "STOPPED external_control.urp",
        "Program running: false",
    ]


def test_driver_runs_through_the_external_control_program(twin: URTwin) -> None:
    """``URDriver(program=...)`` opens ur_rtde with FLAG_USE_EXT_UR_CAP, plays the pendant
    program through the dashboard; its node fetches the script from ur_rtde (port 50002)
    and the arm moves on ``speedj``; a watchdog trip stops the program and re-arming plays
    it again; ``close()`` ends the script, the program stops and stays loaded."""
    drv = open_driver(f"ur://{HOST}?program={EXTERNAL_CONTROL_URP}", robot="ur10")
    assert isinstance(drv, URDriver)
    assert drv.external_control
    drv.connect()
    try:
        assert dashboard(HOST, "programState")[1] == "PLAYING external_control.urp"
        q0 = drv.read_state(timeout_s=1.0).q.copy()
        drv.speedj([0.2, 0, 0, 0, 0, 0], 2.0, 0.1)
        time.sleep(0.3)
        drv.speedj([0.0] * 6, 2.0, 0.1)
        time.sleep(0.2)
        moved = drv.read_state(timeout_s=1.0).q[0] - q0[0]
        # 0.3 s at up to 0.2 rad/s after a 0.1 s ramp: 0.02-0.07 rad; the band allows the
        # ramps and the controller's actuation delay, and fails if nothing moved.
        assert 0.01 < moved < 0.1, moved
        drv.arm_watchdog(0.1)
        time.sleep(0.4)  # no command, no kick: the watchdog stops the program
        assert drv.watchdog_tripped()
        drv.arm_watchdog(0.1)  # plays the program again; its node fetches the script
        assert not drv.watchdog_tripped()
        assert dashboard(HOST, "programState")[1] == "PLAYING external_control.urp"
    finally:
        drv.close()
    deadline = time.monotonic() + 2.0
    while dashboard(HOST, "programState")[1] != "STOPPED external_control.urp":
        assert time.monotonic() < deadline, "the program still runs after close()"
        time.sleep(0.05)
    assert dashboard(HOST, "get loaded program")[1] == f"Loaded program: {EXTERNAL_CONTROL_URP}"


def test_driver_names_a_missing_program_and_a_program_that_never_runs(twin: URTwin) -> None:
    """A path the pendant does not have: DriverError quoting the dashboard's answer. No
    program given and nobody presses play: DriverError after ``program_timeout_s``, saying
    what to do, and the driver is closed (port 50002 free for the next one)."""
    with pytest.raises(DriverError, match=r"File not found: /programs/missing\.urp"):
        URDriver(HOST, robot="ur10", program="/programs/missing.urp").connect()
    waiting = URDriver(HOST, robot="ur10", external_control=True, program_timeout_s=0.5)
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="press play on the pendant"):
        waiting.connect()
    # at least the timeout; at most the timeout plus connecting ur_rtde (~1 s on a loaded
    # two-core machine: the receive and control interfaces' handshakes)
    assert 0.5 <= time.monotonic() - t0 <= 3.0
    assert not waiting.is_connected


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("ur://h?ur_cap_port=70000", "ur_cap_port='70000' must be a port 1..65535"),
        ("ur://h?external_control=maybe", "external_control='maybe' must be 1 or 0"),
        ("ur://h?program=/programs/x.script", "is not a pendant program"),
        ("ur://h?frequency=500", "unknown parameter 'frequency'"),
    ],
)
def test_bad_external_control_options_are_named(url: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(".", r"\.")):
        open_driver(url)


def test_url_options_reach_the_driver() -> None:
    drv = open_driver("ur://h?ur_cap_port=50010")
    assert isinstance(drv, URDriver)
    assert (drv.external_control, drv.ur_cap_port, drv.program) == (True, 50010, None)
    plain = open_driver("ur://h")
    assert isinstance(plain, URDriver)
    assert not plain.external_control


class FakePC:
    """A PC's script server for the node's request: sends ``payload`` after
    ``request_program``, then keeps the connection open (as ur_rtde does) or closes it."""

    def __init__(self, payload: bytes, *, close: bool) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.sock.getsockname()[1])
        self.payload, self.close_after = payload, close
        self.request = b""
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.sock.accept()
        with conn:
            self.request = conn.recv(64)
            conn.sendall(self.payload)
            if not self.close_after:
                time.sleep(1.5)
        self.sock.close()


def test_fetch_reads_up_to_the_loop_end_marker_or_the_close() -> None:
    """The script ends at ``# NODE_CONTROL_LOOP_ENDS`` while the PC keeps the connection
    open, or where the PC closes it; the request is ``request_program\\n``."""
    script = b"# HEADER_BEGIN\nglobal x = 1\n# HEADER_END\n# NODE_CONTROL_LOOP_BEGINS\n  sync()\n"
    pc = FakePC(script + b"# NODE_CONTROL_LOOP_ENDS\nnot part of it\n", close=False)
    t0 = time.monotonic()
    text = fetch_external_control_script("127.0.0.1", pc.port, timeout_s=5.0)
    assert time.monotonic() - t0 < 1.0  # did not wait for the close 1.5 s later
    assert pc.request == b"request_program\n"
    assert text.splitlines()[-1] == "# NODE_CONTROL_LOOP_ENDS"
    assert "not part of it" not in text
    closing = FakePC(b"def prog():\n  sync()\nend\n", close=True)
    assert fetch_external_control_script("127.0.0.1", closing.port).startswith("def prog():")


def test_fetch_fails_cleanly_on_silence_floods_and_garbage() -> None:
    """A PC that never finishes: ProtocolError at the timeout; a line beyond the limit or an
    empty answer: ProtocolError; random bytes then a close: text, never an exception other
    than ProtocolError (fuzzed, fixed seed)."""
    silent = FakePC(b"# HEADER_BEGIN\n", close=False)
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match="no complete script"):
        fetch_external_control_script("127.0.0.1", silent.port, timeout_s=0.3)
    assert 0.3 <= time.monotonic() - t0 < 1.3  # the timeout, plus a loaded machine's wake-up
    flood = FakePC(b"x" * (65 * 2**10), close=False)
    with pytest.raises(ProtocolError, match="a line of more than 65536 bytes"):
        fetch_external_control_script("127.0.0.1", flood.port, timeout_s=2.0)
    empty = FakePC(b"", close=True)
    with pytest.raises(ProtocolError, match="closed without"):
        fetch_external_control_script("127.0.0.1", empty.port)
    with pytest.raises(ProtocolError, match="cannot fetch"):
        fetch_external_control_script("127.0.0.1", free_tcp_port(), timeout_s=1.0)
    rng = np.random.default_rng(20261127)
    for _ in range(20):
        garbage = rng.integers(0, 256, int(rng.integers(1, 4000)), dtype=np.uint8).tobytes()
        pc = FakePC(garbage, close=True)
        # a line over the limit or nothing but whitespace is refused (ProtocolError), never
        # another exception
        with contextlib.suppress(ProtocolError):
            assert isinstance(fetch_external_control_script("127.0.0.1", pc.port), str)


def test_serve_names_a_bad_urcap_address(capsys: pytest.CaptureFixture[str]) -> None:
    """``timedexec serve --urcap`` takes HOST:PORT; anything else exits 2 naming the value and
    the form, before anything is served."""
    from timedexec.cli import main

    for bad in ("nonsense", "h:70000", ":50002"):
        assert main(["serve", "--robot", "ur10", "--urcap", bad]) == 2
        assert f"{bad!r} is not HOST:PORT with a port in 1 .. 65535" in capsys.readouterr().err
