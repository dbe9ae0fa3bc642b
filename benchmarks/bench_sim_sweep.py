"""Full-size simulated sweep: wall time, peak memory, recording size; vectorised vs per-trial.

Runs ``timedexec simulate`` as a subprocess (so its peak memory, workers included, is
measured by sampling /proc for the whole process tree) and, in the same run, times the
obvious alternative — simulating trials one at a time with the same physics — on a subset,
reporting the speed-up ratio.

Targets (issue 2): 33,500 trials with 8 kHz gyro traces in < 60 s on 2 cores, peak memory
< 4 GB.

Usage: python benchmarks/bench_sim_sweep.py [--robot ur10] [--trials 33500] [--jobs 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def tree_rss_bytes(root: int) -> int:
    """Resident memory of ``root`` and all its descendants (Linux /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            ppid = int(fields[1])
            rss[int(entry)] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    total, stack = 0, [root]
    while stack:
        pid = stack.pop()
        total += rss.get(pid, 0)
        stack.extend(children.get(pid, []))
    return total


def run_cli(robot: str, trials: int, jobs: int, out: Path) -> tuple[float, int]:
    cmd = [sys.executable, "-m", "timedexec.cli", "simulate", "--robot", robot,
           "--trials", str(trials), "--seed", "1", "--out", str(out), "--jobs", str(jobs),
           "--quiet"]
    peak = 0
    start = time.perf_counter()
    proc = subprocess.Popen(cmd)
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.is_set():
            peak = max(peak, tree_rss_bytes(proc.pid))
            time.sleep(0.1)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    code = proc.wait()
    elapsed = time.perf_counter() - start
    done.set()
    thread.join()
    if code != 0:
        raise SystemExit(f"simulate failed with exit code {code}")
    return elapsed, peak


def per_trial_loop(robot: str, n: int) -> float:
    """Seconds per trial when trials are simulated one at a time (same code, n = 1)."""
    from timedexec.effects import default_effects
    from timedexec.recording import SweepPlan
    from timedexec.robots import get_robot
    from timedexec.sim import default_settings, simulate_block, sweep_clock

    spec = get_robot(robot)
    settings = default_settings(spec)
    plan = SweepPlan.generate(spec, n, seed=1)
    clock = sweep_clock(plan, settings, 1)
    effects = default_effects(robot)
    start = time.perf_counter()
    for i in range(n):
        simulate_block(spec, settings, effects, plan, clock, np.array([i]), 1)
    return (time.perf_counter() - start) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", default="ur10")
    ap.add_argument("--trials", type=int, default=33_500)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--loop-trials", type=int, default=12, help="trials for the per-trial loop")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sweep.h5"
        elapsed, peak = run_cli(args.robot, args.trials, args.jobs, out)
        size = out.stat().st_size
    loop = per_trial_loop(args.robot, args.loop_trials)
    vec = elapsed / args.trials
    print(f"robot {args.robot}, {args.trials:,} trials, {args.jobs} jobs (cores: {os.cpu_count()})")
    print(f"  wall time (CLI, incl. recording): {elapsed:.1f} s  [target < 60 s]")
    print(f"  peak memory (process tree):       {peak / 2**30:.2f} GiB  [target < 4 GB]")
    print(f"  recording size:                   {size / 1e6:.0f} MB ({size / args.trials / 1e3:.1f} kB per trial)")
    print(f"  per-trial loop (same physics, n=1): {loop * 1e3:.1f} ms per trial "
          f"-> {loop * args.trials:.0f} s for the sweep")
    print(f"  ratio per-trial loop / vectorised sweep: {loop / vec:.0f}x")


if __name__ == "__main__":
    main()
