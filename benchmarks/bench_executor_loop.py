"""The executor's 500 Hz loop vs ur_rtde's own initPeriod/waitPeriod servoJ pattern.

Both run against the same UR10e twin (its own process) through the real ur_rtde client, in
the same run, one after the other, quiet and with two busy processes
(``python -c 'while True: pass'``):

* **executor**: :class:`TimedExecutor` (cycle-locked sender, SCHED_FIFO 5 where allowed)
  streaming back-and-forth moves of joints 1 and 6, with tolerant staleness limits (200 ms)
  and watchdog (2 s) so that the loop's timing, not its faults, is measured (faults are
  counted and recovered from);
* **coasting**: the cycle-locked executor with ``coast=True``: a cycle whose package has
  not arrived by the send time gets its command from the estimate, on time;
* **unlocked**: the same executor sending as soon as each package is handled
  (``cycle_lock=False``), the pre-issue-15 behaviour;
* **ur_rtde**: ``t = initPeriod(); servoJ(q, 0, 0, 0.002, 0.1, 300); waitPeriod(t)`` on a
  sinusoid of joint 1 — the pattern ur_rtde's examples use, same priority.

``--peer`` runs the same phases against the independently written UR peer
(``tests/independent_ur_peer/``: the real control script's semantics, standard library
only) instead of the twin: it costs about a quarter of a core at 500 Hz where the twin costs
0.8, so on a two-core machine the loops are measured rather than the controller's starvation
(its input log gives each package's arrival and the cycle that took it).

Per phase it prints: missed cycles (controller cycles of the streaming span whose register
got no new command, from the twin's truth: each command the twin took has ``arrival_s``
and ``intake_s``) and overwritten commands (sent minus taken); the send-time error
(actual minus intended send time: the cycle-locked target for the executor, ``initPeriod``
+ k periods for ur_rtde) p50/p99; the histogram of the command arrival phase within the
controller cycle (``intake_s - arrival_s``: how long before the boundary that took it the
command arrived; the middle of the window is 1 ms); the twin's CPU use and worst stall
(largest gap between two packages it put on the wire, cumulative over the run); the
executor's own work per cycle (p50/p99) and what its cycle leaves allocated (tracemalloc, on
the in-process simulator, files of ``timedexec/execution`` only).

    python benchmarks/bench_executor_loop.py [--seconds 60] [--host 127.0.0.52] [--peer]
        [--loops executor,coasting,unlocked,ur_rtde] [--warmup 110] [--round-trip 0.0004]
        [--json F]

``--warmup S`` runs each executor loop S seconds unmeasured first, so that the cycle lock's
long-term clock line (``BoundaryLine``: 100 s of arrivals) is in use when it is measured.
Since the eleventh session the lock aims by the controller's probed intake from connect
(``TimedExecutor.probe_intake``), which needs no warm-up; each executor row says whether
the probe answered.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._realtime import fast_wakeup, realtime
from timedexec.drivers import SimDriver, URDriver
from timedexec.errors import ConfigError, DriverError
from timedexec.execution import (
    ExecutorSettings,
    FixedDelays,
    StalenessLimits,
    TimedExecutor,
    intake_echo,
)
from timedexec.twins import URTwin, read_truth

PERIOD_S = 0.002
RT_PRIORITY = 5
MODEL = FixedDelays(robot="ur10e", actuation_s=0.019, response_s=0.0011, actuation_std_s=6e-4)
PHASE_BINS_MS = np.linspace(0.0, 2.0, 11)
#: The executor's default round trip (boundary -> package -> command back), s.
DEFAULT_ROUND_TRIP_S = ExecutorSettings().round_trip_s


def cpu_s(pid: int | None) -> float:
    """User + system CPU seconds of process ``pid`` so far (NaN if unknown)."""
    if pid is None:
        return math.nan
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return math.nan


def twin_commands(truth: Path, t0: float, span: tuple[float, float]) -> dict[str, Any]:
    """The twin's view of the commands whose arrival (host time) lies in ``span``."""
    _, commands = read_truth(truth)
    arr, intake = [], []
    for r in commands.values():
        a, i = r.get("arrival_s"), r.get("intake_s")
        if a is None or i is None or not (span[0] <= t0 + a <= span[1]):
            continue
        arr.append(float(a))
        intake.append(float(i))
    return taken_commands(np.asarray(arr), np.asarray(intake))


