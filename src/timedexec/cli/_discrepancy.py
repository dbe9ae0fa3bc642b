"""``timedexec discrepancy``: where the simulator disagrees with measured delays, and why."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from timedexec.cli._common import (
    add_command,
    add_json,
    add_period,
    add_quiet,
    add_robot,
    add_seed,
    check_files,
    emit,
    float_arg,
    warn,
)
from timedexec.cli._scheduler import add_scheduler, cluster, submit, worker_path
from timedexec.effects import EFFECTS

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``discrepancy`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "discrepancy",
        help="find where the simulator disagrees with measured delays and name the missing effect",
        description=(
            "Compare measured delays with the simulator: simulate every measured condition "
            "(start configuration, joint, direction, time) with the start effect set, "
            "calibrate its parameters, locate the disagreement against the noise floor of "
            "the repeats, score every effect of the vocabulary as the missing explanation "
            "(cross-validated, significance-tested), add the best, recalibrate and repeat. "
            "A name is given only where no data-driven term explains the residuals better; "
            "what the vocabulary leaves is searched in a library of candidate terms (slopes, "
            "hinges, harmonics, bumps in the joint angles or another joint's gravity torque) "
            "and added to the simulator as a discovered effect (JSON: discovered). What "
            "nothing explains is reported as unexplained, with where it sits.\n\n"
            f"Effect vocabulary: {', '.join(EFFECTS)}.\n\n"
            "Output: a summary on stdout; the JSON result (--json) is the full result "
            "(added_effects, gap_before_ms, gap_after_ms, noise_floor_ms, steps, discovered, "
            "unexplained, "
            "...); with --report DIR a markdown report with PNG figures.\n\n"
            "With --scheduler (or $TIMEDEXEC_SCHEDULER) a recording is extracted on a Dask "
            "cluster's workers and the analysis runs there as one task; the result is the "
            "same.\n\n"
            "example:\n  timedexec simulate --robot ur10 --trials 4000 --out ur10.h5 "
            "--truth ur10-truth.csv\n"
            "  timedexec discrepancy ur10-truth.csv --start base --json out.json --report report"
        ),
    )
    p.add_argument("measured", metavar="MEASURED", help="delay table (CSV) or recording (HDF5)")
    add_robot(p, help="robot (default: the table's robot column)")
    p.add_argument(
        "--start",
        default="default",
        help="model to start from: base (base timing only), default (the robot's default "
        "effects) or a comma list of effect names (default,NAME: the defaults plus NAME)",
    )
    add_period(p)
    add_json(p, "the full result (added_effects, gap_before_ms, steps, discovered, ...)")
    p.add_argument("--report", metavar="DIR", help="write a markdown report with figures here")
    p.add_argument(
        "--alpha",
        type=float_arg(0.0, 1.0, low_open=True, fix=" (e.g. 0.01)"),
        default=0.01,
        help="significance level of the tests (0 < alpha <= 1)",
    )
    add_seed(p, help="seed of the cross-validation folds")
    add_scheduler(p, what="the extraction of a recording and the analysis")
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``discrepancy``; return the exit code."""
    from timedexec.discrepancy import analyse_discrepancy

    report = None if args.report is None else Path(args.report)
    check_files(
        args,
        "discrepancy",
        inputs={"MEASURED": args.measured},
        outputs={} if report is None else {"--report (report.md)": report / "report.md"},
        folders={} if report is None else {"--report": report},
        what={"--report (report.md)": "the new discrepancy report"},
    )
    options = {
        "robot": args.robot,
        "start": args.start,
        "period_s": args.period,
        "alpha": args.alpha,
        "seed": args.seed,
    }
    with cluster(args, "discrepancy") as client:
        if client is None:
            result = analyse_discrepancy(args.measured, **options, progress=not args.quiet)
        else:
            measured = _measured_on_cluster(args, client)
            result = submit(client, analyse_discrepancy, measured, **options, progress=False)
    text = result.summary_text()
    if args.report:
        md = result.write_report(args.report)
        text += f"\nreport: {md}"
    for w in result.warnings:
        warn("discrepancy", w)
    emit(args, result.to_dict(), text)
    return 0


def _measured_on_cluster(args: argparse.Namespace, client: Any) -> Any:
    """MEASURED for a cluster run: a recording is extracted on the workers (every chunk a
    task); a delay table is read here and sent with the analysis."""
    from timedexec.delays import DelayTable
    from timedexec.errors import RecordingError
    from timedexec.extraction import extract_recording

    try:
        with open(args.measured, "rb") as fh:
            magic = fh.read(8)
    except FileNotFoundError:
        raise RecordingError(
            f"measured data {args.measured} does not exist (give a delay table CSV or a recording)"
        ) from None
    except OSError as exc:
        raise RecordingError(f"cannot read {args.measured}: {exc.strerror or exc}") from exc
    if magic == b"\x89HDF\r\n\x1a\n":
        return extract_recording(
            worker_path(args.measured, client), jobs=-1, progress=not args.quiet
        ).table
    return DelayTable.read_csv(args.measured)
