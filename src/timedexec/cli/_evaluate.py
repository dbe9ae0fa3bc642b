"""``timedexec evaluate``: delay-compensation strategies on held-out simulated trials."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._common import (
    add_command,
    add_json,
    add_quiet,
    add_robot,
    add_seed,
    check_files,
    emit,
    float_arg,
    int_arg,
    warn,
)
from timedexec.cli._scheduler import add_scheduler, cluster, submit, worker_model
from timedexec.errors import ConfigError

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``evaluate`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "evaluate",
        help="compare delay-compensation strategies on held-out simulated trials",
        description=(
            "Evaluate timed execution on the simulated robot with ground truth. On start "
            "configurations held out of training (a fresh plan seed), each condition (joint "
            "1/2/3/5, both directions) gets a true trial; five strategies predict its actuation "
            "delay: none (no compensation), constant (one latency for all joints: the overall "
            "median, as MoveIt Servo), median (per joint, the published baseline), model (the "
            "learned delay model) and oracle (the true conditional mean of --draws simulated "
            "trials). Reported: the motion-onset timing error (RMS, ms), the seam error of a "
            "conveyor at --speed (cm; speed x timing error, optionally verified by running the "
            "physics with --physics N configurations) and the coverage of the model's 95 % "
            "bounds.\n\n"
            "Output: a table; the JSON result (--json) is {robot, strategies: {none: "
            "{timing_rms_ms, seam_error_cm, ...}, ...}, coverage_95, ...}.\n\n"
            "--task conveyor: the welding case itself (docs/welding.md). A straight belt at "
            "--speed carries a part; the torch (orientation held) follows a --seam on it "
            "through the inverse kinematics, every joint moving, streamed through the "
            "executor on the simulator; the physical torch tip is measured against the seam "
            "over the cruise for each strategy, each shifting the command streams by the "
            "tracking delay (the lag a moving arm keeps; onset-delay shifts are shown below "
            "them). JSON: {robot, task: conveyor, seam, speed_m_s, strategies: {none|constant|"
            "median|model|oracle|model (dry runs): {torch_mean_mm, torch_rms_mm, torch_max_mm, "
            "along_*, across_*}}, onset_strategies, tracking_source, ...}.\n\n"
            "examples:\n  timedexec evaluate --robot kr5 --json kr5-eval.json\n"
            "  timedexec evaluate --task conveyor --robot kr5 --seam curved --json weld.json\n"
            "  timedexec evaluate --task conveyor --twin --robot ur10 --runs 2 --json twin.json"
        ),
    )
    add_robot(p, required=True)
    p.add_argument(
        "--model",
        help="model bundle directory or bundled model name (default: the bundled ROBOT-sim)",
    )
    add_json(p, "the result ({robot, strategies, coverage_95, ...})")
    p.add_argument(
        "--configs",
        type=int_arg(1, 100_000),
        default=None,
        help="held-out configurations (1 .. 100000; default 300; at most the configurations of a sweep the size "
        "of the model's training sweep: the count used is printed, with a warning when fewer)",
    )
    add_seed(p, default=20261, help="plan seed of the held-out set")
    p.add_argument(
        "--draws",
        type=int_arg(2, 1000),
        default=None,
        help="simulated trials behind the oracle (2 .. 1000; default 20)",
    )
    p.add_argument(
        "--speed",
        type=float_arg(0.0, low_open=True, unit="m/s", fix=" (e.g. 0.5)"),
        default=0.5,
        help="seam speed, m/s (finite, > 0)",
    )
    p.add_argument(
        "--physics",
        type=int_arg(0, 10_000, fix=" (0 skips the physics check)"),
        default=None,
        metavar="N",
        help="verify the seam error by running the physics on N configurations (0: skip)",
    )
    p.add_argument(
        "--task",
        choices=("onset", "conveyor"),
        default="onset",
        help="onset: held-out onset timing (the paper's comparison); conveyor: the physical "
        "torch error of a weld on a straight belt",
    )
    p.add_argument(
        "--seam",
        choices=("straight", "curved"),
        default=None,
        help="--task conveyor: the seam's shape (across the belt)",
    )
    p.add_argument(
        "--runs",
        type=int_arg(1, 50),
        default=None,
        help="--task conveyor: publisher phases per work point (stratified), per strategy "
        "(1 .. 50; default 4)",
    )
    p.add_argument(
        "--cells",
        type=int_arg(1, 20),
        default=None,
        help="--task conveyor: work points (the built-in one, then moved by up to 5 cm; "
        "1 .. 20; default 2)",
    )
    p.add_argument(
        "--tracking",
        choices=("sweep", "dry-runs"),
        default=None,
        help="--task conveyor: where the model strategy's tracking model (dead time and "
        "friction offsets) comes from: sweep (default) the calibration sweep's constant-speed "
        "phases alone, the bundle's tracking.json or, without one, the phases run on the "
        "simulator (the dry-run model is then shown too); dry-runs the uncompensated "
        "calibration welds of the task. The JSON's tracking_source says which",
    )
    p.add_argument(
        "--previous-welds",
        type=int_arg(0, 20),
        default=None,
        help="--task conveyor: parts welded the same way before each measured weld (0: every "
        'weld from a fresh start; > 0: experimental, docs/welding.md "Weld after weld")',
    )
    p.add_argument(
        "--twin",
        action="store_true",
        help="--task conveyor: weld in real time through the real client against the "
        "robot's protocol twin (ur_rtde and the UR twin for ur10/ur10e, RSI XML and the RSI "
        "twin for kr5), the torch from the twin's ground truth; one work point, --runs welds "
        "per strategy (default 2), tracking delays from 3 uncompensated welds; same "
        "strategies JSON",
    )
    add_scheduler(p, what="the evaluation (as one task)")
    add_quiet(p)
    p.set_defaults(func=run)


#: Options of one task only, with their defaults: given for the other task they are
#: refused (they would be ignored without a word).
_TASK_OPTIONS: dict[str, dict[str, Any]] = {
    "onset": {"configs": 300, "draws": 20, "physics": 0},
    "conveyor": {
        "seam": "straight",
        "runs": 4,
        "cells": 2,
        "previous_welds": 0,
        "tracking": "sweep",
    },
}
#: --twin's own defaults, and the conveyor options it does not take.
_TWIN_DEFAULTS = {"runs": 2}
_NOT_ON_TWIN = ("cells", "previous_welds", "tracking")


def _task_options(args: argparse.Namespace) -> None:
    """Refuse the options of the other task; fill in this task's defaults.

    Raises
    ------
    ConfigError
        Naming the options given that the chosen ``--task`` does not use.
    """
    from timedexec.errors import ConfigError

    if args.twin:
        if args.task != "conveyor":
            raise ConfigError("--twin applies to --task conveyor: add --task conveyor")
        given = [name for name in _NOT_ON_TWIN if getattr(args, name) is not None]
        if given:
            shown = ", ".join("--" + name.replace("_", "-") for name in given)
            raise ConfigError(f"{shown} do(es) not apply to --twin (one work point, each "
                              "weld from a fresh twin): drop it")  # fmt: skip
        for name, default in _TWIN_DEFAULTS.items():
            if getattr(args, name) is None:
                setattr(args, name, default)
    for task, options in _TASK_OPTIONS.items():
        given = [name for name in options if getattr(args, name) is not None]
        if task != args.task and given:
            shown = ", ".join("--" + name.replace("_", "-") for name in given)
            raise ConfigError(
                f"{shown} appl{'ies' if len(given) == 1 else 'y'} to --task {task}, not to "
                f"--task {args.task}: drop {'it' if len(given) == 1 else 'them'} or use "
                f"--task {task}"
            )
        if task == args.task:
            for name, default in options.items():
                if getattr(args, name) is None:
                    setattr(args, name, default)


def run(args: argparse.Namespace) -> int:
    """Run ``evaluate``; return the exit code."""
    from timedexec.evaluation import evaluate

    _task_options(args)
    check_files(args, "evaluate", inputs={"--model": args.model})
    with cluster(args, "evaluate") as client:
        model = worker_model(args.model, client)
        progress = not args.quiet and client is None
        if args.twin:
            from timedexec.evaluation import evaluate_conveyor_twin

            if args.speed != 0.5:
                raise ConfigError("--speed does not apply to --twin (the example's 0.5 m/s belt)")
            weld = submit(client, evaluate_conveyor_twin, args.robot, model, seam=args.seam,
                          runs=args.runs, seed=args.seed, progress=progress)  # fmt: skip
            emit(args, weld.to_dict(), weld.table())
            return 0
        if args.task == "conveyor":
            from timedexec.evaluation import evaluate_conveyor

            weld = submit(
                client,
                evaluate_conveyor,
                args.robot,
                model,
                seam=args.seam,
                speed_m_s=args.speed,
                cells=args.cells,
                seeds=args.runs,
                oracle_draws=args.runs,
                seed=args.seed,
                progress=progress,
                previous_welds=args.previous_welds,
                tracking=args.tracking.replace("-", " "),
            )
            emit(args, weld.to_dict(), weld.table())
            return 0
        result = submit(
            client,
            evaluate,
            args.robot,
            model,
            n_configs=args.configs,
            seed=args.seed,
            draws=args.draws,
            speed_m_s=args.speed,
            physics_configs=args.physics,
            progress=progress,
        )
    info = result.to_dict()
    for text in info.get("notes", []):
        warn("evaluate", text)
    emit(args, info, result.table())
    return 0
