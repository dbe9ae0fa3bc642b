"""The adaptive sweep against the fixed one on the independent compliant-joint generator.

Issue 39 asks for the adaptive-vs-full claim "on your independent generator where it can be
driven by a plan". ``tests/compliant_sweep.py`` (other physics than :mod:`timedexec.sim`:
two-mass joints with hysteretic, stiffening gears, motor-side encoders, per-trial payload
and friction draws; its own gyro, clock and USB models; no thermal drift) makes trials of
any layout through its :class:`CompliantSession`. :class:`CompliantRunner` below is the
adapter: a :class:`~timedexec.calibration.TrialRunner` whose trials come from one session,
so :func:`~timedexec.calibration.run_adaptive` drives it exactly as it drives a robot (the
design extracts each batch from the recording and chooses the next configurations).

Three sweeps on the same arm, each a recording of the same runner: the adaptive sweep
(``--budget-min``), the fixed sweep (a random plan of the calibration ranges,
``SweepPlan.generate``, the paper's layout) run for ``--full-min`` and scored both stopped
at the adaptive sweep's robot time and whole, and a held-out sweep (another random plan,
``--heldout-trials``) whose **true** actuation delays score the GP bundles (``gpr``, 5-fold
CV) trained on each sweep's extracted delays. Reduced sizes: say so when quoting. The
fixed sweep is generated in one call: ~12 GB of memory for 4 hours (13,000 trials); run one
at a time.

    python benchmarks/bench_adaptive_compliant.py --robot ur10 --out runs/compliant \\
        --budget-min 20 --full-min 180 --heldout-trials 2000 --seed 1
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec.calibration import AdaptiveSettings, run_adaptive
from timedexec.delays import DelayTable
from timedexec.extraction import extract_recording
from timedexec.learning import train_delay_models
from timedexec.recording import Field, RecordingReader, RecordingWriter, SweepPlan

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from compliant_sweep import CompliantConditions, CompliantSession

STILL_S = 4.0
START_S = STILL_S + 0.7  # host time of the first trial (as write_compliant_sweep)


class CompliantRunner:
    """The compliant generator as the robot of a sweep (a ``TrialRunner``; no resume).

    Trials take 1.05-1.07 s, a move to another configuration 0.5 s more (the generator's
    own layout); the sweep clock is the host time since the first trial.
    """

    trial_s = 1.06
    move_s = 0.5

    def __init__(self, robot: str, *, seed: int, length_s: float) -> None:
        self.robot = robot
        self.seed = seed
        self.rng = np.random.default_rng([seed, 0xADA])
        self.session = CompliantSession(self.rng, robot, CompliantConditions(), START_S + length_s)
        self._t = START_S
        self._last_config = -1

    def header(self) -> dict[str, Any]:
        return self.session.header(self.seed)

    def fields(self) -> list[Field]:
        return self.session.fields()

    def prepare(self, out: Path, plan: SweepPlan, first_row: int, resume: bool) -> None:
        if resume:
            raise RuntimeError("CompliantRunner cannot resume a sweep")

    def begin(self, writer: RecordingWriter, plan: SweepPlan) -> None:
        for name, arr in self.session.still(STILL_S).items():
            if not writer.has_static(name):
                writer.write_static(name, arr)

    def now_s(self) -> float:
        return self._t - START_S

    def run(
        self, plan: SweepPlan, rows: NDArray[np.int64], until_s: float
    ) -> Iterator[dict[str, Any]]:
        take, t0 = [], []
        for row in rows.tolist():
            cfg = int(plan.config_index[row])
            t = self._t + (self.move_s if self._last_config not in (-1, cfg) else 0.0)
            if t - START_S + self.trial_s > until_s:
                break
            take.append(row)
            t0.append(t)
            self._t = t + 1.05 + float(self.rng.uniform(0, 0.02))
            self._last_config = cfg
        if take:
            idx = np.asarray(take, dtype=np.int64)
            arrays = self.session.trials(
                plan.q_start_rad[idx], plan.joint[idx], plan.direction[idx], np.asarray(t0)
            )
            yield {"trial": idx, **arrays}

    def finish(self) -> None:
        pass


def fixed_sweep(robot: str, path: Path, n: int, seed: int) -> Path:
    """A fixed sweep (random plan, the paper's layout) of ``n`` trials through the runner."""
    plan = SweepPlan.generate(robot, n, seed=seed)
    runner = CompliantRunner(robot, seed=seed, length_s=1.6 * n)
    with RecordingWriter(path, header=runner.header(), fields=runner.fields(), fsync=False) as w:
        for name, arr in plan.to_arrays().items():
            w.write_static(name, arr)
        runner.begin(w, plan)
        for batch in runner.run(plan, np.arange(n, dtype=np.int64), float("inf")):
            w.append(batch)
    return path


def truth_of(path: Path) -> dict[str, NDArray[Any]]:
    """The held-out sweep's trials and true actuation delays (no extraction needed)."""
    with RecordingReader(path) as r:
        rows = r.read("trial")
        y = r.read("true_actuation_delay_s")
        q = r.static("plan_q_start_rad")[rows]
        joint = r.static("plan_joint")[rows]
        direction = r.static("plan_direction")[rows]
    return {"q": q, "joint": joint, "direction": direction, "y": np.asarray(y, dtype=float)}


def gp_rmse_ms(table: DelayTable, held: dict[str, NDArray[Any]]) -> float:
    """RMSE (ms) of a GP bundle trained on ``table`` against ``held``'s true delays."""
    model = train_delay_models(table, methods=("gpr",), folds=5, random_state=0).model
    p = model.predict_many(held["joint"], held["direction"], held["q"])
    return float(1e3 * np.sqrt(np.mean((held["y"] - p.actuation_mean) ** 2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="ur10", choices=("ur10", "kr5"))
    ap.add_argument("--out", required=True, help="directory for the recordings")
    ap.add_argument("--budget-min", type=float, default=20.0)
    ap.add_argument("--full-min", type=float, default=180.0)
    ap.add_argument("--heldout-trials", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    budget_s = 60.0 * args.budget_min
    wall = time.perf_counter()
    ada = out / f"{args.robot}-adaptive.h5"
    if not ada.exists():
        runner = CompliantRunner(args.robot, seed=args.seed, length_s=budget_s + 60.0)
        settings = AdaptiveSettings(budget_s=budget_s, seed=args.seed, stop_fraction=0.0)
        res = run_adaptive(runner, ada, settings=settings, progress=True)
        print(f"adaptive: {res.trials} trials, {res.robot_time_s / 60:.1f} min, {res.stopped}")
    n_full = int(60.0 * args.full_min / 1.11)  # ~1.06 s a trial + a move per 20 trials
    full = out / f"{args.robot}-fixed.h5"
    if not full.exists():
        fixed_sweep(args.robot, full, n_full, seed=args.seed + 100)
    held_path = out / f"{args.robot}-heldout.h5"
    if not held_path.exists():
        fixed_sweep(args.robot, held_path, args.heldout_trials, seed=args.seed + 200)
    held = truth_of(held_path)
    a = extract_recording(ada, progress=False).table
    f = extract_recording(full, progress=False).table
    t_ada = float(np.asarray(a["t_start"], dtype=float).max())
    f_start = np.asarray(f["t_start"], dtype=float)
    f_at = f.select(f_start <= f_start.min() + (t_ada - float(np.asarray(a["t_start"]).min())))
    rows = {
        "adaptive": (len(a), gp_rmse_ms(a, held)),
        "fixed, same robot time": (len(f_at), gp_rmse_ms(f_at, held)),
        "fixed, whole": (len(f), gp_rmse_ms(f, held)),
    }
    print(f"\n{args.robot} (compliant generator), held-out {len(held['y'])} trials (true delays):")
    for name, (n, rmse) in rows.items():
        print(f"  {name:24} {n:6d} trials  GP RMSE {rmse:.3f} ms")
    ratio = rows["adaptive"][1] / rows["fixed, whole"][1] - 1.0
    print(
        f"  adaptive vs whole fixed: {100 * ratio:+.1f} %; wall {time.perf_counter() - wall:.0f} s"
    )
    (out / f"{args.robot}-result.json").write_text(
        json.dumps({k: {"trials": n, "rmse_ms": r} for k, (n, r) in rows.items()}, indent=1)
    )


if __name__ == "__main__":
    main()
