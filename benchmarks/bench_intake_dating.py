"""How often the probed intake dates the state a whole period off: by the mean response
delay against by the echo depth (``IntakeFix.dated``), on the simulated UR robots.

For each seed the simulated robot (``sim://ROBOT?seed=N``, virtual time: the host clock is
the controller's, so a package stamped ``t`` was sampled at host time ``t`` and the true
``sample_offset_s`` is 0) is connected with the cycle lock, which probes its intake; the
publisher's phase at the probe differs per seed (the catalog's 2-97 % of the period). The
probe is then dated by both rules, as it came and with every package the probe saw made
``--late-ms`` later (a loaded host that delays every package while the probe runs: the
earliest arrival moves, the deadline does not).

Prints per robot: the mean response rule's margin (how far the probe's response was from
flipping the cycle by a period: min / 5 % / median), the share of probes with less than an
eighth of a period to spare (where ``dated`` warns), and for each lateness the probes dated
a whole period off by each rule.

    python benchmarks/bench_intake_dating.py [--seeds 200] [--late-ms 0 0.25 0.5 1 2]
"""

from __future__ import annotations

import argparse
import time
import warnings
from dataclasses import replace

import numpy as np

from timedexec.drivers import open_driver
from timedexec.execution import ExecutorSettings, TimedExecutor, load_delay_model
from timedexec.robots import get_robot_entry


def probe(robot: str, seed: int, model: object) -> tuple[object, float]:
    """The probed (undated) intake fix of one connect, and the model's mean response, s."""
    with open_driver(f"sim://{robot}?seed={seed}") as drv, TimedExecutor(
        drv, model, ExecutorSettings(cycle_lock=True)
    ) as ex:  # fmt: skip
        fix = ex.intake
        assert fix is not None, ex.intake_error
        return fix, float(ex._state.response_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", nargs="+", default=["ur10", "ur10e", "ur5e"])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--late-ms", nargs="+", type=float, default=[0.0, 0.25, 0.5, 1.0, 2.0])
    args = ap.parse_args()
    for robot in args.robots:
        t0 = time.perf_counter()
        model = load_delay_model(f"{robot}-sim")
        timing = get_robot_entry(robot).timing
        fixes = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the near-flip warnings are what is counted
            for seed in range(args.seeds):
                fixes.append(probe(robot, seed, model))
            period = fixes[0][0].period_s
            depth = timing.target_echo_cycles(period)
            margins = np.array([f.dated(r).sample_margin_s for f, r in fixes]) * 1e3
            rows = []
            for late in args.late_ms:
                off_resp = off_echo = 0
                worst_echo = 0.0
                for f, r in fixes:
                    g = replace(f, arrival_offset_s=f.arrival_offset_s + late * 1e-3)
                    by_resp = g.dated(r).sample_offset_s
                    by_echo = replace(g, echo_depth_cycles=depth).dated(r).sample_offset_s
                    off_resp += round(by_resp / period) != 0
                    off_echo += round(by_echo / period) != 0
                    worst_echo = max(worst_echo, abs(by_echo))
                rows.append((late, off_resp, off_echo, worst_echo * 1e3))
        n = len(fixes)
        print(f"{robot}: period {period * 1e3:g} ms, echo depth {depth} cycles, {n} probes "
              f"({time.perf_counter() - t0:.1f} s)")  # fmt: skip
        print(f"  mean-response margin: min {margins.min():.2f} ms, 5 % {np.percentile(margins, 5):.2f}"
              f" ms, median {np.median(margins):.2f} ms; under period/8 "
              f"({period / 8 * 1e3:.2f} ms): {np.mean(margins < period / 8 * 1e3) * 100:.1f} %")  # fmt: skip
        print("  packages late by | a period off: mean response | echo | echo's worst |offset|")
        for late, off_resp, off_echo, worst in rows:
            print(f"  {late:12.2f} ms | {off_resp:4d} ({off_resp / n * 100:5.1f} %)"
                  f"         | {off_echo:4d} | {worst:.3f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