def peer_commands(log: Path, peer: Any, span: tuple[float, float]) -> dict[str, Any]:
    """The independent peer's input log (arrival, intake; controller s) over ``span``."""
    rows = np.loadtxt(log, delimiter=",", ndmin=2) if log.stat().st_size else np.empty((0, 3))
    lo, hi = peer.to_peer_time(span[0]), peer.to_peer_time(span[1])
    keep = (rows[:, 0] >= lo) & (rows[:, 0] <= hi)
    # The peer reads its inputs when its cycle runs, at or after the boundary: the phase is
    # measured against that read.
    return taken_commands(rows[keep, 0], rows[keep, 1], rows[keep, 2])


def taken_commands(a: np.ndarray, i: np.ndarray, read: np.ndarray | None = None) -> dict[str, Any]:
    """Missed cycles and arrival phases of commands that arrived at ``a`` and were taken at
    the cycle boundary ``i`` (controller s), read by the controller at ``read`` (default
    the boundary); ``same_cycle``: packages another one replaced before its cycle read it."""
    if len(i) < 2:
        return {"taken": len(i)}
    cycles = np.round(i / PERIOD_S).astype(np.int64)
    distinct = np.unique(cycles)
    expected = int(distinct.max() - distinct.min() + 1)
    before_ms = ((i if read is None else read) - a) * 1e3
    hist, _ = np.histogram(before_ms, bins=PHASE_BINS_MS)
    return {
        "taken": len(i),
        "cycles": expected,
        "missed_cycles": expected - len(distinct),
        "missed_fraction": (expected - len(distinct)) / expected,
        "same_cycle": len(i) - len(distinct),
        "phase_before_boundary_ms": {
            "p1": float(np.percentile(before_ms, 1)),
            "p50": float(np.percentile(before_ms, 50)),
            "p99": float(np.percentile(before_ms, 99)),
            "within_0.3ms_of_boundary": float(np.mean((before_ms < 0.3) | (before_ms > 1.7))),
        },
        "phase_histogram": hist.tolist(),
    }


#: Tolerant limits for a timing benchmark on a shared two-core machine (as
#: bench_executor.py's 100 periods): a stalled stream is then rare, not the figure.
BENCH_STALENESS = StalenessLimits(floor_s=0.2, ceiling_s=0.2)
#: Long enough that preparing the next plan (GP predictions, Ruckig) between moves, when the
#: loop does not step, never trips it: at 0.3 s it tripped at rest six times in 20 s and each
#: re-arm (a script upload) made the next start late. The benchmark measures the loop's
#: timing; the watchdog's own behaviour is tested in tests/test_execution_safety.py.
BENCH_WATCHDOG_S = 2.0


