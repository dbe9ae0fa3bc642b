"""Prediction latency of every registered delay-model method, against the GP in the same run.

How: train one bundle with every registered method (``train_delay_models(methods=METHODS,
folds=0)``) on a simulated sweep's delay table (default: UR10, 8,000 trials, the bundled
models' size; or ``--bundle DIR`` for an existing bundle holding the methods), load it
back from disk, and time ``DelayModel.predict(joint=J, direction=D, q=Q, method=M)`` (one
command, both delays, mean and std) for each method on the same random start
configurations. The methods take turns in rounds of ``--round`` calls, so a burst of load
on the shared machine hits them alike; wall clock and thread CPU time, p50 and p99, and
the ratio of each method's p50 to the GP's. ``predict_many`` on 1,000 queries likewise.

Usage: python benchmarks/bench_learning_methods.py [--trials 8000] [--bundle DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from timedexec.learning import METHODS, DelayModel, train_delay_models
from timedexec.recording import SweepPlan, calibration_ranges
from timedexec.robots import get_robot
from timedexec.sim import simulate_delays


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robot", default="ur10")
    ap.add_argument("--trials", type=int, default=8000)
    ap.add_argument("--joint", type=int, default=2)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=20_000, help="calls per method")
    ap.add_argument("--round", type=int, default=500, help="calls per method per turn")
    ap.add_argument("--bundle", type=Path, help="time this bundle instead of training one")
    args = ap.parse_args()

    spec = get_robot(args.robot)
    if args.bundle is not None:
        model = DelayModel.load(args.bundle)
        spec = get_robot(model.robot)
    else:
        plan = SweepPlan.generate(spec, args.trials, seed=args.seed)
        table = simulate_delays(spec, plan.q_start_rad, plan.joint, plan.direction,
                                np.arange(len(plan)) * 1.05, seed=args.seed, jobs=2)  # fmt: skip
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            trained = train_delay_models(table, methods=METHODS, folds=0, jobs=2, random_state=0)
            print(f"trained {', '.join(METHODS)} on {len(table):,} trials in "
                  f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
            model = DelayModel.load(trained.model.save(Path(tmp) / "b"), robot=spec)
    methods = model.methods
    print(f"{model.robot} bundle, methods {', '.join(methods)}; joint {args.joint}")

    lo, hi = calibration_ranges(spec)
    rng = np.random.default_rng(0)
    qs = lo + rng.random((1000, 6)) * (hi - lo)
    qs[:, 5] = 0.0
    ds = rng.choice([-1, 1], 1000)
    for m in methods:  # build each method's predictors before timing
        model.predict(joint=args.joint, direction=1, q=qs[0], method=m)

    wall = {m: [] for m in methods}
    cpu = {m: [] for m in methods}
    done = 0
    while done < args.repeat:
        for m in methods:
            for i in range(done, min(done + args.round, args.repeat)):
                q, d = qs[i % 1000], int(ds[i % 1000])
                c0 = time.thread_time_ns()
                t0 = time.perf_counter_ns()
                model.predict(joint=args.joint, direction=d, q=q, method=m)
                wall[m].append((time.perf_counter_ns() - t0) * 1e-3)
                cpu[m].append((time.thread_time_ns() - c0) * 1e-3)
        done += args.round
    print(f"load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"predict (one command, both delays), {args.repeat:,} calls each, µs:")
    ref_wall = float(np.median(wall["gpr"])) if "gpr" in wall else float("nan")
    ref_cpu = float(np.median(cpu["gpr"])) if "gpr" in cpu else float("nan")
    for m in methods:
        w, c = np.asarray(wall[m]), np.asarray(cpu[m])
        print(f"  {m:7} wall p50 {np.median(w):7.1f} p99 {np.percentile(w, 99):7.1f} | "
              f"CPU p50 {np.median(c):7.1f} p99 {np.percentile(c, 99):7.1f} | "
              f"p50 / GP's: wall {np.median(w) / ref_wall:5.2f}, CPU {np.median(c) / ref_cpu:5.2f}")  # fmt: skip

    joints = np.full(1000, args.joint)
    print("predict_many (1,000 commands, both delays), ms:")
    for m in methods:
        best = min(
            _timed(lambda m=m: model.predict_many(joints, ds, qs, method=m)) for _ in range(5)
        )
        print(f"  {m:7} {best * 1e3:7.2f}")


def _timed(fn: object) -> float:
    t0 = time.perf_counter()
    fn()  # type: ignore[operator]
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
