"""SIGKILL an adaptive sweep mid-run, resume it, and compare with an uninterrupted one.

Both through the CLI (``timedexec simulate --adaptive``, same seed and options): the
uninterrupted run; then a run killed with SIGKILL once ``--kill-after`` trials are recorded,
resumed with ``--resume`` (killed and resumed again ``--kills`` times). Prints whether every
trial field, every static (plan, still recording, design log) and the header are equal, bit
for bit, and the trial counts.

    python benchmarks/bench_adaptive_resume.py --robot ur10e --budget-min 15 --kill-after 300
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from timedexec.errors import RecordingError
from timedexec.recording import RecordingReader


def contents(path: Path) -> dict[str, object]:
    """Every trial field (in trial order), static and the header of a recording."""
    with RecordingReader(path) as r:
        order = np.argsort(r.read("trial"))
        out: dict[str, object] = {f"field:{k}": r.read(k)[order] for k in r.fields}
        out.update({f"static:{k}": r.static(k) for k in r.static_names})
        out["header"] = json.dumps(r.header, sort_keys=True)
    return out


def differences(a: dict[str, object], b: dict[str, object]) -> list[str]:
    """Names of the entries that differ (NaN equal to NaN)."""
    bad = sorted(set(a) ^ set(b))
    for k in set(a) & set(b):
        x, y = a[k], b[k]
        if isinstance(x, str):
            if x != y:
                bad.append(k)
        elif not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=np.asarray(x).dtype.kind == "f"):
            bad.append(k)
    return bad


def trials_in(path: Path) -> int:
    try:
        with RecordingReader(path) as r:
            return int(r.n_trials)
    except (RecordingError, OSError):
        return 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="ur10e")
    ap.add_argument("--budget-min", type=float, default=15.0)
    ap.add_argument("--kill-after", type=int, default=300, help="trials recorded before a kill")
    ap.add_argument("--kills", type=int, default=1)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--dir", help="work folder (default: a temporary one)")
    args = ap.parse_args()
    work = Path(args.dir or tempfile.mkdtemp(prefix="adaptive-resume-"))
    work.mkdir(parents=True, exist_ok=True)

    def cmd(out: Path, *extra: str) -> list[str]:
        return [sys.executable, "-m", "timedexec", "simulate", "--robot", args.robot, "--warm",
                "--adaptive", "--budget-min", str(args.budget_min), "--stop-fraction", "0",
                "--seed", str(args.seed), "--out", str(out), "--quiet", *extra]  # fmt: skip

    whole, cut = work / "whole.h5", work / "cut.h5"
    t = time.perf_counter()
    subprocess.run(cmd(whole), check=True)
    wall_whole = time.perf_counter() - t
    killed_at = []
    for k in range(args.kills):
        proc = subprocess.Popen(cmd(cut, *(["--resume"] if k else [])))
        target = (k + 1) * args.kill_after
        while proc.poll() is None and trials_in(cut) < target:
            time.sleep(0.2)
        if proc.poll() is not None:
            break
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        killed_at.append(trials_in(cut))
    subprocess.run(cmd(cut, "--resume"), check=True)
    bad = differences(contents(whole), contents(cut))
    print(json.dumps({
        "robot": args.robot, "budget_min": args.budget_min, "seed": args.seed,
        "trials": trials_in(whole), "killed_with_trials": killed_at,
        "uninterrupted_wall_s": round(wall_whole, 1),
        "equal": not bad, "differing": bad,
    }, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
