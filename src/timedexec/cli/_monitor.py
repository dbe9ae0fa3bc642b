"""``timedexec monitor``: has the robot drifted from its delay model? (no gyro needed)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from timedexec._plot import check_figure_format
from timedexec.cli._common import (
    add_command,
    add_json,
    check_files,
    emit,
    float_arg,
    int_arg,
    note,
)
from timedexec.cli._scheduler import (
    add_scheduler,
    cluster,
    submit,
    worker_model,
    worker_path,
)
from timedexec.robots import get_robot_entry

__all__ = ["EXIT_ALARM", "add_parser", "run"]

#: Exit code when an alarm fired with --fail-on-alarm (without it an alarm exits 0).
EXIT_ALARM = 4


def add_parser(sub: Any) -> None:
    """Add ``monitor`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "monitor",
        help="watch a deployed delay model from the robot's own stream (no gyro): drift alarms",
        description=(
            "Measure every move's lag from command to the state stream showing the motion "
            "(actuation + response, sub-period by inverting the commanded ramp), compare it "
            "with the model's prediction, and run a two-sided CUSUM per joint whose threshold "
            "gives one false alarm per --arl0 moves (docs/monitor.md). The first --warmup "
            "moves of each joint are the reference: the monitor detects change relative to "
            "them (the absolute gap to the model is reported too).\n\n"
            "INPUT: a calibration recording (HDF5; its robot stream only) or an executor's "
            "cycle log saved with timedexec.monitoring.save_cycle_log (.npz).\n\n"
            "Output: per joint ok/alarm/warm-up, moves, shift estimate, and each alarm with "
            "its shift (95 % CI), evidence and the calibration sweep that re-fits it. Exit 0 "
            f"whether or not an alarm fired (printed); with --fail-on-alarm exit {EXIT_ALARM} "
            "on an alarm, and also when nothing could be monitored (no measurable move, or no "
            "joint past its warm-up): only a verdict of ok is an all-clear. Bad input: "
            "exit 2.\n\n"
            "example:\n  timedexec monitor ur10.h5 --model ur10-sim --figure monitor.png"
        ),
    )
    p.add_argument("input", help="recording (.h5) or saved cycle log (.npz)")
    p.add_argument(
        "--model",
        metavar="NAME_OR_DIR",
        help="deployed model: bundle directory or bundled name (default: the model shipped "
        "for the recording's robot, e.g. ur10-sim)",
    )
    p.add_argument(
        "--warmup",
        type=int_arg(20, 100_000, fix=" (moves per joint that set the reference)"),
        default=100,
        help="warm-up moves per joint",
    )
    p.add_argument(
        "--arl0",
        type=float_arg(10.0, 1e12, unit="moves", fix=" (e.g. 10000)"),
        default=10_000.0,
        help="moves per joint between false alarms with no change",
    )
    p.add_argument(
        "--k",
        type=float_arg(
            0.0,
            1.0,
            low_open=True,
            fix=" (0.4 by default: fastest for a 0.8-sd shift; scores are clipped at 1.5 sd)",
        ),
        default=0.4,
        help="CUSUM reference, standardized units",
    )
    p.add_argument(
        "--sweep-time",
        action="store_true",
        help="give a time-input model each trial's sweep time (recordings); default: warm",
    )
    p.add_argument(
        "--every-trial",
        action="store_true",
        help="recordings: one move per trial (default: a condition's repeats are one move; "
        "they share the model's error at that pose)",
    )
    p.add_argument("--figure", metavar="PATH", help="write the monitor figure (PNG, PDF, SVG)")
    p.add_argument(
        "--fail-on-alarm",
        action="store_true",
        help=f"exit {EXIT_ALARM} unless the verdict is ok (an alarm fired, or nothing could be "
        "monitored)",
    )
    add_scheduler(p, what="the monitor (as one task)")
    add_json(p, "the monitor state {settings, joints, alerts}")
    p.set_defaults(func=run)


def _text(summary: dict[str, Any], source: str) -> str:
    from timedexec.monitoring import describe_alert

    lines = [
        f"{source}: threshold {summary['threshold']:.2f} (1 false alarm per "
        f"{summary['arl0_moves']:,.0f} moves per joint; warm-up {summary['warmup_moves']} moves)",
        "joint  state    moves  gap to model  shift since warm-up",
    ]
    for j in summary["joints"]:
        gap = j.get("gap_to_model_ms")
        shift = j.get("shift_ms")
        lines.append(
            f"{j['joint']:>5}  {j['status']:<7}  {j['moves']:>5}  "
            f"{'-' if gap is None else f'{gap:+.2f} ms':>12}  "
            f"{'-' if shift is None else f'{shift:+.2f} ms':>12}"
        )
    verdict = summary["verdict"]
    if summary["alerts"]:
        lines.append("alarms:")
        lines += [f"  {describe_alert(a)}" for a in summary["alerts"]]
    elif verdict == "nothing measured":
        lines.append(
            "nothing measured: the input holds no move from rest whose lag could be "
            "measured, so no change could have been seen (this is not an all-clear)"
        )
    elif verdict == "warming up":
        lines.append(
            f"not yet monitoring: no joint has finished its warm-up of "
            f"{summary['warmup_moves']} moves, so no change could have been seen (this is not "
            "an all-clear; feed more moves or lower --warmup)"
        )
    else:
        lines.append("no alarm")
    return "\n".join(lines)


def watch(
    path: str,
    model: str | None,
    *,
    every_trial: bool,
    warmup: int,
    arl0: float,
    k: float,
    sweep_time: bool,
) -> tuple[Any, str, bool]:
    """Read INPUT and run the monitor over every move in it: one task on a cluster.

    Returns the fed ``DelayMonitor``, the model it compared with, and whether that model
    was chosen from the input's robot (no ``--model``). A model for another robot (or
    controller period) than the input's is refused.
    """
    from timedexec.errors import ConfigError
    from timedexec.monitoring import DelayMonitor, load_cycle_log, moves_from_recording

    if Path(path).suffix.lower() == ".npz":
        if every_trial:
            raise ConfigError(
                "--every-trial applies to recordings (one move per trial); a cycle log has "
                "no trials: drop --every-trial"
            )
        arrays, meta = load_cycle_log(path)
        robot, period, moves = meta["robot"], meta["period_s"], None
    else:
        moves, meta = moves_from_recording(path, collapse_repeats=not every_trial)
        robot, period = meta["robot"], meta["period_s"]
    defaulted = model is None
    if model is None:
        if not robot:
            raise ConfigError(f"{path} does not name its robot; give --model NAME_OR_DIR")
        model = get_robot_entry(robot).shipped_model
    from timedexec.execution import check_model_robot, load_delay_model

    loaded = load_delay_model(model)
    if robot:  # a model for another robot would report a "gap" of tens of ms as ok
        check_model_robot(loaded, robot, against=f"{path} comes from")
    mon = DelayMonitor(
        loaded,
        warmup_moves=warmup,
        arl0_moves=arl0,
        reference_k=k,
        sweep_time=sweep_time,
        period_s=period,
    )
    if moves is None:
        mon.feed_log(arrays)
    else:
        mon.update(moves)
    return mon, model, defaulted


def run(args: argparse.Namespace) -> int:
    """Run ``monitor``; 0 (alarm or not), or 4 on an alarm with --fail-on-alarm."""
    from timedexec.monitoring import monitor_figure

    outputs = {"--figure": args.figure} if args.figure else {}
    check_files(
        args, "monitor", inputs={"INPUT": args.input, "--model": args.model}, outputs=outputs
    )
    if args.figure:
        check_figure_format(args.figure, "--figure")
    path = Path(args.input)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no such file; give a recording (.h5) or a cycle log (.npz)"
        )
    with cluster(args, "monitor") as client:
        model = worker_model(args.model, client)
        mon, model, defaulted = submit(
            client,
            watch,
            worker_path(path, client),
            model,
            every_trial=args.every_trial,
            warmup=args.warmup,
            arl0=args.arl0,
            k=args.k,
            sweep_time=args.sweep_time,
        )
    if defaulted:
        note("monitor", f"no --model: using the bundled {model}")
    summary = mon.summary() | {"input": str(path), "model": str(args.model or model)}
    if args.figure:
        monitor_figure(mon, args.figure)
    text = _text(summary, str(path))
    if args.figure:
        text += f"\nwrote the figure to {args.figure}"
    emit(args, summary, text)
    return EXIT_ALARM if (args.fail_on_alarm and summary["verdict"] != "ok") else 0
