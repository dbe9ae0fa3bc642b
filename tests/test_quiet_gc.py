"""The quiet garbage collector of the loops that keep a controller's clock (the executor on a
real-time driver, the UR twin): what is alive on entry is frozen, collections are timed, and
everything is put back on exit."""

from __future__ import annotations

import gc

import numpy as np

from timedexec._realtime import quiet_gc
from timedexec.drivers import SimDriver
from timedexec.execution import FixedDelays, TimedExecutor

MODEL = FixedDelays(robot="ur10e", actuation_s=0.019, response_s=0.0011, actuation_std_s=6e-4)


def test_quiet_gc_freezes_what_lives_and_times_collections() -> None:
    """Inside: the objects alive on entry are frozen (a full collection does not walk
    them), a collection is counted with a positive duration; after: nothing frozen, the
    callback gone (a collection afterwards is not counted)."""
    gc.unfreeze()  # whatever an earlier test left frozen: start from nothing frozen
    keep = [np.zeros(3) for _ in range(1000)]  # alive on entry: frozen
    with quiet_gc() as pauses:
        assert gc.get_freeze_count() >= len(keep)
        assert pauses.count == 0
        gc.collect()
        assert pauses.count == 1
        assert pauses.max_s > 0.0
    assert gc.get_freeze_count() == 0
    gc.collect()
    assert pauses.count == 1
    del keep


def test_executor_quiets_the_collector_only_on_a_real_time_driver() -> None:
    """A real-time driver (the simulator in real time): frozen while connected, thawed at
    close; a virtual-time driver (no clock to keep): the collector is left alone."""
    gc.unfreeze()
    with TimedExecutor(SimDriver("ur10e", virtual=False, physics_rate_hz=2000), MODEL) as ex:
        assert ex.gc_pauses is not None
        assert gc.get_freeze_count() > 0
        ex.idle(ex.now() + 0.05)
    assert gc.get_freeze_count() == 0
    with TimedExecutor(SimDriver("ur10e", physics_rate_hz=2000), MODEL) as ex:
        assert ex.gc_pauses is None
        assert gc.get_freeze_count() == 0
