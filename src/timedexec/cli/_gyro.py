"""``timedexec gyro check PORT``: does a gyro meet what calibration needs (exit 0), or not (2)."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._common import Formatter, add_command, add_json, emit, float_arg, note

__all__ = ["add_parser", "run"]

#: Exit code of a gyro that falls short: bad input, as for every command (cli._main).
EXIT_UNFIT = 2


def add_parser(sub: Any) -> None:
    """Add ``gyro`` (with its ``check`` subcommand) to the subparsers ``sub``."""
    p = add_command(
        sub,
        "gyro",
        help="check a gyro board before a calibration (docs/gyro-kit.md)",
        description="Work with the gyro that a calibration uses as ground truth.",
    )
    gyro_sub = p.add_subparsers(dest="gyro_command", metavar="SUBCOMMAND", required=True)
    c = gyro_sub.add_parser(
        "check",
        help="measure a gyro at rest and say whether it meets what calibration needs",
        formatter_class=Formatter,
        description=(
            "Connect to a gyro (docs/gyro-protocol.md frames), measure it at rest for "
            "--duration-s seconds and report: the sample rate and its drift against the "
            "host clock, lost samples and corrupted frames, the noise density at rest per "
            "axis, and the full-scale range the noise suggests (from the part's typical "
            "noise) against the one you state. Exit 0 when all of it meets what calibration "
            "needs (8 kHz within 2 %, drift within 500 ppm, at most 0.1 % lost and 0.01 % "
            "corrupted frames, noise at most 0.02 °/s/√Hz, the stated range), else exit 2 "
            "with one line per problem saying what to fix. A port that cannot be opened "
            "exits 3.\n\n"
            "Keep the sensor still during the check.\n\n"
            "example:\n  timedexec gyro check /dev/ttyACM0 --duration-s 10 --json check.json"
        ),
    )
    c.add_argument("port", help="the gyro's serial port (/dev/ttyACM0, COM3, a pty, sim://)")
    c.add_argument(
        "--duration-s",
        type=float_arg(0.5, 3600.0, unit="s"),
        default=10.0,
        metavar="S",
        help="how long to measure, s",
    )
    c.add_argument(
        "--full-scale-dps",
        type=int,
        choices=(250, 500, 1000, 2000),
        default=500,
        help="the range the firmware was built with (FS_DPS) and recordings will state, °/s",
    )
    c.add_argument(
        "--sensor",
        choices=("mpu6000", "icm42688p"),
        default="mpu6000",
        help="the part on the board (its typical noise sets the range inference)",
    )
    add_json(c, "the figures and the verdict {port, rate_hz, ..., ok, problems}")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``gyro check``; return 0 for a fit gyro, 2 otherwise."""
    from timedexec.sensors import check_gyro

    result = check_gyro(
        args.port,
        duration_s=args.duration_s,
        full_scale_dps=args.full_scale_dps,
        sensor=args.sensor,
        progress=lambda message: note("gyro check", message),
    )
    emit(args, result.to_dict(), result.summary())
    return 0 if result.ok else EXIT_UNFIT
