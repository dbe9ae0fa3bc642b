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


#: Largest machine cost, as a fraction of real time, at which the real-time twin tests run:
#: the CPU time of a fixed workload, stepping six joints of the vectorised ``JointBank``
#: at the UR10e twin's 4 kHz (the old twin simulator's core), per second of controller
#: time. Above it the twin, the real client and the gyro twin saturate two cores: on a VM
#: where the whole (then vectorised) simulator cost 0.48, the UR10e twin used 1.3-2.4
#: cores, even ur_rtde's own servo pattern missed 46 % of cycles, response delays reached
#: 29 ms and a P loop on the lagging states diverged. Those runs measure the machine, not
#: the code; the tests are skipped there with the measured figure in the reason.
#: A fixed workload, not the twin's simulator itself: the simulator got 3x cheaper (it
#: steps the joints in floats) while the twin's protocol side did not, and with the gate
#: on the new simulator's cost (0.15 on this VM) three gated tests ran here and failed
#: (live UR and RSI calibration, the 60 s jittery stream). The old gate allowed 0.35 of
#: the old simulator at rest; this workload costs 0.57-0.68 of that on the same machine
#: (four paired runs): 0.18 is below 0.57 x 0.35 = 0.20 and below this VM's quietest
#: reading (0.21), where the tests fail.
MAX_TWIN_COST = 0.18


@functools.cache
def twin_cost() -> float:
    """CPU seconds per second of controller time of the gate's fixed workload (see
    :data:`MAX_TWIN_COST`): eight ``JointBank.step`` of six joints per 2 ms cycle."""
    import numpy as np

    from timedexec.effects import default_effects
    from timedexec.robots import get_robot
    from timedexec.sim import JointBank, default_settings, joint_params

    spec = get_robot("ur10e")
    settings = default_settings(spec)
    q0 = np.array(spec.home_q_rad)
    params, _, _ = joint_params(
        spec, settings, default_effects("ur10e"), np.broadcast_to(q0, (6, 6)),
        np.arange(1, 7), np.zeros(6),
    )  # fmt: skip
    bank = JointBank(params, q0, 0.002 / 8, settings.servo.onset_threshold_rad_s)
    v_ref = np.full(6, 0.05)
    for _ in range(160):
        bank.step(v_ref, 0.0)
    n = 4000
    t0 = time.perf_counter()
    for _ in range(n):
        bank.step(v_ref, 0.0)
    return (time.perf_counter() - t0) / (n / 8) / 0.002


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("realtime_twin") is not None and twin_cost() > MAX_TWIN_COST:
        pytest.skip(
            f"this machine runs the twin gate's workload at {twin_cost():.2f} of real time "
            f"(> {MAX_TWIN_COST}): a real-time twin end to end would measure the machine"
        )
