"""``timedexec calibrate``: a live calibration sweep through a robot driver and a gyro."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from timedexec.cli._common import (
    MAX_TRIALS,
    add_command,
    add_json,
    add_quiet,
    add_robot,
    add_seed,
    check_files,
    emit,
    float_arg,
    int_arg,
    shell_command,
    sweep_stopped,
    warn,
)
from timedexec.errors import ConfigError, DatingWarning, TimedExecError

if TYPE_CHECKING:
    from timedexec.drivers import RobotURL

__all__ = ["add_parser", "resume_command", "run"]


def add_parser(sub: Any) -> None:
    """Add ``calibrate`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "calibrate",
        help="run a calibration sweep on a robot (or a simulated one) with a gyro",
        description=(
            "Run calibration trials through a robot driver with the gyro on the flange and "
            "record them (HDF5, resumable): per trial wait until still, send the single-joint "
            "command on the arrival of a state package, record every package (raw and parsed) "
            "and the gyro stream. A still recording opens the sweep.\n\n"
            "Robot URLs: sim://ur10 (simulator, virtual time), ur://HOST (ur_rtde), "
            "rsi://[LISTEN_IP:]PORT[?robot=IP] (KUKA RSI, this PC listens on the UDP port; "
            "loopback unless LISTEN_IP is given, docs/rsi.md). --imu: a serial port "
            "(/dev/ttyUSB0, a pty) or sim:// (required for real robots; sim:// robots bring "
            "their own virtual gyro).\n\n"
            "A robot or gyro that stops answering ends the command with exit code 3; "
            "--resume continues the recording.\n\n"
            "examples:\n  timedexec calibrate --robot-url ur://192.168.1.10 --imu /dev/ttyUSB0 "
            "--sensor-profile gyro.json --seed 1 --out ur10.h5   # adaptive, <= 45 min\n"
            "  timedexec calibrate --robot-url ur://192.168.1.10 --imu /dev/ttyUSB0 "
            "--sensor-profile gyro.json --trials 33500 --seed 1 --out ur10.h5 --resume"
            "   # the paper's fixed sweep, ~9.7 h\n"
            "  timedexec calibrate --robot-url 'sim://ur10e?warm=1' --budget-min 10 --seed 1 "
            "--out ur10e.h5\n  timedexec calibrate --robot-url sim://ur10 --trials 40 --seed 1 "
            "--out cal.h5"
        ),
    )
    p.add_argument(
        "--robot-url", required=True, help="sim://ROBOT, ur://HOST or rsi://[LISTEN_IP:]PORT"
    )
    p.add_argument("--imu", help="gyro URL (serial device, pty path)")
    add_robot(
        p,
        help="robot model, passed to the driver (default: asked from the controller for ur://, "
        "kr5 for rsi://, the URL's robot for sim://)",
    )
    p.add_argument(
        "--trials",
        type=int_arg(
            1, MAX_TRIALS, fix=" (the paper's sweep: 33500; about 1 s of robot time each)"
        ),
        help=f"number of trials of a fixed sweep (with --seed; 1 .. {MAX_TRIALS:,}); not with "
        "--adaptive. Without --trials and --plan the sweep is adaptive (--budget-min 45)",
    )
    add_seed(p, help="plan seed")
    p.add_argument("--plan", help="plan file (.npz with the arrays of SweepPlan.to_arrays)")
    p.add_argument("--out", required=True, help="recording to write (HDF5)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted sweep")
    p.add_argument(
        "--no-tracking-phases",
        dest="tracking_phases",
        action="store_false",
        help="skip the tracking phases after the sweep (default: per joint, 0.05 and 0.25 "
        "rad/s both ways, each held 0.8 s, 30-40 s of robot time; the dead time and "
        "friction offsets they give, the tracking model of conveyor tasks, go to "
        "OUT-stem.tracking.json, which train --tracking puts into the bundle; "
        "docs/calibration.md)",
    )
    p.add_argument(
        "--sensor-profile",
        metavar="FILE.json",
        help="the gyro's constants as measured (docs/sensor-constants.md): full_scale_dps, "
        "nominal_rate_hz, block_samples, group_delay_s, transport_latency_s",
    )
    p.add_argument(
        "--gyro-group-delay",
        metavar="MS",
        type=float_arg(0.0, 50.0, unit="ms"),
        help="the gyro filter's group delay, ms (overrides the profile)",
    )
    p.add_argument(
        "--gyro-transport-latency",
        metavar="MS",
        type=float_arg(0.0, 50.0, unit="ms"),
        help="minimum latency from sampling to host arrival, ms (overrides the profile); "
        "real robots need both constants (profile or these two options)",
    )
    p.add_argument(
        "--max-correction-deg",
        metavar="DEG",
        type=float_arg(0.0, 360.0, unit="degrees"),
        help="rsi:// only: the largest correction per axis from the pose where RSI started, "
        "degrees (the RSI configuration's AXISCORR limits; default 90; per axis: the URL's "
        "?max_correction_deg=D1,...,D6). A sweep over RSI is planned around that pose within "
        "it; a --plan that leaves it is refused before anything moves",
    )
    add_adaptive_options(p)
    add_quiet(p)
    add_json(p, "the summary (recording, planned, recorded_now, ...)")
    p.set_defaults(func=run)


def add_adaptive_options(p: Any) -> None:
    """``--adaptive`` and its options (``calibrate`` and ``simulate`` share them)."""
    g = p.add_argument_group(
        "adaptive sweep (docs/calibration.md: when to use it rather than the fixed sweep)"
    )
    g.add_argument(
        "--adaptive",
        action="store_true",
        help="the default of calibrate when neither --trials nor --plan is given: "
        "choose each batch of trials from a Gaussian-process model of the trials so far "
        "(where another trial lowers the model's expected error over the workspace most), "
        "until --budget-min of robot time or until another 10 minutes would lower the "
        "estimated error by less than a tenth of the noise floor; resumable (--resume)",
    )
    g.add_argument(
        "--budget-min",
        metavar="M",
        type=float_arg(1.0, 24 * 60.0, unit="min"),
        default=45.0,
        help="robot time the adaptive sweep may take, min (1 .. 1440)",
    )
    g.add_argument(
        "--batch-min",
        metavar="M",
        type=float_arg(0.5, 60.0, unit="min"),
        default=3.0,
        help="robot time of one adaptive batch, min: the next is chosen while it runs",
    )
    g.add_argument(
        "--stop-fraction",
        metavar="F",
        type=float_arg(0.0, 0.99),
        default=0.1,
        help="the stopping rule: stop when another 10 minutes would lower the estimated "
        "error by less than F times the noise floor (and the newest batches, predicted "
        "before they were measured, bear the estimate out); 0: run to --budget-min",
    )
    g.add_argument(
        "--workspace",
        metavar="FILE",
        help="where the robot works (the adaptive sweep samples there): a JSON file with "
        '{"q_min_rad": [6], "q_max_rad": [6]} (a joint-range box, within the calibration '
        'ranges) or {"configurations_rad": [[6], ...]}, or a CSV of configurations (6 '
        "angles per row, rad); default the robot's calibration ranges",
    )


def adaptive_settings(args: argparse.Namespace) -> tuple[Any, Any]:
    """The :class:`~timedexec.calibration.AdaptiveSettings` and
    :class:`~timedexec.calibration.Workspace` of the adaptive options.

    Raises
    ------
    ConfigError
        ``--trials`` or ``--plan`` with ``--adaptive``; an unreadable workspace file.
    """
    from timedexec.calibration import AdaptiveSettings, Workspace

    if getattr(args, "plan", None) is not None:
        raise ConfigError("--adaptive chooses its own trials: drop --plan")
    settings = AdaptiveSettings(
        budget_s=args.budget_min * 60.0,
        batch_s=args.batch_min * 60.0,
        stop_fraction=args.stop_fraction,
        seed=args.seed,
    )
    if args.workspace is None:
        return settings, Workspace()
    return settings, read_workspace(args.workspace)


def read_workspace(path: str) -> Any:
    """The workspace in ``path``: JSON (a box or configurations) or CSV (configurations).

    Raises
    ------
    ConfigError
        An unreadable or malformed file, naming it and the expected form.
    """
    import json

    import numpy as np

    from timedexec.calibration import Workspace

    form = (
        '{"q_min_rad": [6 angles], "q_max_rad": [6 angles]} or {"configurations_rad": '
        "[[6 angles], ...]} (JSON), or a CSV with 6 angles (rad) per row"
    )
    try:
        if path.lower().endswith(".json"):
            with open(path, encoding="utf-8") as f:
                d = json.load(f)
            if not isinstance(d, dict) or not set(d) <= {
                "q_min_rad",
                "q_max_rad",
                "configurations_rad",
            }:
                raise ConfigError(f"--workspace {path}: expected {form}")
            return Workspace.from_dict(d)
        rows = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
    except (OSError, ValueError, TypeError) as exc:
        raise ConfigError(f"--workspace {path}: cannot read it ({exc}); expected {form}") from exc
    if rows.shape[1] != 6:
        raise ConfigError(f"--workspace {path}: rows of {rows.shape[1]} values; expected {form}")
    return Workspace(configurations_rad=tuple(map(tuple, rows.tolist())))


def run(args: argparse.Namespace) -> int:
    """Run ``calibrate``; return the exit code."""
    from timedexec.calibration import DriverRunner, Workspace, run_adaptive, run_calibration
    from timedexec.drivers import RobotURL, open_driver
    from timedexec.recording import SweepPlan, SweepProtocol

    url = RobotURL.parse(args.robot_url)
    simulated = url.scheme == "sim"
    robot = _robot(args, url)
    if not args.adaptive and args.trials is None and args.plan is None:
        # The default sweep is the adaptive one: about 5 % above the paper's 9.7 h
        # sweep's model error in 45 min of robot time (docs/calibration.md).
        args.adaptive = True
    if args.adaptive:
        if args.trials is not None:
            raise ConfigError("--adaptive chooses its own trials: drop --trials")
        adaptive = adaptive_settings(args)
    elif (args.trials is None) == (args.plan is None):
        raise ConfigError("give either --trials N (with --seed S) or --plan PLAN, not both")
    if not simulated and not args.imu:
        raise ConfigError("--imu is required for real robots: give the gyro's serial port")
    imu = args.imu if args.imu and "://" not in args.imu else None
    check_files(
        args,
        "calibrate",
        # the recording refuses an existing file itself unless --resume continues it
        inputs={"--plan": args.plan, "--imu": imu, "--workspace": args.workspace},
        outputs={"--out": args.out},
        devices=("--imu",),
    )
    _check_gyro_constants(args, real=not simulated)
    # Everything the user gave is checked before anything connects: the first error
    # reported is the real one (a broken profile was found only after the robot answered).
    if imu is not None and not os.path.exists(imu):
        raise ConfigError(
            f"--imu {imu}: no such port; check that the sensor is plugged in and the path is "
            "right (ls /dev/ttyUSB* /dev/ttyACM* /dev/serial/by-id/)"
        )
    gyro_constants = _gyro_constants(args)
    if simulated and not args.imu and gyro_constants is not None:
        _check_simulated_gyro(gyro_constants, SweepProtocol.for_robot(robot).gyro, url.text)
    # The driver gets the robot model the user named (a UR controller reporting another
    # model, or a KUKA that says nothing, is then driven as that model); without --robot a
    # UR driver asks the controller's dashboard, and the sweep is planned for its answer.
    options: dict[str, Any] = {"seed": args.seed} if simulated else {}
    if not simulated and robot is not None:
        options["robot"] = robot
    if args.max_correction_deg is not None:
        options["max_correction_deg"] = _max_correction(args, url)
    try:
        with contextlib.ExitStack() as stack:
            driver = stack.enter_context(open_driver(url, **options))
            # The robot's default protocol at the period the controller runs (RSI: 12 or
            # 4 ms, as the URL's period= says), from its spec: no simulator involved.
            protocol = SweepProtocol.for_robot(
                robot or driver.robot, period_s=driver.controller_period_s
            )
            if gyro_constants is not None:
                protocol = dataclasses.replace(protocol, gyro=gyro_constants)
            reach = getattr(driver, "reachable_range_rad", None)
            if args.adaptive:
                plan = None  # the adaptive sweep chooses its own trials
            elif args.plan:
                plan = _read_plan(args.plan, protocol.robot)
            elif callable(reach) and args.resume and os.path.exists(args.out):
                # a sweep planned around the pose where RSI first started goes on with its
                # own configurations (checked against this session's reach below)
                plan = _recorded_plan(args.out, protocol.robot, args.seed)
            elif callable(reach):  # RSI: around the pose where RSI started, within reach
                lo, hi = reach()
                margin = _trial_excursion_rad(protocol)
                plan = SweepPlan.generate(protocol.robot, args.trials, seed=args.seed,
                                          q_range_rad=(lo + margin, hi - margin))  # fmt: skip
            else:
                plan = SweepPlan.generate(protocol.robot, args.trials, seed=args.seed)
            if callable(reach) and plan is not None:  # refused before anything moves (exit 2)
                driver.check_reachable(  # type: ignore[attr-defined]
                    plan.q_start_rad, margin_rad=_trial_excursion_rad(protocol),
                    what="the plan's configuration",
                )  # fmt: skip
                if not args.quiet:
                    _say_rsi_plan(driver, plan)
            gyro: Any
            if simulated and not args.imu:
                gyro = driver.gyro(seed=args.seed)  # type: ignore[attr-defined]
            else:
                from timedexec.sensors import open_gyro

                gyro = stack.enter_context(open_gyro(args.imu))
            if args.adaptive:
                workspace = adaptive[1]
                if callable(reach):  # RSI: within the correction's reach, before moving
                    margin = _trial_excursion_rad(protocol)
                    if workspace is not None and workspace.is_list:
                        driver.check_reachable(  # type: ignore[attr-defined]
                            workspace.configurations_rad, margin_rad=margin,
                            what="the workspace's configuration",
                        )  # fmt: skip
                    else:
                        lo, hi = reach()
                        workspace = (workspace or Workspace()).cut_to(
                            lo + margin, hi - margin,
                            reach="RSI's reach from the pose where RSI started, less a "
                            "trial's excursion",
                            fix="raise max_correction_deg (rsi://...?max_correction_deg=D or "
                            "--max-correction-deg) or start RSI nearer the workspace",
                        )  # fmt: skip
                runner = DriverRunner(driver, gyro, protocol, source=args.robot_url)
                done = run_adaptive(
                    runner,
                    args.out,
                    settings=adaptive[0],
                    workspace=workspace,
                    resume=args.resume,
                    progress=not args.quiet,
                )
                tracking = _tracking_phases(args, driver, protocol, runner)
                return adaptive_done(args, done, tracking)
            assert plan is not None
            result = run_calibration(
                driver,
                gyro,
                plan,
                args.out,
                protocol=protocol,
                resume=args.resume,
                progress=not args.quiet,
                source=args.robot_url,
            )
            tracking = _tracking_phases(args, driver, protocol, result)
    except (KeyboardInterrupt, OSError) as exc:
        return sweep_stopped("calibrate", exc, args.out, resume_command(args))
    info = result.summary()
    info["tracking"] = tracking
    emit(
        args,
        info,
        f"recorded {info['recorded_now']} trials ({info['planned']} planned) to {info['recording']}"
        + _tracking_text(tracking),
    )
    return 0


def tracking_path(out: str) -> str:
    """Where ``calibrate --out OUT`` writes the tracking phases' model: OUT's stem +
    ``.tracking.json``."""
    return os.path.splitext(out)[0] + ".tracking.json"


def _tracking_phases(
    args: argparse.Namespace, driver: Any, protocol: Any, sweep: Any
) -> dict[str, Any] | None:
    """Run the tracking phases after the sweep (unless ``--no-tracking-phases``) through an
    uncompensated, cycle-locked executor on the sweep's driver, from where the sweep left
    the robot (``sweep``: the sweep's ``origin_s`` and ``session``, a
    ``CalibrationResult`` or ``DriverRunner``); write the fitted tracking model with the
    phases' settings and lags to :func:`tracking_path`; return what was written (None when
    skipped)."""
    if not args.tracking_phases:
        return None
    import json
    import warnings

    import numpy as np

    from timedexec._files import write_atomic
    from timedexec.execution import ExecutorSettings, FixedDelays, TimedExecutor
    from timedexec.tasks import TrackingDelays, TrackingPhases, fit_joint_lags, run_tracking_phases

    base = FixedDelays(robot=protocol.robot, controller_period_s=protocol.controller_period_s)
    phases = TrackingPhases()
    settings = ExecutorSettings(compensate=False, cycle_lock=True)
    try:
        with warnings.catch_warnings():
            # The probe's dating at connect knows no response delay yet (0): the runs are
            # dated again below by the sweep's, which warns if that is near a flip.
            warnings.simplefilter("ignore", DatingWarning)
            with TimedExecutor(driver, base, settings) as ex:
                t0 = ex.now()
                runs = run_tracking_phases(ex, phases)
                robot_time_s = ex.now() - t0
    except ConfigError as exc:  # e.g. a joint limit near the sweep's last pose
        warn("calibrate", f"tracking phases skipped ({exc}); the sweep is recorded")
        return {"skipped": str(exc)}
    # The phases' positions are dated by the probed intake, whose whole-period ambiguity
    # is resolved by the mean response delay (IntakeFix.dated): with none known (0) a
    # publisher phase whose response is past half a period dated every position a cycle
    # late (simulated UR10, 8 ms cycle, response ~4.9 ms: lag 20.9 ms for 13.0 physical,
    # a conveyor weld 3.6 mm off). The sweep just recorded measures it: date by its median.
    response_s, sampling = _sweep_timing(
        args.out, sweep.origin_s, sweep.session, protocol.controller_period_s
    )
    base = dataclasses.replace(base, response_s=response_s)
    runs = [r if r.intake is None else dataclasses.replace(r, intake=r.intake.dated(response_s))
            for r in runs]  # fmt: skip
    # The controller's echo depth, from the probe and the sweep's gyro: the gyro dated
    # the sweep's states by itself (host time of sampling minus the controller stamp,
    # whatever the publisher's phase), which lies some whole periods from the probe's
    # boundary. Known, it dates every phase by counting packages, and the executor does so
    # on every later connect (the model carries it).
    fix = next((r.intake for r in runs if r.intake is not None), None)  # one per session
    depth, echo = None, {"cycles": None, "why": "no intake probe (no cycle lock)"}
    if fix is not None:
        if sampling is None:
            echo["why"] = "no sampling instant from this session's sweep (nothing recorded now)"
        else:
            depth, margin, why = fix.echo_depth_at(sampling(fix.probed_at_s), response_s)
            echo = {"cycles": depth, "margin_ms": round(margin * 1e3, 3), "why": why}
    if depth is not None:
        runs = [r if r.intake is None else dataclasses.replace(
                    r, intake=dataclasses.replace(r.intake, echo_depth_cycles=depth)
                    .dated(response_s))
                for r in runs]  # fmt: skip
    elif fix is not None:
        warn("calibrate", f"the controller's echo depth not measured ({echo['why']}): the "
             "executor dates states by the mean response delay, which warns where that is "
             "fragile")  # fmt: skip
    model = dataclasses.replace(
        TrackingDelays.calibrate_phases(base, runs), echo_depth_cycles=depth
    )
    lags = [
        {"joint": r.joint, "speed_rad_s": r.speed_rad_s,
         "lag_ms": round(float(fit_joint_lags(r.plan, *r.window())[r.joint - 1]) * 1e3, 3)}
        for r in runs
    ]  # fmt: skip
    data = {
        "robot": protocol.robot,
        "controller_period_s": protocol.controller_period_s,
        "source": args.robot_url,
        "phases": phases.to_dict(),
        "robot_time_s": round(robot_time_s, 3),
        "response_s": response_s,
        "echo_depth": echo,
        "tracking": model.to_dict(),
        "lags": lags,
    }
    path = tracking_path(args.out)
    write_atomic(path, json.dumps(data, indent=1) + "\n")
    return {"path": path, "robot_time_s": data["robot_time_s"],
            "dead_time_ms": (np.asarray(model.dead_time_s) * 1e3).round(3).tolist(),
            "echo_depth_cycles": depth}  # fmt: skip


def _sweep_timing(
    recording: str, origin_s: float, session: int, period_s: float
) -> tuple[float, Callable[[float], float] | None]:
    """What the recording's sweep measured of the state's timing (extracted as `extract`
    does): the median response delay of its trials, s (0 with a warning where none was
    measured: the phases' positions may then be dated a controller cycle off), and where
    this session recorded trials, the host time of a package's sampling minus its
    controller stamp as a function of host time (the line through this session's last
    trials' :func:`~timedexec.extraction.sampling_offsets` at controller period
    ``period_s``, for the clocks' drift; None where it recorded none)."""
    import numpy as np

    from timedexec.extraction import extract_recording, sampling_offsets
    from timedexec.recording import RecordingReader

    why = "no trial measured one"
    try:
        table = extract_recording(recording, progress=False).table
        r = np.asarray(table["response_delay"], dtype=float)
        trials = np.asarray(table["trial"], dtype=np.int64)
    except TimedExecError as exc:
        r, trials, why = np.zeros(0), np.zeros(0, np.int64), f"its extraction failed ({exc})"
    ok = np.isfinite(r)
    if not ok.any():
        warn("calibrate", f"no response delay from the sweep to date the tracking phases "
             f"by: {why}; dated with none, they may be a controller cycle off")  # fmt: skip
        return 0.0, None
    response_s = float(np.median(r[ok]))
    if not math.isfinite(origin_s):
        return response_s, None
    by_trial = dict(zip(trials[ok], r[ok], strict=True))
    with RecordingReader(recording) as rec:
        rows = np.flatnonzero(rec.read("session") == session)[-_SAMPLING_TRIALS:]
        if not len(rows):
            return response_s, None
        trial = rec.read("trial", rows)
        t0 = rec.read("t0_s", rows)
        host = rec.read("state_host_time_s", rows)
        stamp = rec.read("state_controller_time_s", rows)
    resp = np.array([by_trial.get(int(k), np.nan) for k in trial])
    offset = origin_s + t0 + sampling_offsets(host, stamp, resp, period_s)
    with np.errstate(invalid="ignore"):
        at = origin_s + t0 + np.nanmean(host, axis=1)  # host time of the trial's packages
    good = np.isfinite(offset) & np.isfinite(at)
    if good.sum() < 3:
        return response_s, None
    at, offset = at[good], offset[good]
    # a line (the clocks drift: 100 ppm is 1 ms over 10 s), refitted without the trials
    # further from it than 3 robust sd (a trial the extraction got wrong)
    line = np.polyfit(at - at[-1], offset, 1)
    res = offset - np.polyval(line, at - at[-1])
    spread = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    keep = np.abs(res) <= max(3.0 * spread, 1e-4)
    if keep.sum() >= 3:
        line = np.polyfit(at[keep] - at[-1], offset[keep], 1)
    return response_s, lambda t: float(np.polyval(line, t - at[-1]))


#: The last trials of the session whose sampling instants date the probe.
_SAMPLING_TRIALS = 50


def _tracking_text(tracking: dict[str, Any] | None) -> str:
    """The summary line's part about the tracking phases."""
    if tracking is None:
        return ""
    if "skipped" in tracking:
        return "; tracking phases skipped"
    depth = tracking.get("echo_depth_cycles")
    return (
        f"; tracking phases ({tracking['robot_time_s']:.0f} s of robot time) fitted to "
        f"{tracking['path']}"
        + ("" if depth is None else f" (echo depth {depth} cycles)")
    )


def adaptive_done(
    args: argparse.Namespace, result: Any, tracking: dict[str, Any] | None = None
) -> int:
    """Report an adaptive sweep (summary, and the figure of its estimated error against
    robot time next to the recording; the tracking phases' model); exit code 0."""
    from timedexec.calibration import plot_design_log

    info = result.summary()
    info["tracking"] = tracking
    figure = plot_design_log(result.path)
    info["figure"] = None if figure is None else str(figure)
    why = {
        "converged": "the stopping rule: another 10 minutes would improve the model by less "
        "than a tenth of the noise floor",
        "budget": "the budget of robot time",
        "workspace": "every candidate of the workspace measured",
    }.get(result.stopped, result.stopped)
    last = [n for n in info["batches"] if n["error_s"] == n["error_s"]]  # not NaN
    err = f"; estimated error {1e3 * last[-1]['error_after_s']:.2f} ms" if last else ""
    emit(
        args,
        info,
        f"recorded {info['recorded_now']} trials ({info['trials']} in all, "
        f"{info['robot_time_s'] / 60:.1f} min of robot time) to {info['recording']}{err}; "
        f"stopped by {why}"
        + (f"; figure {figure}" if figure is not None else "")
        + _tracking_text(tracking),
    )
    return 0


def resume_command(args: argparse.Namespace) -> str:
    """The command that continues this run: the same options and ``--resume``."""
    return shell_command(
        "calibrate",
        [
            ("--robot-url", args.robot_url),
            ("--imu", args.imu),
            ("--robot", args.robot),
            ("--trials", args.trials),
            ("--seed", args.seed),
            ("--plan", args.plan),
            ("--adaptive", args.adaptive),
            ("--budget-min", args.budget_min if args.adaptive else None),
            ("--batch-min", args.batch_min if args.adaptive else None),
            ("--stop-fraction", args.stop_fraction if args.adaptive else None),
            ("--workspace", args.workspace),
            ("--sensor-profile", args.sensor_profile),
            ("--gyro-group-delay", args.gyro_group_delay),
            ("--gyro-transport-latency", args.gyro_transport_latency),
            ("--max-correction-deg", args.max_correction_deg),
            ("--out", args.out),
            ("--json", args.json),
            ("--quiet", args.quiet),
            ("--no-tracking-phases", not args.tracking_phases),
            ("--resume", True),
        ],
    )


def _robot(args: argparse.Namespace, url: RobotURL) -> str | None:
    """The robot model the sweep is for: ``--robot``, the simulator's name, ``kr5`` for
    RSI, or None for ``ur://`` (ask the controller).

    Raises
    ------
    ConfigError
        ``--robot`` contradicts the ``sim://`` URL's robot.
    """
    from timedexec.drivers import DEFAULT_SIM_ROBOT

    if url.scheme == "sim":
        named = url.robot or DEFAULT_SIM_ROBOT
        if args.robot is not None and args.robot != named:
            raise ConfigError(
                f"--robot {args.robot} contradicts --robot-url {args.robot_url} (a simulated "
                f"{named}); drop --robot or use sim://{args.robot}"
            )
        return str(named)
    if url.scheme == "rsi":
        return str(args.robot or "kr5")
    return None if args.robot is None else str(args.robot)


def _max_correction(args: argparse.Namespace, url: RobotURL) -> float:
    """``--max-correction-deg`` for an ``rsi://`` URL that does not set it otherwise."""
    if url.scheme != "rsi":
        raise ConfigError(
            f"--max-correction-deg is for KUKA RSI (rsi://PORT) only; {url.text} has no "
            "correction limit: drop the option"
        )
    given = url.options.get("max_correction_deg")
    if given is not None and given != args.max_correction_deg:
        raise ConfigError(
            f"--max-correction-deg {args.max_correction_deg:g} contradicts the URL's "
            f"max_correction_deg={given}; give it once"
        )
    return float(args.max_correction_deg)


def _recorded_plan(path: str, robot: str, seed: int) -> Any:
    """The plan a recording holds (what ``--resume`` continues)."""
    from timedexec.recording import RecordingReader, SweepPlan

    names = ("plan_q_start_rad", "plan_joint", "plan_direction", "plan_config_index",
             "plan_repeat")  # SweepPlan.to_arrays  # fmt: skip
    with RecordingReader(path) as rec:
        arrays = {k: rec.static(k) for k in names}
    return SweepPlan.from_arrays(robot, arrays, seed=seed)


def _trial_excursion_rad(protocol: Any) -> float:
    """How far one trial moves its joint from the start configuration, rad (ramp, hold
    and ramp at the profile's speed), plus 0.5° for the ramps' rounding."""
    prof = protocol.profile
    ramp = prof.speed_rad_s / prof.acceleration_rad_s2
    return float(prof.speed_rad_s * (ramp + prof.hold_s)) + math.radians(0.5)


def _say_rsi_plan(driver: Any, plan: Any) -> None:
    """On stderr: where RSI started, how many configurations the sweep has and where."""
    import numpy as np

    q0 = np.degrees(driver.start_pose_rad)
    q = np.degrees(plan.q_start_rad)
    n_cfg = len(np.unique(plan.config_index))
    span = ", ".join(f"A{j + 1} {q[:, j].min():.1f}..{q[:, j].max():.1f}°" for j in range(6))
    limit = np.degrees(driver.max_correction_rad)
    lim = f"{limit[0]:g}°" if np.all(limit == limit[0]) else "/".join(f"{v:g}" for v in limit) + "°"
    print(
        f"RSI started at ({', '.join(f'{v:.1f}' for v in q0)})°; the sweep's {n_cfg} "
        f"configurations ({len(plan)} trials) lie within {span} (max correction {lim})",
        file=sys.stderr,
    )


def _check_gyro_constants(args: argparse.Namespace, *, real: bool) -> None:
    """A real robot's sweep needs the gyro's group delay and transport latency (a missing
    one would shift every delay by its error, silently); checked before connecting."""
    given = args.sensor_profile is not None
    both = args.gyro_group_delay is not None and args.gyro_transport_latency is not None
    if real and not (given or both):
        raise ConfigError(
            "give the gyro's group delay and transport latency (--sensor-profile FILE.json, "
            "or --gyro-group-delay MS and --gyro-transport-latency MS); an error in them "
            "shifts every measured delay by the same amount (docs/sensor-constants.md)"
        )


def _gyro_constants(args: argparse.Namespace) -> Any:
    """The gyro's constants as the user gave them (``--sensor-profile``, then the options
    on top of it, or of the default sensor's), or None when none were given (the robot's
    default protocol then keeps its sensor's: a simulated robot's simulated gyro).

    Raises
    ------
    ConfigError
        An unreadable or invalid profile, or implausible values (e.g. milliseconds where
        seconds belong), before anything connects.
    """
    from timedexec.recording import GyroHeader

    if args.sensor_profile is None and (
        args.gyro_group_delay is None and args.gyro_transport_latency is None
    ):
        return None
    gyro = GyroHeader.from_json(args.sensor_profile) if args.sensor_profile else GyroHeader()
    changes: dict[str, float] = {}
    if args.gyro_group_delay is not None:
        changes["group_delay_s"] = args.gyro_group_delay * 1e-3
    if args.gyro_transport_latency is not None:
        changes["transport_latency_s"] = args.gyro_transport_latency * 1e-3
    return dataclasses.replace(gyro, **changes)


#: How far a constant given for a simulated gyro may be from the simulated sensor's, s.
_SIM_GYRO_TOLERANCE_S = 1e-6


def _check_simulated_gyro(given: Any, simulated: Any, url: str) -> None:
    """Refuse constants for the simulated gyro of a ``sim://`` robot that are not its own:
    every gyro sample would be dated by their difference, and every delay with it.

    Raises
    ------
    ConfigError
        Naming each contradicting constant, the simulated sensor's value and the fix.
    """
    wrong = [
        f"{key} {getattr(given, key) * 1e3:g} ms (the simulated gyro's: "
        f"{getattr(simulated, key) * 1e3:g} ms)"
        for key in ("group_delay_s", "transport_latency_s")
        if abs(getattr(given, key) - getattr(simulated, key)) > _SIM_GYRO_TOLERANCE_S
    ]
    if given.full_scale_dps != simulated.full_scale_dps:
        wrong.append(
            f"full_scale_dps {given.full_scale_dps} (the simulated gyro's: "
            f"{simulated.full_scale_dps})"
        )
    if wrong:
        raise ConfigError(
            f"{url} records its own simulated gyro, whose constants are known; the given "
            f"{'; '.join(wrong)} would shift every extracted delay by the difference: drop "
            "--sensor-profile / --gyro-group-delay / --gyro-transport-latency, or give --imu "
            "with a real gyro"
        )


def _read_plan(path: str, robot: Any) -> Any:
    """The sweep plan in the .npz file ``path`` (the arrays of ``SweepPlan.to_arrays``).

    Raises
    ------
    ConfigError
        An unreadable file, a missing array or arrays that do not form a plan, naming
        the file, what is wrong and the fix.
    """
    import zipfile

    import numpy as np

    from timedexec.errors import TimedExecError
    from timedexec.recording import SweepPlan

    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ConfigError(
            f"--plan {path}: cannot read it as a .npz plan ({exc}); save one with "
            "numpy.savez(PATH, **SweepPlan.to_arrays())"
        ) from exc
    except AttributeError:  # a plain .npy array, not an archive of named arrays
        arrays = {}
    try:
        return SweepPlan.from_arrays(robot, arrays)
    except KeyError as exc:
        raise ConfigError(
            f"--plan {path}: the array {exc.args[0]!r} is missing (it holds "
            f"{', '.join(sorted(arrays)) or 'no named arrays'}); a plan file holds the arrays "
            "of SweepPlan.to_arrays(): plan_q_start_rad, plan_joint, plan_direction, "
            "plan_config_index, plan_repeat"
        ) from None
    except TimedExecError:
        raise
    except (TypeError, ValueError, IndexError) as exc:
        raise ConfigError(
            f"--plan {path}: its arrays do not form a sweep plan ({exc}); save one with "
            "numpy.savez(PATH, **SweepPlan.to_arrays())"
        ) from exc
