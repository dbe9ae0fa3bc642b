"""``timedexec simulate``: a calibration sweep on a simulated robot, recorded to HDF5."""

from __future__ import annotations

import argparse
from typing import Any

from timedexec.cli._calibrate import adaptive_done, adaptive_settings, add_adaptive_options
from timedexec.cli._common import (
    MAX_TRIALS,
    add_command,
    add_jobs,
    add_json,
    add_period,
    add_quiet,
    add_robot,
    add_seed,
    check_files,
    emit,
    int_arg,
    shell_command,
    sweep_stopped,
)
from timedexec.cli._scheduler import add_scheduler, cluster, cluster_jobs
from timedexec.effects import EFFECTS
from timedexec.errors import ConfigError

__all__ = ["add_parser", "resume_command", "run"]


def add_parser(sub: Any) -> None:
    """Add ``simulate`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "simulate",
        help="simulate a calibration sweep on a virtual robot and record it (HDF5)",
        description=(
            "Simulate a calibration sweep in virtual time on the embedded simulated robot: "
            "per trial one joint moves out and back while the state packages, the command and "
            "an 8 kHz gyro on the flange are recorded, exactly as a live sweep records them, "
            "plus the ground truth (true onset and delays).\n\n"
            "Output: REC.h5 (see docs/recording-format.md) and, with --truth, the ground-truth "
            "delay table (CSV). Same seed, same output.\n\n"
            "example:\n  timedexec simulate --robot ur10 --trials 2000 --seed 1 "
            "--out ur10.h5 --truth ur10-truth.csv"
        ),
    )
    add_robot(p, required=True)
    p.add_argument(
        "--trials",
        type=int_arg(1, MAX_TRIALS, fix=" (the paper's sweep: 33500)"),
        help=f"number of trials (1 .. {MAX_TRIALS:,}; the paper: 33500); required unless "
        "--adaptive",
    )
    add_seed(p)
    p.add_argument("--out", required=True, help="recording to write (HDF5)")
    p.add_argument("--truth", help="also write the ground-truth delay table here (CSV)")
    p.add_argument(
        "--effects",
        default="default",
        help="effect set: default, base, a comma list of effect names, or default,NAME,... "
        f"(the robot's defaults plus those named); the vocabulary: {', '.join(EFFECTS)}",
    )
    p.add_argument(
        "--warm",
        action="store_true",
        help="a warm robot: powered on 4 h before the sweep (as one taken out of production; "
        "thermal_drift has settled); default cold, powered on as the sweep starts. The "
        "recording's power_on_s says which, and models trained on it say which thermal "
        "state they answer for",
    )
    add_period(p)
    add_adaptive_options(p)
    add_jobs(p, help="worker processes (output does not depend on it)")
    add_scheduler(p, what="the simulation blocks (the recording is written here)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run")
    add_quiet(p)
    add_json(p, "the summary (trials, recording, recording_bytes, truth, ...)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``simulate``; return the exit code."""
    from timedexec.effects import parse_effects
    from timedexec.robots import get_robot
    from timedexec.sim import default_settings, simulate_sweep

    check_files(
        args,
        "simulate",
        # the recording refuses an existing file itself unless --resume continues it
        inputs={"--workspace": args.workspace},
        outputs={"--out": args.out, "--truth": args.truth},
        what={"--truth": "the ground-truth delay table (CSV)"},
    )
    spec = get_robot(args.robot, period_s=args.period)
    effects = parse_effects(args.effects, spec.name)
    if args.adaptive:
        return _adaptive(args, spec, effects)
    if args.trials is None:
        raise ConfigError("give --trials N (or --adaptive)")
    try:
        with cluster(args, "simulate") as client:
            result = simulate_sweep(
                spec,
                args.trials,
                args.out,
                seed=args.seed,
                effects=effects,
                settings=default_settings(spec),
                truth_path=args.truth,
                resume=args.resume,
                jobs=cluster_jobs("simulate", args, client),
                progress=not args.quiet,
                warm=args.warm,
            )
    except (KeyboardInterrupt, OSError) as exc:
        return sweep_stopped("simulate", exc, args.out, resume_command(args))
    info = result.summary()
    text = (
        f"recorded {info['trials']:,} trials of {spec.name} to {info['recording']} "
        f"({info['recording_bytes'] / 1e6:.1f} MB)"
    )
    if info["truth"]:
        text += f"; ground truth in {info['truth']}"
    emit(args, info, text)
    return 0


def _adaptive(args: argparse.Namespace, spec: Any, effects: Any) -> int:
    """``simulate --adaptive``: the adaptive sweep on the batch simulator (what
    ``calibrate --robot-url sim://ROBOT --adaptive`` records, at the batch simulator's speed)."""
    from timedexec.calibration import run_adaptive
    from timedexec.sim import SimulatedRunner, default_settings

    if args.trials is not None:
        raise ConfigError("--adaptive chooses its own trials: drop --trials")
    for flag, given in (("--truth", args.truth), ("--scheduler", args.scheduler)):
        if given:
            raise ConfigError(f"{flag} is not available with --adaptive (drop it)")
    settings, workspace = adaptive_settings(args)
    runner = SimulatedRunner(
        spec, seed=args.seed, effects=effects, settings=default_settings(spec), warm=args.warm
    )
    try:
        result = run_adaptive(
            runner,
            args.out,
            settings=settings,
            workspace=workspace,
            resume=args.resume,
            progress=not args.quiet,
        )
    except (KeyboardInterrupt, OSError) as exc:
        return sweep_stopped("simulate", exc, args.out, resume_command(args))
    return adaptive_done(args, result)


def resume_command(args: argparse.Namespace) -> str:
    """The command that continues this run: the same options and ``--resume``."""
    return shell_command(
        "simulate",
        [
            ("--robot", args.robot),
            ("--trials", args.trials),
            ("--seed", args.seed),
            ("--effects", None if args.effects == "default" else args.effects),
            ("--warm", args.warm),
            ("--period", args.period),
            ("--adaptive", args.adaptive),
            ("--budget-min", args.budget_min if args.adaptive else None),
            ("--batch-min", args.batch_min if args.adaptive else None),
            ("--stop-fraction", args.stop_fraction if args.adaptive else None),
            ("--workspace", args.workspace),
            ("--jobs", None if args.jobs == 1 else args.jobs),
            ("--scheduler", args.scheduler),
            ("--out", args.out),
            ("--truth", args.truth),
            ("--json", args.json),
            ("--quiet", args.quiet),
            ("--resume", True),
        ],
    )
