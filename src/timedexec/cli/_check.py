"""``timedexec check``: does a recording meet the documented contract (exit 0), or not (2)."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._common import add_command, add_json, check_files, emit, note

__all__ = ["add_parser", "run"]

#: Exit code of a recording with problems: bad input, as for every command (cli._main).
EXIT_INVALID = 2


def add_parser(sub: Any) -> None:
    """Add ``check`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "check",
        help="check a recording against the recording contract (docs/recording-format.md)",
        description=(
            "Check that a recording holds what `timedexec extract` needs, as "
            "docs/recording-format.md ('What extraction needs') states it: the container, "
            "every required per-trial field with an accepted unit, the static arrays, the "
            "header keys (the gyro's group delay and transport latency included: "
            "docs/sensor-constants.md) and, unless --shallow, the data itself (finite "
            "times, counters that count samples, complete gyro windows, trial indices inside "
            "the plan). For recordings written by other software as much as by "
            "`timedexec simulate` or `timedexec calibrate`.\n\n"
            "Output: 'REC.h5: a valid timedexec recording' (exit 0), or one problem per "
            "line, each naming the field, attribute or header key (exit 2).\n\n"
            "example:\n  timedexec check my-sweep.h5 --json"
        ),
    )
    p.add_argument("recording", help="recording (HDF5)")
    p.add_argument(
        "--shallow",
        action="store_true",
        help="check the structure only (fields, units, statics, header); do not read the data",
    )
    add_json(p, "the verdict {recording, valid, problems}")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``check``; return 0 for a valid recording, 2 otherwise."""
    from timedexec.extraction import check_recording

    check_files(args, "check", inputs={"RECORDING": args.recording})
    # A problem is one line (a message of the store may span several).
    problems = [" ".join(p.split()) for p in check_recording(args.recording, deep=not args.shallow)]
    info = {"recording": args.recording, "valid": not problems, "problems": problems}
    if args.shallow:
        note("check", "--shallow: the structure was checked, the data was not read")
    text = "\n".join(problems) if problems else f"{args.recording}: a valid timedexec recording"
    emit(args, info, text)
    return EXIT_INVALID if problems else 0
