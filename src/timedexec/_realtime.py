"""Real-time scheduling for loops that keep a controller's clock (twins, live runs)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

__all__ = ["realtime", "try_realtime"]


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
