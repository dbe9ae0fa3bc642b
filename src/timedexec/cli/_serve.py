"""``timedexec serve``: a protocol twin, a simulated UR or KUKA controller on the network."""

from __future__ import annotations

import argparse
import contextlib
import sys
from typing import Any

from timedexec._files import check_folder_takes_files
from timedexec.cli._common import (
    add_command,
    add_period,
    add_robot,
    add_seed,
    check_files,
    int_arg,
    note,
)
from timedexec.errors import ConfigError
from timedexec.robots import ROBOT_NAMES, get_robot_entry

__all__ = ["add_parser", "run"]


def _speaks(interface: str) -> list[str]:
    """The catalog's robots whose controller speaks ``interface``."""
    return [n for n in ROBOT_NAMES if get_robot_entry(n).twin.interface == interface]


def add_parser(sub: Any) -> None:
    """Add ``serve`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "serve",
        help="run a protocol twin: a simulated UR or KUKA controller on the network",
        description=(
            "Serve a simulated robot controller that real clients talk to: for "
            f"{'/'.join(_speaks('ur_rtde'))} a UR controller (RTDE on 30004, dashboard on "
            "29999, script port 30003) for the ur_rtde client; for "
            f"{'/'.join(_speaks('kuka_rsi'))} a KUKA controller sending RSI XML over UDP to "
            "the PC's port every 12 ms (or --period 0.004). With --imu-link, a simulated gyro "
            "on the flange streams over a pseudo-terminal linked at that path. Runs until "
            "Ctrl-C or SIGTERM, then exits 0. Binds 127.0.0.1 unless told otherwise.\n\n"
            "examples:\n  timedexec serve --robot ur10 --imu-link /tmp/gyro\n"
            "  timedexec calibrate --robot-url ur://127.0.0.1 --imu /tmp/gyro --trials 20 "
            "--out ur.h5\n  timedexec serve --robot kr5 --rsi-port 49152"
        ),
    )
    add_robot(p, required=True)
    p.add_argument("--host", default="127.0.0.1", help="address to bind (UR) / to send to (RSI)")
    p.add_argument("--imu-link", help="path for a symlink to the gyro's pseudo-terminal")
    p.add_argument("--truth", help="write ground truth (JSON lines) here")
    p.add_argument(
        "--urcap",
        type=_host_port,
        default=None,
        metavar="HOST:PORT",
        help="UR: where the pendant program /programs/external_control.urp (an External "
        "Control URCap node) asks for its script when played (default 127.0.0.1:50002: "
        "ur_rtde with FLAG_USE_EXT_UR_CAP on this machine)",
    )
    p.add_argument(
        "--rsi-port",
        type=int_arg(1, 65535),
        default=49152,
        help="the PC's RSI UDP port (KUKA; 1 .. 65535)",
    )
    add_period(p, help="RSI period, s (KUKA kr5: 0.012 or 0.004)")
    add_seed(p)
    p.set_defaults(func=run)


_URCAP_DEFAULT = ("127.0.0.1", 50002)


def _host_port(text: str) -> tuple[str, int]:
    """argparse type: ``HOST:PORT`` with a port in 1 .. 65535."""
    host, sep, port = text.strip().rpartition(":")
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not HOST:PORT with a port in 1 .. 65535; e.g. 192.168.1.5:50002"
        )
    return host, int(port)


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C or SIGTERM; return the exit code (0: stopped as asked)."""
    import signal
    import threading

    if not _is_ur(args.robot):  # options of the UR twin only, before any path
        if args.urcap is not None:
            raise ConfigError(
                f"--urcap applies to the UR twins (External Control URCap); {args.robot} "
                "speaks RSI: drop --urcap"
            )
        if args.imu_link:
            raise ConfigError(
                "--imu-link is available for the UR twin; the RSI twin has no gyro yet"
            )
    _check_serve_paths(args)
    if args.urcap is None:
        args.urcap = _URCAP_DEFAULT
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if _is_ur(args.robot):
        from timedexec.twins import run_ur_twin

        print(
            f"serving a simulated {args.robot} on {args.host} (Ctrl-C stops); its pendant "
            f"program /programs/external_control.urp asks {args.urcap[0]}:{args.urcap[1]} "
            "for its script",
            file=sys.stderr,
        )
        with contextlib.suppress(KeyboardInterrupt):
            run_ur_twin(
                args.robot,
                args.host,
                seed=args.seed,
                truth_path=args.truth,
                imu_link=args.imu_link,
                stop_event=stop,
                external_control=args.urcap,
            )
        return 0
    from timedexec.twins import RSITwin

    # Wait for the PC's first answer before counting late answers (else RSI stops with
    # RSITimeout 1.2 s after start when no PC listens yet, as a real KSS would).
    options: dict[str, Any] = {
        "robot": args.robot, "host": args.host, "seed": args.seed, "truth_path": args.truth,
        "wait_for_pc": True,
    }  # fmt: skip
    if args.period:
        options["period_s"] = args.period
    with RSITwin(args.rsi_port, **options):
        print(
            f"sending RSI frames of a simulated {args.robot} to {args.host}:{args.rsi_port} "
            "(Ctrl-C stops)",
            file=sys.stderr,
        )
        with contextlib.suppress(KeyboardInterrupt):
            while not stop.wait(0.5):
                pass
    return 0


