"""``timedexec demo``: the end-to-end job on the embedded simulated robot."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._common import (
    add_command,
    add_json,
    add_robot,
    add_seed,
    check_files,
    emit,
    int_arg,
)

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``demo`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "demo",
        help="run the end-to-end job on the embedded simulated robot",
        description=(
            "The end-to-end job on the embedded simulated robot, no hardware needed: "
            "simulate a calibration sweep (state packages, commands and an 8 kHz gyro, "
            "recorded to HDF5), extract the actuation and response delays, train the delay "
            "models with 10-fold cross-validation, evaluate delay compensation on held-out "
            "trials, follow a conveyor seam at 0.5 m/s without and with compensation, and "
            "write a report with tables and figures in the published layout.\n\n"
            "Output folder: ROBOT-sweep.h5 (recording), ROBOT-delays.csv (delay table), model/ "
            "(bundle, cv.json), evaluation.json, conveyor.json, report/report.md (+ PNG). "
            "Prints the delays per joint, the models' errors against the median, the timing "
            "and seam errors per strategy and the conveyor result; --json gives them as "
            "JSON. Default: 8,000 trials (1-2 minutes); --quick: 2,000 (about 30 s)."
            "\n\nexample:\n  timedexec demo --robot kr5 --quick --out demo-out"
        ),
    )
    add_robot(p, default="ur10")
    p.add_argument(
        "--quick", action="store_true", help="2,000 trials instead of 8,000 (about 30 s)"
    )
    p.add_argument("--out", default="timedexec-demo", help="output folder")
    add_seed(p)
    p.add_argument(
        "--trials",
        type=int_arg(160, 10_000_000, fix=" (--quick: 2000)"),
        help="calibration trials (>= 160; overrides --quick)",
    )
    p.add_argument(  # tests: a tiny evaluation
        "--eval-configs", type=int_arg(1, 100_000), help=argparse.SUPPRESS
    )
    add_json(p, "the summary (summary, extraction_rmse_ms, cv_ms, evaluation, conveyor, ...)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``demo``; return the exit code."""
    from timedexec.report import run_demo
    from timedexec.robots import get_robot

    quick = args.quick
    trials = args.trials if args.trials is not None else (2000 if quick else 8000)
    check_files(args, "demo", folders={"--out": args.out})
    info = run_demo(
        args.robot,
        args.out,
        trials=trials,
        seed=args.seed,
        eval_configs=args.eval_configs,
        eval_draws=10 if quick else 20,
        progress=True,
    )
    emit(args, info, _text(info, get_robot(args.robot).description, trials))
    return 0


def _text(info: dict[str, Any], description: str, trials: int) -> str:
    """The demo's summary for the terminal."""
    lines = [
        f"timedexec demo: {description}, {trials:,} simulated calibration trials",
        "",
        "measured delays per joint, median (2.5-97.5 %), ms:",
        "joint  actuation            response",
    ]
    for j, row in info["summary"]["joints"].items():
        a, r = row["actuation_delay"], row["response_delay"]
        lines.append(
            f"{j:>5}  {a['median_ms']:5.1f} ({a['p2_5_ms']:5.1f}-{a['p97_5_ms']:5.1f})  "
            f"{r['median_ms']:5.1f} ({r['p2_5_ms']:5.1f}-{r['p97_5_ms']:5.1f})"
        )
    err = info["extraction_rmse_ms"]
    lines.append(
        f"extraction error against the simulator's truth: actuation "
        f"{err['actuation_delay']:.2f} ms RMS, response {err['response_delay']:.2f} ms RMS; "
        f"{info['summary']['flagged']} trials flagged"
    )
    lines += [
        "",
        f"model error, {info['folds']}-fold CV average (ms; noise floor = replicate scatter):",
    ]
    for delay, row in info["cv_ms"].items():
        cells = "  ".join(f"{m} {v:.2f}" for m, v in row.items())
        lines.append(
            f"  {delay.split('_')[0]:<9} {cells}  floor {info['noise_floor_ms'][delay]:.2f}"
        )
    ev = info["evaluation"]["strategies"]
    used = info["evaluation"].get("n_configurations")
    where = (
        "" if used is None else f" ({info['evaluation']['n_trials']:,} on {used} configurations)"
    )
    lines += [
        "",
        f"held-out trials{where}, motion-onset timing error and seam error at 0.5 m/s:",
    ]
    for name, row in ev.items():
        lines.append(
            f"  {name:<9} {row['timing_rms_ms']:6.2f} ms RMS  {row['seam_error_cm']:.3f} cm"
        )
    lines += [f"  note: {text}" for text in info["evaluation"].get("notes", [])]
    cov = info["evaluation"]["coverage_95"]
    if cov is not None:
        lines.append(f"  the model's 95 % timing bounds held on {100 * cov:.1f} % of trials")
    conv = info["conveyor"]
    lines += [
        "",
        "conveyor at 0.5 m/s, physical torch-to-seam lag in the simulator (+ late, - early), "
        "mean over the cruise / last 100 ms:",
        *(
            f"  {name:<22} {leg['mean_lag_cm']:+.2f} / {leg['final_lag_cm']:+.2f} cm"
            for name, leg in conv.items()
        ),
        f"  (compensated: commands sent {conv['compensated']['actuation_shift_ms']:.0f} ms early; "
        "feedback: the executor's position correction on its back-dated state)",
        "",
        f"report: {info['report']}",
        f"model bundle: {info['model']}   delay table: {info['delays']}",
    ]
    return "\n".join(lines)
