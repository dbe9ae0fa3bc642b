"""The ``timedexec discrepancy`` subcommand (wired into :mod:`timedexec.cli`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from timedexec.effects import EFFECT_NAMES
from timedexec.robots import ROBOT_NAMES

__all__ = ["add_parser"]

Emit = Callable[[dict[str, Any], argparse.Namespace, str], None]


def add_parser(sub: Any, formatter_class: type[argparse.HelpFormatter], emit: Emit) -> None:
    """Add the ``discrepancy`` subcommand to the subparsers ``sub``.

    ``emit(result, args, text)`` prints the result (JSON when ``args.json`` is true, else the
    text).
    """
    p = sub.add_parser(
        "discrepancy",
        help="find where the simulator disagrees with measured delays and name the missing effect",
        formatter_class=formatter_class,
        description=(
            "Compare measured delays with the simulator: simulate every measured condition "
            "(start configuration, joint, direction, time) with the start effect set, "
            "calibrate its parameters, locate the disagreement against the noise floor of "
            "the repeats, score every effect of the vocabulary as the missing explanation "
            "(cross-validated, significance-tested), add the best, recalibrate and repeat. "
            "What no effect explains is reported as unexplained, with where it sits.\n\n"
            f"Effect vocabulary: {', '.join(EFFECT_NAMES)}.\n\n"
            "Output: a summary on stdout; with --json OUT.json the full result (added_effects, "
            "gap_before_ms, gap_after_ms, noise_floor_ms, steps, unexplained, ...; '-' prints "
            "it to stdout); with --report DIR a markdown report with PNG figures.\n\n"
            "example:\n  timedexec simulate --robot ur10 --trials 4000 --out ur10.h5 "
            "--truth ur10-truth.csv\n"
            "  timedexec discrepancy ur10-truth.csv --start base --json out.json --report report"
        ),
    )
    p.add_argument("measured", metavar="MEASURED", help="delay table (CSV) or recording (HDF5)")
    p.add_argument(
        "--robot", help=f"robot ({', '.join(ROBOT_NAMES)}; default: the table's robot column)"
    )
    p.add_argument(
        "--start",
        default="default",
        help="model to start from: base (base timing only), default (the robot's default "
        "effects) or a comma list of effect names",
    )
    p.add_argument("--period", type=float, help="controller period, s (kr5: 0.012 or 0.004)")
    p.add_argument("--json", metavar="OUT.json", help="write the result as JSON ('-': stdout)")
    p.add_argument("--report", metavar="DIR", help="write a markdown report with figures here")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level of the tests")
    p.add_argument("--seed", type=int, default=0, help="seed of the cross-validation folds")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")

    def run(args: argparse.Namespace) -> int:
        from timedexec.discrepancy import analyse_discrepancy

        result = analyse_discrepancy(
            args.measured,
            robot=args.robot,
            start=args.start,
            period_s=args.period,
            alpha=args.alpha,
            seed=args.seed,
            progress=not args.quiet,
        )
        info = result.to_dict()
        text = result.summary_text()
        if args.json and args.json != "-":
            result.write_json(args.json)
            text += f"\nresult: {args.json}"
        if args.report:
            md = result.write_report(args.report)
            text += f"\nreport: {md}"
        for w in result.warnings:
            print(f"timedexec discrepancy: warning: {w}", file=sys.stderr)
        emit(info, argparse.Namespace(json=args.json == "-"), text)
        return 0

    p.set_defaults(func=run)
