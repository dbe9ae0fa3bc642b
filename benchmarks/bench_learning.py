"""Full-size training time and memory; the GP and the LM net against their obvious alternatives.

1. **Full-size training** (issue 5: <= 10 min, <= 6 GB on 2 cores): 33,500 trials, all four
   methods, per joint and combined, both delays, 10-fold CV plus the final fits
   (``train_delay_models``). Peak memory is the largest sampled total RSS of this process
   and its joblib workers (``/proc``, every 0.2 s); the sum of each process's own peak
   (VmHWM) is printed as an upper bound. The CV table is printed beside the paper's.
2. **GP vs scikit-learn** on ~3,000 trials of one joint (the size scikit-learn's exact
   ``GaussianProcessRegressor`` can handle): fit time and held-out RMSE, split by start
   configuration, in the same run. Same kernel family (constant x ARD RBF + white noise,
   normalised targets, one optimiser start each).
3. **LM net: BLAS Levenberg-Marquardt vs MINPACK** (``scipy.optimize.least_squares
   (method="lm")``) on one per-joint fit: time and final objective.

The table is a simulated sweep's ground truth (``simulate_delays``; same size and structure
as a measured one), or ``--table`` (a delay table CSV, e.g. from ``timedexec extract``).

Usage: python benchmarks/bench_learning.py [--trials 33500] [--jobs 2] [--table T.csv]
       [--skip-full] [--skip-sklearn]
"""

from __future__ import annotations

import argparse
import os
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from timedexec.delays import DelayTable
from timedexec.learning import DelayGP, LMNeuralNet, encode_inputs, train_delay_models
from timedexec.recording import SweepPlan
from timedexec.sim import simulate_delays


def simulated_table(robot: str, trials: int, seed: int, jobs: int) -> DelayTable:
    """Ground-truth delay table of a simulated sweep (about 1 s per 1,000 trials)."""
    plan = SweepPlan.generate(robot, trials, seed=seed)
    t_start = np.arange(len(plan)) * 1.05  # about one trial per second, as recorded sweeps
    return simulate_delays(
        robot, plan.q_start_rad, plan.joint, plan.direction, t_start, seed=seed, jobs=jobs
    )


class TreeMemory:
    """Samples the total RSS of this process and its descendants from /proc."""

    def __init__(self, interval_s: float = 0.2) -> None:
        self.interval_s = interval_s
        self.peak_bytes = 0
        self.hwm: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _status(pid: int) -> dict[str, int]:
        out: dict[str, int] = {}
        try:
            with open(f"/proc/{pid}/status") as fh:
                for line in fh:
                    key, _, value = line.partition(":")
                    if key in ("PPid", "VmRSS", "VmHWM"):
                        parts = value.split()
                        out[key] = int(parts[0]) * (1024 if key != "PPid" else 1)
        except (OSError, ValueError, IndexError):
            pass
        return out

    def _tree(self) -> dict[int, dict[str, int]]:
        stats = {}
        for name in os.listdir("/proc"):
            if name.isdigit():
                st = self._status(int(name))
                if st:
                    stats[int(name)] = st
        root = os.getpid()
        mine = {root}
        changed = True
        while changed:
            changed = False
            for pid, st in stats.items():
                if pid not in mine and st.get("PPid") in mine:
                    mine.add(pid)
                    changed = True
        return {pid: stats[pid] for pid in mine if pid in stats}

    def _run(self) -> None:
        while not self._stop.is_set():
            tree = self._tree()
            total = sum(st.get("VmRSS", 0) for st in tree.values())
            self.peak_bytes = max(self.peak_bytes, total)
            for pid, st in tree.items():
                self.hwm[pid] = max(self.hwm.get(pid, 0), st.get("VmHWM", 0))
            self._stop.wait(self.interval_s)

    def __enter__(self) -> TreeMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def full_size(table: DelayTable, jobs: int) -> None:
    print(f"\n== full-size training: {len(table):,} trials, 4 methods, per joint + combined, "
          f"both delays, 10-fold CV + final fits, {jobs} jobs ==")  # fmt: skip
    print(f"load average before: {os.getloadavg()[0]:.1f} (2 cores shared with other work)")
    with TreeMemory() as mem:
        start = time.perf_counter()
        result = train_delay_models(table, folds=10, jobs=jobs, random_state=0, progress=True)
        wall = time.perf_counter() - start
    assert result.cv is not None
    print(result.cv.table_text())
    fit_s = ", ".join(f"{m} {s:.0f} s" for m, s in result.cv.fit_seconds.items())
    print(f"\nwall time {wall:.0f} s (target <= 600 s: {'PASS' if wall <= 600 else 'FAIL'}); "
          f"CPU seconds in fits: {fit_s}")  # fmt: skip
    peak_gb = mem.peak_bytes / 1e9
    print(f"peak memory (sampled total RSS of the process tree) {peak_gb:.2f} GB; sum of "
          f"per-process peaks {sum(mem.hwm.values()) / 1e9:.2f} GB "
          f"(target <= 6 GB: {'PASS' if peak_gb <= 6 else 'FAIL'})")  # fmt: skip
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    cv = result.cv.to_dict()["actuation_delay"]
    floor = result.cv.noise_floor_ms["actuation_delay"]
    keys = [k for k in cv["median"] if k != "average"]
    beats = all(cv[m][k] < cv["median"][k] for m in ("nn", "rt", "gpr") for k in keys)
    gp_ratio = max(cv["gpr"][k] / floor[k] for k in keys)
    print(
        f"actuation: every learned model beats the median on every column: {beats}; "
        f"GP error / noise floor <= {gp_ratio:.3f} (target <= 1.10)"
    )


