#!/usr/bin/env python
"""Rebuild the shipped delay models in models/ (one per robot of the catalog: ur10-sim ...).

For each simulated robot, as a user would with a real one: simulate a calibration sweep
(state packages, commands and an 8 kHz gyro, recorded to HDF5), extract the *measured*
delay table from the recording, cross-validate the four methods (10 folds) and train them
on all data into a model bundle. The recording lives in a temporary directory and is
deleted; only the bundle (arrays.npz + manifest.json, hundreds of kB), the CV scores and
tables are written:

* ``cv-published.json`` / ``cv-published-table.txt``: CV with the paper's inputs
  (configuration, joint, direction), beside the paper's Tables I/II;
* ``cv.json`` / ``cv-table.txt``: CV of the bundled models, which also take the sweep
  time as an input (``time_input``): the simulated robots warm up (``thermal_drift``), and
  the bundle predicts the warm robot (end of the sweep) unless given a time.

The bundle carries the GP's standard-deviation calibration from that CV (``std_scale`` in
the manifest, listed at the end of ``cv-table.txt``; docs/models.md, "Calibrated
uncertainty").

Trials: 8,000 (100 start configurations x 4 joints x 2 directions x 10 repeats; ~2.5 min
per robot on two cores) for ur10 and kr5; 33,500 (the published size) for a controller
period of 2 ms or less (ur10e, ur5e), which leaves a noise floor of about 0.6 ms that 8,000
trials do not resolve the pose dependence against (~10 min). ``--trials N`` sets one count
for all. Same seed, same bundles (byte for byte, on the same platform). Each bundle is
written to ``<out>/<the robot's shipped_model>``.

usage: python scripts/train_bundled_models.py [--robots ur10,ur10e,kr5,...] [--trials N]
       [--seed 1] [--jobs 2] [--out models]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from timedexec.extraction import extract_recording
from timedexec.learning import train_delay_models
from timedexec.recording import FULL_SWEEP_TRIALS
from timedexec.robots import ROBOT_NAMES, RobotSpec, get_robot, get_robot_entry
from timedexec.sim import simulate_sweep


def default_trials(spec: RobotSpec) -> int:
    """8,000 trials where that resolves the pose dependence against the noise floor; the
    published 33,500 at a controller period of 2 ms or less (a noise floor of ~0.6 ms)."""
    return FULL_SWEEP_TRIALS if spec.controller_period_s <= 0.002 else 8000


def build(robot: str, trials: int, seed: int, jobs: int, out_root: Path) -> dict[str, object]:
    """Simulate, extract, train and save one robot's bundle; return a summary."""
    spec = get_robot(robot)
    out = out_root / get_robot_entry(spec.name).shipped_model
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=f"timedexec-{spec.name}-") as tmp:
        rec = Path(tmp) / "sweep.h5"
        print(f"[{spec.name}] simulating {trials:,} trials", file=sys.stderr)
        simulate_sweep(spec, trials, rec, seed=seed, jobs=jobs, progress=False)
        t_sim = time.perf_counter() - start
        print(f"[{spec.name}] extracting the measured delays", file=sys.stderr)
        table = extract_recording(rec, jobs=jobs, progress=False).table
        t_ext = time.perf_counter() - start - t_sim
    print(f"[{spec.name}] 10-fold CV with the published inputs", file=sys.stderr)
    published = train_delay_models(
        table,
        folds=10,
        jobs=jobs,
        random_state=seed,
        final=False,
        period_s=spec.controller_period_s,
    ).cv
    assert published is not None
    print(published.table_text(), file=sys.stderr)
    print(f"[{spec.name}] training with the sweep time as an input (10-fold CV + final fits)",
          file=sys.stderr)  # fmt: skip
    result = train_delay_models(
        table,
        folds=10,
        jobs=jobs,
        random_state=seed,
        progress=False,
        period_s=spec.controller_period_s,
        source=f"scripts/train_bundled_models.py: simulate_sweep({spec.name!r}, {trials}, "
        f"seed={seed}) -> extract_recording (measured delays)",
        time_input=True,
    )
    t_train = time.perf_counter() - start - t_sim - t_ext
    model = result.model
    model.save(out)
    assert result.cv is not None
    (out / "cv.json").write_text(json.dumps(result.cv.to_dict(), indent=2) + "\n")
    (out / "cv-table.txt").write_text(result.cv.table_text() + "\n")
    (out / "cv-published.json").write_text(json.dumps(published.to_dict(), indent=2) + "\n")
    (out / "cv-published-table.txt").write_text(published.table_text() + "\n")
    print(result.cv.table_text(), file=sys.stderr)
    return {
        "robot": spec.name,
        "period_s": spec.controller_period_s,
        "trials": len(table),
        "bundle": str(out),
        "arrays_bytes": model.manifest["arrays"]["bytes"],
        "simulate_s": round(t_sim, 1),
        "extract_s": round(t_ext, 1),
        "train_s": round(t_train, 1),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", default=",".join(ROBOT_NAMES))
    parser.add_argument("--trials", type=int, help="trials per robot (default: see above)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--out",
        default=str(Path(__file__).resolve().parent.parent / "models"),
    )
    args = parser.parse_args(argv)
    out_root = Path(args.out)
    out_root.mkdir(parents=True, exist_ok=True)
    for robot in [r.strip() for r in args.robots.split(",") if r.strip()]:
        trials = args.trials or default_trials(get_robot(robot))
        summary = build(robot, trials, args.seed, args.jobs, out_root)
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
