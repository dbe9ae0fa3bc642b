"""The RSI intake probe: where the controller takes an answer, found by holding answers
back (``KukaRSIDriver.probe_intake``, ``timedexec.drivers._rsi_intake``), and the command
placement it enables."""

from __future__ import annotations

import time

import numpy as np
import pytest

from timedexec.drivers import KukaRSIDriver, RSIIntake, find_latency_step
from timedexec.twins import RSITwin

T12 = 0.012


def _latencies(phases: np.ndarray, step_s: float, base: int = 9) -> list[int | None]:
    return [base + int(p > step_s) for p in phases]


def test_the_rsi_probe_shares_the_step_search_and_its_weighting() -> None:
    """The step of ``base -> base + 1`` cycles is found between the bracketing send phases,
    also with a delayed answer before the deadline and a lost echo; a trial that made a
    cycle the step says it missed weighs 3x (an answer is delayed, never early), and when
    every trial shows ``base`` the step lies between the last phase and the period."""
    phases = np.arange(16) * T12 / 16  # 0.75 ms apart
    step = find_latency_step(phases, _latencies(phases, 0.0064), T12)
    assert (step.mismatches, step.trials, step.base) == (0, 16, 9)
    assert step.phase_s == pytest.approx(0.5 * (phases[8] + phases[9]))  # 6.375 ms, 6.4 true
    noisy = _latencies(phases, 0.0064)
    noisy[7], noisy[3] = 10, None  # one answer delayed across the deadline, one echo lost
    step = find_latency_step(phases, noisy, T12)
    assert (step.mismatches, step.trials, step.base) == (1, 15, 9)
    assert abs(step.phase_s - 0.0064) < 0.75e-3  # one spacing
    early = _latencies(phases, 0.0064)
    early[10] = 9  # made a cycle past the step: cheaper as 1 delayed trial before a later step
    assert find_latency_step(phases, early, T12).phase_s == pytest.approx(
        0.5 * (phases[10] + phases[11])
    )
    step = find_latency_step(phases, [9] * 16, T12)
    assert (step.mismatches, step.base) == (0, 9)
    assert step.phase_s == pytest.approx(0.5 * (phases[-1] + T12))  # the wrap: 11.625 ms
    assert np.isnan(find_latency_step(phases, [None] * 16, T12).phase_s)


def test_placement_error_counts_from_the_deadline_the_answer_makes() -> None:
    """An answer sent before a deadline is taken there, one sent after at the next; the
    placement error is that deadline less the call less 1.5 periods."""
    fix = RSIIntake(deadline_offset_s=0.0105, period_s=T12, probed_at_s=0.0, resolution_s=1e-4,
                    arrival_offset_s=0.004, latency_cycles=9, trials=16, mismatches=0)  # fmt: skip
    c = 2.0  # any frame's controller time
    assert fix.deadline_after_s(c, c + 0.010) == pytest.approx(c + 0.0105)
    assert fix.deadline_after_s(c, c + 0.011) == pytest.approx(c + 0.0225)
    assert fix.deadline_after_s(c, c - 0.005) == pytest.approx(c - 0.0015)
    call = c + 0.004 - T12  # a call right after the previous frame, answered with this one
    assert fix.placement_error_s(c, c + 0.0045, call) == pytest.approx(0.0105 - 0.004 + T12 - 0.018)
    # within 0.5 ms of a deadline: counted at the next (the probed deadline lies late)
    assert fix.placement_error_s(c, c + 0.0102, call) == pytest.approx(0.0225 - 0.004 + T12 - 0.018)


@pytest.mark.slow
def test_probe_finds_the_twins_boundary_whatever_its_packing_phase() -> None:
    """Against the RSI twin, the probed deadline lies at the twin's cycle boundary (mod a
    period) for seeds whose packing phase differs by several ms, while the frames' earliest
    arrival moves with that phase: dated by arrival, the states would carry it.

    Measured on the shared two-core machine (load 3-5): deadline minus the twin's boundary
    0.04-0.6 ms over 12 probes (the answer's trip to the twin, about 0.1 ms, is in it),
    earliest arrival minus the boundary 12.7-21.3 ms. The bound, 1.5 ms: the coarse round
    resolves a quarter of 1.5 ms around the step, the fine round a quarter of that, and a
    twin behind its own cycle on a loaded machine (up to 11 % of its frames sent 1-7 ms late
    where the phase is small) can still move a trial near the step."""
    arrivals = []
    for seed in (1, 3):
        with KukaRSIDriver(0, robot="kr5", progress=False) as drv, RSITwin(
            drv.port, robot="kr5", seed=seed, timeout_packets=2000
        ) as twin:  # fmt: skip
            state = drv.read_state(timeout_s=5.0)
            fix = drv.probe_intake()
            # Host time of the twin's boundary at the driver's controller time 0.
            boundary = twin.t0_host_s + twin.controller_time_of_ipoc(state.ipoc)
            boundary -= state.controller_time_s
            off = (fix.deadline_offset_s - boundary + 0.5 * T12) % T12 - 0.5 * T12
            assert abs(off) < 1.5e-3, (seed, off, fix.summary())
            assert fix.trials >= 12
            assert fix.latency_cycles >= 1
            arrivals.append(fix.arrival_offset_s - boundary)
            assert np.allclose(drv.read_state(timeout_s=1.0).correction, 0.0)  # put back
    assert abs(arrivals[0] - arrivals[1]) > 3e-3, arrivals  # the phases differ (seeds 1, 3)


@pytest.mark.slow
def test_the_commanded_position_is_the_twins_set_point_after_placed_commands() -> None:
    """``commanded_q_rad`` (what the conveyor weld's approach checks before the seam's
    speed stream starts) is the controller's set-point: after a probed, placed speedj
    motion has come to rest, it equals the twin's ``ASPos`` (to 1e-6 rad: the XML's six
    decimals of a degree are 1.7e-8 rad), where the driver's own profile (start pose +
    integrated correction) may not: the placement's lead is in the answers, not in the
    profile (0.012-0.027 mrad apart in this test, 0.2 mrad after a weld's approach)."""
    with KukaRSIDriver(0, robot="kr5", progress=False) as drv, RSITwin(
        drv.port, robot="kr5", seed=2, timeout_packets=2000
    ):  # fmt: skip
        drv.read_state(timeout_s=5.0)
        drv.probe_intake()
        qd = np.array([0.2, -0.1, 0.15, 0.3, -0.2, 0.25])
        for k in range(25):  # a ramp of speed commands a cycle apart, as the executor sends
            drv.speedj(qd * min(1.0, (k + 1) / 10), 4.0, T12)
            drv.read_state(timeout_s=1.0)
        drv.stop(4.0)
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            state = drv.read_state(timeout_s=1.0)
        commanded = drv.commanded_q_rad()
        assert commanded is not None
        assert state.q_setpoint is not None
        assert np.max(np.abs(commanded - state.q_setpoint)) < 1e-6, commanded - state.q_setpoint
        assert np.max(np.abs(state.q_setpoint - drv.start_pose_rad)) > 0.05  # it moved
