"""The intake probe at connect against the independent UR peer: its cost and how well it dates.

Each run starts the independent UR peer (``tests/independent_ur_peer/``, CB3 125 Hz by
default, its package ``--publish-delay`` into the cycle, its cycle at SCHED_FIFO 10 where
allowed, as in ``tests/test_welding.py``), connects a :class:`TimedExecutor` through the
real ur_rtde client (cycle lock, ``realtime_priority=5``), which probes the intake at
connect, probes it once more (``TimedExecutor.probe_intake``, timed) and compares that fix
with the peer's truth: the peer stamps each package with its cycle boundary on
``time.monotonic`` (``t0 + k * period``), so the packages' true sampling offset is the
peer's ``t0``. Per run it prints the probe's cost (s), the trials with an echo, the trials
off the step, the resolution the probe claims and the dating error (``sample_offset_s``
minus the truth, modulo one period, ms): what ``sampling_times_s`` dates the reported
positions by. Quiet, then with ``--busy`` busy processes (``python -c 'while True:
pass'``) beside it.

    python benchmarks/bench_intake_probe.py [--runs 8] [--loads quiet,loaded] [--busy 2]
        [--version 3.15.7] [--publish-delay 0.0005] [--host-base 127.0.0.21] [--json F]

Measured (2026-11-28, the shared two-core VM, others' jobs running; CB3, package 0.5 ms
in): see the commit that added this file and the report of the wt-rtlock session.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from timedexec.drivers import URDriver
from timedexec.errors import DriverError
from timedexec.execution import ExecutorSettings, TimedExecutor


def busy(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def one_run(host: str, version: str, publish_delay_s: float) -> dict[str, Any]:
    """One connect against a fresh peer (which probes), then one more probe timed: its cost
    and its fix against the truth."""
    from independent_ur_peer import run_peer

    extra = ("--publish-delay", str(publish_delay_s), "--rt-priority", "10")
    row: dict[str, Any] = {"probe_s": math.nan, "error": None}
    with run_peer(host, model="UR10", version=version, extra_args=extra) as peer:
        settings = ExecutorSettings(cycle_lock=True, coast=True, realtime_priority=5)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with TimedExecutor(URDriver(host, robot="ur10"), "ur10-sim", settings) as ex:
                t = time.monotonic()
                try:
                    fix = ex.probe_intake()
                except DriverError as exc:
                    fix, row["error"] = None, str(exc)
                row["probe_s"] = time.monotonic() - t
                period = ex.period_s
                t0 = peer.to_host_times([0.0])[0]  # the peer's boundary k * period here
    if fix is not None:
        dating = (fix.sample_offset_s - t0 + 0.5 * period) % period - 0.5 * period
        row |= {
            "trials": fix.trials,
            "mismatches": fix.mismatches,
            "resolution_ms": fix.resolution_s * 1e3,
            "dating_error_ms": dating * 1e3,
        }
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=8, help="connects per load")
    p.add_argument("--loads", default="quiet,loaded")
    p.add_argument("--busy", type=int, default=2, help="busy processes in the loaded phase")
    p.add_argument("--version", default="3.15.7", help="peer version (3.x: CB3 125 Hz)")
    p.add_argument("--publish-delay", type=float, default=0.0005, help="s into the cycle")
    p.add_argument("--host-base", default="127.0.0.21", help="first of the loopback hosts")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    prefix, first = args.host_base.rsplit(".", 1)
    results: dict[str, list[dict[str, Any]]] = {}
    k = 0
    for load in args.loads.split(","):
        procs = busy(args.busy) if load == "loaded" else []
        try:
            rows = []
            for _ in range(args.runs):
                rows.append(one_run(f"{prefix}.{int(first) + k % 40}", args.version, args.publish_delay))  # fmt: skip
                k += 1
                r = rows[-1]
                if r["error"] is None and "dating_error_ms" in r:
                    print(f"{load:6s} probe {r['probe_s']:.3f} s  trials {r['trials']:2d}  off "
                          f"{r['mismatches']:2d}  resolution {r['resolution_ms']:.3f} ms  "
                          f"dating {r['dating_error_ms']:+.3f} ms", flush=True)  # fmt: skip
                else:
                    print(f"{load:6s} no fix: {str(r['error'])[:150]}", flush=True)
        finally:
            for proc in procs:
                proc.kill()
                proc.wait()
        results[load] = rows
        ok = [r for r in rows if "dating_error_ms" in r]
        if ok:
            cost = np.array([r["probe_s"] for r in ok])
            err = np.array([r["dating_error_ms"] for r in ok])
            within = sum(abs(r["dating_error_ms"]) < r["resolution_ms"] + 0.15 for r in ok)
            print(f"{load}: {len(ok)}/{len(rows)} fixes, probe {np.median(cost):.3f} s median "
                  f"({cost.min():.3f}-{cost.max():.3f}), dating {err.min():+.3f} to "
                  f"{err.max():+.3f} ms, {within}/{len(ok)} within resolution + 0.15 ms")  # fmt: skip
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
