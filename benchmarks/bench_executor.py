"""The executor's 500 Hz loop against the UR twin (UR10e) through the real ur_rtde client.

Runs the TimedExecutor for ``--seconds`` (default 60) streaming back-and-forth joint moves,
then, for the same time, the obvious alternative: a loop paced by the host clock
(``time.sleep`` to the next 2 ms tick, sending the same kind of speedj without waiting for
the state). Prints, for both:

* missed cycles: controller cycles in which no new command reached the register (the
  previous speed held), and overwritten commands (two commands in one cycle: the earlier
  one never acts) — from the send times mapped to the controller clock of the twin
  (``t0_monotonic_s``) plus the loopback latency;
* the executor's send-time error: send time minus the earliest arrival of the package it
  answers (lower-envelope clock model of controller time), percentiles;
* packages replaced inside ur_rtde before the loop read them (sequence gaps).

    python benchmarks/bench_executor.py [--seconds 60] [--host 127.0.0.51] [--no-rt]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

from timedexec._realtime import try_realtime
from timedexec.drivers import URDriver
from timedexec.execution import ExecutorSettings, FixedDelays, StalenessLimits, TimedExecutor
from timedexec.twins import URTwin

PERIOD_S = 0.002
#: Host-to-twin loopback latency used to map a send time to its register cycle, s.
WIRE_S = 0.0003


def register_view(send_s: np.ndarray, t0: float) -> dict[str, float]:
    """Commands per controller cycle over the streaming span."""
    cyc = np.ceil((send_s - t0 + WIRE_S) / PERIOD_S).astype(np.int64)
    span = int(cyc.max() - cyc.min() + 1)
    counts = np.bincount(cyc - cyc.min(), minlength=span)
    return {
        "cycles": span,
        "missed_cycles": int(np.sum(counts == 0)),
        "overwritten_commands": int(np.sum(np.maximum(counts - 1, 0))),
        "missed_fraction": float(np.mean(counts == 0)),
    }


def run_executor(host: str, seconds: float, t0: float, coast: bool) -> dict[str, object]:
    model = FixedDelays(robot="ur10e", actuation_s=0.019, response_s=0.0011, actuation_std_s=6e-4)
    settings = ExecutorSettings(staleness=StalenessLimits.from_stale_periods(100), coast=coast)
    with TimedExecutor(URDriver(host), model, settings) as ex:
        ex.log.clear()
        q0 = ex.estimate().q_rad.copy()
        end = ex.now() + seconds
        k = 0
        while ex.now() < end:
            target = q0.copy()
            target[0] += 0.4 if k % 2 == 0 else 0.0
            target[5] += 0.6 if k % 2 == 0 else 0.0
            plan = ex.prepare(ex.plan(target, start_q_rad=ex.estimate().q_rad))
            ex.execute(plan, start_time_s=ex.now() + ex.lead_time_s(plan) + 0.01, settle_s=0.02)
            k += 1
        timing = ex.log.timing()
        log = ex.log.arrays()
    sends = log["send_s"][np.isfinite(log["send_s"])]
    return {"moves": k, "timing": timing, "register": register_view(sends, t0)}


def run_naive(host: str, seconds: float, t0: float) -> dict[str, object]:
    """Host-clock-paced loop: speedj every 2 ms by time.sleep, not synchronised to the
    controller (the latest package is used when there is one)."""
    sends: list[float] = []
    with URDriver(host) as drv:
        drv.read_state()
        start = time.monotonic()
        tick = start
        k = 0
        while tick - start < seconds:
            tick += PERIOD_S
            delay = tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            phase = (time.monotonic() - start) % 2.0
            v = 0.4 * math.sin(math.pi * phase)
            sends.append(time.monotonic())
            drv.speedj([v, 0, 0, 0, 0, 0], 8.0, 0.1)
            k += 1
        drv.stop(8.0)
    arr = np.asarray(sends)
    lateness = np.diff(arr) - PERIOD_S
    return {
        "commands": k,
        "register": register_view(arr, t0),
        "pacing_error_s": {
            "p50": float(np.percentile(lateness, 50)),
            "p99": float(np.percentile(lateness, 99)),
        },
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--host", default="127.0.0.51")
    p.add_argument("--no-rt", action="store_true", help="do not ask for SCHED_FIFO")
    p.add_argument("--json", help="write the figures as JSON here")
    p.add_argument("--coast", action="store_true", help="executor with coast=True")
    args = p.parse_args(argv)
    rt = False if args.no_rt else try_realtime(5)
    load = os.getloadavg()[0]
    with URTwin("ur10e", args.host, seed=1) as twin:
        ex = run_executor(args.host, args.seconds, twin.t0_monotonic_s, args.coast)
        naive = run_naive(args.host, args.seconds, twin.t0_monotonic_s)
        twin_stats = twin.stats()
    out = {
        "seconds": args.seconds,
        "load_average": load,
        "realtime_priority": rt,
        "executor": ex,
        "naive_sleep_loop": naive,
        "twin": twin_stats,
    }
    t = ex["timing"]
    assert isinstance(t, dict)
    e, n = ex["register"], naive["register"]
    assert isinstance(e, dict)
    assert isinstance(n, dict)
    err = t["send_error_s"]
    print(f"UR10e twin, 500 Hz, {args.seconds:.0f} s per loop, load {load:.1f}, RT {rt}")
    print(
        f"executor : {t['cycles']} packages handled of {t['expected_cycles']} "
        f"({t['missed']} replaced in ur_rtde); register: {e['missed_cycles']} missed cycles "
        f"({e['missed_fraction'] * 100:.2f} %), {e['overwritten_commands']} overwritten"
    )
    parts = " / ".join(f"{k} {v * 1e3:.2f}" for k, v in err.items() if k != "mean")
    print(f"           send-time error (ms): {parts}")
    print(
        f"sleep loop: register: {n['missed_cycles']} missed cycles "
        f"({n['missed_fraction'] * 100:.2f} %), {n['overwritten_commands']} overwritten"
    )
    ratio = (n["missed_cycles"] + n["overwritten_commands"]) / max(
        1, e["missed_cycles"] + e["overwritten_commands"]
    )
    print(f"missed + overwritten, sleep loop / executor: {ratio:.1f}x")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(out, fh, indent=2, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
