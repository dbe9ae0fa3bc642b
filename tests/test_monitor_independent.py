"""DelayMonitor on cycle logs from the independent generator (tests/independent_cycle_log.py).

The monitor's claims (docs/monitor.md, "Measured": a 2 ms shift detected within 200 moves
with >= 95 % probability, the right joint named, <= 1 false alarm per 10,000 moves, the
observed lag = actuation + response + a constant) were measured on the simulator only.
These tests assert them at a bounded scale on logs of a second, independently written
generator with different physics (its module docstring has the table), through the real
path: ``DelayMonitor("<robot>-sim", warmup_moves=100)`` fed the documented cycle-log
columns (``feed_log``; one log also round-trips through ``save_cycle_log`` /
``load_cycle_log``). Seeds are fixed; every threshold says what was measured
(``benchmarks/bench_monitor_independent.py``: 100 runs per robot, ~80,000 UR10 and ~24,000
UR10e no-step moves) and why its margin. Bounded form: see ``FAST``. About 30 s.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from independent_cycle_log import Conditions, IndependentCycleLog
from timedexec.monitoring import DelayMonitor, load_cycle_log, save_cycle_log

JOINTS = (1, 2, 3, 5)
WARMUP = 100
STEP_FROM = 110  # the step joint's generated move the +2 ms starts at (after its warm-up)
WITHIN = 200
CHUNK = 40
#: Bounded form of the detection and false-alarm runs: every plan moves 3 of the 4 watched
#: joints (1-3 in the benchmark) over 0.03-0.3 rad (0.03-0.6), streams 0.05-0.1 s before
#: its start (0.06-0.2) and rests 0.35-0.5 s (0.35-0.9): each joint warms up in ~135 plans
#: instead of ~200, and a plan has fewer rows (the monitor's cost is per streamed row).
FAST = Conditions(min_joints=3, distance_rad=(0.03, 0.3), pre_s=(0.05, 0.1), idle_s=(0.35, 0.5))


@pytest.fixture(scope="module")
def models() -> dict[str, Any]:
    """The bundled models, loaded once (a DelayMonitor per run shares them)."""
    return {r: DelayMonitor(f"{r}-sim", warmup_moves=WARMUP).model for r in ("ur10", "ur10e")}


def _key(joint: int, send_s: float) -> tuple[int, float]:
    return int(joint), round(float(send_s), 9)


# ----------------------------------------------------------------------------- the lag
@pytest.mark.parametrize(("robot", "plans"), [("ur10", 300), ("ur10e", 70)])
def test_lag_matches_the_generators_truth(robot, plans, models, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Every generated move is recognised, and the measured lag agrees with the truth
    (actuation + response, docs/architecture.md) up to a constant of the method.

    Benchmark (no-step chains; UR10 80,244 / UR10e 24,050 moves): lag - truth median
    +0.21 / +0.51 ms, IQR 0.96 / 0.75 ms, p5..p95 -0.51..+1.77 / -0.18..+1.38 ms; no move
    unseen, 13 / 20 skipped (no package in the onset window: a joint that a
    time-synchronised plan moves at a few cm/s). The constant is not the simulator's
    (-1.1 ms, docs/monitor.md) and depends on the move's peak speed (a second-order drive
    lags a long commanded ramp more than a short one): slow moves about +1 ms, fast ones
    -0.3 ms, hence the spread (simulator: std 0.3 ms).
    Thresholds: |median| <= 1.0 ms (the monitor's "lag = actuation + response + c" with c
    of about a millisecond; measured 0.21-0.51, margin 0.5 ms, while the median of these
    ~140-600 moves is known to ~0.1 ms); IQR <= 1.5 ms (measured 0.75-0.96); 90 % of the
    moves within 2.5 ms of the median (measured p5..p95 -0.7..+1.6 ms around it); skipped
    <= 1 % (measured < 0.1 %). A monitor that timed the lag from the wrong command, lost
    the sub-period ramp inversion (the first package showing motion is quantised by the
    8 ms cycle) or missed moves fails these.
    """
    gen = IndependentCycleLog(robot, Conditions(), seed=7)
    arrays, truth = gen.generate(plans)
    path = save_cycle_log(tmp_path / "log.npz", arrays, period_s=gen.period_s, robot=robot)
    back, meta = load_cycle_log(path)
    assert meta["period_s"] == gen.period_s
    mon = DelayMonitor(models[robot], warmup_moves=WARMUP)
    mon.feed_log(back)
    t = {
        _key(j, s): tl
        for j, s, tl in zip(truth["joint"], truth["send_s"], truth["true_lag_s"], strict=True)
    }
    err, skipped, measured = [], 0, 0
    for st in mon.states():
        skipped += st.skipped
        measured += len(st.lag_s)
        err += [lag - t[_key(st.joint, s)] for s, lag in zip(st.send_s, st.lag_s, strict=True)]
    err_ms = np.array(err) * 1e3
    n = len(truth["joint"])
    assert measured + skipped == n, f"{n - measured - skipped} of {n} moves not recognised"
    assert skipped <= 0.01 * n
    med = float(np.median(err_ms))
    iqr = float(np.subtract(*np.percentile(err_ms, [75, 25])))
    near = float(np.mean(np.abs(err_ms - med) <= 2.5))
    assert abs(med) <= 1.0, f"median lag - truth {med:+.2f} ms"
    assert iqr <= 1.5, f"IQR {iqr:.2f} ms"
    assert near >= 0.9, f"only {near:.0%} within 2.5 ms of the median"


