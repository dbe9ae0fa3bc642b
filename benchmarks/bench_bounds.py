"""Coverage of the GP's 95 % prediction bounds on held-out sweeps of new configurations.

Issue 39's bounds measurement. For one simulated robot, each ``--train LABEL=SOURCE``
(a recording, extracted once and cached, or a measured delay CSV; ``:time`` after it
trains with the sweep time as an input) becomes a GP bundle (``train_delay_models``,
method ``gpr``, ``--folds`` configuration-grouped CV for the std calibration and the
bounds' quantile), saved under ``--bundles`` and reused from there. Each bundle is scored on
the **true** actuation delays of separate held-out simulated sweeps (``simulate --truth``,
other seeds and configurations), only on the held-out trials whose thermal state its
manifest says it answers for: RMSE (ms), the share inside the Gaussian ``mean ± 1.96 std``
(before) and inside :meth:`DelayModel.predict_bounds` (the split-conformal bound stored in
the bundle, ``bound_z``), overall and the range over joints.

    python benchmarks/bench_bounds.py --robot ur10e --bundles runs/ur10e-bundles \\
        --train adaptive-warm=ur10e-adaptive45-full.h5 \\
        --train full-warm=ur10e-full-warm-delays.csv \\
        --train adaptive-cold=ur10e-adaptive45-cold.h5:time \\
        --train fixed10k-cold=ur10e-fixed-cold10k-delays.csv:time \\
        --heldout warm=ur10e-heldout-warm.csv --heldout cold=ur10e-heldout-cold.csv \\
        --json ur10e-bounds.json
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from timedexec.delays import DelayTable
from timedexec.extraction import extract_recording
from timedexec.learning import DelayModel, thermal_mismatch, train_delay_models


def table_of(source: str, cache: Path) -> DelayTable:
    """The measured delay table of a recording (extracted once, cached) or a CSV."""
    if source.endswith(".csv"):
        return DelayTable.read_csv(source)
    if cache.exists():
        return DelayTable.read_csv(cache)
    table = extract_recording(source, progress=False).table
    table.to_csv(cache)
    return table


def bundle_of(label: str, spec: str, out: Path, folds: int) -> tuple[DelayModel, dict[str, Any]]:
    """Train (or load the saved) GP bundle ``label`` from ``SOURCE[:time]``."""
    source, _, flag = spec.partition(":")
    time_input = flag == "time"
    directory = out / label
    info: dict[str, Any] = {"source": source, "time_input": time_input}
    if (directory / "manifest.json").exists():
        model = DelayModel.load(directory)
    else:
        table = table_of(source, out / f"{label}-delays.csv")
        wall = time.perf_counter()
        model = train_delay_models(
            table, methods=("gpr",), folds=folds, time_input=time_input, random_state=0
        ).model
        info["train_wall_s"] = time.perf_counter() - wall
        model.save(directory)
    info["trials"] = model.manifest["training_data"]["trials"]
    info["thermal_state"] = (model.thermal_state or {}).get("state")
    info["bound_z"] = model.manifest.get("bound_z", {}).get("actuation_delay", {})
    info["std_scale"] = model.std_scale.get("actuation_delay", {})
    return model, info


def score(model: DelayModel, held: DelayTable) -> dict[str, Any]:
    """RMSE and coverage (Gaussian, new bounds; overall and per joint) on the held-out
    trials in the thermal state the bundle answers for."""
    t = np.asarray(held["t_since_power_on"], dtype=float)
    ok = np.array([thermal_mismatch(model.thermal_state, [v]) is None for v in t])
    out: dict[str, Any] = {"trials": int(ok.sum()), "of": len(ok)}
    if not ok.any():
        return out
    h = held.select(ok)
    joint = np.asarray(h["joint"])
    args = (joint, np.asarray(h["direction"]), h.q)
    kw = {"t_s": np.asarray(h["t_since_power_on"], dtype=float), "method": "gpr"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the mask already left out the other thermal state
        p = model.predict_many(*args, **kw)  # type: ignore[arg-type]
        b = model.predict_bounds(*args, **kw)  # type: ignore[arg-type]
    y = np.asarray(h["true_actuation_delay"], dtype=float)
    gauss = np.abs(y - p.actuation_mean) <= 1.96 * p.actuation_std
    new = (y >= b.actuation_lower_s) & (y <= b.actuation_upper_s)
    out["rmse_ms"] = float(1e3 * np.sqrt(np.mean((y - p.actuation_mean) ** 2)))
    out["gaussian"] = float(gauss.mean())
    out["bounds"] = float(new.mean())
    per = [float(new[joint == j].mean()) for j in np.unique(joint)]
    out["bounds_joint_min"], out["bounds_joint_max"] = min(per), max(per)
    out["half_width_ms"] = float(1e3 * np.mean(b.actuation_upper_s - b.actuation_lower_s) / 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", required=True)
    ap.add_argument("--bundles", required=True, help="directory of the (cached) bundles")
    ap.add_argument("--train", action="append", default=[], help="LABEL=SOURCE[:time]")
    ap.add_argument("--heldout", action="append", default=[], help="NAME=truth.csv")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    out = Path(args.bundles)
    out.mkdir(parents=True, exist_ok=True)
    held = {n: DelayTable.read_csv(p) for n, p in (s.split("=", 1) for s in args.heldout)}
    rows = []
    for item in args.train:
        label, spec = item.split("=", 1)
        model, info = bundle_of(label, spec, out, args.folds)
        row: dict[str, Any] = {"robot": args.robot, "bundle": label, **info}
        for name, h in held.items():
            row[name] = score(model, h)
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(f"\n{args.robot}: bundle | held-out | answers for | RMSE ms | Gaussian | bounds (joints)")
    for r in rows:
        for name in held:
            s = r[name]
            if not s.get("trials"):
                print(f"{r['bundle']:16} | {name:5} | 0 of {s['of']} | | |")
                continue
            print(
                f"{r['bundle']:16} | {name:5} | {s['trials']} of {s['of']} | {s['rmse_ms']:.3f} | "
                f"{100 * s['gaussian']:.1f} % | {100 * s['bounds']:.1f} % "
                f"({100 * s['bounds_joint_min']:.1f}-{100 * s['bounds_joint_max']:.1f})"
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