def run_executor(
    host: str,
    seconds: float,
    *,
    lock: bool = True,
    coast: bool = False,
    warmup_s: float = 0.0,
    round_trip_s: float = DEFAULT_ROUND_TRIP_S,
    on_start: Callable[[], None] = lambda: None,
) -> dict[str, Any]:
    settings = ExecutorSettings(
        realtime_priority=RT_PRIORITY,
        round_trip_s=round_trip_s,
        cycle_lock=lock,
        coast=coast,
        staleness=BENCH_STALENESS,
        watchdog_timeout_s=BENCH_WATCHDOG_S,
    )
    with TimedExecutor(URDriver(host), MODEL, settings) as ex:
        ex.idle(ex.now() + 0.3)
        q0 = ex.estimate().q_rad.copy()
        k = 0
        faults: list[str] = []

        def moves(end: float) -> None:
            nonlocal k
            while ex.now() < end:
                target = q0.copy()
                target[0] += 0.4 if k % 2 == 0 else 0.0
                target[5] += 0.6 if k % 2 == 0 else 0.0
                plan = ex.prepare(ex.plan(target, start_q_rad=ex.estimate().q_rad))
                try:
                    ex.execute(
                        plan, start_time_s=ex.now() + ex.lead_time_s(plan) + 0.01, settle_s=0.02
                    )
                except (DriverError, ConfigError) as exc:
                    # A loaded machine: a stale stream, a watchdog trip, a start made late
                    # by a re-arm. Counted; recover (at rest, watchdog re-armed) and go on.
                    faults.append(str(exc)[:120])
                    for _ in range(3):
                        try:
                            ex.recover()
                            break
                        except DriverError as again:
                            faults.append(f"recover: {str(again)[:100]}")
                k += 1

        # The same moves while the clock line gathers its span (not measured).
        moves(ex.now() + warmup_s)
        ex.log.clear()
        faults.clear()
        k = 0
        coasted0 = ex.coasted
        on_start()
        start = ex.now()
        moves(start + seconds)
        stop = ex.now()
        log = ex.log.arrays()
        work = ex.log.work()
        phase = ex.send_phase
        rt = ex.realtime
        gcp = ex.gc_pauses
        coasted = ex.coasted - coasted0
        line = ex.clock_line
        intake = ex.intake.summary() if ex.intake is not None else {"error": ex.intake_error}
    sent = np.isfinite(log["send_s"])
    from scipy.ndimage import minimum_filter1d

    off = np.where(log["coasted"], np.inf, log["arrival_s"] - log["controller_s"])
    env = minimum_filter1d(off, size=250, mode="nearest")
    offset = phase.offset_s if phase is not None else 0.0
    # The locked loop logs its target (the clock line's, once it has one); the unlocked
    # loop's intended time is the package's earliest arrival.
    intended = np.where(
        np.isfinite(log["target_s"]), log["target_s"], log["controller_s"] + env + offset
    )
    err = (log["send_s"] - intended)[sent]
    w = work[np.isfinite(work)]
    if not len(err):
        err = w = np.full(1, math.nan)
    return {
        "span": (start, stop),
        "moves": k,
        "faults": faults,
        "commands": int(sent.sum()),
        "coasted": coasted,
        "clock_line": line is not None,
        "intake": intake,
        "echo": intake_echo(log),
        "realtime": rt,
        "send_error_ms": {f"p{p}": float(np.percentile(err, p) * 1e3) for p in (50, 99)},
        "work_us": {f"p{p}": float(np.percentile(w, p) * 1e6) for p in (50, 99)},
        "gc": {"count": gcp.count, "max_ms": gcp.max_s * 1e3} if gcp is not None else {},
    }


def run_ur_rtde(
    host: str, seconds: float, on_start: Callable[[], None] = lambda: None, **_: Any
) -> dict[str, Any]:
    """ur_rtde's own pattern: initPeriod / servoJ / waitPeriod."""
    import rtde_control
    import rtde_receive

    with realtime(RT_PRIORITY) as rt:
        recv = rtde_receive.RTDEReceiveInterface(host)
        ctrl = rtde_control.RTDEControlInterface(host)
    try:
        q0 = np.asarray(recv.getActualQ(), float)
        sends = np.empty(int(seconds / PERIOD_S) + 10)
        ticks = np.empty_like(sends)
        n = 0
        on_start()
        start = time.monotonic()
        while n < len(sends) - 1 and time.monotonic() - start < seconds:
            t = ctrl.initPeriod()
            ticks[n] = time.monotonic()
            q = q0.copy()
            q[0] += 0.2 * math.sin(2 * math.pi * 0.5 * (ticks[n] - start))
            sends[n] = time.monotonic()
            ctrl.servoJ(list(q), 0.0, 0.0, PERIOD_S, 0.1, 300.0)
            ctrl.waitPeriod(t)
            n += 1
        stop = time.monotonic()
        ctrl.servoStop(2.0)
        ctrl.stopScript()
    finally:
        ctrl.disconnect()
        recv.disconnect()
    s = sends[:n]
    # Intended: waitPeriod ends one period after the previous initPeriod (ur_rtde keeps no
    # absolute schedule), and the command leaves right after initPeriod.
    err = np.diff(s) - PERIOD_S
    return {
        "span": (start, stop),
        "commands": n,
        "realtime": rt,
        "send_error_ms": {f"p{p}": float(np.percentile(err, p) * 1e3) for p in (50, 99)},
    }


