"""The peer process: the script port (30003), the listeners, the command line (``main``)."""

from __future__ import annotations

import argparse
import contextlib
import re
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

from .constants import (
    DASHBOARD_PORT,
    DEFAULT_EXTERNAL_CONTROL_PROGRAM,
    DEFAULT_URCAP,
    MAX_CONNECTIONS,
    MAX_SCRIPT_BYTES,
    RTDE_PORT,
    SCRIPT_PORT,
)
from .controller import Controller
from .dashboard import serve_dashboard
from .physics import DEFAULT_Q0
from .rtde import RtdeServer

_PROGRAM_RE = re.compile(r"^(def|sec)\s+\w+\s*\(\s*\)\s*:.*?^end\s*$", re.M | re.S)


def _serve_script(sock: socket.socket, ctl: Controller) -> None:
    buf = ""
    try:
        while not ctl.stop_event.is_set():
            chunk = sock.recv(65536)
            if not chunk:
                return
            buf += chunk.decode("utf-8", "replace").replace("\r", "")
            if len(buf) > MAX_SCRIPT_BYTES:
                ctl.event("script_abuse", buffered=len(buf))
                return
            while True:
                m = _PROGRAM_RE.search(buf)
                if m is None:
                    break
                ctl.load_program(m.group(0))
                buf = buf[m.end() :]
    except OSError:
        return
    finally:
        with contextlib.suppress(OSError):
            sock.close()


def _listen(host: str, port: int) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind((host, port))
    s.listen(8)
    s.settimeout(0.2)
    return s


def _accept_loop(
    lsock: socket.socket, ctl: Controller, handle: Callable[[socket.socket], None]
) -> None:
    """Accept connections, each handled in a thread until it ends (at most MAX_CONNECTIONS)."""
    slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
    while not ctl.stop_event.is_set():
        try:
            sock, _ = lsock.accept()
        except TimeoutError:
            continue
        except OSError:
            return
        sock.settimeout(None)
        if not slots.acquire(blocking=False):
            ctl.event("connection_refused", port=lsock.getsockname()[1], limit=MAX_CONNECTIONS)
            sock.close()
            continue

        def run(sock: socket.socket = sock) -> None:
            try:
                handle(sock)
            finally:
                slots.release()

        threading.Thread(target=run, daemon=True).start()


def _parse_version(text: str) -> tuple[int, int, int, int]:
    parts = [int(x) for x in text.split(".")]
    while len(parts) < 3:
        parts.append(0)
    if len(parts) < 4:
        parts.append(108318 if parts[0] >= 4 else 1000)
    return parts[0], parts[1], parts[2], parts[3]


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(
        prog="python -m independent_ur_peer",
        description="An independently written Universal Robots controller peer for the real "
        "ur_rtde client.",
    )
    ap.add_argument("--host", default="127.0.0.171", help="loopback address to listen on")
    ap.add_argument("--model", default="UR10")
    ap.add_argument("--version", default="5.11.1", help="PolyScope version, e.g. 5.11.1, 3.15.7")
    ap.add_argument("--truth", type=Path, default=None, help="CSV truth log to append to")
    ap.add_argument(
        "--stop-decel",
        type=float,
        default=3.0,
        help="program-stop deceleration, rad/s^2 (leading axis)",
    )
    ap.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        help="SCHED_FIFO priority of the controller cycle (Linux, needs the right; 0: normal)",
    )
    ap.add_argument(
        "--input-log",
        type=Path,
        default=None,
        help="CSV of every RTDE input package: arrival_s,intake_s,read_s (controller s: "
        "arrival, the boundary of the cycle that took it, when that cycle read the inputs)",
    )
    ap.add_argument(
        "--publish-delay",
        type=float,
        default=0.0,
        help="s from the cycle boundary to sending its state package (below one period; "
        "0: as soon as the cycle is computed)",
    )
    ap.add_argument(
        "--start-delay",
        type=float,
        default=0.1,
        help="s from script upload to runtime_state PLAYING",
    )
    ap.add_argument(
        "--servo-friction",
        type=float,
        default=0.0,
        help="Coulomb friction per unit inertia, rad/s^2: the actual joints follow the "
        "delayed reference through a PD position servo against friction (0: they are it)",
    )
    ap.add_argument(
        "--q0",
        default=",".join(str(q) for q in DEFAULT_Q0),
        help="initial joint positions, rad, comma separated",
    )
    ap.add_argument(
        "--urcap",
        default=DEFAULT_URCAP,
        metavar="HOST:PORT",
        help="where the External Control URCap's installation says the PC serves the script",
    )
    ap.add_argument(
        "--external-control-program",
        default=DEFAULT_EXTERNAL_CONTROL_PROGRAM,
        metavar="PATH",
        help="the installed pendant program holding the External Control node",
    )
    args = ap.parse_args(argv)
    q0 = [float(x) for x in args.q0.split(",")]
    if len(q0) != 6:
        ap.error("--q0 needs 6 values")
    urcap_host, _, urcap_port = args.urcap.rpartition(":")
    if not urcap_host or not urcap_port.isdigit() or not 0 < int(urcap_port) < 65536:
        ap.error(f"--urcap {args.urcap!r} is not HOST:PORT")
    ctl = Controller(
        args.model,
        _parse_version(args.version),
        args.truth,
        args.stop_decel,
        args.start_delay,
        q0,
        urcap=(urcap_host, int(urcap_port)),
        installed_program=args.external_control_program,
    )
    ctl.rt_priority = args.rt_priority
    if not 0.0 <= args.servo_friction < 100.0:
        ap.error(f"--servo-friction {args.servo_friction} outside [0, 100) rad/s^2")
    ctl.arm.friction = args.servo_friction
    if not 0 <= args.publish_delay < 1.0 / ctl.rate_hz:
        ap.error(f"--publish-delay {args.publish_delay} s outside [0, one period)")
    ctl.publish_delay_s = args.publish_delay
    if args.input_log is not None:
        # line-buffered: a reader sees every package up to the last cycle
        ctl.input_log = open(args.input_log, "a", encoding="ascii", buffering=1)  # noqa: SIM115
    rtde = RtdeServer(ctl)
    listeners = [
        (_listen(args.host, RTDE_PORT), rtde.on_accept),
        (_listen(args.host, DASHBOARD_PORT), lambda s: serve_dashboard(s, ctl)),
        (_listen(args.host, SCRIPT_PORT), lambda s: _serve_script(s, ctl)),
    ]
    signal.signal(signal.SIGTERM, lambda *_: ctl.stop_event.set())
    signal.signal(signal.SIGINT, lambda *_: ctl.stop_event.set())
    threads = [
        threading.Thread(target=_accept_loop, args=(ls, ctl, h), daemon=True) for ls, h in listeners
    ]
    for t in threads:
        t.start()
    loop = threading.Thread(target=ctl.run, name="controller")
    ctl.t0 = time.monotonic()
    ctl.event("peer_started", rate_hz=ctl.rate_hz, t0_monotonic=f"{ctl.t0:.6f}")
    loop.start()
    print("ready", flush=True)
    while not ctl.stop_event.wait(0.05):
        pass
    loop.join(timeout=2.0)
    for ls, _ in listeners:
        with contextlib.suppress(OSError):
            ls.close()
    with ctl.lock:
        conns = list(ctl.connections)
    for c in conns:
        c.close()
    ctl.event("peer_exit")
    if ctl._truth is not None:
        ctl._truth.close()
    if ctl.input_log is not None:
        ctl.input_log.close()
    return 0
