"""Learning curves of the adaptive sweep against the fixed (random-configuration) sweep.

Issue 39's measurement. For one simulated robot: an adaptive sweep's recording
(``timedexec simulate --adaptive [--warm]``, or ``calibrate --adaptive`` on ``sim://``) and
a fixed sweep's (``timedexec simulate --trials 33500 [--warm]``; its plan visits random
configurations, so a prefix in time is the fixed sweep stopped then), each extracted once
(the measured delays, as a user has them). At each robot time T: a GP bundle
(``train_delay_models``, method ``gpr``, ``--folds`` CV for the std calibration) trained on
the trials started before T, scored on the **true** actuation delays of separate held-out
simulated sweeps (other seeds, other configurations), only on the held-out trials whose
thermal state the bundle says it answers for (its manifest's ``thermal_state``; the others
are counted): RMSE (ms) and the share of trials inside the bundle's 95 % bounds
(mean +- 1.96 std, std the calibrated trial std).

    python benchmarks/bench_adaptive.py --robot ur10e \\
        --adaptive ur10e-adaptive45.h5 --fixed ur10e-full-warm.h5 \\
        --fixed-table ur10e-full-warm-delays.csv \\
        --heldout warm=ur10e-heldout-warm.csv --heldout cold=ur10e-heldout-cold.csv \\
        --times-min 10,20,30,45 --fixed-times-min 10,20,45,90,180,360,full \\
        --json ur10e-curves.json --figure ur10e-curves.png
    python benchmarks/bench_adaptive.py --robot ur10e --merge a.json,b.json --figure f.png

``--fixed-table`` / ``--adaptive-table``: an extraction made before (``timedexec extract``),
to skip extracting again. Each held-out table is a ground-truth CSV (``simulate --truth``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._plot import subplots
from timedexec.delays import DelayTable
from timedexec.extraction import extract_recording
from timedexec.learning import thermal_mismatch, train_delay_models


def table_of(recording: str | None, csv: str | None) -> DelayTable:
    """The measured delay table of a recording (or its earlier extraction)."""
    if csv:
        return DelayTable.read_csv(csv)
    assert recording is not None
    return extract_recording(recording, progress=False).table


def answered(model: Any, held: DelayTable) -> np.ndarray:
    """Mask of the held-out trials in the thermal state the bundle answers for."""
    state = model.thermal_state
    t = np.asarray(held["t_since_power_on"], dtype=float)
    return np.array([thermal_mismatch(state, [v]) is None for v in t])


def score(model: Any, held: DelayTable) -> dict[str, float]:
    """RMSE (ms) and 95 % coverage on the held-out trials the bundle answers for (and,
    for comparison, the RMSE on all of them, ``rmse_all_ms``)."""
    ok = answered(model, held)
    out = {"trials": int(ok.sum()), "left_out_other_thermal_state": int((~ok).sum())}
    out["rmse_all_ms"] = _errors(model, held)[0]
    if ok.any():
        out["rmse_ms"], out["coverage_95"] = _errors(model, held.select(ok))
    else:
        out["rmse_ms"] = out["coverage_95"] = math.nan
    return out


def _errors(model: Any, h: DelayTable) -> tuple[float, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the mask already left out the other thermal state
        p = model.predict_many(
            np.asarray(h["joint"]),
            np.asarray(h["direction"]),
            h.q,
            t_s=np.asarray(h["t_since_power_on"], dtype=float),
            method="gpr",
        )
    err = np.asarray(h["true_actuation_delay"], dtype=float) - p.actuation_mean
    inside = np.abs(err) <= 1.96 * p.actuation_std
    return float(1e3 * np.sqrt(np.mean(err**2))), float(np.mean(inside))


def curve(
    table: DelayTable,
    times_s: list[float],
    held: dict[str, DelayTable],
    *,
    folds: int,
    time_input: bool,
    label: str,
) -> list[dict[str, Any]]:
    """Train on each prefix in robot time and score it."""
    t_start = np.asarray(table["t_start"], dtype=float)
    out = []
    for t in times_s:
        sub = table.select(t_start < t)
        wall = time.perf_counter()
        model = train_delay_models(
            sub, methods=("gpr",), folds=folds, time_input=time_input, random_state=0
        ).model
        row: dict[str, Any] = {
            "sweep": label,
            "robot_time_min": float(min(t, t_start.max()) / 60.0),
            "trials": len(sub),
            "train_wall_s": time.perf_counter() - wall,
            "thermal_state": model.thermal_state,
        }
        for name, h in held.items():
            row[name] = score(model, h)
        out.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "thermal_state"}), flush=True)
    return out


def times_of(text: str, table: DelayTable) -> list[float]:
    end = float(np.max(np.asarray(table["t_start"], dtype=float))) + 60.0
    return [end if v == "full" else float(v) * 60.0 for v in text.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", required=True)
    ap.add_argument("--adaptive", help="adaptive sweep recording")
    ap.add_argument("--adaptive-table", help="its extraction (CSV), instead of extracting")
    ap.add_argument("--fixed", help="fixed sweep recording")
    ap.add_argument("--fixed-table", help="its extraction (CSV), instead of extracting")
    ap.add_argument("--heldout", action="append", default=[], help="NAME=truth.csv")
    ap.add_argument("--times-min", default="10,20,30,45")
    ap.add_argument("--fixed-times-min", default="10,20,45,90,180,full")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--time-input", action="store_true", help="train with the time input")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--figure")
    ap.add_argument("--merge", help="comma list of --json outputs: plot them together, run nothing")
    args = ap.parse_args()
    if args.merge:
        docs = [json.loads(Path(p).read_text()) for p in args.merge.split(",")]
        rows_all = [r for d in docs for r in d["rows"]]
        names = [k for k in rows_all[0] if isinstance(rows_all[0][k], dict) and "rmse_ms" in rows_all[0][k]]
        plot(args.robot, rows_all, names, args.figure)
        return
    held = {}
    for item in args.heldout:
        name, path = item.split("=", 1)
        held[name] = DelayTable.read_csv(path)
    rows: list[dict[str, Any]] = []
    if args.adaptive or args.adaptive_table:
        a = table_of(args.adaptive, args.adaptive_table)
        rows += curve(a, times_of(args.times_min, a), held, folds=args.folds,
                      time_input=args.time_input, label="adaptive")  # fmt: skip
    if args.fixed or args.fixed_table:
        f = table_of(args.fixed, args.fixed_table)
        rows += curve(f, times_of(args.fixed_times_min, f), held, folds=args.folds,
                      time_input=args.time_input, label="fixed")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps({"robot": args.robot, "rows": rows}, indent=1))
    if args.figure:
        plot(args.robot, rows, list(held), args.figure)


def plot(robot: str, rows: list[dict[str, Any]], names: list[str], path: str) -> None:
    """RMSE against robot time, one line per sweep and held-out set."""
    fig, ax = subplots(figsize=(6.4, 3.8), constrained_layout=True)
    for label, style in (("adaptive", "o-"), ("fixed", "s--")):
        for name in names:
            pts = [(r["robot_time_min"], r[name]["rmse_ms"]) for r in rows
                   if r["sweep"] == label and math.isfinite(r[name]["rmse_ms"])]  # fmt: skip
            if pts:
                x, y = zip(*pts, strict=True)
                ax.plot(x, y, style, label=f"{label} sweep, {name} held-out")
    ax.set_xscale("log")
    ax.set_xlabel("robot time, min")
    ax.set_ylabel("GP RMSE on true actuation delays, ms")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(f"{robot}: learning curves, adaptive vs fixed sweep", fontsize=10)
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
