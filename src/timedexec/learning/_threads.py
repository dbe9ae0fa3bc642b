"""BLAS threading for model fits.

Fits here are many small dense problems (a few hundred to a few thousand rows). Run with
a multithreaded BLAS on a shared two-core machine, one likelihood evaluation of a 150-
condition GP took 400 ms instead of 3.8 ms single-threaded (threads spin waiting for a
core another process holds). So fits run BLAS single-threaded and parallelism comes from
joblib across folds and models (which also scales out through Dask).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["BLAS_PIN", "BlasPin", "single_threaded_blas"]


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Limit BLAS to one thread inside the block (restored afterwards): :data:`BLAS_PIN`.

    It was threadpoolctl's ``threadpool_limits``, which looks up the loaded libraries on
    every call (2.3 ms here): 716 fits of a two-robot fleet spent 1.65 of their 5.6 s in it.
    """
    with BLAS_PIN:
        yield


class BlasPin:
    """Pin BLAS to one thread around short calls: ``enter()`` ... ``exit()`` (~3 µs).

    A multithreaded OpenBLAS splits even a 200 × 200 matrix-vector product across threads;
    on a loaded machine the 99th percentile of such a product rose from 34 µs to 817 µs
    (``benchmarks/bench_learning_predict.py``). The fast predictor therefore runs its
    products on one thread. Setting the thread count is process-wide, so nested and
    concurrent callers share a counter: the first entrant saves and lowers the count, the
    last one restores it. threadpoolctl's context manager does the same at ~500 µs a call;
    this keeps its library handles and costs a few µs.
    """

    def __init__(self) -> None:
        import threading

        self._lock = threading.Lock()
        self._depth = 0
        self._libs: list[Any] | None = None
        self._saved: list[int] = []

    def _controllers(self) -> list[Any]:
        if self._libs is None:
            try:
                import scipy.linalg  # noqa: F401  (loads SciPy's own BLAS: pin it too)
                from threadpoolctl import ThreadpoolController

                self._libs = list(ThreadpoolController().select(user_api="blas").lib_controllers)
            except Exception:  # pragma: no cover - no threadpoolctl or no known BLAS
                self._libs = []
        return self._libs

    def enter(self) -> None:
        """Lower BLAS to one thread (first entrant saves the previous counts)."""
        with self._lock:
            if self._depth == 0:
                libs = self._controllers()
                self._saved = [lib.get_num_threads() for lib in libs]
                for lib, n in zip(libs, self._saved, strict=True):
                    if n != 1:
                        lib.set_num_threads(1)
            self._depth += 1

    def exit(self) -> None:
        """Restore the saved thread counts when the last caller leaves."""
        with self._lock:
            self._depth -= 1
            if self._depth == 0:
                for lib, n in zip(self._controllers(), self._saved, strict=True):
                    if n != 1:
                        lib.set_num_threads(n)

    def __enter__(self) -> BlasPin:
        """Hold the pin for a block (a control loop): per-call pins inside then only count."""
        self.enter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.exit()


#: The process-wide pin used by :meth:`DelayModel.predict <timedexec.learning.DelayModel.predict>`.
BLAS_PIN = BlasPin()
