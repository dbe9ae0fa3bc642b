"""The conveyor weld over belt speeds: does the tracking model hold at every speed?

Issue 40 item 2: ``timedexec evaluate --task conveyor`` on the UR10, UR10e and KR 5 at
belt speeds 0.01, 0.05, 0.1, 0.3 and 1.0 m/s must exit 0 everywhere, with the tracking
model's torch mean <= 1 mm and not worse than no compensation. Each cell of the grid runs
the real CLI in this process (``timedexec.cli.main``, ``--json`` into a temporary folder)
and reads its result; the table gives the exit code, the torch mean (mm) of ``none``,
``median`` (per-joint constant shift), ``model`` (dead time + friction offsets, fitted on
the calibration welds) and ``oracle``, whether the model meets both targets, and the
number of calibration welds behind it (more than 3: runs that disagreed, welded again
automatically).

Usage: python benchmarks/bench_conveyor_speeds.py [--robots ur10 ur10e kr5]
       [--speeds 0.01 0.05 0.1 0.3 1.0] [--runs 4] [--cells 2]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import tempfile
import time
from pathlib import Path

from timedexec.cli import main

ROBOTS = ("ur10", "ur10e", "kr5")
SPEEDS = (0.01, 0.05, 0.1, 0.3, 1.0)


def one(robot: str, speed: float, runs: int, cells: int) -> dict[str, object]:
    """Run ``evaluate --task conveyor`` once; return its exit code, result and stderr."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "weld.json")
        argv = ["evaluate", "--task", "conveyor", "--robot", robot, "--speed", str(speed),
                "--runs", str(runs), "--cells", str(cells), "--quiet", "--json", out]  # fmt: skip
        err = io.StringIO()
        t0 = time.monotonic()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(argv)
        doc = json.loads(Path(out).read_text()) if code == 0 and os.path.exists(out) else {}
    return {"code": code, "doc": doc, "stderr": err.getvalue(), "s": time.monotonic() - t0}


def main_bench() -> None:
    """Print the table (markdown)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=list(ROBOTS))
    ap.add_argument("--speeds", nargs="+", type=float, default=list(SPEEDS))
    ap.add_argument("--runs", type=int, default=4, help="publisher phases per work point")
    ap.add_argument("--cells", type=int, default=2, help="work points")
    args = ap.parse_args()
    head = "| robot | belt m/s | exit | none | median | model | oracle | model ok | cal. welds |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    failures = 0
    for robot in args.robots:
        for speed in args.speeds:
            r = one(robot, speed, args.runs, args.cells)
            doc = r["doc"]
            assert isinstance(doc, dict)
            if r["code"] != 0:
                failures += 1
                last = str(r["stderr"]).strip().splitlines()[-1:] or [""]
                print(f"| {robot} | {speed:g} | {r['code']} | {last[0][:80]} |")
                continue
            s = {k: v["torch_mean_mm"] for k, v in doc["strategies"].items()}
            ok = s["model"] <= 1.0 and s["model"] <= s["none"]
            failures += not ok
            row = (
                f"| {robot} | {speed:g} | 0 | {s['none']:.2f} | {s['median']:.2f} | "
                f"{s['model']:.2f} | {s['oracle']:.2f} | {'yes' if ok else 'NO'} | "
                f"{doc['calibration_runs']} |"
            )
            print(row, flush=True)
    print(f"\n{failures} cell(s) missing a target")


if __name__ == "__main__":
    main_bench()
