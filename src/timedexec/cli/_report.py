"""``timedexec report``: tables and figures (PNG + markdown) from any results."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._common import add_command, out

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``report`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "report",
        help="tables and figures (PNG + markdown) from recordings, delay tables and results",
        description=(
            "Build a markdown report with figures in the published layout from any results: "
            "recordings (.h5: gyro PSD before/after filtering, one trial's commanded, measured "
            "and reported speed with both delays), delay tables (.csv: histograms and per-joint "
            "boxplots), model bundle folders (Tables I-II beside the paper with the noise "
            "floor, and Fig. 6: the model's delays against the joint 2 and 3 angles with a "
            "±2σ band, dotted with the trials of the last delay table given before it), "
            "`train --json` output (Tables I-II), `evaluate --json` output (strategies, bound "
            "coverage) and the demo's conveyor.json (the seam run, figure).\n\n"
            "Output: DIR/report.md linking PNG figures in DIR.\n\nexample:\n  timedexec "
            "report ur10.h5 ur10-delays.csv models/my-ur10 eval.json --out report/"
        ),
    )
    p.add_argument(
        "results", nargs="+", help="recordings, delay tables, model bundles, JSON results"
    )
    p.add_argument("--out", required=True, help="report folder")
    p.add_argument("--trial", type=int, default=0, help="recorded trial (row) for Fig. 5")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``report``; return the exit code."""
    from timedexec.report import build_report

    path = build_report(args.results, args.out, trial=args.trial)
    out(f"report written to {path}")
    return 0
