"""Real-time scheduling, prompt wake-ups and a quiet garbage collector for loops that keep a
controller's clock (twins, live runs)."""

from __future__ import annotations

import contextlib
import gc
import os
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

__all__ = [
    "CPU_DMA_LATENCY",
    "SPIN_S",
    "GcPauses",
    "fast_wakeup",
    "quiet_gc",
    "realtime",
    "try_realtime",
    "wait_until",
]

#: The last part of a :func:`wait_until` is spun, s (``time.sleep`` alone overshoots by
#: 50-100 µs).
SPIN_S = 1.5e-4


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


#: Linux PM QoS file: while a process holds it open with a value written, no CPU enters an
#: idle state whose exit latency exceeds that many µs (kernel doc "PM Quality Of Service
#: Interface"; cyclictest and real-time control stacks hold it at 0).
CPU_DMA_LATENCY = "/dev/cpu_dma_latency"


@contextlib.contextmanager
def fast_wakeup(max_latency_us: int = 0, path: str = CPU_DMA_LATENCY) -> Iterator[bool]:
    """Keep the CPUs out of deep idle states for the block; yields whether the OS agreed.

    A 2 ms loop sleeps most of each period; on an idle machine the CPU then drops into a
    deep C-state (on a VM the vCPU is descheduled) and wakes late. Measured here
    (``benchmarks/bench_wakeup_latency.py``, SCHED_FIFO, 2 ms deadlines, quiet machine):
    the executor's wait was 0.3-3.7 ms late at p99 without (five runs) and 0.003-0.23 ms
    with this; cyclictest holds the same request for its own 0.08-0.17 ms (``--laptop``,
    which skips it: max 14 ms). Beside busy processes the CPUs seldom idle and it changes
    little. The request is system-wide and lasts while the file is open (root, or a udev
    rule granting the file). Where it is refused the loop runs as before and the caller
    says so."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    except OSError:
        yield False
        return
    try:
        try:
            os.write(fd, struct.pack("=i", int(max_latency_us)))
            granted = True
        except OSError:
            granted = False
        yield granted
    finally:
        os.close(fd)


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


def wait_until(t_s: float, clock: Callable[[], float] = time.monotonic) -> float:
    """Sleep, then spin (the last :data:`SPIN_S`), until ``clock()`` reaches ``t_s``;
    return the clock then. The executor's cycle lock waits for its send time with it
    (``benchmarks/bench_wakeup_latency.py`` measures how late it wakes)."""
    now = clock()
    rest = t_s - now - SPIN_S
    if rest > 0:
        time.sleep(rest)
    now = clock()
    while now < t_s:
        now = clock()
    return now
