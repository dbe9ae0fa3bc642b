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
    float_arg,
    warn,
)
from timedexec.cli._scheduler import add_scheduler, cluster, cluster_jobs, worker_path

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``extract`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "extract",
        help="extract actuation and response delays from a recording (delay table CSV)",
        description=(
            "Extract the actuation and response delay of every trial of a recording made by "
            "`timedexec simulate`, `timedexec calibrate` or any recorder that follows "
            "docs/recording-format.md (`timedexec check` validates one): lossy-stream "
            "repair, gyro clock fit that follows the oscillator's drift, zero-rate, then per "
            "trial the onset (noise-adaptive local fit with a standard error, default) or "
            "the published extrema method. Trials that cannot be measured keep their row "
            "with NaN delays and a reason in the `flag` column; a trial whose response delay "
            "alone is not trustworthy (a compliant gear whose deflection cannot be separated "
            "from the state's age) keeps both delays and a reason in `response_flag`.\n\n"
            "Output: the delay table (CSV; docs: timedexec.delays).\n\n"
            "With --scheduler (or $TIMEDEXEC_SCHEDULER) the trial chunks are extracted on a "
            "Dask cluster's workers (the recording must be at the same path on every "
            "worker); the table is the same.\n\n"
            "examples:\n  timedexec extract ur10.h5 --out ur10-delays.csv --jobs 2\n"
            "  timedexec extract /shared/ur10.h5 --out ur10-delays.csv --scheduler tcp://10.0.0.5:8786"
        ),
    )
    p.add_argument("recording", help="recording (HDF5)")
    p.add_argument("--out", required=True, help="delay table to write (CSV)")
    p.add_argument("--method", default="fit", choices=("fit", "extrema"), help="extraction method")
    p.add_argument(
        "--clock-window",
        type=float_arg(0.0, low_open=True, unit="s"),
        default=None,
        metavar="SECONDS",
        help="length of the windows in which the gyro's clock is fitted (blended, to follow "
        "the oscillator's drift); if not given, chosen from the data",
    )
    p.add_argument(
        "--max-se",
        type=float_arg(0.0, low_open=True, unit="ms"),
        default=None,
        metavar="MS",
        help="flag a trial 'uncertain' when the standard error of its actuation or response "
        "delay exceeds this, ms; if not given, 2 ms (timedexec.extraction.MAX_SE_S)",
    )
    add_jobs(p)
    add_scheduler(p, what="the extraction")
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

    from timedexec.delays import RESPONSE_FLAG_WHY
    from timedexec.extraction import MAX_SE_S, extract_recording

    check_files(
        args,
        "extract",
        inputs={"RECORDING": args.recording},
        outputs={"--out": args.out},
        what={"--out": "the delay table (CSV)"},
    )
    with cluster(args, "extract") as client:
        result = extract_recording(
            worker_path(args.recording, client),
            method=args.method,
            jobs=cluster_jobs("extract", args, client),
            clock_window_s=args.clock_window,
            max_se_s=MAX_SE_S if args.max_se is None else args.max_se * 1e-3,
            progress=not args.quiet,
        )
    info = {**result.summary(), "out": args.out, "method": args.method}
    if info.get("damaged_rows"):
        from timedexec.recording import damage_note

        warn("extract", damage_note(args.recording, info["damaged_rows"], len(result.table)))
    bad_time = int(info.get("flags", {}).get("bad_time", 0))
    if bad_time:
        warn(
            "extract",
            f"{bad_time} trial(s) of {args.recording} have a t0_s or cmd_send_time_s that is "
            "not finite: flagged 'bad_time' and left out, the others extracted; `timedexec "
            f"check {args.recording}` names the field",
        )
    result.table.to_csv(args.out)
    table = result.table
    text = (
        f"extracted {len(table):,} trials ({info['flagged']} flagged) with method "
        f"{args.method} to {args.out}; filter cutoff {info['filter_cutoff_hz']:.0f} Hz, gyro "
        f"clock {info['gyro_rate_error_ppm']:+.0f} ppm off nominal"
    )
    if info.get("response_flagged"):
        reasons = ", ".join(f"{r} {c}" for r, c in info["response_flags"].items())
        why = "; ".join(f"{r}: {RESPONSE_FLAG_WHY[r]}" for r in info["response_flags"]
                        if r in RESPONSE_FLAG_WHY)  # fmt: skip
        text += (
            f"\n{info['response_flagged']} trials have a response_flag ({reasons}): their "
            "actuation delay is sound, their response delay is not used for training "
            f"({why}; docs/architecture.md)"
        )
    for name in ("actuation_delay", "response_delay"):
        # Ground truth where the recording has it (a simulator's; another recorder may
        # state one delay, or leave it NaN): scored over the measured trials that have it.
        if f"true_{name}" not in table:
            continue
        ok = table.usable(name)
        err = (table[name] - table[f"true_{name}"])[ok]
        err = err[np.isfinite(err)]
        if err.size:
            rmse = float(np.sqrt(np.mean(err**2)) * 1e3)
            info[f"{name}_rmse_ms"] = rmse
            text += f"\n{name} error against the recording's ground truth: RMSE {rmse:.3f} ms"
    emit(args, info, text)
    return 0
