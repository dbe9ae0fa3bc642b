"""``timedexec fleet``: every robot of a manifest, extracted, trained, evaluated and checked,
on a Dask cluster or on this machine, with a fleet report."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from timedexec.cli._common import (
    add_command,
    add_jobs,
    add_json,
    add_quiet,
    add_seed,
    check_files,
    emit,
    float_arg,
    int_arg,
    warn,
)
from timedexec.cli._scheduler import add_scheduler, cluster, cluster_jobs
from timedexec.robots import ROBOT_NAMES

__all__ = ["add_parser", "run"]

_REPORT_FILES = ("fleet.csv", "fleet.json", "report.md", "fleet.png", "run.json", "costs.csv")


def add_parser(sub: Any) -> None:
    """Add ``fleet`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "fleet",
        help="extract, train, evaluate and check every robot of a fleet (on a Dask cluster)",
        description=(
            "Process a fleet: for every robot of MANIFEST, its sweep (a recording, or a "
            "sim:// sweep simulated on the spot) -> delay table -> delay models with "
            "cross-validation -> evaluation on held-out simulated trials -> a drift check of "
            "the model it runs today; then a fleet report: per robot the delay medians and "
            "spreads, the model's error against the noise floor, the monitor state, and which "
            "robots need a new calibration, with a figure comparing robots.\n\n"
            "MANIFEST is a CSV file with a header `name,robot,source,deployed` and one line "
            f"per robot: name (its output folder), robot ({', '.join(ROBOT_NAMES)}), source (a "
            "recording path relative to the manifest, an fsspec URL such as s3://..., or "
            "sim://ROBOT?trials=N&seed=S), deployed (optional: its model bundle today, or a "
            "shipped model's name). docs/fleet.md has the details.\n\n"
            "With --scheduler (or $TIMEDEXEC_SCHEDULER) each robot is one task on that Dask "
            "cluster: a worker that dies loses nothing (the robot reruns elsewhere), a robot "
            "whose data cannot be used is reported and the others complete. --out and the "
            "recordings must then be on storage every worker shares. Without a scheduler the "
            "robots run here, --jobs at a time. The tables are the same either way.\n\n"
            "Output in --out: fleet.csv (one row per robot), fleet.json (everything, the "
            "--json document), report.md and fleet.png, run.json and costs.csv (where and at "
            "what cost each robot ran), and robots/NAME/ (delays.csv, model/, "
            "evaluation.json, drift.json, result.json). Exit 1 when a robot failed (the "
            "report names it and why).\n\n"
            "examples:\n  timedexec fleet plant-a.csv --out fleet-2026-11 --jobs 2\n"
            "  timedexec fleet /shared/plant-a.csv --out /shared/fleet-2026-11 "
            "--scheduler tcp://10.0.0.5:8786"
        ),
    )
    p.add_argument("manifest", metavar="MANIFEST", help="the fleet manifest (CSV)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_scheduler(p, what="every robot")
    add_jobs(p, help="robots processed at once on this machine (without --scheduler)")
    from timedexec.learning import DEFAULT_METHODS, METHODS

    p.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma list of {', '.join(METHODS)} (`timedexec train --help` describes them)",
    )
    p.add_argument(
        "--folds", type=int_arg(2, 100), default=10, help="cross-validation folds (2 .. 100)"
    )
    add_seed(p, help="seed of the folds and the estimators")
    p.add_argument(
        "--configs",
        type=int_arg(0, 100_000, fix=" (0 skips the evaluation)"),
        default=300,
        help="held-out simulated configurations of each robot's evaluation (0: skip it)",
    )
    p.add_argument(
        "--draws",
        type=int_arg(2, 1000),
        default=20,
        help="simulated trials behind the oracle (2 .. 1000)",
    )
    p.add_argument(
        "--drift",
        type=float_arg(0.0, low_open=True, unit="ms", fix=" (e.g. 1)"),
        default=1.0,
        metavar="MS",
        help="smallest shift from the deployed model reported as drift, ms",
    )
    p.add_argument(
        "--alpha",
        type=float_arg(0.0, 1.0, low_open=True, fix=" (e.g. 0.001)"),
        default=1e-3,
        help="false-alarm probability of the drift check, per robot",
    )
    add_quiet(p)
    add_json(p, "the fleet document (settings, summary, robots: every robot's numbers)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``fleet``; return the exit code (1 when a robot failed)."""
    from timedexec.fleet import FleetSettings, read_manifest, run_fleet
    from timedexec.learning import check_methods

    out = Path(args.out)
    check_files(
        args,
        "fleet",
        inputs={"MANIFEST": args.manifest},
        outputs={f"--out ({name})": out / name for name in _REPORT_FILES},
        folders={"--out": out},
    )
    settings = FleetSettings(
        methods=check_methods(args.methods),
        folds=args.folds,
        seed=args.seed,
        eval_configs=args.configs,
        eval_draws=args.draws,
        drift_ms=args.drift,
        drift_alpha=args.alpha,
    )
    manifest = read_manifest(args.manifest)
    with cluster(args, "fleet") as client:
        jobs = cluster_jobs("fleet", args, client)
        result = run_fleet(
            manifest,
            out,
            scheduler=client,
            jobs=1 if client is not None else jobs,
            settings=settings,
            progress=not args.quiet,
        )
    for robot in result.failed:
        warn("fleet", f"{robot.name}: {robot.failed_stage} failed: {robot.error}")
    emit(args, result.document, result.summary_text())
    return 1 if result.failed else 0
