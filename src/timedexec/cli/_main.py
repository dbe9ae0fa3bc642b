"""The ``timedexec`` command: a thin layer over the library.

Results go to stdout (or the file named), progress and status to stderr. Every subcommand
returns an exit code: 0 success, 2 bad input (a :class:`~timedexec.errors.ConfigError` or
:class:`~timedexec.errors.RecordingError`), 1 any other failure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Sequence
from typing import Any

from timedexec._version import __version__
from timedexec.cli import _discrepancy, _evaluate, _train
from timedexec.errors import ConfigError, TimedExecError
from timedexec.robots import ROBOT_NAMES

__all__ = ["main"]


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="timedexec",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(
            "workflow:\n"
            "  timedexec calibrate --robot-url ur://HOST --imu /dev/ttyUSB0 --trials N --out rec.h5\n"
            "      (or: timedexec simulate --robot ur10 --trials N --out rec.h5)\n"
            "  timedexec extract rec.h5 --out delays.csv\n"
            "  timedexec train delays.csv --out model/ --json cv.json\n"
            "  timedexec evaluate --robot ur10 --model model/\n"
            "  timedexec report rec.h5 delays.csv model/ --out report/\n\n"
            "`timedexec COMMAND --help` describes each command. Exit codes: 0 success, "
            "2 bad input (the message says what and how to fix it), 1 other failures."
        ),
        description=(
            "Measure, model and compensate the actuation and response delays of industrial "
            "robot arms. Every command runs on the embedded simulated robots when no robot "
            "is attached."
        ),
    )
    parser.add_argument("--version", action="version", version=f"timedexec {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_simulate(sub)
    _add_serve(sub)
    _add_calibrate(sub)
    _add_extract(sub)
    _add_report(sub)
    for mod in (_train, _evaluate, _discrepancy):
        mod.add_parser(sub, _Formatter, _emit)
    _add_demo(sub)
    return parser


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    pass


def _emit(result: dict[str, Any], args: argparse.Namespace, text: str) -> None:
    """Results to stdout: JSON with --json, else the human-readable text."""
    if getattr(args, "json", False):
        print(json.dumps(result, indent=2))
    else:
        print(text)


def _add_simulate(sub: Any) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a calibration sweep on a virtual robot and record it (HDF5)",
        formatter_class=_Formatter,
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
    p.add_argument("--robot", required=True, help=f"simulated robot: {', '.join(ROBOT_NAMES)}")
    p.add_argument(
        "--trials", type=int, required=True, help="number of trials (>= 1; the paper: 33500)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", required=True, help="recording to write (HDF5)")
    p.add_argument("--truth", help="also write the ground-truth delay table here (CSV)")
    p.add_argument(
        "--effects",
        default="default",
        help="effect set: default, base, or a comma list of effect names",
    )
    p.add_argument("--period", type=float, help="controller period, s (kr5: 0.012 or 0.004)")
    p.add_argument(
        "--jobs", type=int, default=1, help="worker processes (output does not depend on it)"
    )
    p.add_argument("--resume", action="store_true", help="continue an interrupted run")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from timedexec.effects import parse_effects
    from timedexec.robots import get_robot
    from timedexec.sim import default_settings, simulate_sweep

    spec = get_robot(args.robot, period_s=args.period)
    if args.trials < 1:
        raise ConfigError(f"--trials {args.trials}: the number of trials must be >= 1")
    effects = parse_effects(args.effects, spec.name)
    result = simulate_sweep(
        spec,
        args.trials,
        args.out,
        seed=args.seed,
        effects=effects,
        settings=default_settings(spec),
        truth_path=args.truth,
        resume=args.resume,
        jobs=args.jobs,
        progress=not args.quiet,
    )
    info = result.summary()
    text = (
        f"recorded {info['trials']:,} trials of {spec.name} to {info['recording']} "
        f"({info['recording_bytes'] / 1e6:.1f} MB)"
    )
    if info["truth"]:
        text += f"; ground truth in {info['truth']}"
    _emit(info, args, text)
    return 0


def _add_serve(sub: Any) -> None:
    p = sub.add_parser(
        "serve",
        help="run a protocol twin: a simulated UR or KUKA controller on the network",
        formatter_class=_Formatter,
        description=(
            "Serve a simulated robot controller that real clients talk to: for ur10/ur10e a "
            "UR controller (RTDE on 30004, dashboard on 29999, script port 30003) for the "
            "ur_rtde client; for kr5 a KUKA controller sending RSI XML over UDP to the PC's "
            "port every 12 ms (or --period 0.004). With --imu-link, a simulated gyro on the "
            "flange streams over a pseudo-terminal linked at that path. Runs until Ctrl-C. "
            "Binds 127.0.0.1 unless told otherwise.\n\n"
            "examples:\n  timedexec serve --robot ur10 --imu-link /tmp/gyro\n"
            "  timedexec calibrate --robot-url ur://127.0.0.1 --imu /tmp/gyro --trials 20 "
            "--out ur.h5\n  timedexec serve --robot kr5 --rsi-port 49152"
        ),
    )
    p.add_argument("--robot", required=True, choices=ROBOT_NAMES, help="simulated robot")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (UR) / to send to (RSI)")
    p.add_argument("--imu-link", help="path for a symlink to the gyro's pseudo-terminal")
    p.add_argument("--truth", help="write ground truth (JSON lines) here")
    p.add_argument("--rsi-port", type=int, default=49152, help="the PC's RSI UDP port (kr5)")
    p.add_argument("--period", type=float, help="RSI period, s (kr5: 0.012 or 0.004)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.set_defaults(func=_cmd_serve)


def _cmd_serve(args: argparse.Namespace) -> int:
    import signal
    import threading

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.robot.startswith("ur"):
        from timedexec.twins import run_ur_twin

        print(f"serving a simulated {args.robot} on {args.host} (Ctrl-C stops)", file=sys.stderr)
        with contextlib.suppress(KeyboardInterrupt):
            run_ur_twin(
                args.robot,
                args.host,
                seed=args.seed,
                truth_path=args.truth,
                imu_link=args.imu_link,
                stop_event=stop,
            )
        return 0
    from timedexec.twins import RSITwin

    # Wait for the PC's first answer before counting late answers (else RSI stops with
    # RSITimeout 1.2 s after start when no PC listens yet, as a real KSS would).
    options: dict[str, Any] = {
        "host": args.host, "seed": args.seed, "truth_path": args.truth, "wait_for_pc": True,
    }  # fmt: skip
    if args.period:
        options["period_s"] = args.period
    if args.imu_link:
        raise ConfigError("--imu-link is available for the UR twin; the RSI twin has no gyro yet")
    with RSITwin(args.rsi_port, **options):
        print(
            f"sending RSI frames of a simulated kr5 to {args.host}:{args.rsi_port} (Ctrl-C stops)",
            file=sys.stderr,
        )
        with contextlib.suppress(KeyboardInterrupt):
            while not stop.wait(0.5):
                pass
    return 0


def _add_calibrate(sub: Any) -> None:
    p = sub.add_parser(
        "calibrate",
        help="run a calibration sweep on a robot (or a simulated one) with a gyro",
        formatter_class=_Formatter,
        description=(
            "Run calibration trials through a robot driver with the gyro on the flange and "
            "record them (HDF5, resumable): per trial wait until still, send the single-joint "
            "command on the arrival of a state package, record every package (raw and parsed) "
            "and the gyro stream. A still recording opens the sweep.\n\n"
            "Robot URLs: sim://ur10 (simulator, virtual time), ur://HOST (ur_rtde), "
            "rsi://PORT (KUKA RSI, this PC listens on the UDP port). --imu: a serial port "
            "(/dev/ttyUSB0, a pty) or sim:// (required for real robots; sim:// robots bring "
            "their own virtual gyro).\n\n"
            "examples:\n  timedexec calibrate --robot-url sim://ur10 --trials 40 --seed 1 "
            "--out cal.h5\n  timedexec calibrate --robot-url ur://192.168.1.10 --imu "
            "/dev/ttyUSB0 --trials 33500 --seed 1 --out ur10.h5 --resume"
        ),
    )
    p.add_argument("--robot-url", required=True, help="sim://ROBOT, ur://HOST or rsi://PORT")
    p.add_argument("--imu", help="gyro URL (serial device, pty path)")
    p.add_argument("--robot", help="robot spec for ur:// and rsi:// (ur10, ur10e, kr5)")
    p.add_argument("--trials", type=int, help="number of trials (with --seed)")
    p.add_argument("--seed", type=int, default=0, help="plan seed")
    p.add_argument("--plan", help="plan file (.npz with the arrays of SweepPlan.to_arrays)")
    p.add_argument("--out", required=True, help="recording to write (HDF5)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted sweep")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from urllib.parse import urlsplit

    import numpy as np

    from timedexec.calibration import run_calibration
    from timedexec.drivers import open_driver
    from timedexec.recording import SweepPlan
    from timedexec.sim import default_settings

    scheme = urlsplit(args.robot_url).scheme
    robot = args.robot
    if scheme == "sim":
        robot = robot or (urlsplit(args.robot_url).netloc or "ur10")
    elif robot is None:
        robot = "kr5" if scheme == "rsi" else "ur10"
    settings = default_settings(robot)
    if (args.trials is None) == (args.plan is None):
        raise ConfigError("give either --trials N (with --seed S) or --plan PLAN, not both")
    if args.plan:
        try:
            arrays = dict(np.load(args.plan, allow_pickle=False))
        except (OSError, ValueError) as exc:
            raise ConfigError(f"--plan {args.plan}: cannot read it ({exc})") from exc
        plan = SweepPlan.from_arrays(settings.robot, arrays)
    else:
        if args.trials < 1:
            raise ConfigError(f"--trials {args.trials}: the number of trials must be >= 1")
        plan = SweepPlan.generate(settings.robot, args.trials, seed=args.seed)
    options = {"seed": args.seed} if scheme == "sim" else {}
    driver = open_driver(args.robot_url, **options)
    with driver:
        if scheme == "sim" and not args.imu:
            gyro: Any = driver.gyro(seed=args.seed)  # type: ignore[attr-defined]
            result = run_calibration(
                driver,
                gyro,
                plan,
                args.out,
                protocol=settings.protocol,
                resume=args.resume,
                progress=not args.quiet,
                source=args.robot_url,
            )
        else:
            if not args.imu:
                raise ConfigError("--imu is required for real robots: give the gyro's serial port")
            from timedexec.sensors import open_gyro

            with open_gyro(args.imu) as gyro:
                result = run_calibration(
                    driver,
                    gyro,
                    plan,
                    args.out,
                    protocol=settings.protocol,
                    resume=args.resume,
                    progress=not args.quiet,
                    source=args.robot_url,
                )
    info = result.summary()
    _emit(
        info,
        args,
        f"recorded {info['recorded_now']} trials ({info['planned']} planned) to {info['recording']}",
    )
    return 0


def _add_extract(sub: Any) -> None:
    p = sub.add_parser(
        "extract",
        help="extract actuation and response delays from a recording (delay table CSV)",
        formatter_class=_Formatter,
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
    p.add_argument("--jobs", type=int, default=1, help="worker processes (joblib)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_cmd_extract)


def _cmd_extract(args: argparse.Namespace) -> int:
    import numpy as np

    from timedexec.extraction import extract_recording

    result = extract_recording(
        args.recording, method=args.method, jobs=args.jobs, progress=not args.quiet
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
    _emit(info, args, text)
    return 0


def _add_report(sub: Any) -> None:
    p = sub.add_parser(
        "report",
        help="tables and figures (PNG + markdown) from recordings, delay tables and results",
        formatter_class=_Formatter,
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
    p.set_defaults(func=_cmd_report)


def _cmd_report(args: argparse.Namespace) -> int:
    from timedexec.report import build_report

    path = build_report(args.results, args.out, trial=args.trial)
    print(f"report written to {path}")
    return 0


def _add_demo(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="run the end-to-end job on the embedded simulated robot",
        formatter_class=_Formatter,
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
            "and seam errors per strategy and the conveyor result; --json prints them as "
            "JSON. Default: 8,000 trials (1-2 minutes); --quick: 2,000 (about 30 s)."
            "\n\nexample:\n  timedexec demo --robot kr5 --quick --out demo-out"
        ),
    )
    p.add_argument("--robot", default="ur10", choices=("ur10", "ur10e", "kr5"))
    p.add_argument("--quick", action="store_true", help="2,000 trials instead of 8,000 (about 30 s)")
    p.add_argument("--out", default="timedexec-demo", help="output folder")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--trials", type=int, help="calibration trials (overrides --quick)")
    p.add_argument("--eval-configs", type=int, help=argparse.SUPPRESS)  # tests: tiny evaluation
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    from timedexec.report import run_demo

    quick = args.quick
    trials = args.trials or (2000 if quick else 8000)
    info = run_demo(
        args.robot,
        args.out,
        trials=trials,
        seed=args.seed,
        eval_configs=args.eval_configs or 300,
        eval_draws=10 if quick else 20,
        progress=True,
    )
    from timedexec.robots import get_robot

    spec = get_robot(args.robot)
    lines = [
        f"timedexec demo: {spec.description}, {trials:,} simulated calibration trials",
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
    lines += [
        "",
        "held-out trials, motion-onset timing error and seam error at 0.5 m/s:",
    ]
    for name, row in ev.items():
        lines.append(
            f"  {name:<9} {row['timing_rms_ms']:6.2f} ms RMS  {row['seam_error_cm']:.3f} cm"
        )
    cov = info["evaluation"]["coverage_95"]
    if cov is not None:
        lines.append(f"  the model's 95 % timing bounds held on {100 * cov:.1f} % of trials")
    conv = info["conveyor"]
    lines += [
        "",
        "conveyor at 0.5 m/s, physical torch-to-seam lag in the simulator (+ late, - early), "
        "mean over the cruise / last 100 ms:",
        *(
            f"  {name:<22} {run['mean_lag_cm']:+.2f} / {run['final_lag_cm']:+.2f} cm"
            for name, run in conv.items()
        ),
        f"  (compensated: commands sent {conv['compensated']['actuation_shift_ms']:.0f} ms early; "
        "feedback: the executor's position correction on its back-dated state)",
        "",
        f"report: {info['report']}",
        f"model bundle: {info['model']}   delay table: {info['delays']}",
    ]
    _emit(info, args, "\n".join(lines))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``timedexec`` command line; return the process exit code."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args))
    except TimedExecError as exc:
        print(f"timedexec {args.command}: error: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError | OSError) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