def _is_truth_file(path: str) -> bool:
    """Whether ``path`` starts like a twin's ground truth (a JSON ``meta`` event line).

    Only the first line is read (at most 64 KiB), so a large foreign file costs nothing.
    """
    import json

    try:
        with open(path, "rb") as fh:
            first = fh.readline(65536)
        record = json.loads(first.decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(record, dict) and record.get("event") == "meta"


def _is_ur(robot: str) -> bool:
    """Whether ``robot``'s controller is a UR (RTDE); else it speaks KUKA RSI."""
    return get_robot_entry(robot).twin.interface == "ur_rtde"


def _check_serve_paths(args: argparse.Namespace) -> None:
    """Refuse ``--truth`` and ``--imu-link`` paths the twin could not write, before serving.

    ``--truth`` follows the output-path policy (a regular file or nothing; the UR twin
    appends to it, the RSI twin replaces it when it stops); ``--imu-link`` is a symbolic
    link the twin makes (an existing symlink there is replaced, anything else refused).
    Both folders must exist and take a new file now, not when the twin first writes
    (a thread's traceback, or the truth lost after a whole session).

    Raises
    ------
    ConfigError
        Naming the option, the path and the reason.
    """
    import os
    from pathlib import Path

    ur = _is_ur(args.robot)
    check_files(
        args,
        "serve",
        outputs={"--truth": args.truth},
        # the UR twin appends to an existing file; the RSI twin replaces it when it stops
        what={} if ur else {"--truth": "this session's ground truth when the twin stops"},
    )
    if args.truth and os.path.isfile(args.truth):
        if not _is_truth_file(args.truth):
            raise ConfigError(
                f"--truth {args.truth} exists and is not a twin's ground-truth file (JSON "
                "lines starting with an \"event\": \"meta\" line); serve never writes into a "
                "file it did not make: give a new path (or a truth file of an earlier session)"
            )
        if ur:
            note(
                "serve",
                f"--truth {args.truth} exists; this session's ground truth is appended to it",
            )
    if args.imu_link and os.path.lexists(args.imu_link) and not os.path.islink(args.imu_link):
        raise ConfigError(
            f"--imu-link {args.imu_link} exists and is not a symbolic link; the twin makes a "
            "symlink to its pseudo-terminal there: give a new path (or an old link)"
        )
    if (
        args.imu_link
        and args.truth
        and Path(args.imu_link).absolute() == Path(args.truth).absolute()
    ):
        raise ConfigError(
            f"--imu-link {args.imu_link} and --truth {args.truth} are the same path; give two"
        )
    for option, path in (("--truth", args.truth), ("--imu-link", args.imu_link)):
        if not path:
            continue
        folder = Path(path).parent if str(Path(path).parent) else Path(".")
        if not folder.is_dir():
            raise ConfigError(
                f"{option} {path}: the folder {folder} does not exist; create it first"
            )
        check_folder_takes_files(folder, option, path)
