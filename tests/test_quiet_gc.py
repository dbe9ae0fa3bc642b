"""The quiet garbage collector and the prompt wake-ups of the loops that keep a controller's
clock (the executor on a real-time driver, the UR twin): what is alive on entry is frozen,
collections are timed, the CPUs kept out of deep idle states, and everything is put back on
exit."""

from __future__ import annotations

import gc
import os
import struct
from pathlib import Path

import numpy as np

from timedexec._realtime import CPU_DMA_LATENCY, fast_wakeup, quiet_gc
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
        assert ex.fast_wakeup == _can_hold_pm_qos()
        ex.idle(ex.now() + 0.05)
    assert gc.get_freeze_count() == 0
    assert not ex.fast_wakeup
    with TimedExecutor(SimDriver("ur10e", physics_rate_hz=2000), MODEL) as ex:
        assert ex.gc_pauses is None
        assert gc.get_freeze_count() == 0
        assert not ex.fast_wakeup


def _can_hold_pm_qos() -> bool:
    return os.access(CPU_DMA_LATENCY, os.W_OK)


def _pm_qos_target_us() -> int:
    with open(CPU_DMA_LATENCY, "rb") as f:
        return int(struct.unpack("=i", f.read(4))[0])


def test_fast_wakeup_holds_the_pm_qos_target_at_zero_while_inside(tmp_path: Path) -> None:
    """Where the OS grants it, the system's PM QoS CPU latency target reads 0 µs inside and
    its previous value after (the request lasts while the file is open); where the file
    cannot be opened the block still runs and says it was not granted; the value written is
    the 4-byte binary integer the kernel reads."""
    with fast_wakeup(path=str(tmp_path / "absent" / "cpu_dma_latency")) as granted:
        assert granted is False
    stand_in = tmp_path / "cpu_dma_latency"
    stand_in.write_bytes(b"")
    with fast_wakeup(7, path=str(stand_in)) as granted:
        assert granted is True
    assert stand_in.read_bytes() == struct.pack("=i", 7)
    if not _can_hold_pm_qos():
        return  # not root here: the stand-in above is what can be checked
    before = _pm_qos_target_us()
    with fast_wakeup() as granted:
        assert granted is True
        assert _pm_qos_target_us() == 0
    assert _pm_qos_target_us() == before  # (another process holding 0 meanwhile would fail it)
