"""The fits' single-thread BLAS pin: kept library handles vs threadpoolctl's per-call lookup.

Every model fit runs BLAS on one thread (``timedexec.learning.single_threaded_blas``). It was
``threadpoolctl.threadpool_limits(limits=1, user_api="blas")``, which finds the loaded
libraries anew on every call; it is now the process-wide pin that keeps their handles
(``BLAS_PIN``). Same run, interleaved: the cost of one enter/exit each way, and the training
of one simulated sweep's delay models (``train_delay_models``, median and GP, 5 folds) with
either pin, wall time best of ``--repeat``.

    python benchmarks/bench_blas_pin.py [--trials 160] [--repeat 3]
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from threadpoolctl import threadpool_limits

import timedexec.learning._threads as threads
from timedexec.learning import single_threaded_blas


@contextlib.contextmanager
def lookup_each_call() -> Iterator[None]:
    """The previous pin: threadpoolctl's context manager (library lookup per call)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


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
    from timedexec.extraction import extract_recording
    from timedexec.learning import train_delay_models
    from timedexec.sim import simulate_sweep

    kept = single_threaded_blas
    print(f"one enter/exit: kept handles {per_call_us(kept):.1f} µs, "
          f"lookup each call {per_call_us(lookup_each_call):.1f} µs")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "sweep.h5"
        simulate_sweep("ur10", args.trials, rec, seed=1, repeats=3, progress=False)
        table = extract_recording(rec, progress=False).table
        best: dict[str, float] = {}
        pins = (("kept", kept), ("lookup", lookup_each_call))
        for rep in range(args.repeat):
            for name, pin in pins if rep % 2 == 0 else pins[::-1]:  # interleaved
                _patch_users(pin)
                t = time.perf_counter()
                train_delay_models(table, methods=("median", "gpr"), folds=5, progress=False)
                best[name] = min(best.get(name, float("inf")), time.perf_counter() - t)
        _patch_users(kept)
    print(f"training ({args.trials} trials, median + GP, 5 folds), best of {args.repeat}: "
          f"kept {best['kept']:.2f} s, lookup {best['lookup']:.2f} s, "
          f"ratio lookup/kept {best['lookup'] / best['kept']:.2f}")  # fmt: skip


def _patch_users(pin: object) -> None:
    """Point the modules that imported the pin at ``pin``."""
    import timedexec.learning._gp as gp
    import timedexec.learning._nn as nn
    import timedexec.learning._tree as tree

    for mod in (gp, nn, tree):
        mod.single_threaded_blas = pin  # type: ignore[attr-defined]
    threads.single_threaded_blas = pin  # type: ignore[assignment]


if __name__ == "__main__":
    main()