def versus_sklearn(table: DelayTable, rows: int) -> None:
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, WhiteKernel
    from sklearn.gaussian_process.kernels import ConstantKernel as C

    joint = 2
    m = np.flatnonzero(table["joint"] == joint)[:rows]
    X = encode_inputs(table.q[m], table["direction"][m])
    config = np.unique(table.q[m], axis=0, return_inverse=True)[1].reshape(-1)
    test = config % 5 == 0
    print(f"\n== GP vs scikit-learn: joint {joint}, {len(m):,} trials "
          f"({(~test).sum():,} train / {test.sum():,} test, split by configuration) ==")  # fmt: skip
    for delay in ("actuation_delay", "response_delay"):
        y = table[delay][m]
        t0 = time.perf_counter()
        ours = DelayGP(random_state=0).fit(X[~test], y[~test])
        t_ours = time.perf_counter() - t0
        mu, sd = ours.predict(X[test], return_std=True)
        d = X.shape[1]
        kernel = C(1.0) * RBF(np.full(d, np.sqrt(d)), (1e-2, 1e3)) + WhiteKernel(0.5, (1e-6, 1e1))
        sk = GaussianProcessRegressor(kernel, normalize_y=True, random_state=0)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # bound warnings for irrelevant inputs
            sk.fit(X[~test], y[~test])
        t_sk = time.perf_counter() - t0
        mu2, sd2 = sk.predict(X[test], return_std=True)
        rmse = 1e3 * np.sqrt(np.mean((mu - y[test]) ** 2))
        rmse2 = 1e3 * np.sqrt(np.mean((mu2 - y[test]) ** 2))
        # calibration: share of test trials inside mean ± 2 std (0.954 if Gaussian)
        cov = np.mean(np.abs(y[test] - mu) <= 2 * sd)
        cov2 = np.mean(np.abs(y[test] - mu2) <= 2 * sd2)
        print(f"{delay:16} DelayGP: fit {t_ours:6.2f} s, RMSE {rmse:.3f} ms, 2-sigma cover "
              f"{cov:.3f} | sklearn: fit {t_sk:6.2f} s, RMSE {rmse2:.3f} ms, cover {cov2:.3f} | "
              f"fit speed-up x{t_sk / t_ours:.0f}")  # fmt: skip


def versus_minpack(table: DelayTable) -> None:
    m = np.flatnonzero(table["joint"] == 2)
    X = encode_inputs(table.q[m], table["direction"][m])
    y = table["actuation_delay"][m]
    print(f"\n== LM net: BLAS Marquardt vs MINPACK, joint 2 actuation, {len(m):,} trials "
          f"({len(np.unique(X, axis=0))} conditions), 30 units, one start, no early stopping ==")  # fmt: skip
    res = {}
    for solver in ("marquardt", "scipy-lm"):
        net = LMNeuralNet(solver=solver, n_restarts=1, validation_fraction=0.0, max_iter=60,
                          random_state=0)  # fmt: skip
        t0 = time.perf_counter()
        net.fit(X, y)
        res[solver] = (time.perf_counter() - t0, net.objective_)
        print(f"{solver:10} {res[solver][0]:7.2f} s  objective {res[solver][1]:.4f}")
    ratio = res["scipy-lm"][0] / res["marquardt"][0]
    print(f"MINPACK / Marquardt time: x{ratio:.1f} (60 iterations / function evaluations each)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robot", default="ur10")
    ap.add_argument("--trials", type=int, default=33_500)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--table", type=Path, help="delay table CSV instead of a simulated one")
    ap.add_argument("--sklearn-rows", type=int, default=3000)
    ap.add_argument("--skip-full", action="store_true")
    ap.add_argument("--skip-sklearn", action="store_true")
    args = ap.parse_args()
    if args.table:
        table = DelayTable.read_csv(args.table).validated_for_training()
    else:
        t0 = time.perf_counter()
        table = simulated_table(args.robot, args.trials, args.seed, args.jobs)
        print(
            f"simulated {len(table):,} trials of {args.robot} in {time.perf_counter() - t0:.0f} s"
        )
    if not args.skip_full:
        full_size(table, args.jobs)
    if not args.skip_sklearn:
        versus_sklearn(table, args.sklearn_rows)
        versus_minpack(table)


if __name__ == "__main__":
    main()
