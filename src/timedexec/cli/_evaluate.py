"""The ``timedexec evaluate`` subcommand (wired into :mod:`timedexec.cli` by its owner)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from timedexec.robots import ROBOT_NAMES

__all__ = ["add_parser"]

Emit = Callable[[dict[str, Any], argparse.Namespace, str], None]


def add_parser(sub: Any, formatter_class: type[argparse.HelpFormatter], emit: Emit) -> None:
    """Add ``evaluate`` to the subparsers ``sub``; results go through ``emit``."""
    p = sub.add_parser(
        "evaluate",
        help="compare delay-compensation strategies on held-out simulated trials",
        formatter_class=formatter_class,
        description=(
            "Evaluate timed execution on the simulated robot with ground truth. On start "
            "configurations held out of training (a fresh plan seed), each condition (joint "
            "1/2/3/5, both directions) gets a true trial; five strategies predict its actuation "
            "delay: none (no compensation), constant (one latency for all joints: the overall "
            "median, as MoveIt Servo), median (per joint, the published baseline), model (the "
            "learned delay model) and oracle (the true conditional mean of --draws simulated "
            "trials). Reported: the motion-onset timing error (RMS, ms), the seam error of a "
            "conveyor at --speed (cm; speed x timing error, optionally verified by running the "
            "physics with --physics N configurations) and the coverage of the model's 95 %% "
            "bounds.\n\n"
            "Output: a table, or with --json OUT.json the JSON {robot, strategies: {none: "
            "{timing_rms_ms, seam_error_cm, ...}, ...}, coverage_95, ...}.\n\n"
            "example:\n  timedexec evaluate --robot kr5 --json kr5-eval.json"
        ),
    )
    p.add_argument("--robot", required=True, choices=ROBOT_NAMES, help="simulated robot")
    p.add_argument(
        "--model",
        help="model bundle directory or bundled model name (default: the bundled ROBOT-sim)",
    )
    p.add_argument(
        "--json",
        metavar="OUT.json",
        help="write the result as JSON to this file ('-': stdout)",
    )
    p.add_argument("--configs", type=int, default=300, help="held-out configurations")
    p.add_argument("--seed", type=int, default=20261, help="plan seed of the held-out set")
    p.add_argument("--draws", type=int, default=20, help="simulated trials behind the oracle")
    p.add_argument("--speed", type=float, default=0.5, help="seam speed, m/s")
    p.add_argument(
        "--physics",
        type=int,
        default=0,
        metavar="N",
        help="verify the seam error by running the physics on N configurations",
    )
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_run(emit))


def _run(emit: Emit) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        from timedexec.errors import ConfigError
        from timedexec.evaluation import evaluate

        if args.speed <= 0:
            raise ConfigError(f"--speed {args.speed}: the seam speed must be > 0 m/s")
        result = evaluate(
            args.robot,
            args.model,
            n_configs=args.configs,
            seed=args.seed,
            draws=args.draws,
            speed_m_s=args.speed,
            physics_configs=args.physics,
            progress=not args.quiet,
        )
        info = result.to_dict()
        if args.json and args.json != "-":
            with open(args.json, "w", encoding="utf-8") as fh:
                json.dump(info, fh, indent=2)
                fh.write("\n")
            text = result.table() + f"\nwrote {args.json}"
            shown = argparse.Namespace(**{**vars(args), "json": False})
            emit(info, shown, text)
        else:
            emit(
                info, argparse.Namespace(**{**vars(args), "json": args.json == "-"}), result.table()
            )
        return 0

    return run