def allocations_per_cycle(cycles: int = 3000) -> dict[str, float]:
    """What the streaming cycle leaves allocated in ``timedexec/execution`` files
    (tracemalloc; virtual-time simulator, 2 kHz physics; the simulator's own allocations
    excluded): blocks alive after ``cycles`` and after three times as many, and the growth
    per cycle between the two. Measured: ~0.4 B per cycle, the clock line's window filling
    (an earliest arrival per 0.5 s, bounded at 120 s: 60,000 cycles); the rest alive is
    bounded too (numpy's small-array caches). The cycle log (``_log.py``), a record that
    doubles its arrays as it fills, is left out; 1,000 cycles run first. Caution: the
    simulator keeps a truth event (two small arrays) per command, up to 10,000, and numpy
    hands them buffers from its caches that a temporary of the executor's malloc'ed first:
    tracemalloc then blames the executor's line. After the tasks split (the command's
    temporaries in another order) that read 16 B per cycle (1 block) where main read 0.4;
    with the simulator's truth events dropped, 51 blocks stayed alive after 3,000 cycles,
    54 on main: no growth of the executor's own."""
    drv = SimDriver("ur10e", seed=1, physics_rate_hz=2000)
    flt = [
        tracemalloc.Filter(True, "*timedexec/execution/*"),
        tracemalloc.Filter(False, "*timedexec/execution/_log.py"),
    ]
    with TimedExecutor(drv, MODEL) as ex:
        q0 = ex.estimate().q_rad.copy()
        target = q0.copy()
        target[0] += 1.5
        plan = ex.prepare(ex.plan(target, minimum_duration_s=25.0))  # streams throughout
        ex.schedule(plan, ex.now() + ex.lead_time_s(plan) + 0.01)
        for _ in range(1000):
            ex.step()
        tracemalloc.start(1)
        snaps = [tracemalloc.take_snapshot().filter_traces(flt)]
        for n in (cycles, 2 * cycles):
            for _ in range(n):
                ex.step()
            snaps.append(tracemalloc.take_snapshot().filter_traces(flt))
        streaming = bool(np.isfinite(ex.log.arrays()["send_s"][-1]))
        tracemalloc.stop()

    def alive(a: Any, b: Any) -> tuple[int, int]:
        stats = b.compare_to(a, "filename")
        return sum(st.size_diff for st in stats), sum(st.count_diff for st in stats)

    bytes1, blocks1 = alive(snaps[0], snaps[1])
    bytes2, blocks2 = alive(snaps[0], snaps[2])
    return {
        "cycles": cycles,
        "streaming_throughout": streaming,
        "blocks_alive_after": blocks1,
        "blocks_alive_after_3x": blocks2,
        "growth_bytes_per_cycle": (bytes2 - bytes1) / (2 * cycles),
    }


def run_unlocked(host: str, seconds: float, **kw: Any) -> dict[str, Any]:
    return run_executor(host, seconds, lock=False, **kw)


def run_coasting(host: str, seconds: float, **kw: Any) -> dict[str, Any]:
    return run_executor(host, seconds, coast=True, **kw)


RUNS = (
    ("executor", run_executor),
    ("coasting", run_coasting),
    ("unlocked", run_unlocked),
    ("ur_rtde", run_ur_rtde),
)


