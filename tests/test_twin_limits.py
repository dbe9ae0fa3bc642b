"""The UR twin under abusive input: per-connection limits on the script and dashboard ports,
and RTDE protocol versions the real controller does not speak.

A good ``ur_rtde`` client must keep its package rate while another connection sends a huge
line: the twin used to buffer such a line without limit and rescan it on every read, which
took the GIL from the thread that sends the state packages (125 -> 15 packages/s with a
30 MiB line). Each twin runs in its own process on its own loopback address (the client's
ports are fixed).
"""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

from timedexec.twins import (
    DASHBOARD_PORT,
    RTDE_HEADER_SIZE,
    RTDE_PORT,
    SCRIPT_PORT,
    RTDEPackageType,
    URTwin,
    decode_rtde_header,
    encode_rtde_package,
)

try:
    import rtde_receive
except ImportError:
    rtde_receive = None

needs_ur_rtde = pytest.mark.skipif(
    rtde_receive is None, reason="needs the ur_rtde client (pip install ur_rtde)"
)

HOST = "127.0.0.42"  # no other test uses it
PERIOD_S = 0.008  # UR10 (CB3): 125 Hz
#: What the abusive client sends: 30 MiB without a newline, in 1 MiB writes.
FLOOD_BYTES = 30 * 2**20


@pytest.fixture(scope="module")
def twin():  # type: ignore[no-untyped-def]
    with URTwin("ur10", HOST, seed=1) as t:
        yield t


def count_packages(recv: object, duration_s: float) -> int:
    """New controller time stamps a receive interface shows in ``duration_s`` (polled every
    0.5 ms: well under the 8 ms period)."""
    n, last = 0, None
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        ts = recv.getTimestamp()  # type: ignore[attr-defined]
        if ts != last:
            n += 1
            last = ts
        time.sleep(5e-4)
    return n


class Flood(threading.Thread):
    """Connect to ``port`` and send a line of :data:`FLOOD_BYTES` without a newline; when
    the twin closes the connection, connect again; until stopped. Counts the closes."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.stop = threading.Event()
        self.closed = 0
        self.first_close_s: float | None = None
        self.sent_when_closed: list[int] = []

    def run(self) -> None:
        block = b"x" * 2**20
        t0 = time.monotonic()
        while not self.stop.is_set():
            sent = 0
            with socket.create_connection((HOST, self.port), timeout=5.0) as sock:
                try:
                    while sent < FLOOD_BYTES and not self.stop.is_set():
                        sock.sendall(block)
                        sent += len(block)
                    if sent >= FLOOD_BYTES:  # accepted it all: keep the line open
                        self.stop.wait()
                except OSError:  # reset or broken pipe: the twin closed it
                    self.closed += 1
                    self.sent_when_closed.append(sent)
                    if self.first_close_s is None:
                        self.first_close_s = time.monotonic() - t0


@needs_ur_rtde
@pytest.mark.parametrize("port", [DASHBOARD_PORT, SCRIPT_PORT], ids=["dashboard", "script"])
def test_a_huge_line_closes_that_connection_and_the_good_client_keeps_its_rate(
    twin: URTwin, port: int
) -> None:
    """While another client keeps sending 30 MiB lines without a newline to the dashboard
    or the script port (reconnecting whenever the twin closes it), a ur_rtde receive
    interface keeps its package rate, and the twin closes each abusive connection after
    about the line limit (64 KiB), at once."""
    recv = rtde_receive.RTDEReceiveInterface(HOST)
    try:
        count_packages(recv, 0.3)  # the stream is up
        before = count_packages(recv, 2.0)
        flood = Flood(port)
        flood.start()
        try:
            during = count_packages(recv, 2.0)
        finally:
            flood.stop.set()
            flood.join(timeout=10)
        after = count_packages(recv, 1.0)
    finally:
        recv.disconnect()
    nominal = 2.0 / PERIOD_S  # 250 packages in 2 s
    # Band: the loaded two-core CI machine drops packages in any 2 s window (the twin and
    # the client share it with the flood), so the rate under the flood is compared with the
    # rate just before it, measured the same way: at least 80 %, and at least 60 % of the
    # nominal 125 Hz as in test_ur_twin (the unlimited buffer gave 12 %).
    assert during >= 0.8 * before, (before, during)
    assert during >= 0.6 * nominal, (before, during)
    assert after >= 0.6 * nominal / 2, after
    # The abusive connection is closed, again and again, long before 30 MiB: the twin
    # reads at most the limit plus what the socket buffers hold (a few MiB on loopback).
    assert flood.closed >= 2, flood.closed
    assert flood.first_close_s is not None
    assert flood.first_close_s < 1.0
    assert max(flood.sent_when_closed) < FLOOD_BYTES // 2
    assert twin.is_alive


def dashboard_lines(*lines: bytes) -> list[str]:
    """The dashboard's welcome line and its answers to ``lines`` on a new connection."""
    with socket.create_connection((HOST, DASHBOARD_PORT), timeout=5.0) as sock:
        reader = sock.makefile("rb")
        answers = [reader.readline().decode().rstrip("\n")]
        for line in lines:
            sock.sendall(line + b"\n")
            answers.append(reader.readline().decode().rstrip("\n"))
        return answers