# ----------------------------------------------------------------------------- detection
def _detection_run(model: Any, seed: int, joint: int) -> tuple[int | None, int | None]:
    """(moves of ``joint`` from the step to its alarm or None, first joint to alarm after
    the step or None). Alarms before the step re-baseline their joint."""
    cond = FAST.replace(step_joint=joint, step_s=0.002, step_from_move=STEP_FROM)
    gen = IndependentCycleLog("ur10", cond, seed=seed)
    mon = DelayMonitor(model, warmup_moves=WARMUP)
    first_step, first_after = math.inf, None
    for _ in range(100):  # a run needs ~150-200 plans
        # big chunks until the step, then small ones (less run-on after the alarm)
        rows, truth = gen.generate(CHUNK if math.isinf(first_step) else CHUNK // 4)
        if math.isinf(first_step) and truth["stepped"].any():
            first_step = float(truth["send_s"][truth["stepped"]].min())
        for a in mon.feed_log(rows):
            sj = next(s for s in mon.states() if s.joint == a.joint)
            send_at = sj.send_s[a.move - 1]
            if send_at < first_step:
                mon.rebaseline(a.joint)
                continue
            first_after = first_after or a.joint
            if a.joint == joint:
                return sum(s >= first_step for s in sj.send_s[: a.move]), first_after
            mon.rebaseline(a.joint)
        st = next((s for s in mon.states() if s.joint == joint), None)
        if st is not None and sum(s >= first_step for s in st.send_s) >= WITHIN:
            return None, first_after
    return None, first_after


def test_detects_a_2ms_step_on_the_right_joint(models) -> None:  # type: ignore[no-untyped-def]
    """+2 ms of dead time on one joint (1, 2, 3, 5 in turn) after its warm-up, 20 seeded
    runs on the UR10: detected within 200 of its moves, the right joint alarming first,
    in >= 18 of 20 (this seed set: 20/20, median 14, max 32 moves); median moves to
    detection <= 40.

    Benchmark (100 runs, 1-3 joints per plan): UR10 detected 100/100 within 200 moves,
    median 11, p90 26, max 74 moves; the right joint first in 98/100 (the two others: a
    false alarm on another joint after the step). The claim is >= 95 %; at a true 95 %
    rate 18 of 20 or more happen with probability 0.92, at 98 % with 0.99; a monitor
    detecting 80 % passes with probability 0.21, one naming the joint by chance (1 in 4)
    never. Moves to detection: 40 is ~3.5x the measured median (simulator: 7; the
    independent residuals are ~3x wider), so the fixed-seed sample of 20 passes while a
    CUSUM needing several times the evidence fails.
    """
    delays, right = [], 0
    for seed in range(20):
        joint = JOINTS[seed % 4]
        d, first = _detection_run(models["ur10"], 1000 + seed, joint)
        if d is not None and d <= WITHIN and first == joint:
            right += 1
            delays.append(d)
    assert right >= 18, f"{right}/20 detected on the right joint within {WITHIN} moves"
    assert np.median(delays) <= 40, f"median moves to detection {np.median(delays)}"


# ----------------------------------------------------------------------------- false alarms
def _false_alarms(
    model: Any, cond: Conditions, seed: int, plans: int, robot: str = "ur10"
) -> tuple[int, int]:
    """(alarms, monitored moves after the warm-up) of a no-step log; alarmed joints
    re-baselined."""
    gen = IndependentCycleLog(robot, cond, seed=seed)
    mon = DelayMonitor(model, warmup_moves=WARMUP)
    alarms, exposure = 0, 0
    for _ in range(plans // CHUNK):
        rows, _ = gen.generate(CHUNK)
        for a in mon.feed_log(rows):
            alarms += 1
            exposure += a.move - WARMUP
            mon.rebaseline(a.joint)
    exposure += sum(max(0, st.moves - WARMUP) for st in mon.states() if st.alarm is None)
    return alarms, exposure


def test_false_alarms_with_the_host_wandering(models) -> None:  # type: ignore[no-untyped-def]
    """No step, the generator's default host (read-time wander common to a plan, AR(1)
    over plans; per-package jitter, stalls, lost packages) on the UR10e, whose 2 ms period
    the wander crosses often: at most one alarm in ~2,600 monitored moves.

    The wander correlates consecutive residuals of a joint and pushes whole plans past the
    controller's intake (a period later) in bursts. Before the monitor clipped its scores
    and scaled them by their long-run variance this made 3.2 (UR10) and 10.5 (UR10e)
    false alarms per 10,000 moves against the design's 1 (docs/monitor.md, "Measured on
    logs we did not write"). Seeds 31, 32, 33 of this bounded form: 1, 3, 10 alarms
    before, 0, 0, 1 now; this test runs seed 32. At the design rate it expects 0.26 alarms
    and passes (<= 1) with probability 0.97; a monitor at ten times the rate fails with
    probability 0.73. It cannot confirm "<= 1 per 10,000" (the benchmark's ~100,000 moves
    do); it catches a monitor gone far off.
    """
    alarms, exposure = _false_alarms(models["ur10e"], FAST, seed=32, plans=1000, robot="ur10e")
    assert exposure >= 2_400
    assert alarms <= 1, f"{alarms} false alarms in {exposure} moves"
