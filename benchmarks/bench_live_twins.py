"""Live calibration against the protocol twins, checked against their ground truth.

Runs ``run_calibration`` through the real clients — ``ur_rtde`` (``ur://``) against the UR10
twin with its gyro twin on a pty, and the RSI driver (``rsi://PORT``) against the KR 5 RSI
twin with a gyro twin fed by its physics (``rsi_gyro_factory``) — extracts the delays and
compares them with the twins' truth (``timedexec.twins._truth``). Prints per
robot: trials, flagged trials, trials whose gyro window the runner lost the start of,
actuation and response error (RMS / max, ms) of the ``fit`` extraction and, as the obvious
alternative on the same recording, of the published ``extrema`` method (and the RMS
ratio), the gyro transport latency measured before the run against the one the recording's
arrivals imply, how late the twin ran at worst, and the run time.

Set-up as in ``tests/test_live_twins.py``: gyro read every 2 ms, client threads at
SCHED_FIFO 5 (twins at 10) where the OS allows it, the pty's transport latency measured
and put into the settings.

    python benchmarks/bench_live_twins.py [--trials 20] [--seed 1] [--robots ur10 kr5]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._realtime import realtime
from timedexec.calibration import run_calibration
from timedexec.drivers import HostTimeTap, open_driver
from timedexec.extraction import extract_recording
from timedexec.recording import GyroHeader, SweepPlan, SweepProtocol
from timedexec.sensors import open_gyro
from timedexec.twins import (
    GyroClockTruth,
    TwinTruth,
    compare_with_truth,
    envelope_transport_latency,
    free_udp_port,
    gyro_window_start_s,
    measure_gyro_transport_latency,
    publish_controller_origin,
    rsi_gyro_factory,
    twin_truth_table,
)

UR_HOST = "127.0.0.62"  # tests use .61; a loopback address of its own (fixed ports)
CLIENT_RT_PRIORITY = 5
GYRO_READ_PERIOD_S = 0.002


def evaluate(
    recording: Path, truth: TwinTruth, clock: GyroClockTruth, pre_s: float
) -> dict[str, Any]:
    """Errors of both extraction methods, window starts, envelope latency."""
    row: dict[str, Any] = {}
    for method in ("fit", "extrema"):
        table = extract_recording(recording, method=method, progress=False).table
        summary = compare_with_truth(table, truth).summary()
        row[method] = summary
    starts = gyro_window_start_s(recording, clock, truth)
    row["slid"] = int(np.sum(np.abs(starts + pre_s) > 2e-3))
    row["envelope_latency_ms"] = 1e3 * envelope_transport_latency(recording, clock, truth)
    return row


def run_ur(trials: int, seed: int, work: Path, rt: int | None) -> dict[str, Any]:
    from timedexec.twins import URTwin

    plan = SweepPlan.generate("ur10", trials, seed=seed, repeats=3)
    link, truth_path, out = str(work / "ur_gyro"), work / "ur_truth.jsonl", work / "ur.h5"
    t_start = time.monotonic()
    twin = URTwin(
        "ur10", UR_HOST, seed=seed, q0_rad=plan.q_start_rad[0], imu_link=link,
        truth_path=truth_path,
    )  # fmt: skip
    with twin, realtime(rt):
        with (
            HostTimeTap(open_driver(f"ur://{UR_HOST}")) as robot,
            open_gyro(link, read_period_s=GYRO_READ_PERIOD_S) as gyro,
        ):
            clock = GyroClockTruth.from_truth(truth_path)
            latency = measure_gyro_transport_latency(gyro, clock)
            protocol = SweepProtocol.for_robot("ur10", gyro=GyroHeader(transport_latency_s=latency))
            t_run = time.monotonic()
            run_calibration(robot, gyro, plan, out, protocol=protocol, progress=False)
            run_s = time.monotonic() - t_run
        stats = twin.stats()
    truth = twin_truth_table(out, truth_path, twin.t0_monotonic_s, host_times=robot)
    row = evaluate(out, truth, clock, protocol.profile.pre_s)
    row.update(
        _truth=truth,
        robot="ur10 (ur_rtde)",
        latency_ms=1e3 * latency,
        twin_late_ms=1e3 * float(stats["max_lateness_s"]),
        run_s=run_s,
        total_s=time.monotonic() - t_start,
    )
    return row


def run_rsi(trials: int, seed: int, work: Path, rt: int | None) -> dict[str, Any]:
    from timedexec.twins import RSITwin

    plan = SweepPlan.generate("kr5", trials, seed=seed, repeats=3)
    link, truth_path, out = str(work / "rsi_gyro"), work / "rsi_truth.jsonl", work / "rsi.h5"
    port = free_udp_port()
    t_start = time.monotonic()
    twin = RSITwin(
        port, seed=seed, q0_rad=plan.q_start_rad[0], truth_path=str(truth_path),
        wait_for_pc=True, controller_factory=rsi_gyro_factory(link),
    )  # fmt: skip
    with twin:
        publish_controller_origin(link, twin.t0_host_s)
        with (
            realtime(rt),
            HostTimeTap(open_driver(f"rsi://{port}")) as robot,
            open_gyro(link, read_period_s=GYRO_READ_PERIOD_S) as gyro,
        ):
            clock = GyroClockTruth.from_truth(link + ".truth.jsonl")
            latency = measure_gyro_transport_latency(gyro, clock)
            protocol = SweepProtocol.for_robot("kr5", gyro=GyroHeader(transport_latency_s=latency))
            t_run = time.monotonic()
            run_calibration(robot, gyro, plan, out, protocol=protocol, progress=False)
            run_s = time.monotonic() - t_run
        status = twin.stop()
    truth = twin_truth_table(out, truth_path, host_times=robot)
    row = evaluate(out, truth, clock, protocol.profile.pre_s)
    row.update(
        _truth=truth,
        robot="kr5 (RSI)",
        latency_ms=1e3 * latency,
        twin_late_ms=1e3 * status.max_send_lateness_s,
        run_s=run_s,
        total_s=time.monotonic() - t_start,
    )
    return row


def _fmt(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.3f}"


def print_table(rows: list[dict[str, Any]], trials: int) -> None:
    head = (
        f"{'robot':<16} {'trials':>6} {'flag':>4} {'slid':>4} {'act rms':>8} {'act max':>8} "
        f"{'resp rms':>8} {'resp max':>8} {'respM max':>9} {'ext act':>8} {'ext resp':>8} "
        f"{'ratio':>6} "
        f"{'lat pre':>7} {'lat env':>7} {'late':>6} {'run s':>6}"
    )
    print(head)
    print("-" * len(head))
    for row in rows:
        if "error" in row:
            print(f"{row['robot']:<16} {trials:>6}  not run: {row['error']}")
            continue
        fit, ext = row["fit"], row["extrema"]
        ratio = ext["actuation_rms_ms"] / fit["actuation_rms_ms"]
        print(
            f"{row['robot']:<16} {fit['trials']:>6} {fit['flagged']:>4} {row['slid']:>4} "
            f"{_fmt(fit['actuation_rms_ms']):>8} {_fmt(fit['actuation_max_ms']):>8} "
            f"{_fmt(fit['response_rms_ms']):>8} {_fmt(fit['response_max_ms']):>8} "
            f"{_fmt(fit['response_motion_max_ms']):>9} {_fmt(ext['actuation_rms_ms']):>8} "
            f"{_fmt(ext['response_rms_ms']):>8} "
            f"{ratio:>6.1f} {row['latency_ms']:>7.3f} {row['envelope_latency_ms']:>7.3f} "
            f"{row['twin_late_ms']:>6.1f} {row['run_s']:>6.1f}"
        )
    notes = (
        "errors: extracted minus the twin's truth over unflagged trials, ms; act = actuation,",
        "  resp = response against the mean package age, respM against the motion-weighted age;",
        "flag: trials extraction flagged; slid: trials whose gyro window the runner recorded",
        "  late (> 2 ms); ext: the published extrema method on the same recording, ratio = its",
        "  actuation RMS / fit's; lat pre / env: gyro transport latency measured before the run",
        "  / implied by the run's arrivals, ms; late: worst lateness of a twin package, ms;",
        "  run s: run_calibration wall time.",
    )
    print("\n" + "\n".join(notes))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--robots", nargs="+", default=["ur10", "kr5"], choices=["ur10", "kr5"])
    parser.add_argument("--no-rt", action="store_true", help="client at normal priority")
    parser.add_argument("--json", action="store_true", help="also print the rows as JSON")
    args = parser.parse_args(argv)
    rt = None if args.no_rt else CLIENT_RT_PRIORITY
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench_live_twins_") as tmp:
        for robot in args.robots:
            runner = run_ur if robot == "ur10" else run_rsi
            print(f"running {robot} ...", file=sys.stderr)
            try:
                rows.append(runner(args.trials, args.seed, Path(tmp), rt))
            except Exception as exc:  # report and go on with the other robot
                name = "ur10 (ur_rtde)" if robot == "ur10" else "kr5 (RSI)"
                rows.append({"robot": name, "error": f"{type(exc).__name__}: {exc}"})
    print_table(rows, args.trials)
    if args.json:
        public = [{k: v for k, v in row.items() if not k.startswith("_")} for row in rows]
        print(json.dumps(public, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
