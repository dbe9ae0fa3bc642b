"""Simulated delay statistics beside the published ones (DESIGN.md §1, Tables I-II).

For each robot, simulate a sweep with the default effects (ground truth only, no recording)
and print: actuation and response medians and 95 % ranges; per-joint medians; the median
predictor's error per joint (RMS deviation from the joint's median, the paper's "median"
row); the replicate noise floor (RMS scatter of the repeats of one condition) and the share
of the variance that the condition (configuration, joint, direction) explains; and the
fraction of trials whose first-package actuation + response lies on the period grid.

Usage: python benchmarks/bench_sim_stats.py [--trials 8000] [--seed 1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from timedexec.effects import default_effects
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.sim import BLOCK_TRIALS, default_settings, simulate_block, sweep_clock

PUBLISHED = {
    # actuation median row of Table I and response median row of Table II, ms
    "kr5": {"act": (2.27, 2.68, 4.61, 3.51, 3.67), "resp": (2.13, 2.37, 4.30, 3.09, 3.33)},
    "ur10": {"act": (6.18, 4.64, 6.08, 2.59, 5.33), "resp": (4.82, 2.00, 4.08, 4.90, 5.09)},
}
RANGES = {
    "kr5": "actuation median 85-95 ms, >=95 % in 75-110 ms, joint 2 highest; response > 12 ms",
    "ur10": "actuation median 15-25 ms, >=95 % in 5-45 ms; response 0-35 ms",
}


def simulate(robot: str, n: int, seed: int) -> tuple[SweepPlan, dict[str, np.ndarray]]:
    spec = get_robot(robot)
    settings = default_settings(spec)
    effects = default_effects(robot)
    plan = SweepPlan.generate(spec, n, seed=seed)
    clock = sweep_clock(plan, settings, seed)
    keys = ("true_actuation_delay_s", "true_response_delay_s", "state_host_time_s",
            "state_qd_rad_s", "cmd_send_time_s")
    out: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for start in range(0, n, BLOCK_TRIALS):
        rows = np.arange(start, min(start + BLOCK_TRIALS, n))
        b = simulate_block(spec, settings, effects, plan, clock, rows, seed)
        j = plan.joint[rows] - 1
        b["state_qd_rad_s"] = b["state_qd_rad_s"][np.arange(len(rows)), :, j]
        for k in keys:
            out[k].append(b[k])
    return plan, {k: np.concatenate(v) for k, v in out.items()}


def explained(values: np.ndarray, plan: SweepPlan, mask: np.ndarray) -> tuple[float, float, float]:
    """(median-predictor RMSE, replicate noise floor, share of variance explained), ms."""
    v = values[mask]
    rmse = float(np.sqrt(np.mean((v - np.median(v)) ** 2)))
    cond = (plan.config_index * 100 + plan.joint * 10 + (plan.direction + 1) // 2)[mask]
    _, inv = np.unique(cond, return_inverse=True)
    means = np.bincount(inv, v) / np.bincount(inv)
    resid = v - means[inv]
    dof = len(v) - len(means)
    floor = float(np.sqrt(np.sum(resid**2) / max(dof, 1)))
    share = 1.0 - floor**2 / float(np.var(v, ddof=1))
    return rmse, floor, share


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=8000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    for robot in ("kr5", "ur10"):
        t = time.perf_counter()
        plan, out = simulate(robot, args.trials, args.seed)
        elapsed = time.perf_counter() - t
        period = get_robot(robot).controller_period_s
        act = out["true_actuation_delay_s"] * 1e3
        resp = out["true_response_delay_s"] * 1e3
        print(f"\n== {robot}: {args.trials} trials, default effects ({elapsed:.1f} s)")
        print(f"published: {RANGES[robot]}")
        lo, hi = (75, 110) if robot == "kr5" else (5, 45)
        print(
            f"simulated: actuation median {np.median(act):.1f} ms, 2.5-97.5 % "
            f"{np.percentile(act, 2.5):.1f}-{np.percentile(act, 97.5):.1f} ms, "
            f"{100 * np.mean((act >= lo) & (act <= hi)):.1f} % in {lo}-{hi} ms"
        )
        print(
            f"           response median {np.median(resp):.1f} ms, 2.5-97.5 % "
            f"{np.percentile(resp, 2.5):.1f}-{np.percentile(resp, 97.5):.1f} ms, "
            f"{100 * np.mean(resp > period * 1e3):.1f} % above one period ({period * 1e3:.0f} ms)"
        )
        qd = out["state_qd_rad_s"]
        first = np.argmax(np.abs(qd) > 1e-6, axis=1)
        total = out["state_host_time_s"][np.arange(len(first)), first] - out["cmd_send_time_s"]
        k = total / period
        on_grid = np.mean(np.abs(k - np.round(k)) * period < 0.6e-3)
        print(
            f"           first-package actuation + response within 0.6 ms of a period multiple: "
            f"{100 * on_grid:.1f} % of trials"
        )
        print("  joint | act median | median-pred. error (paper) | noise floor | explained"
              " | resp median | median-pred. error (paper)")
        rows = [(j, plan.joint == j) for j in (1, 2, 3, 5)] + [("comb.", np.ones(len(plan), bool))]
        for i, (name, mask) in enumerate(rows):
            a_err, a_floor, a_share = explained(act, plan, mask)
            r_err, _, _ = explained(resp, plan, mask)
            pa, pr = PUBLISHED[robot]["act"][i], PUBLISHED[robot]["resp"][i]
            print(
                f"  {name!s:>5} | {np.median(act[mask]):7.1f} ms | {a_err:5.2f} ms ({pa:.2f})"
                f"            | {a_floor:5.2f} ms    | {100 * a_share:5.1f} %"
                f"  | {np.median(resp[mask]):7.1f} ms | {r_err:5.2f} ms ({pr:.2f})"
            )


if __name__ == "__main__":
    main()
