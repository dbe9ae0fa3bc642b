"""Shared test configuration: end-to-end tests that need a machine fast enough to run a
protocol twin in real time."""

from __future__ import annotations

import functools
import os
import time
from typing import TypeVar

import pytest

T = TypeVar("T")

#: ``TIMEDEXEC_FULL_TESTS=1`` runs the slow end-to-end tests (``-m slow``) at their full
#: size instead of the bounded form CI runs (.ci/run must stay under 15 minutes): every case
#: of a family, every fold of the published protocol, more kills, trials and phases. Each
#: test says in a comment what its bounded size still proves and why its tolerances hold
#: there; the full size is for a release or after changing what the test covers.
#: Read it through :func:`full_or_bounded`, one convention for every test.
FULL_TESTS = os.environ.get("TIMEDEXEC_FULL_TESTS", "") == "1"


def full_or_bounded(full: T, bounded: T) -> T:
    """``full`` with ``TIMEDEXEC_FULL_TESTS=1``, else ``bounded`` (the size CI runs)."""
    return full if FULL_TESTS else bounded


#: Largest cost of the UR10e twin's simulator (4 kHz physics, all joints moving) as a
#: fraction of real time at which the real-time twin tests run. Above it the twin, the real
#: client and the gyro twin saturate two cores: on a VM where the vectorised simulator cost
#: 0.48 at rest, the UR10e twin used 1.3-2.4 cores, even ur_rtde's own servo pattern missed 46 % of cycles, response delays reached 29 ms
#: and a P loop on the lagging states diverged. Those runs measure the machine, not the
#: code; the tests are skipped there with the measured figure in the reason.
#: 0.18, not the 0.35 it was when the simulator was vectorised over the six joints: stepped
#: in floats it costs 0.5-0.6 of what it did (moving, against the old cost at rest, same
#: machine), while the twin's protocol side did not get cheaper; on this VM (0.22-0.26
#: moving now, 0.43-0.57 at rest before) three of the gated tests failed when run (live
#: UR and RSI calibration, the 60 s jittery stream), as the old gate had foreseen. 0.18
#: keeps the old gate's decisions.
MAX_TWIN_COST = 0.18


@functools.cache
def twin_cost() -> float:
    """Seconds of CPU per second of controller time of the UR10e twin's simulator with
    every joint moving (its dearest case: a joint at rest is not stepped)."""
    from timedexec.sim import ControllerSim, SpeedJ

    sim = ControllerSim("ur10e", physics_rate_hz=4000.0)
    sim.submit(SpeedJ((0.05,) * 6, 2.0))
    for _ in range(20):
        sim.cycle()
    n = 250
    t0 = time.perf_counter()
    for _ in range(n):
        sim.cycle()
    return (time.perf_counter() - t0) / n / sim.period_s


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("realtime_twin") is not None and twin_cost() > MAX_TWIN_COST:
        pytest.skip(
            f"this machine runs the UR10e twin's simulator at {twin_cost():.2f} of real time "
            f"(> {MAX_TWIN_COST}): a real-time twin end to end would measure the machine"
        )
