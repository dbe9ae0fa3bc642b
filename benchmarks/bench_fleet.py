"""The fleet on a real Dask LocalCluster: 1 vs 2 workers on the same fleet, and one robot's cost.

1. **Scaling** (issue 18: speed-up >= 1.7x on 2 cores, scheduler overhead <= 5 % of task
   time). The same fleet (``--robots`` simulated recordings made beforehand, so that the
   run reads recordings as a real fleet does) runs through ``run_fleet`` in this process
   (``jobs=1``, no Dask: the baseline), then on a ``LocalCluster`` of 1 and of 2 worker
   processes (1 thread each), ``--repeat`` times alternating, workers warmed up (modules
   imported) as a long-lived cluster's are. Printed per configuration: the wall time
   (median of the repeats), the speed-up of 2 workers over 1, the peak RSS of each worker
   process (``ru_maxrss``), and from Dask's task stream the task time (a robot's
   ``compute``) and the **scheduler overhead per task**: the time a worker sat idle
   between finishing one robot and starting the next while robots were still waiting,
   plus the time from submitting to the first start and from the last finish to the
   client having the result, per task. The fleet tables of every run are compared byte by
   byte with the baseline's.

   ``--malloc dask`` keeps the nanny's ``MALLOC_TRIM_THRESHOLD_=65536`` (Dask's default;
   with it glibc stops adapting its mmap threshold and numpy's large temporaries are
   mapped and faulted in afresh each time), ``--malloc glibc`` leaves glibc's default
   (docs/fleet.md recommends it for timedexec workers).

2. **One robot's cost** (``--cost TRIALS``): one robot's stages in a fresh process (CPU
   seconds, wall seconds, peak RSS, bytes read per stage; recording size), for docs/fleet.md.

The machine this ran on may be shared: the load average is printed before and after.

Usage: python benchmarks/bench_fleet.py [--robots 6] [--trials 800] [--repeat 3]
       [--methods median,rt,gpr] [--folds 5] [--malloc glibc|dask]
       python benchmarks/bench_fleet.py --cost 8000 [--methods median,nn,rt,gpr] [--folds 10]
"""

from __future__ import annotations

import argparse
import filecmp
import itertools
import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from timedexec.fleet import FleetSettings, run_fleet

ROBOTS = ("ur10", "kr5", "ur10e")


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _source_fingerprint() -> str:
    """sha256 of timedexec's source as imported: a run compares tables only with runs of
    the same code (on a shared checkout, others may edit it meanwhile)."""
    import hashlib

    import timedexec

    h = hashlib.sha256()
    for path in sorted(Path(timedexec.__file__).parent.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def _two_worker_makespan(tasks: list[float]) -> float:
    """Makespan of the given task times on 2 idle workers, dispatched in order to whichever
    is free first (what Dask does with equal priorities)."""
    free = [0.0, 0.0]
    for t in tasks:
        i = free.index(min(free))
        free[i] += t
    return max(free)


def _make_fleet(folder: Path, robots: int, trials: int) -> Path:
    """``robots`` simulated recordings and their manifest (made once, not timed)."""
    from timedexec.sim import simulate_sweep

    lines = ["name,robot,source,deployed"]
    for i in range(robots):
        robot = ROBOTS[i % len(ROBOTS)]
        rec = folder / f"robot-{i}.h5"
        if not rec.exists():
            simulate_sweep(robot, trials, rec, seed=100 + i, repeats=5, progress=False, jobs=-1)
        lines.append(f"robot-{i},{robot},{rec.name},{robot}-sim")
    manifest = folder / "fleet.csv"
    manifest.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return manifest


def _warm() -> int:
    """Run on a worker: import what a robot's run imports (a long-lived worker has)."""
    import scipy.optimize  # noqa: F401
    import sklearn.base  # noqa: F401

    import timedexec.evaluation
    import timedexec.extraction
    import timedexec.fleet
    import timedexec.learning
    import timedexec.sim  # noqa: F401

    return os.getpid()


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _overhead(stream: list[dict[str, Any]], t_submit: float, t_done: float) -> dict[str, float]:
    """Task time and scheduler overhead per task from Dask's task stream."""
    by_worker: dict[str, list[tuple[float, float]]] = {}
    for rec in stream:
        for ss in rec["startstops"]:
            if ss["action"] == "compute":
                by_worker.setdefault(rec["worker"], []).append((ss["start"], ss["stop"]))
    spans = sorted(s for v in by_worker.values() for s in v)
    durations = [b - a for a, b in spans]
    n = len(spans)
    compute = sum(b - a for a, b in spans)
    last_start = max(a for a, _ in spans)
    gaps = 0.0
    for v in by_worker.values():
        v.sort()
        for (_, stop), (start, _) in itertools.pairwise(v):
            if start <= last_start:  # a robot was still waiting: the gap is dispatch
                gaps += start - stop
    first = min(a for a, _ in spans) - t_submit
    last = t_done - max(b for _, b in spans)
    per_task = (gaps + first + last) / n
    return {
        "tasks": n,
        "durations_s": durations,
        "task_s": compute / n,
        "overhead_per_task_s": per_task,
        "overhead_pct": 100.0 * per_task / (compute / n),
    }


def _cluster_run(
    manifest: Path, out: Path, workers: int, settings: FleetSettings, malloc: str
) -> dict[str, Any]:
    import dask
    from distributed import Client, LocalCluster

    config: dict[str, Any] = {}
    if malloc == "glibc":
        config["distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"] = None
    with dask.config.set(config):
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True,
            dashboard_address=None, silence_logs=logging.ERROR,
        )  # fmt: skip
    try:
        with Client(cluster) as client:
            client.wait_for_workers(workers)
            client.run(_warm)
            env = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
            from distributed import get_task_stream

            t0 = time.time()
            with get_task_stream(client=client) as ts:
                result = run_fleet(
                    manifest, out, scheduler=client, settings=settings, progress=False
                )
            t1 = time.time()
            rss = client.run(_peak_rss_mb)
            stream = ts.data
    finally:
        cluster.close()
    return {
        "wall_s": result.wall_s,
        "failed": [r.name for r in result.failed],
        "peak_rss_mb": sorted(rss.values()),
        "malloc_trim_threshold": sorted({str(v) for v in env.values()}),
        **_overhead(stream, t0, t1),
    }


