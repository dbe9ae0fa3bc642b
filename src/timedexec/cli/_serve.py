"""``timedexec serve``: a protocol twin, a simulated UR or KUKA controller on the network."""

from __future__ import annotations

import argparse
import contextlib
import sys
from typing import Any

from timedexec.cli._common import add_command, add_period, add_robot, add_seed
from timedexec.errors import ConfigError

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``serve`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "serve",
        help="run a protocol twin: a simulated UR or KUKA controller on the network",
        description=(
            "Serve a simulated robot controller that real clients talk to: for ur10/ur10e a "
            "UR controller (RTDE on 30004, dashboard on 29999, script port 30003) for the "
            "ur_rtde client; for kr5 a KUKA controller sending RSI XML over UDP to the PC's "
            "port every 12 ms (or --period 0.004). With --imu-link, a simulated gyro on the "
            "flange streams over a pseudo-terminal linked at that path. Runs until Ctrl-C or "
            "SIGTERM, then exits 0. Binds 127.0.0.1 unless told otherwise.\n\n"
            "examples:\n  timedexec serve --robot ur10 --imu-link /tmp/gyro\n"
            "  timedexec calibrate --robot-url ur://127.0.0.1 --imu /tmp/gyro --trials 20 "
            "--out ur.h5\n  timedexec serve --robot kr5 --rsi-port 49152"
        ),
    )
    add_robot(p, required=True)
    p.add_argument("--host", default="127.0.0.1", help="address to bind (UR) / to send to (RSI)")
    p.add_argument("--imu-link", help="path for a symlink to the gyro's pseudo-terminal")
    p.add_argument("--truth", help="write ground truth (JSON lines) here")
    p.add_argument("--rsi-port", type=int, default=49152, help="the PC's RSI UDP port (kr5)")
    add_period(p, help="RSI period, s (kr5: 0.012 or 0.004)")
    add_seed(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C or SIGTERM; return the exit code (0: stopped as asked)."""
    import signal
    import threading

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.robot.startswith("ur"):
        from timedexec.twins import run_ur_twin

        print(f"serving a simulated {args.robot} on {args.host} (Ctrl-C stops)", file=sys.stderr)
        with contextlib.suppress(KeyboardInterrupt):
            run_ur_twin(
                args.robot,
                args.host,
                seed=args.seed,
                truth_path=args.truth,
                imu_link=args.imu_link,
                stop_event=stop,
            )
        return 0
    from timedexec.twins import RSITwin

    # Wait for the PC's first answer before counting late answers (else RSI stops with
    # RSITimeout 1.2 s after start when no PC listens yet, as a real KSS would).
    options: dict[str, Any] = {
        "host": args.host, "seed": args.seed, "truth_path": args.truth, "wait_for_pc": True,
    }  # fmt: skip
    if args.period:
        options["period_s"] = args.period
    if args.imu_link:
        raise ConfigError("--imu-link is available for the UR twin; the RSI twin has no gyro yet")
    with RSITwin(args.rsi_port, **options):
        print(
            f"sending RSI frames of a simulated kr5 to {args.host}:{args.rsi_port} (Ctrl-C stops)",
            file=sys.stderr,
        )
        with contextlib.suppress(KeyboardInterrupt):
            while not stop.wait(0.5):
                pass
    return 0
