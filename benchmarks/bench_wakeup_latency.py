"""The machine's own wake-up latency at 500 Hz: the floor under every send-time figure.

Issue 15 asks a send-time error p99 <= 0.5 ms of the executor's 500 Hz loop. No user-space
sender can be more punctual than the operating system wakes it: this measures that floor on
the machine at hand, in the same run, two ways, quiet and beside two busy processes
(``python -c 'while True: pass'``):

* **os**: ``cyclictest`` (rt-tests, the Linux real-time community's latency test; C, a
  ``clock_nanosleep`` to absolute deadlines every 2 ms, memory locked) at SCHED_FIFO
  ``--priority``. Skipped, with a note, when it is not installed (``apt-get install
  rt-tests``).
* **python**: the executor's own wait (``timedexec._realtime.wait_until``: sleep to
  just before the deadline, spin the rest) to absolute deadlines every 2 ms, same priority,
  without the PM QoS request;
* **python+qos**: the same while holding the request (``timedexec._realtime.fast_wakeup``),
  as the executor does on a real-time driver.

Per phase and source: the lateness after each deadline, p50 / p99 / p99.9 / max, the share of
cycles later than 0.5 ms, and the hypervisor's steal time over the phase (``/proc/stat``: CPU
time the host gave to other guests). The ratio python/os p99 says how much of the floor is
Python's; if the os p99 itself is above 0.5 ms, the target cannot be met on this machine by
any sender, ours or ur_rtde's ``initPeriod/waitPeriod``.

    python benchmarks/bench_wakeup_latency.py [--seconds 30] [--priority 5] [--json F]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from timedexec._realtime import fast_wakeup, realtime, wait_until

PERIOD_S = 0.002
LATE_S = 0.0005  # the p99 target


def steal_jiffies() -> tuple[int, int]:
    """(steal, total) CPU jiffies of the whole machine so far (``/proc/stat``'s cpu line)."""
    with open("/proc/stat", encoding="ascii") as f:
        fields = [int(x) for x in f.readline().split()[1:]]
    return fields[7] if len(fields) > 7 else 0, sum(fields[:8])


@contextlib.contextmanager
def busy(n: int) -> Iterator[None]:
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        time.sleep(0.5 if n else 0.0)
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def python_lateness(seconds: float, priority: int) -> tuple[np.ndarray, bool]:
    """Lateness (s) of the executor's wait at each 2 ms deadline for ``seconds``."""
    n = int(seconds / PERIOD_S)
    late = np.empty(n)
    with realtime(priority) as granted:
        t0 = time.monotonic() + 0.01
        for k in range(n):
            target = t0 + k * PERIOD_S
            late[k] = wait_until(target) - target
    return late, granted


def os_lateness(seconds: float, priority: int) -> np.ndarray | None:
    """Lateness (s) histogram of cyclictest at 2 ms, expanded to samples (None: missing)."""
    exe = shutil.which("cyclictest")
    if exe is None:
        return None
    cmd = [exe, "-q", "-m", f"-p{priority}", f"-i{round(PERIOD_S * 1e6)}",
           f"-D{max(1, round(seconds))}", "-h20000"]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        print(f"cyclictest failed ({out.returncode}): {out.stderr.strip()[:200]}")
        return None
    us, counts, overflow = [], [], 0
    for line in out.stdout.splitlines():
        if line.startswith("# Histogram Overflows:"):
            overflow = int(line.split(":")[1].split()[0])
        elif line and not line.startswith("#"):
            a, b = line.split()[:2]
            if int(b):
                us.append(int(a))
                counts.append(int(b))
    samples = np.repeat(np.array(us, dtype=float) * 1e-6, counts)
    return np.concatenate([samples, np.full(overflow, 0.02)])  # overflow: >= 20 ms


def figures(late: np.ndarray) -> dict[str, float]:
    q = np.percentile(late, [50, 99, 99.9]) * 1e3
    return {"p50_ms": float(q[0]), "p99_ms": float(q[1]), "p999_ms": float(q[2]),
            "max_ms": float(late.max() * 1e3), "late_share": float(np.mean(late > LATE_S))}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="per phase and source")
    ap.add_argument("--priority", type=int, default=5, help="SCHED_FIFO priority")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    print(f"{args.seconds:.0f} s per phase and source, 2 ms deadlines, SCHED_FIFO {args.priority}")
    print("| phase | source | p50 | p99 | p99.9 | max (ms) | later than 0.5 ms | steal |")
    print("|---|---|---|---|---|---|---|---|")
    for phase, n_busy in (("quiet", 0), ("2 busy", 2)):
        with busy(n_busy):
            for source in ("os", "python", "python+qos"):
                s0 = steal_jiffies()
                if source == "os":
                    late = os_lateness(args.seconds, args.priority)
                    note = "" if late is not None else "cyclictest not installed (rt-tests)"
                else:
                    with (
                        fast_wakeup()
                        if source == "python+qos"
                        else contextlib.nullcontext(False) as qos
                    ):
                        late, granted = python_lateness(args.seconds, args.priority)
                    note = "" if granted else "SCHED_FIFO refused: normal priority"
                    if source == "python+qos" and not qos:
                        note += " PM QoS request refused"
                s1 = steal_jiffies()
                steal = (s1[0] - s0[0]) / max(s1[1] - s0[1], 1)
                if late is None:
                    print(f"| {phase} | {source} | {note} | | | | | |")
                    continue
                f = figures(late)
                rows.append({"phase": phase, "source": source, "steal": steal, "note": note, **f})
                print(f"| {phase} | {source} | {f['p50_ms']:.3f} | {f['p99_ms']:.3f} | "
                      f"{f['p999_ms']:.3f} | {f['max_ms']:.2f} | {100 * f['late_share']:.2f} % | "
                      f"{100 * steal:.1f} % |{' ' + note if note else ''}", flush=True)  # fmt: skip
    for phase in ("quiet", "2 busy"):
        by = {r["source"]: r for r in rows if r["phase"] == phase}
        if {"os", "python", "python+qos"} <= by.keys():
            os_p99 = max(by["os"]["p99_ms"], 1e-3)
            print(f"{phase}: p99 / cyclictest's: python {by['python']['p99_ms'] / os_p99:.2f}, "
                  f"python+qos {by['python+qos']['p99_ms'] / os_p99:.2f}")  # fmt: skip
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