def scaling(args: argparse.Namespace) -> None:
    settings = FleetSettings(
        methods=tuple(args.methods.split(",")), folds=args.folds,
        eval_configs=args.configs, eval_draws=3,
    )  # fmt: skip
    work = Path(args.dir or tempfile.mkdtemp(prefix="bench-fleet-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"load average before: {_load()} (2 cores: above 2, the numbers below are slowed)")
    manifest = _make_fleet(work, args.robots, args.trials)
    print(
        f"fleet: {args.robots} robots x {args.trials} trials (recordings in {work}), methods "
        f"{','.join(settings.methods)}, {settings.folds}-fold CV, evaluation {settings.eval_configs} "
        f"configurations; malloc: {args.malloc}"
    )
    code = _source_fingerprint()
    base = run_fleet(manifest, work / "local", jobs=1, settings=settings, progress=False)
    print(
        f"in this process, no Dask: {base.wall_s:.1f} s; failed: {[r.name for r in base.failed]}; "
        f"source {code}"
    )
    runs: dict[int, list[dict[str, Any]]] = {1: [], 2: []}
    same = True
    for rep in range(args.repeat):
        for workers in (1, 2):
            out = work / f"w{workers}-{rep}"
            r = _cluster_run(manifest, out, workers, settings, args.malloc)
            runs[workers].append(r)
            if _source_fingerprint() != code:
                print(
                    "  timedexec's source changed during the run (someone edited it): tables not compared"
                )
                code = _source_fingerprint()
                continue
            same &= all(
                filecmp.cmp(out / f, work / "local" / f, shallow=False)
                for f in ("fleet.csv", "fleet.json")
            )
            print(
                f"  run {rep + 1}, {workers} worker(s): {r['wall_s']:.1f} s, task {r['task_s']:.2f} s, "
                f"overhead {r['overhead_per_task_s'] * 1e3:.0f} ms/task ({r['overhead_pct']:.1f} %), "
                f"peak RSS per worker {', '.join(f'{m:.0f}' for m in r['peak_rss_mb'])} MB "
                f"(MALLOC_TRIM_THRESHOLD_={r['malloc_trim_threshold']}); load {_load()}"
            )
    w1 = statistics.median(r["wall_s"] for r in runs[1])
    w2 = statistics.median(r["wall_s"] for r in runs[2])
    ov = statistics.median(r["overhead_pct"] for rs in runs.values() for r in rs)
    ov_ms = statistics.median(r["overhead_per_task_s"] for rs in runs.values() for r in rs) * 1e3
    rss = max(m for rs in runs.values() for r in rs for m in r["peak_rss_mb"])
    # what the task graph allows on 2 idle cores: the 1-worker runs' task times, scheduled
    # on 2 workers, plus the measured overhead per task
    allowed = statistics.median(
        (sum(r["durations_s"]) + r["tasks"] * r["overhead_per_task_s"])
        / (_two_worker_makespan(r["durations_s"]) + r["tasks"] / 2 * r["overhead_per_task_s"])
        for r in runs[1]
    )
    summary = {
        "robots": args.robots,
        "trials": args.trials,
        "local_s": base.wall_s,
        "one_worker_s": w1,
        "two_workers_s": w2,
        "speedup": w1 / w2,
        "speedup_allowed_by_tasks": allowed,
        "overhead_ms_per_task": ov_ms,
        "overhead_pct": ov,
        "peak_rss_mb_per_worker": rss,
        "identical_tables": same,
        "load_after": _load(),
    }
    print(
        f"median wall: 1 worker {w1:.1f} s, 2 workers {w2:.1f} s: speed-up {w1 / w2:.2f}x "
        f"(target >= 1.7x; the task times of the 1-worker runs allow {allowed:.2f}x on 2 idle "
        f"cores); scheduler overhead {ov_ms:.0f} ms per task = {ov:.1f} % of task "
        f"time (target <= 5 %); peak RSS per worker <= {rss:.0f} MB; tables identical to the "
        f"local run: {same}"
    )
    print(f"load average after: {_load()}")
    print(json.dumps(summary))


_COST_CHILD = r"""
import json, sys
from timedexec.fleet import parse_manifest, FleetSettings, run_robot
trials, methods, folds, folder = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
m = parse_manifest(f"name,robot,source,deployed\nr,ur10,sim://ur10?trials={trials}&seed=1,ur10-sim\n", base=folder)
s = FleetSettings(methods=tuple(methods.split(",")), folds=folds, eval_configs=300, eval_draws=20)
r = run_robot(m.entries[0], folder, s)
import os
rec = os.path.join(folder, "robots", "r", "recording.h5")
print(json.dumps({"status": r.status, "error": r.error, "costs": r.costs,
                  "recording_mb": os.path.getsize(rec) / 1e6}))
"""


def cost(args: argparse.Namespace) -> None:
    work = Path(args.dir or tempfile.mkdtemp(prefix="bench-fleet-cost-"))
    work.mkdir(parents=True, exist_ok=True)
    print(
        f"one ur10 robot, {args.cost} trials, {args.methods}, {args.folds}-fold CV, in a fresh process; load {_load()}"
    )
    proc = subprocess.run(
        [sys.executable, "-c", _COST_CHILD, str(args.cost), args.methods, str(args.folds), str(work)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    total = {"wall_s": 0.0, "cpu_s": 0.0, "read_mb": 0.0}
    for stage, c in doc["costs"].items():
        print(
            f"  {stage:<9} cpu {c['cpu_s']:7.1f} s  wall {c['wall_s']:7.1f} s  peak RSS "
            f"{c['peak_rss_mb']:6.0f} MB  read {c['read_mb'] or 0:7.1f} MB"
        )
        for k in total:
            total[k] += c[k] or 0.0
    print(
        f"  total     cpu {total['cpu_s']:7.1f} s  wall {total['wall_s']:7.1f} s  recording "
        f"{doc['recording_mb']:.1f} MB; status {doc['status']}; load {_load()}"
    )
    print(json.dumps({"trials": args.cost, **doc, "total": total}))


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--robots", type=int, default=6)
    p.add_argument("--trials", type=int, default=800)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--methods", default="median,rt,gpr")
    p.add_argument("--folds", type=int, default=5)
    p.add_argument("--configs", type=int, default=20, help="evaluation configurations per robot")
    p.add_argument("--malloc", choices=("glibc", "dask"), default="glibc")
    p.add_argument(
        "--cost", type=int, metavar="TRIALS", help="measure one robot of TRIALS trials instead"
    )
    p.add_argument("--dir", help="working folder (default: a new temporary one)")
    args = p.parse_args()
    if args.cost:
        cost(args)
    else:
        scaling(args)


if __name__ == "__main__":
    main()
