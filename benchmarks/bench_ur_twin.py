"""Stream timing of the UR twin as the real ``ur_rtde`` receive client sees it.

For the e-Series twin (500 Hz) and the CB3 twin (125 Hz) this connects
``rtde_receive.RTDEReceiveInterface``, polls ``getTimestamp()`` every 50 µs for
``--duration`` seconds and reports the host inter-arrival period (mean, std, max), the
packages missed (gaps in the controller time stamps), and the host receipt latency against
the simulated send time. The obvious alternative, a bare ``time.sleep`` loop at 500 Hz in
this process (absolute deadlines, no network, no simulation), runs in the same session;
the ratio of the period standard deviations says what the twin and the client add.

The twin's own cost is reported too: its process CPU time over the wall time of the
measurement (``/proc/<pid>/stat``; a share of one core) and its worst stall, the largest gap
between two consecutive state packages the twin put on the wire (``stats()["max_send_gap_s"]``),
beside the largest gap the client saw.

Run: ``python benchmarks/bench_ur_twin.py [--duration 20] [--only ur10e]``. Figures go to
stdout.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import rtde_receive

from timedexec.sim import ControllerSim
from timedexec.twins import URTwin


def process_cpu_s(pid: int) -> float:
    """CPU time (user + system) a process has used so far, s (Linux ``/proc``)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def measure_twin(robot: str, host: str, duration_s: float) -> dict[str, float]:
    """Stream statistics of one twin read by the real receive client."""
    with URTwin(robot, host, seed=0) as twin:
        recv = rtde_receive.RTDEReceiveInterface(host)
        assert twin.pid is not None
        cpu0, wall0 = process_cpu_s(twin.pid), time.monotonic()
        host_t, stamps = [], []
        last = None
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            ts = recv.getTimestamp()
            if ts != last:
                host_t.append(time.monotonic())
                stamps.append(ts)
                last = ts
            time.sleep(50e-6)
        cpu_share = (process_cpu_s(twin.pid) - cpu0) / (time.monotonic() - wall0)
        recv.disconnect()
        stats = twin.stats()
        t0 = twin.t0_monotonic_s
        period = twin.period_s
    h = np.array(host_t[1:])  # the first read may be a package from before the loop
    c = np.array(stamps[1:])
    sim = ControllerSim(robot, seed=0)
    send = t0 + c + np.array([sim.packing_phase_s(t) for t in c])
    dh = np.diff(h)
    cycles = np.round(np.diff(c) / period).astype(int)
    return {
        "period_s": period,
        "packages": float(len(c)),
        "missed": float(np.sum(cycles - 1)),
        "mean_ms": float(dh.mean() * 1e3),
        "std_ms": float(dh.std() * 1e3),
        "max_ms": float(dh.max() * 1e3),
        "latency_median_ms": float(np.median(h - send) * 1e3),
        "latency_p99_ms": float(np.percentile(h - send, 99) * 1e3),
        "twin_late_sends": float(stats["late_sends"]),
        "twin_max_lateness_ms": float(stats["max_lateness_s"] * 1e3),
        "twin_realtime": float(bool(stats.get("realtime", False))),
        "twin_cpu_percent": 100.0 * cpu_share,
        "twin_max_send_gap_ms": float(stats.get("max_send_gap_s", float("nan")) * 1e3),
    }


def measure_sleep_loop(period_s: float, duration_s: float) -> dict[str, float]:
    """A bare time.sleep loop to absolute deadlines: the baseline."""
    n = int(duration_s / period_s)
    stamps = np.empty(n)
    deadlines = np.empty(n)
    deadline = time.monotonic()
    for i in range(n):
        deadline += period_s
        remaining = deadline - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)
        stamps[i] = time.monotonic()
        deadlines[i] = deadline
    d = np.diff(stamps)
    return {
        "mean_ms": float(d.mean() * 1e3),
        "std_ms": float(d.std() * 1e3),
        "max_ms": float(d.max() * 1e3),
        "late": float(np.sum(stamps - deadlines > 0.5e-3)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per measurement")
    parser.add_argument(
        "--only", choices=("ur10e", "ur10"), default=None, help="measure one twin only"
    )
    args = parser.parse_args(argv)
    d = args.duration
    print(f"UR twin stream timing, {d:.0f} s each, read by ur_rtde's receive interface")
    twins = {"ur10e 500 Hz": ("ur10e", "127.0.0.41"), "ur10 125 Hz": ("ur10", "127.0.0.42")}
    results = {
        name: measure_twin(robot, host, d)
        for name, (robot, host) in twins.items()
        if args.only in (None, robot)
    }
    baseline = measure_sleep_loop(0.002, d)
    header = (
        f"{'stream':<14}{'packages':>9}{'missed':>8}{'mean ms':>9}{'std ms':>8}{'max ms':>8}"
        f"{'lat med ms':>11}{'lat p99 ms':>11}{'late sends':>11}{'RT':>4}"
    )
    print(header)
    for name, r in results.items():
        print(
            f"{name:<14}{r['packages']:>9.0f}{r['missed']:>8.0f}{r['mean_ms']:>9.4f}"
            f"{r['std_ms']:>8.3f}{r['max_ms']:>8.2f}{r['latency_median_ms']:>11.3f}"
            f"{r['latency_p99_ms']:>11.3f}{r['twin_late_sends']:>11.0f}"
            f"{'yes' if r['twin_realtime'] else 'no':>4}"
        )
    print(
        f"{'sleep loop 500':<14}{'':>9}{'':>8}{baseline['mean_ms']:>9.4f}"
        f"{baseline['std_ms']:>8.3f}{baseline['max_ms']:>8.2f}{'':>11}{'':>11}"
        f"{baseline['late']:>11.0f}{'no':>4}"
    )
    for name, r in results.items():
        print(
            f"{name}: twin CPU {r['twin_cpu_percent']:.1f} % of a core; worst stall "
            f"{r['twin_max_send_gap_ms']:.2f} ms between packages sent "
            f"(client saw {r['max_ms']:.2f} ms)"
        )
    if "ur10e 500 Hz" in results:
        ratio = results["ur10e 500 Hz"]["std_ms"] / baseline["std_ms"]
        print(f"period std ratio, twin 500 Hz via ur_rtde / bare sleep loop: {ratio:.2f}")
    print(
        "(lat = host receipt - simulated send time; late sends: twin packages put on the "
        "wire > 0.5 ms after their send time; for the sleep loop: wake-ups > 0.5 ms late)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
