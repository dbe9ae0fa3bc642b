"""Real-time scheduling and a quiet garbage collector for loops that keep a controller's
clock (twins, live runs)."""

from __future__ import annotations

import contextlib
import gc
import os
import time
from collections.abc import Iterator
from typing import Any

__all__ = ["GcPauses", "quiet_gc", "realtime", "try_realtime"]


def try_realtime(priority: int | None) -> bool:
    """Give the calling thread SCHED_FIFO ``priority`` if the OS allows it (Linux, root or
    CAP_SYS_NICE); return whether it worked. Threads it starts afterwards inherit it."""
    if priority is None or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except (OSError, ValueError):
        return False
    return True


@contextlib.contextmanager
def realtime(priority: int | None) -> Iterator[bool]:
    """:func:`try_realtime` for a block, restoring the previous policy afterwards; yields
    whether real-time scheduling was granted."""
    if priority is None or not hasattr(os, "sched_getscheduler"):
        yield False
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    granted = try_realtime(priority)
    try:
        yield granted
    finally:
        if granted:
            os.sched_setscheduler(0, policy, param)


class GcPauses:
    """The garbage collections seen while :func:`quiet_gc` holds: count and longest, s."""

    def __init__(self) -> None:
        self.count = 0
        self.max_s = 0.0
        self._started = 0.0

    def callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._started = time.perf_counter()
            return
        self.count += 1
        self.max_s = max(self.max_s, time.perf_counter() - self._started)


@contextlib.contextmanager
def quiet_gc() -> Iterator[GcPauses]:
    """Keep the garbage collector from stalling a loop that keeps a controller's clock.

    A full collection walks every object of the process (numpy, SciPy, scikit-learn, a
    simulator: tens of thousands), 10-35 ms on a two-core VM, and one comes every few tens
    of seconds from a loop's per-cycle allocations: 5-17 missed e-Series cycles. Everything
    alive on entry is frozen (``gc.freeze``: never scanned again until the block ends), so a
    collection only walks what was made since. Yields the pauses seen meanwhile."""
    pauses = GcPauses()
    gc.collect()
    gc.freeze()
    gc.callbacks.append(pauses.callback)
    try:
        yield pauses
    finally:
        with contextlib.suppress(ValueError):
            gc.callbacks.remove(pauses.callback)
        gc.unfreeze()
