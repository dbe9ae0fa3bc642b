"""The fits' single-thread BLAS pin: kept library handles vs threadpoolctl's per-call lookup.

Every model fit runs BLAS on one thread (``timedexec.learning.single_threaded_blas``). It was
``threadpoolctl.threadpool_limits(limits=1, user_api="blas")``, which finds the loaded
libraries anew on every call; it now keeps their handles. Same run: the cost of one
enter/exit each way (interleaved, best of ``--repeat``), the training of one simulated
sweep's delay models (``train_delay_models``, median and GP, 5 folds) and how many pins it
enters (counted by a profiled run), so the lookup's share of the old training time is
``pins x (lookup - kept)``. (The old pin cannot be swapped into the fits from here without
reaching into the package's private modules.)

    python benchmarks/bench_blas_pin.py [--trials 160] [--repeat 3]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import tempfile
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from timedexec.extraction import extract_recording
from timedexec.learning import single_threaded_blas, train_delay_models
from timedexec.sim import simulate_sweep


def lookup_each_call() -> threadpool_limits:
    """The previous pin: threadpoolctl's context manager (library lookup per call)."""
    return threadpool_limits(limits=1, user_api="blas")


def per_call_us(pin: object, n: int = 300) -> float:
    t = time.perf_counter()
    for _ in range(n):
        with pin():  # type: ignore[operator]
            pass
    return (time.perf_counter() - t) / n * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=160)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    kept = lookup = float("inf")
    for _ in range(args.repeat):
        kept = min(kept, per_call_us(single_threaded_blas))
        lookup = min(lookup, per_call_us(lookup_each_call))
    print(f"one enter/exit: kept handles {kept:.1f} µs, lookup each call {lookup:.1f} µs "
          f"({lookup / kept:.0f}x)")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "sweep.h5"
        simulate_sweep("ur10", args.trials, rec, seed=1, repeats=3, progress=False)
        table = extract_recording(rec, progress=False).table

        def train() -> None:
            train_delay_models(table, methods=("median", "gpr"), folds=5, progress=False)

        best = float("inf")
        for _ in range(args.repeat):
            t = time.perf_counter()
            train()
            best = min(best, time.perf_counter() - t)
        prof = cProfile.Profile()
        prof.runcall(train)
        stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
        pins = sum(v[1] for k, v in stats.items() if k[2] == "single_threaded_blas")
    old = best + pins * (lookup - kept) * 1e-6
    print(f"training ({args.trials} trials, median + GP, 5 folds), best of {args.repeat}: "
          f"{best:.2f} s with the kept pin, {pins} pins entered; with the lookup per call "
          f"~{old:.2f} s ({old / best:.2f}x)")  # fmt: skip


if __name__ == "__main__":
    main()
