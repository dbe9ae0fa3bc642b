"""One prediction from a model bundle against scikit-learn's predict on the same fitted GP.

Issue 5 targets: one prediction (one joint, both delays, mean and std) <= 100 µs at the
99th percentile, >= 10x faster than scikit-learn's ``GaussianProcessRegressor.predict`` on
the same fitted GP, the same numbers to 1e-9 s.

How: train the GP bundle (``train_delay_models(methods="gpr", folds=0)``, as
``timedexec train`` does) on a simulated sweep's delay table (default 8,000 trials, the
bundled models' size), load it back from disk, and rebuild, from the bundle's own arrays,
the scikit-learn twin of each per-joint GP (``ConstantKernel(σ_f²) * RBF(ℓ · x_scale) +
WhiteKernel(σ_n²)``, ``normalize_y=True``, no optimiser), fitted on the same trials. Then

* agreement: max |difference| of means and trial standard deviations on 1,000 random
  start configurations, both delays;
* latency: ``DelayModel.predict(joint=J, direction=D, q=Q)`` (both delays, mean and std)
  against two ``predict(x, return_std=True)`` calls of the twins, same queries, wall clock
  and thread CPU time (CPU time excludes the time the scheduler gives other processes on a
  shared machine; the load average is printed).

``--bundle DIR`` times an existing bundle too (e.g. models/ur10-sim, or a full-size one).

Usage: python benchmarks/bench_learning_predict.py [--trials 8000] [--bundle DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from timedexec.learning import DelayModel, encode_inputs, train_delay_models
from timedexec.recording import SweepPlan, calibration_ranges
from timedexec.robots import get_robot
from timedexec.sim import simulate_delays


def percentiles(samples_s: np.ndarray) -> str:
    us = samples_s * 1e6
    return f"p50 {np.median(us):7.1f} µs  p99 {np.percentile(us, 99):7.1f} µs"


def time_calls(fn: Any, queries: list[Any], repeat: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and thread-CPU seconds per call."""
    wall = np.empty(repeat)
    cpu = np.empty(repeat)
    n = len(queries)
    for i in range(repeat):
        q = queries[i % n]
        c0 = time.thread_time_ns()
        t0 = time.perf_counter_ns()
        fn(q)
        wall[i] = (time.perf_counter_ns() - t0) * 1e-9
        cpu[i] = (time.thread_time_ns() - c0) * 1e-9
    return wall, cpu


def sklearn_twin(model: DelayModel, delay: str, joint: int, X: np.ndarray, y: np.ndarray) -> Any:
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, WhiteKernel
    from sklearn.gaussian_process.kernels import ConstantKernel as C

    a = model._group("gpr", delay, str(joint))
    sf2, sn2, _, _ = (float(v) for v in a["scalars"])
    kernel = C(sf2, "fixed") * RBF(a["length_scale"] * a["x_scale"], "fixed") + WhiteKernel(
        sn2, "fixed"
    )
    return GaussianProcessRegressor(kernel, alpha=0.0, normalize_y=True, optimizer=None).fit(X, y)