def test_dashboard_line_limit_is_per_connection(twin: URTwin) -> None:
    """A dashboard line of 64 KiB + 1 byte closes that connection (EOF, no answer); a line
    just under the limit is answered (named back as not understood), and a new connection
    works."""
    assert dashboard_lines(b"x" * (64 * 2**10 - 1))[1].startswith("could not understand")
    with socket.create_connection((HOST, DASHBOARD_PORT), timeout=5.0) as sock:
        reader = sock.makefile("rb")
        reader.readline()  # welcome
        sock.sendall(b"y" * (64 * 2**10 + 1))
        assert reader.readline() == b""  # closed without an answer
    assert dashboard_lines(b"PolyscopeVersion")[1].startswith("URSoftware 3.15.7.")


def rtde_request(sock: socket.socket, kind: int, payload: bytes) -> bytes:
    """Send one RTDE request, return its reply's payload."""
    sock.sendall(encode_rtde_package(kind, payload))
    head = b""
    while len(head) < RTDE_HEADER_SIZE:
        head += sock.recv(RTDE_HEADER_SIZE - len(head))
    size, got = decode_rtde_header(head)
    assert got == kind
    body = b""
    while len(body) < size - RTDE_HEADER_SIZE:
        body += sock.recv(size - RTDE_HEADER_SIZE - len(body))
    return body


@pytest.mark.parametrize(
    ("payload", "reply"),
    [
        (struct.pack(">H", 2), b"\x01"),
        (struct.pack(">H", 1), b"\x01"),
        (struct.pack(">H", 3), b"\x00"),
        (struct.pack(">H", 99), b"\x00"),
        (struct.pack(">H", 0), b"\x00"),
        (b"\x02", b"\x00"),  # one byte: not a uint16 version
        (b"", b"\x00"),
    ],
)
def test_rtde_protocol_versions_as_the_controller_answers(
    twin: URTwin, payload: bytes, reply: bytes
) -> None:
    """REQUEST_PROTOCOL_VERSION: versions 1 and 2 are accepted (1), anything else, and a
    malformed request, is "not accepted" (0), as a PolyScope 3.x/5.x controller answers;
    the connection stays open and a later request for version 2 is accepted."""
    with socket.create_connection((HOST, RTDE_PORT), timeout=5.0) as sock:
        kind = RTDEPackageType.REQUEST_PROTOCOL_VERSION
        assert rtde_request(sock, kind, payload) == reply
        assert rtde_request(sock, kind, struct.pack(">H", 2)) == b"\x01"


def closed_by_twin(port: int, first: bytes, block: bytes, repeats: int) -> bool:
    """Send ``first`` and then ``block`` ``repeats`` times; whether the twin closed the
    connection (a reset or broken pipe while sending, or end of stream after it)."""
    with socket.create_connection((HOST, port), timeout=5.0) as sock:
        try:
            sock.sendall(first)
            for _ in range(repeats):
                sock.sendall(block)
            return sock.recv(1) == b""
        except (ConnectionResetError, BrokenPipeError):
            return True


def test_script_program_limit_closes_the_connection(twin: URTwin) -> None:
    """A program that grows past the limit (4 MiB) without its closing ``end`` closes that
    connection; a complete program uploaded afterwards on a new connection starts."""
    line = b"  x = 1\n" * (2**20 // 8)  # 1 MiB of short lines
    assert closed_by_twin(SCRIPT_PORT, b"def flood():\n", line, 64)
    with socket.create_connection((HOST, SCRIPT_PORT), timeout=5.0) as sock:
        sock.sendall(b"junk before a program\ndef rtde_control():\n  sync()\nend\n")
        time.sleep(0.05)
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:  # the twin logs the upload and starts the program
        if "PLAYING" in dashboard_lines(b"programState")[1]:
            break
        time.sleep(0.05)
    else:
        pytest.fail("the program uploaded after the abusive one did not start")
    assert dashboard_lines(b"stop")[1] == "Stopped"
    assert np.isfinite(twin.controller_time_s())