def busy(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--host", default="127.0.0.52")
    p.add_argument(
        "--round-trip",
        type=float,
        default=DEFAULT_ROUND_TRIP_S,
        help="the executor's round_trip_s, s: boundary -> package -> command back (default: "
        "the loopback twin's shortest)",
    )
    p.add_argument(
        "--warmup",
        type=float,
        default=0.0,
        help="seconds each executor loop streams before it is measured: >= 105 lets the "
        "cycle lock's long-term clock line form (LINE_MIN_SPAN_S + a refit); ur_rtde's "
        "pattern has no lock and starts at once",
    )
    p.add_argument("--busy", type=int, default=2, help="busy processes in the loaded phase")
    p.add_argument(
        "--twin-rt",
        type=int,
        default=10,
        help="SCHED_FIFO priority of the twin's (or the peer's) cycle where allowed (default "
        "10, as a controller's cycle; the clients get 5)",
    )
    p.add_argument(
        "--peer",
        action="store_true",
        help="run against the independent UR peer (tests/independent_ur_peer/), not the twin",
    )
    p.add_argument(
        "--loops",
        default=",".join(name for name, _ in RUNS),
        help="comma list of the loops to run (default: all)",
    )
    p.add_argument("--json", help="write the figures as JSON here")
    args = p.parse_args(argv)
    unknown = set(args.loops.split(",")) - {name for name, _ in RUNS}
    if unknown:
        p.error(f"--loops: unknown {sorted(unknown)}; choose from {[n for n, _ in RUNS]}")
    runs = [(name, run) for name, run in RUNS if name in args.loops.split(",")]
    out: dict[str, Any] = {
        "seconds": args.seconds,
        "warmup_s": args.warmup,
        "round_trip_s": args.round_trip,
        "load_average_start": os.getloadavg()[0],
    }
    out["controller"] = "independent peer" if args.peer else "UR10e twin"
    out["loops"] = [name for name, _ in runs]
    out["allocations"] = allocations_per_cycle()
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        # Every loop under the same wake-up policy: the CPUs kept out of deep idle states
        # for the whole run (system-wide), as on a real-time PC; the executor would hold it
        # itself, ur_rtde's pattern would not.
        out["fast_wakeup"] = stack.enter_context(fast_wakeup())
        if args.peer:
            sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
            from independent_ur_peer import run_peer

            log = Path(tmp) / "inputs.csv"
            peer = stack.enter_context(
                run_peer(args.host, model="UR10", version="5.11.1",
                         extra_args=("--input-log", str(log),
                                     "--rt-priority", str(args.twin_rt)))
            )  # fmt: skip
            pid = peer.process.pid

            def commands(span: tuple[float, float]) -> dict[str, Any]:
                return peer_commands(log, peer, span)

            def stats() -> dict[str, float]:
                return {"max_send_gap_s": math.nan, "max_lateness_s": math.nan}
        else:
            truth = Path(tmp) / "truth.jsonl"
            twin = stack.enter_context(
                URTwin("ur10e", args.host, seed=1, truth_path=truth, rt_priority=args.twin_rt)
            )
            pid = twin.pid

            def commands(span: tuple[float, float]) -> dict[str, Any]:
                return twin_commands(truth, twin.t0_monotonic_s, span)

            def stats() -> dict[str, float]:
                return dict(twin.stats())

        for load in ("quiet", "loaded"):
            procs = busy(args.busy) if load == "loaded" else []
            try:
                for name, run in runs:
                    c0 = math.nan

                    def mark() -> None:  # the measured span starts (after any warm-up)
                        nonlocal c0
                        c0 = cpu_s(pid)

                    try:
                        res = run(
                            args.host,
                            args.seconds,
                            warmup_s=args.warmup,
                            round_trip_s=args.round_trip,
                            on_start=mark,
                        )
                    except (DriverError, ConfigError) as exc:
                        # a phase that cannot run is reported, the others still measured
                        out[f"{name}_{load}"] = {"error": str(exc)}
                        continue
                    c1 = cpu_s(pid)
                    span = res.pop("span")
                    time.sleep(0.1)  # the truth file is flushed every 10 ms
                    res["twin"] = commands(span)
                    # the twin's truth holds commands (taken or superseded); the peer's log
                    # every input package (watchdog kicks and register clears too)
                    res["twin"]["overwritten"] = (
                        res["twin"].get("same_cycle", 0)
                        if args.peer
                        else res["commands"] - res["twin"]["taken"]
                    )
                    st = stats()
                    res["twin_cpu_percent"] = 100 * (c1 - c0) / (span[1] - span[0])
                    res["twin_worst_send_gap_ms"] = 1e3 * float(st["max_send_gap_s"])
                    res["twin_max_lateness_ms"] = 1e3 * float(st["max_lateness_s"])
                    res["load_average"] = os.getloadavg()[0]
                    out[f"{name}_{load}"] = res
            finally:
                for proc in procs:
                    proc.kill()
                    proc.wait()
    report(out)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(out, fh, indent=2, default=float)
    return 0


def report(out: dict[str, Any]) -> None:
    print(
        f"{out['controller']}, 500 Hz, {out['seconds']:.0f} s per loop and load (after "
        f"{out.get('warmup_s', 0):.0f} s of warm-up for the executor's loops); CPUs kept "
        f"out of deep idle (/dev/cpu_dma_latency 0): {'yes' if out['fast_wakeup'] else 'no'}"
    )
    a = out["allocations"]
    print(
        f"executor allocations (timedexec/execution, cycle log aside): "
        f"{a['blocks_alive_after']} blocks alive after {a['cycles']} cycles, "
        f"{a['blocks_alive_after_3x']} after {3 * a['cycles']}; growth "
        f"{a['growth_bytes_per_cycle']:.2f} B per cycle"
    )
    head = (
        f"{'loop':9} {'load':7} {'loadavg':>7} {'RT':>3} {'missed %':>8} {'overwr':>6} "
        f"{'send err p50/p99 ms':>20} {'phase p1/p50/p99 ms':>20} {'<0.3ms':>6} "
        f"{'work p50/p99 us':>16} {'twin CPU':>8} {'twin stall':>10}"
    )
    print(head)
    for load in ("quiet", "loaded"):
        for name in out["loops"]:
            r = out[f"{name}_{load}"]
            if "error" in r:
                print(f"{name:9} {load:7} failed: {r['error']}")
                continue
            t = r["twin"]
            ph = t.get("phase_before_boundary_ms", {})
            e = r["send_error_ms"]
            w = r.get("work_us", {})
            work = f"{w['p50']:.0f}/{w['p99']:.0f}" if w else "-"
            print(
                f"{name:9} {load:7} {r['load_average']:7.1f} {'y' if r['realtime'] else 'n':>3} "
                f"{100 * t.get('missed_fraction', math.nan):8.2f} {t.get('overwritten', 0):6d} "
                f"{e['p50']:9.3f}/{e['p99']:<9.3f} "
                f"{ph.get('p1', math.nan):6.2f}/{ph.get('p50', math.nan):.2f}/"
                f"{ph.get('p99', math.nan):<6.2f} "
                f"{100 * ph.get('within_0.3ms_of_boundary', math.nan):5.1f}% {work:>16} "
                f"{r['twin_cpu_percent']:7.1f}% {r['twin_worst_send_gap_ms']:8.1f}ms"
            )
            gc_note = ""
            if r.get("gc"):
                gc_note = f"; {r['gc']['count']} collections, longest {r['gc']['max_ms']:.2f} ms"
            if r.get("coasted"):
                gc_note += f"; {r['coasted']} of {r['commands']} commands from the estimate"
            if "clock_line" in r:
                gc_note += f"; clock line {'in use' if r['clock_line'] else 'not yet'}"
            echo = r.get("echo") or {}
            if echo.get("matched"):
                gc_note += (
                    f"; target_qd echo: {100 * echo['missed_fraction']:.2f} % of {echo['matched']}"
                    f" cycles ({100 * echo['coverage']:.0f} % of the packages) took no new"
                    f" command, {echo['overwritten']} overwritten"
                )
            intake = r.get("intake") or {}
            if "deadline_offset_ms" in intake:
                gc_note += (
                    f"; intake probed ({intake['trials']} echoes, {intake['mismatches']} off"
                    f" the step, packages {intake['package_lead_ms']:.2f} ms after a deadline)"
                )
            elif intake:
                gc_note += f"; intake not probed: {intake.get('error')}"
            print(
                f"{'':17} arrival phase histogram (ms before boundary, 0.2 ms bins): "
                f"{t.get('phase_histogram')}{gc_note}"
            )
    for load in ("quiet", "loaded"):
        ex = out.get(f"executor_{load}", {}).get("twin", {})
        ur = out.get(f"ur_rtde_{load}", {}).get("twin", {})
        if "missed_fraction" in ex and "missed_fraction" in ur:
            ratio = ur["missed_fraction"] / max(ex["missed_fraction"], 1e-9)
            print(f"{load}: missed cycles, ur_rtde / executor = {ratio:.2f}x")


if __name__ == "__main__":
    sys.exit(main())
