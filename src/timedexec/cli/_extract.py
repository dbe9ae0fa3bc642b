"""``timedexec extract``: actuation and response delays of a recording (delay table CSV)."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._common import (
    add_command,
    add_jobs,
    add_json,
    add_quiet,
    check_files,
    emit,
    used_jobs,
)

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``extract`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "extract",
        help="extract actuation and response delays from a recording (delay table CSV)",
        description=(
            "Extract the actuation and response delay of every trial of a recording made by "
            "`timedexec simulate` or `timedexec calibrate`: gyro clock fit, zero-rate, PSD-"
            "designed low-pass filter, then per trial the onset (sub-sample local fit, "
            "default) or the published extrema method. Trials that cannot be measured keep "
            "their row with NaN delays and a reason in the `flag` column.\n\n"
            "Output: the delay table (CSV; docs: timedexec.delays).\n\n"
            "example:\n  timedexec extract ur10.h5 --out ur10-delays.csv --jobs 2"
        ),
    )
    p.add_argument("recording", help="recording (HDF5)")
    p.add_argument("--out", required=True, help="delay table to write (CSV)")
    p.add_argument("--method", default="fit", choices=("fit", "extrema"), help="extraction method")
    add_jobs(p)
    add_quiet(p)
    add_json(
        p,
        "the summary (trials, flagged, filter_cutoff_hz, ..., and against a simulator's "
        "ground truth actuation_delay_rmse_ms, response_delay_rmse_ms)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``extract``; return the exit code."""
    import numpy as np

    from timedexec.extraction import extract_recording

    check_files(
        args,
        "extract",
        inputs={"RECORDING": args.recording},
        outputs={"--out": args.out},
        what={"--out": "the delay table (CSV)"},
    )
    result = extract_recording(
        args.recording,
        method=args.method,
        jobs=used_jobs("extract", args.jobs),
        progress=not args.quiet,
    )
    result.table.to_csv(args.out)
    info = {**result.summary(), "out": args.out, "method": args.method}
    table = result.table
    text = (
        f"extracted {len(table):,} trials ({info['flagged']} flagged) with method "
        f"{args.method} to {args.out}; filter cutoff {info['filter_cutoff_hz']:.0f} Hz, gyro "
        f"clock {info['gyro_rate_error_ppm']:+.0f} ppm off nominal"
    )
    if "true_actuation_delay" in table:
        ok = np.array([not f for f in table["flag"]], dtype=bool)
        for name in ("actuation_delay", "response_delay"):
            err = (table[name] - table[f"true_{name}"])[ok]
            rmse = float(np.sqrt(np.mean(err**2)) * 1e3) if ok.any() else float("nan")
            info[f"{name}_rmse_ms"] = rmse
            text += f"\n{name} error against the simulator's ground truth: RMSE {rmse:.3f} ms"
    emit(args, info, text)
    return 0
