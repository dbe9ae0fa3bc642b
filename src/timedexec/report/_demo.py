"""The end-to-end demo: sweep, extraction, models, evaluation, conveyor, report.

Everything runs on the embedded simulated robot; each step writes its result into the
output folder in the format the corresponding subcommand writes, so any step can be
repeated by hand (``timedexec extract``, ``train``, ``evaluate``, ``report``).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._files import make_dir, write_atomic
from timedexec.errors import ConfigError
from timedexec.robots import get_robot

__all__ = ["DEMO_STEPS", "run_demo"]

#: The demo's steps, in order (progress lines on stderr name them).
DEMO_STEPS = (
    "simulate a calibration sweep",
    "extract the delays",
    "train the delay models",
    "evaluate on held-out trials",
    "track a conveyor seam",
    "write the report",
)

#: Seed offset of the held-out evaluation plan from the sweep's plan seed.
_HELD_OUT_SEED = 20_261


#: The demo's record of what it wrote in its output folder: only files named there are
#: ever replaced by a later demo run.
DEMO_MARKER = ".timedexec-demo.json"


def _claim(out: Path, paths: list[Path]) -> None:
    """Make sure the demo only replaces what an earlier demo wrote in ``out``, then record
    ``paths`` as the demo's (in :data:`DEMO_MARKER`) before anything is written.

    Raises
    ------
    ConfigError
        When ``out`` holds one of ``paths`` (or a piece of an unfinished recording) that no
        demo wrote: a user's own file is never replaced.
    """
    marker = out / DEMO_MARKER
    owned: set[str] = set()
    if marker.is_file():
        try:
            owned = set(json.loads(marker.read_text()).get("written", []))
        except (OSError, ValueError, AttributeError):
            owned = set()
    names = {p.name for p in paths}
    recording = paths[0].name  # its journal and temporary files start with its name

    def ours(name: str) -> bool:
        return name in owned or (recording in owned and name.startswith(recording))

    present = sorted(
        p.name
        for p in (out.iterdir() if out.is_dir() else [])
        if (p.name in names or p.name.startswith(recording)) and not ours(p.name)
    )
    if present:
        raise ConfigError(
            f"--out {out} already holds {', '.join(present)}, which no earlier demo wrote "
            "there; the demo never replaces files it did not make: give a new or empty "
            "folder (or move those files away)"
        )
    make_dir(out, "output folder (--out)")
    write_atomic(marker, json.dumps({"written": sorted(names | owned)}, indent=1) + "\n")


def _write_json(path: Path, data: dict[str, Any]) -> Path:
    return write_atomic(path, json.dumps(data, indent=2) + "\n")


def run_demo(
    robot: str = "ur10",
    out_dir: str | os.PathLike[str] = "timedexec-demo",
    *,
    trials: int = 8000,
    seed: int = 0,
    jobs: int | None = None,
    folds: int = 10,
    eval_configs: int | None = None,
    eval_draws: int = 20,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the whole pipeline on the simulated ``robot``; return a JSON-safe summary.

    Parameters
    ----------
    robot : str
        A name in :data:`~timedexec.robots.ROBOT_NAMES`.
    out_dir : path
        Output folder (created): ``ROBOT-sweep.h5`` (recording), ``ROBOT-delays.csv``,
        ``model/`` (bundle with ``cv.json``), ``evaluation.json``, ``conveyor.json`` and
        ``report/report.md`` with its figures.
    trials : int
        Calibration trials to simulate (the paper's sweep: 33,500).
    seed : int
        Seed of the sweep plan and the simulation; the held-out evaluation uses another.
    jobs : int, optional
        Worker processes (default: up to 2).
    folds : int
        Cross-validation folds of the model training (>= 2).
    eval_configs : int, optional
        Held-out configurations (8 trials each); default: as many as a held-out sweep of
        ``trials`` trials holds (its size is the training sweep's).
    eval_draws : int
        Draws behind the oracle.

    Returns
    -------
    dict
        ``robot``, ``trials``, ``summary`` (per-joint delays), ``extraction_rmse_ms``,
        ``folds`` (CV folds used: at most one per start configuration), ``cv_ms`` (median and learned models' average CV error per delay),
        ``evaluation`` (timing RMS and seam error per strategy, bound coverage),
        ``conveyor`` (physical seam lag without and with compensation), ``seconds`` per
        step, and the paths written.
    """
    from timedexec.evaluation import evaluate, held_out_capacity
    from timedexec.extraction import extract_recording
    from timedexec.learning import train_delay_models
    from timedexec.report._report import build_report, delay_summary
    from timedexec.sim import simulate_sweep
    from timedexec.tasks import compare_seam_tracking

    spec = get_robot(robot)
    if trials < 160:
        raise ConfigError(
            f"trials={trials}: the demo needs at least 160 trials (two start configurations x "
            "4 joints x 2 directions x 10 repeats) to cross-validate models; use --trials 160 "
            "or more"
        )
    if folds < 2:
        raise ConfigError(f"folds={folds}: cross-validation needs at least 2 folds")
    if (eval_configs is not None and eval_configs < 1) or eval_draws < 2:
        raise ConfigError(
            f"eval_configs={eval_configs} must be >= 1 and eval_draws={eval_draws} >= 2"
        )
    out = Path(out_dir)
    rec = out / f"{spec.name}-sweep.h5"
    delays = out / f"{spec.name}-delays.csv"
    model_dir = out / "model"
    eval_json = out / "evaluation.json"
    conveyor_json = out / "conveyor.json"
    written = [rec, delays, model_dir, eval_json, conveyor_json, out / "report"]
    _claim(out, written)
    n_jobs = jobs or min(2, os.cpu_count() or 1)
    seconds: dict[str, float] = {}
    clock = [time.monotonic()]

    def step(k: int, detail: str) -> None:
        now = time.monotonic()
        if k > 0:
            seconds[DEMO_STEPS[k - 1]] = round(now - clock[0], 2)
        clock[0] = now
        if progress and k < len(DEMO_STEPS):
            print(f"[{k + 1}/{len(DEMO_STEPS)}] {DEMO_STEPS[k]}: {detail}", file=sys.stderr)

    for stale in out.glob(f"{spec.name}-sweep.h5*"):
        stale.unlink()
    step(0, f"{trials:,} trials of the {spec.name} (state packages, commands, 8 kHz gyro)")
    simulate_sweep(spec, trials, rec, seed=seed, jobs=n_jobs, progress=progress)

    step(1, "gyro filtering, sub-sample fit of onsets and report latency")
    table = extract_recording(rec, jobs=n_jobs, progress=progress).table
    table.to_csv(delays)
    ok = np.array([not f for f in table["flag"]], dtype=bool)
    extraction_rmse_ms = {
        name: float(np.sqrt(np.mean((table[name] - table[f"true_{name}"])[ok] ** 2)) * 1e3)
        for name in ("actuation_delay", "response_delay")
    }

    configs = len(np.unique(np.column_stack([table[f"q{k}"] for k in range(1, 7)]), axis=0))
    folds = min(folds, configs)  # folds split by start configuration
    step(2, f"median, LM neural net, linear-leaf tree, GP; {folds}-fold CV")
    trained = train_delay_models(
        table.select(ok),
        folds=folds,
        jobs=n_jobs,
        random_state=seed,
        progress=progress,
        source=str(delays),
    )
    assert trained.model is not None  # final=True
    assert trained.cv is not None  # folds >= 2
    trained.model.save(model_dir)
    cv = trained.cv.to_dict()
    _write_json(model_dir / "cv.json", cv)
    cv_ms = {
        delay: {method: cols["average"] for method, cols in by_method.items()}
        for delay, by_method in cv.items()
    }

    # The held-out sweep has the training sweep's size: it holds at most `capacity`
    # configurations, and the line says how many are used.
    capacity = held_out_capacity(spec.name, trials)
    if eval_configs is None:
        eval_configs = capacity
    used = min(eval_configs, capacity)
    shortfall = (
        f" (of {eval_configs} asked: a held-out sweep of {trials:,} trials holds {capacity})"
        if used < eval_configs
        else ""
    )
    step(3, f"{used} held-out configurations{shortfall} x 8 conditions, 5 strategies")
    evaluation = evaluate(
        spec.name,
        model_dir,
        n_configs=eval_configs,
        seed=seed + _HELD_OUT_SEED,
        draws=eval_draws,
        sweep_trials=trials,
        progress=progress,
    )
    eval_info = evaluation.to_dict()
    _write_json(eval_json, eval_info)

    step(4, "joint 1 follows a seam at 0.5 m/s: uncompensated, compensated, + feedback")
    conveyor = compare_seam_tracking(spec.name, trained.model, speed_m_s=0.5, seed=seed + 1)
    _write_json(conveyor_json, conveyor)

    step(5, "tables and figures in the published layout")
    report = build_report(
        [rec, delays, model_dir, eval_json, conveyor_json],
        out / "report",
    )
    step(len(DEMO_STEPS), "")
    return {
        "robot": spec.name,
        "trials": trials,
        "folds": folds,
        "summary": delay_summary(table),
        "extraction_rmse_ms": extraction_rmse_ms,
        "cv_ms": cv_ms,
        "noise_floor_ms": {d: v["average"] for d, v in trained.cv.noise_floor_ms.items()},
        "evaluation": {
            "strategies": {
                name: {k: row[k] for k in ("timing_rms_ms", "seam_error_cm")}
                for name, row in eval_info["strategies"].items()
            },
            "coverage_95": eval_info.get("coverage_95"),
            "n_trials": eval_info["n_trials"],
            "n_configurations": eval_info["n_configurations"],
            "notes": eval_info.get("notes", []),
        },
        "conveyor": {
            name: {
                k: run[k]
                for k in (
                    "mean_lag_cm",
                    "final_lag_cm",
                    "estimated_mean_lag_cm",
                    "actuation_shift_ms",
                )
            }
            for name, run in conveyor["runs"].items()
        },
        "seconds": seconds,
        "report": str(report),
        "delays": str(delays),
        "recording": str(rec),
        "model": str(model_dir),
    }
