"""``timedexec train``: delay models with cross-validation, saved as a model bundle.

``timedexec train DELAYS.csv --out DIR [--folds 10] [--methods median,nn,rt,gpr]
[--json [CV.json]] [--jobs N]``: cross-validates every method (any registered one,
:data:`timedexec.learning.METHODS`; default the paper's four) per joint and combined for
both delays, prints Tables I/II beside the paper's numbers, and writes the model bundle
trained on all data to DIR (``manifest.json``, ``arrays.npz``) with ``cv.json`` and
``cv-table.txt``. The JSON result (``--json``) is the CV scores, the same document as
``DIR/cv.json``. Results to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

from timedexec._files import write_atomic
from timedexec.cli._common import (
    add_command,
    add_jobs,
    add_json,
    add_period,
    add_quiet,
    add_seed,
    check_files,
    emit,
    int_arg,
)
from timedexec.cli._scheduler import add_scheduler, cluster, cluster_jobs
from timedexec.errors import ConfigError

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``train`` to the subparsers ``sub``."""
    from timedexec.learning import DEFAULT_METHODS, METHODS, describe_methods

    p = add_command(
        sub,
        "train",
        help=f"train delay models ({', '.join(METHODS)}) with 10-fold CV",
        description=(
            "Train delay models on a delay table (from `timedexec extract`): one model per "
            "joint and one combined, actuation and response delay separately. The methods "
            f"(--methods; default {','.join(DEFAULT_METHODS)}, the paper's):\n"
            f"{describe_methods()}\n\n"
            "Cross-validation as published: --folds folds (split by start configuration, so "
            "repeats of a test condition never train), error = sqrt(mean of fold MSEs) in ms, "
            "printed as Tables I/II beside the paper's numbers with the noise floor (replicate "
            "scatter). Then every method is trained on all data into a model bundle in --out "
            "(manifest.json + arrays.npz, no pickle), with cv.json and cv-table.txt. The JSON "
            "result (--json) is the CV scores, the document of cv.json.\n\n"
            "With --scheduler (or $TIMEDEXEC_SCHEDULER) every fit runs as a task on a Dask "
            "cluster; the scores and the bundle are the same.\n\n"
            "example:\n  timedexec train ur10-delays.csv --out models/my-ur10 --jobs 2 "
            "--json cv.json"
        ),
    )
    p.add_argument("delays", metavar="DELAYS.csv", help="delay table (CSV)")
    p.add_argument("--out", required=True, metavar="DIR", help="bundle directory to write")
    p.add_argument(
        "--folds",
        type=int_arg(0, 100, fix=" (0 trains without cross-validation)"),
        default=10,
        help="cross-validation folds (0: train without CV; 2 .. 100)",
    )
    p.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma list of {', '.join(METHODS)} (see above)",
    )
    add_json(p, "the CV scores ({delay: {method: {column: ms}}}; needs --folds >= 2)")
    add_jobs(p, help="worker processes (joblib; -1: all)")
    add_scheduler(p, what="the cross-validation and training fits")
    add_period(
        p,
        help="controller period the table was measured at, s (default: the robot's; kr5: "
        "0.012 or 0.004)",
    )
    p.add_argument(
        "--time-input",
        action="store_true",
        help="add the sweep time (t_start) as an input beside the published ones: separates "
        "warm-up drift from pose dependence; the bundle predicts at the end of the sweep (warm)",
    )
    p.add_argument(
        "--tracking",
        metavar="FILE.tracking.json",
        help="the tracking model calibrate fitted on its tracking phases (dead time and "
        "friction offsets per joint): written into the bundle as tracking.json, which "
        "evaluate --task conveyor then uses (docs/calibration.md)",
    )
    add_seed(p, help="seed of the folds and the estimators")
    add_quiet(p)
    p.set_defaults(func=run)


def _read_tracking(path: str, robot: str) -> dict[str, Any]:
    """The tracking model of a ``calibrate`` tracking file, checked.

    Raises
    ------
    ConfigError
        Not such a file, or one for another robot than the delay table's.
    """
    from timedexec.execution import FixedDelays
    from timedexec.tasks import TrackingDelays

    try:
        data = json.loads(Path(path).read_text())
    except ValueError as exc:
        raise ConfigError(f"--tracking {path}: not JSON ({exc}); give calibrate's "
                          "OUT.tracking.json") from exc  # fmt: skip
    if not isinstance(data, dict) or "tracking" not in data or "robot" not in data:
        raise ConfigError(f"--tracking {path}: no tracking model in it; give calibrate's "
                          "OUT.tracking.json")  # fmt: skip
    if data["robot"] != robot:
        raise ConfigError(f"--tracking {path} is for {data['robot']!r}, the delay table for "
                          f"{robot!r}: give the tracking file of the same robot's sweep")  # fmt: skip
    TrackingDelays.from_dict(FixedDelays(robot=robot), data["tracking"])  # checks it
    return dict(data["tracking"])


def run(args: argparse.Namespace) -> int:
    """Run ``train``; return the exit code."""
    from timedexec.delays import DelayTable
    from timedexec.learning import check_methods, train_delay_models

    methods = check_methods(args.methods)
    if args.folds < 0 or args.folds == 1:
        raise ConfigError(f"--folds {args.folds}: use 0 (no cross-validation) or 2 or more")
    if args.folds == 0 and args.json is not None:
        raise ConfigError("--json needs cross-validation; drop --folds 0")
    path = Path(args.delays)
    out = Path(args.out)
    bundle = {
        f"--out (the bundle's {name})": out / name
        for name in ("manifest.json", "arrays.npz", "cv.json", "cv-table.txt")
    }
    check_files(
        args,
        "train",
        inputs={"DELAYS.csv": path, "--tracking": args.tracking},
        outputs=bundle,
        folders={"--out": out},
        what={
            "--out (the bundle's manifest.json)": "the new bundle's (as are arrays.npz, "
            "cv.json and cv-table.txt)"
        },
    )
    table = DelayTable.read_csv(path)
    tracking = None
    if args.tracking is not None:
        tracking = _read_tracking(args.tracking, ",".join(table.robots))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    with cluster(args, "train") as client:
        jobs = cluster_jobs("train", args, client)
        if not args.quiet:
            workers = "every worker of the cluster" if client is not None else f"{jobs} job(s)"
            print(
                f"training {', '.join(methods)} on {len(table):,} trials of {path} "
                f"({args.folds}-fold CV, {workers})",
                file=sys.stderr,
            )
        result = train_delay_models(
            table,
            methods=methods,
            folds=args.folds,
            jobs=jobs,
            random_state=args.seed,
            progress=not args.quiet,
            period_s=args.period,
            source=str(path),
            source_sha256=digest,
            time_input=args.time_input,
        )
    model = result.model
    model.save(out)
    if tracking is not None:
        from timedexec.tasks import TrackingDelays

        TrackingDelays.from_dict(model, tracking).save(out)
    bundle_bytes = int(model.manifest["arrays"]["bytes"])
    text_parts = []
    cv: dict[str, Any] = {}
    if result.cv is not None:
        cv = result.cv.to_dict()
        table_text = result.cv.table_text()
        write_atomic(out / "cv.json", json.dumps(cv, indent=2) + "\n")
        write_atomic(out / "cv-table.txt", table_text + "\n")
        text_parts.append(table_text)
    text_parts.append(
        f"bundle for {model.robot} at {model.period_s * 1e3:g} ms written to {out} "
        f"({bundle_bytes / 1e3:.0f} kB arrays) in {result.seconds:.1f} s"
    )
    emit(args, cv, "\n".join(text_parts))
    return 0
