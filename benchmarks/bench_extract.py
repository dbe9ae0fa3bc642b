"""Extraction throughput on the full-size recording, and its accuracy against ground truth.

Simulates (or reuses, ``--recording``) a sweep, then times ``extract_recording`` with the
given workers and, in the same run, the straightforward alternative — a per-trial loop that
reads one trial, converts its gyro to rad/s, filters it with ``scipy.signal.filtfilt`` and
takes the argmax — on a subset, extrapolated to the sweep. Also prints the accuracy table
(fit and extrema methods against the simulator's ground truth).

Targets (issue 4): 33,500 trials extracted in <= 60 s on 2 cores; actuation RMSE <= 0.2 ms,
response RMSE <= 0.5 ms, < 2 % flagged, over >= 1,000 trials per robot.

Usage: python benchmarks/bench_extract.py [--trials 33500] [--jobs 2] [--recording REC.h5]
       python benchmarks/bench_extract.py --accuracy-only --trials 2000
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import signal

from timedexec.extraction import extract_recording
from timedexec.recording import RecordingReader
from timedexec.sim import simulate_sweep


def naive_loop(path: Path, n: int) -> float:
    """Seconds per trial of a per-trial filtfilt + argmax loop."""
    taps = signal.firwin(161, 60.0, fs=8000.0)
    start = time.perf_counter()
    with RecordingReader(path) as reader:
        lsb = reader.header["gyro"]["lsb_per_dps"]
        for i in range(n):
            raw = reader.read("gyro_raw", rows=np.array([i]))[0]
            rate = np.deg2rad(raw / lsb)
            speed = np.linalg.norm(rate - rate[:200].mean(axis=0), axis=1)
            filt = signal.filtfilt(taps, [1.0], speed)
            _ = int(np.argmax(filt))
            host = reader.read("state_host_time_s", rows=np.array([i]))[0]
            qd = reader.read("state_qd_rad_s", rows=np.array([i]))[0]
            _ = host[int(np.argmax(np.abs(qd).max(axis=1)))]
    return (time.perf_counter() - start) / n


def accuracy(path: Path, jobs: int) -> list[str]:
    lines = []
    for method in ("fit", "extrema"):
        table = extract_recording(path, method=method, jobs=jobs, progress=False).table
        ok = np.array([not f for f in table["flag"]], dtype=bool)
        row = [method]
        for name in ("actuation_delay", "response_delay"):
            err = (table[name] - table[f"true_{name}"])[ok] * 1e3
            row.append(f"{np.sqrt(np.mean(err**2)):.3f} ms (bias {err.mean():+.3f})")
        row.append(f"{100 * (1 - ok.mean()):.2f} %")
        lines.append(" | ".join(row))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", default="ur10")
    ap.add_argument("--trials", type=int, default=33_500)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--recording", type=Path)
    ap.add_argument("--loop-trials", type=int, default=200)
    ap.add_argument("--accuracy-only", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.accuracy_only:
            print("robot | method | actuation RMSE | response RMSE | flagged")
            for robot, seed in (("ur10", 1), ("kr5", 2), ("ur10e", 3)):
                path = Path(tmp) / f"{robot}.h5"
                simulate_sweep(robot, args.trials, path, seed=seed, jobs=args.jobs, progress=False)
                for line in accuracy(path, args.jobs):
                    print(f"{robot} ({args.trials} trials) | {line}")
            return
        path = args.recording
        if path is None:
            path = Path(tmp) / "sweep.h5"
            t = time.perf_counter()
            simulate_sweep(args.robot, args.trials, path, seed=1, jobs=args.jobs, progress=False)
            print(f"simulated {args.trials:,} trials in {time.perf_counter() - t:.1f} s")
        with RecordingReader(path) as reader:
            n = reader.n_trials
        t = time.perf_counter()
        result = extract_recording(path, jobs=args.jobs, progress=False)
        elapsed = time.perf_counter() - t
        loop = naive_loop(path, min(args.loop_trials, n))
        print(f"extract: {n:,} trials, {args.jobs} jobs: {elapsed:.1f} s "
              f"({elapsed / n * 1e3:.2f} ms per trial)  [target <= 60 s for 33,500]")
        print(f"per-trial loop (filtfilt + argmax): {loop * 1e3:.2f} ms per trial -> "
              f"{loop * n:.0f} s for the sweep; ratio loop / extract = {loop * n / elapsed:.1f}x")
        print(f"flagged: {result.n_flagged} ({100 * result.n_flagged / n:.2f} %)")


if __name__ == "__main__":
    main()