def time_bundle(model: DelayModel, joint: int, queries: list[Any], repeat: int) -> str:
    def call(qd: Any) -> None:
        model.predict(joint=joint, direction=qd[1], q=qd[0])

    call(queries[0])  # builds the joint's predictors
    wall, cpu = time_calls(call, queries, repeat)
    return f"wall {percentiles(wall)} | CPU {percentiles(cpu)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robot", default="ur10")
    ap.add_argument("--trials", type=int, default=8000)
    ap.add_argument("--joint", type=int, default=2)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=20_000)
    ap.add_argument("--bundle", type=Path, action="append", default=[])
    args = ap.parse_args()

    spec = get_robot(args.robot)
    plan = SweepPlan.generate(spec, args.trials, seed=args.seed)
    table = simulate_delays(spec, plan.q_start_rad, plan.joint, plan.direction,
                            np.arange(len(plan)) * 1.05, seed=args.seed, jobs=2)  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        trained = train_delay_models(table, methods="gpr", folds=0, jobs=2, random_state=0)
        model = DelayModel.load(trained.model.save(Path(tmp) / "b"), robot=spec)
    rows = np.flatnonzero(table["joint"] == args.joint)
    X = encode_inputs(table.q[rows], table["direction"][rows])
    n_cond = len(np.unique(X, axis=0))
    print(f"{spec.name}: GP bundle from {len(table):,} trials; joint {args.joint}: "
          f"{len(rows):,} trials, {n_cond} conditions")  # fmt: skip
    t0 = time.perf_counter()
    twins = {d: sklearn_twin(model, d, args.joint, X, table[d][rows]) for d in
             ("actuation_delay", "response_delay")}  # fmt: skip
    print(f"scikit-learn twins fitted on the same {len(rows):,} trials in "
          f"{time.perf_counter() - t0:.1f} s")  # fmt: skip

    lo, hi = calibration_ranges(spec)
    rng = np.random.default_rng(0)
    qs = lo + rng.random((1000, 6)) * (hi - lo)
    qs[:, 5] = 0.0
    ds = rng.choice([-1, 1], 1000)
    queries = list(zip(qs, ds, strict=True))

    # agreement
    worst = 0.0
    for q, d in queries:
        p = model.predict(joint=args.joint, direction=int(d), q=q)
        x = encode_inputs(q[None, :], [d])
        for delay, mean, std in (
            ("actuation_delay", p.actuation_mean, p.actuation_std),
            ("response_delay", p.response_mean, p.response_std),
        ):
            m2, s2 = twins[delay].predict(x, return_std=True)
            worst = max(worst, abs(mean - m2[0]), abs(std - s2[0]))
    print(f"agreement with scikit-learn over {len(queries)} queries, both delays, mean and std: "
          f"max |diff| {worst:.2e} s (target <= 1e-9: {'PASS' if worst <= 1e-9 else 'FAIL'})")  # fmt: skip

    print(f"load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    wall, cpu = time_calls(
        lambda qd: model.predict(joint=args.joint, direction=int(qd[1]), q=qd[0]),
        queries,
        args.repeat,
    )
    ours_p99 = np.percentile(wall, 99)
    with model.pinned():  # how a control loop holds it (TimedExecutor does)
        wall_held, cpu_held = time_calls(
            lambda qd: model.predict(joint=args.joint, direction=int(qd[1]), q=qd[0]),
            queries,
            args.repeat,
        )
    held_p99 = np.percentile(wall_held, 99)

    def sk_call(qd: Any) -> None:
        x = encode_inputs(qd[0][None, :], [qd[1]])
        twins["actuation_delay"].predict(x, return_std=True)
        twins["response_delay"].predict(x, return_std=True)

    wall_sk, cpu_sk = time_calls(sk_call, queries, max(args.repeat // 20, 500))
    print(f"DelayModel.predict  wall {percentiles(wall)} | CPU {percentiles(cpu)}")
    print(f"  inside pinned()   wall {percentiles(wall_held)} | CPU {percentiles(cpu_held)}")
    print(f"scikit-learn x2     wall {percentiles(wall_sk)} | CPU {percentiles(cpu_sk)}")
    speed = np.median(wall_sk) / np.median(wall)
    print(f"p99 <= 100 µs: per call {'PASS' if ours_p99 <= 100e-6 else 'FAIL'} "
          f"({ours_p99 * 1e6:.1f} µs), inside pinned() {'PASS' if held_p99 <= 100e-6 else 'FAIL'} "
          f"({held_p99 * 1e6:.1f} µs); "
          f"speed-up over scikit-learn (median): x{speed:.0f} "
          f"({'PASS' if speed >= 10 else 'FAIL'} >= 10x)")  # fmt: skip

    for path in args.bundle:
        m = DelayModel.load(path)
        j = m.joints[1] if len(m.joints) > 1 else m.joints[0]
        ncond = len(m._group("gpr", "actuation_delay", str(j))["y_train"])
        print(f"bundle {path} ({m.robot}, joint {j}, {ncond} conditions): "
              f"{time_bundle(m, j, queries, args.repeat)}")  # fmt: skip


if __name__ == "__main__":
    main()
