"""DelayMonitor: per-move cost, detection delay and false-alarm rate on the simulator.

Per-move cost: one ``update`` of one move (the model query included) after the warm-up,
against a naive monitor that recomputes everything (all residuals' normal scores and both
CUSUMs from the first move) on each new move, in the same run. The executor's own work per
cycle is 30-60 µs (median, docs/execution.md); a move spans hundreds of cycles.

Detection: a simulated UR10 pool (warm robot, distinct configurations) of baseline moves and
of moves with joint 2's drive offset +2 ms; runs resample it (seeded) as in
tests/test_monitor.py. False alarms: the same resampling at the operating threshold
(chains of 10,000 monitored moves with their own warm-up).

    python benchmarks/bench_monitor.py [--runs 200] [--chains 100]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from timedexec.effects import EffectSet, JointOffset, default_effects
from timedexec.learning import DelayModel
from timedexec.monitoring import (
    DelayMonitor,
    false_alarm_rate,
    moves_from_trials,
    run_lengths,
    standardize,
    warmup_reference,
)
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.sim import default_settings, simulate_block, sweep_clock

JOINTS = (1, 2, 3, 5)


def pool(robot: str = "ur10") -> dict:  # type: ignore[type-arg]
    spec = get_robot(robot)
    st = default_settings(spec)
    profile = dataclasses.replace(st.protocol.profile, record_s=0.2)
    st = st.replace(protocol=dataclasses.replace(st.protocol, profile=profile))
    base = EffectSet(tuple(e for e in default_effects(robot) if e.name != "thermal_drift"))
    off = list(base.get("joint_offset").offsets_s)  # type: ignore[union-attr]
    off[1] += 0.002
    drift = base.with_effect(JointOffset(offsets_s=tuple(off)))
    kw = {"acceleration_rad_s2": 8.0, "speed_rad_s": 0.4}
    plan = SweepPlan.generate(spec, 2048, seed=21, repeats=1)
    clock = sweep_clock(plan, st, 21)
    moves = []
    t = time.perf_counter()
    for s in range(0, 2048, 512):
        moves += moves_from_trials(
            simulate_block(spec, st, base, plan, clock, np.arange(s, s + 512), 21), **kw
        )
    plan2 = SweepPlan.generate(spec, 512, seed=22, repeats=1, joints=(2,))
    d = simulate_block(spec, st, drift, plan2, sweep_clock(plan2, st, 22), np.arange(512), 22)
    drifted = moves_from_trials(d, **kw)
    print(f"simulated 2,560 trials in {time.perf_counter() - t:.1f} s")
    return {
        "base": {j: [m for m in moves if m.joint == j] for j in JOINTS},
        "all": moves,
        "drifted": drifted,
    }


class NaiveMonitor:
    """Recompute everything per move: residual scores and both CUSUMs from move 1."""

    def __init__(self, mon: DelayMonitor) -> None:
        self.mon = mon
        self.res: dict[int, list[float]] = {}

    def update(self, move) -> bool:  # type: ignore[no-untyped-def]
        from timedexec.execution import predict_delays

        p = predict_delays(self.mon.model, [move.joint], [move.direction], move.q_start_rad[None])
        r = self.res.setdefault(move.joint, [])
        r.append(move.lag_s - float(p.actuation_mean[0] + p.response_mean[0]))
        n = self.mon.warmup_moves
        if len(r) <= n:
            return False
        warm, lrv = warmup_reference(r[:n])
        z = standardize(r[n:], warm, lrv)
        up = down = 0.0
        k = self.mon.reference_k
        fired = False
        for x in z:
            up = max(0.0, up + x - k)
            down = max(0.0, down - x - k)
            fired |= max(up, down) > self.mon.threshold
        return fired


def cost(p: dict, n_moves: int = 2000) -> None:  # type: ignore[type-arg]
    model = DelayModel.load("ur10-sim")
    moves = [m for j in JOINTS for m in p["base"][j][:250]]
    rng = np.random.default_rng(1)
    order = [moves[i] for i in rng.permutation(len(moves))]
    mon = DelayMonitor(model)
    naive = NaiveMonitor(DelayMonitor(model))
    warm = order[:600]
    mon.update(warm)
    for m in warm:
        naive.update(m)
    stream = [order[600 + (i % 400)] for i in range(n_moves)]
    t_inc, t_naive = [], []
    for i, m in enumerate(stream):
        t = time.perf_counter()
        mon.update(m)
        t_inc.append(time.perf_counter() - t)
        if i < 600:  # the naive monitor grows O(n) per move: 600 is enough to show it
            t = time.perf_counter()
            naive.update(m)
            t_naive.append(time.perf_counter() - t)
    inc, nai = np.array(t_inc) * 1e6, np.array(t_naive) * 1e6
    print(f"per-move update (model query included), {len(inc)} moves after the warm-up:")
    print(
        f"  incremental DelayMonitor   p50 {np.percentile(inc, 50):7.0f} µs  p99 "
        f"{np.percentile(inc, 99):7.0f} µs"
    )
    print(
        f"  naive recompute-everything p50 {np.percentile(nai, 50):7.0f} µs  p99 "
        f"{np.percentile(nai, 99):7.0f} µs  (at 150-300 monitored moves per joint; "
        "grows linearly)"
    )
    print(
        f"  ratio naive/incremental (p50): {np.percentile(nai, 50) / np.percentile(inc, 50):.1f}x"
    )
    t = time.perf_counter()
    _ = moves_from_trials  # extraction cost measured below
    print("  executor's own work per cycle: 30-60 µs (median, docs/execution.md)")
    del t


def detection(p: dict, runs: int) -> None:  # type: ignore[type-arg]
    model = DelayModel.load("ur10-sim")
    delays, right, false, exposure, missed, common = [], 0, 0, 0, 0, 0
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        mon = DelayMonitor(model)

        def draw(j: int, drifted: bool, rng=rng):  # type: ignore[no-untyped-def]
            src = p["drifted"] if drifted else p["base"][j]
            return src[int(rng.integers(len(src)))]

        before = mon.update([draw(j, False) for _ in range(200) for j in JOINTS])
        after = mon.update([draw(j, j == 2) for _ in range(300) for j in JOINTS])
        common += sum(a.test == "common" for a in before + after)
        before = [a for a in before if a.test != "common"]
        after = [a for a in after if a.test != "common"]
        false += len(before) + sum(a.joint != 2 for a in after)
        exposure += 4 * 100 + 3 * 300
        j2 = [a for a in after if a.joint == 2]
        if j2 and j2[0].move - 200 <= 200:
            delays.append(j2[0].move - 200)
            right += after[0].joint == 2
        else:
            missed += 1
    d = np.array(delays)
    print(f"detection of +2 ms on joint 2 ({runs} resampled runs, warm-up 100):")
    print(f"  detected within 200 moves: {len(d)}/{runs} = {len(d) / runs:.1%}")
    print(
        f"  delay (moves of joint 2): median {np.median(d):.0f}, p90 {np.percentile(d, 90):.0f},"
        f" max {d.max():.0f}"
    )
    print(f"  right joint named first: {right}/{len(d)}")
    print(f"  false alarms during the runs: {false} in {exposure:,} unchanged joint-moves")
    print(f"  common-shift alerts during the runs: {common}")


def false_alarms(p: dict, chains: int) -> None:  # type: ignore[type-arg]
    model = DelayModel.load("ur10-sim")
    mon = DelayMonitor(model)
    mon.update(p["all"])
    rng = np.random.default_rng(3)
    n = mon.warmup_moves
    alarms, exposure = 0, 0.0
    for j in JOINTS:
        res = mon.history(j)["residual_ms"]
        z = np.empty((chains, 10_000))
        for c in range(chains):
            warm, lrv = warmup_reference(rng.choice(res, n))
            z[c] = standardize(rng.choice(res, 10_000), warm, lrv)
        rl = run_lengths(z, mon.threshold, mon.reference_k)
        alarms += int(np.isfinite(rl).sum())
        exposure += float(np.where(np.isfinite(rl), rl, 10_000).sum())
    k = mon.reference_k
    print(f"false alarms at the operating threshold h = {mon.threshold:.2f} (k {k}, warm-up {n}):")
    print(
        f"  design (Siegmund, averaged over the warm-up's error): 1 per {mon.arl0_moves:,.0f}; "
        f"nominal with a known warm-up: 1 per {1 / false_alarm_rate(mon.threshold, k):,.0f}"
    )
    print(
        f"  simulated on resampled residuals: {alarms} alarms in {exposure:,.0f} moves = "
        f"1 per {exposure / max(alarms, 1):,.0f}"
    )
    for j in JOINTS:
        r = mon.history(j)["residual_ms"]
        print(
            f"  joint {j}: residual median {np.median(r):+.2f} ms, IQR "
            f"{np.subtract(*np.percentile(r, [75, 25])):.2f} ms, p99-p50 "
            f"{np.percentile(r, 99) - np.median(r):.2f} ms"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--chains", type=int, default=100)
    args = ap.parse_args()
    p = pool()
    t = time.perf_counter()
    moves_from_trials  # noqa: B018
    cost(p)
    detection(p, args.runs)
    false_alarms(p, args.chains)
    print(f"(benchmark body {time.perf_counter() - t:.0f} s)")


if __name__ == "__main__":
    main()
