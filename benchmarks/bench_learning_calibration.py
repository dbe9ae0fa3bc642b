"""Coverage of the executor's 95 % timing bounds: the GP's own std against the calibrated one.

For each training sweep (``--sweeps``, seeds 0, 1, ...): simulate ``--trials`` true delays
of the robot (``simulate_delays``; a sweep plan of ``trials / 80`` configurations x 4 joints
x 2 directions x 10 repeats, trials 1.05 s apart as the sweep clock lays them out, so an
800-trial sweep is a 14-minute cold robot), cross-validate the GP as training does (10
folds by start configuration, ``fold_of_configuration``; one GP per joint and one combined)
to get the held-out standardised residuals ``z = (y - mean) / std`` of the actuation delay,
train the GP bundle (``train_delay_models(methods="gpr")``), and check the actuation delay
of 10 fresh plans' configurations (one trial per condition, the same sweep times) against
``TimingBounds.around(mean, std, 0.95, period)`` for three std's from the same fits:

* ``gp``: the GP's own trial std (factor 1, what bundles reported before calibration);
* ``rms``: the factor ``max(1, sqrt(mean z²))`` (``std_scale_factor``, the rule training
  stores in the bundle);
* ``q95``: the alternative rule ``max(1, q95(|z|) / 1.96)`` (the Gaussian 95 % quantile),
  computed from the same held-out residuals.

Prints per rule the mean coverage over the sweeps, its range and the per-joint means.

Usage: python benchmarks/bench_learning_calibration.py [--robot ur10] [--trials 800]
       [--sweeps 10]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from timedexec.delays import DelayTable
from timedexec.execution import TimingBounds
from timedexec.learning import (
    encode_inputs,
    fold_of_configuration,
    make_estimator,
    std_scale_factor,
    train_delay_models,
)
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.sim import simulate_delays

KEYS = ("1", "2", "3", "5", "combined")


def held_out_z(table: DelayTable, folds: int, random_state: int) -> dict[str, np.ndarray]:
    """Held-out ``(y - mean) / std`` of the GP's actuation delay, per model (KEYS).

    The cross-validation of ``train_delay_models``: folds by start configuration, one GP per
    joint (inputs configuration and direction) and one combined (plus the joint one-hot);
    ``std`` is the single-trial std (latent + noise) a bundle reports before calibration.
    """
    t = table.validated_for_training()
    q = t.q
    joint = t["joint"].astype(np.int64)
    direction = t["direction"].astype(np.int64)
    y = t["actuation_delay"].astype(float)
    config = np.unique(q, axis=0, return_inverse=True)[1].reshape(-1)
    fold = fold_of_configuration(config, folds, random_state)
    joints = tuple(sorted({int(j) for j in joint}))
    z: dict[str, np.ndarray] = {}
    for key in KEYS:
        if key == "combined":
            rows = np.arange(len(y))
            X = encode_inputs(q, direction, joint, joints)
        else:
            rows = np.flatnonzero(joint == int(key))
            X = encode_inputs(q[rows], direction[rows])
        parts = []
        for k in range(folds):
            test = fold[rows] == k
            if not test.any() or test.all():
                continue
            gp = make_estimator("gpr", random_state=random_state + k)
            gp.fit(X[~test], y[rows][~test])
            mean, std = gp.predict(X[test], return_std=True)
            parts.append((y[rows][test] - mean) / std)
        z[key] = np.concatenate(parts)
    return z


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robot", default="ur10")
    parser.add_argument("--trials", type=int, default=800)
    parser.add_argument("--sweeps", type=int, default=10)
    args = parser.parse_args()
    period = get_robot(args.robot).controller_period_s
    n = args.trials
    t = np.arange(n) * 1.05

    cover: dict[str, list[list[float]]] = {"gp": [], "rms": [], "q95": []}
    start = time.perf_counter()
    for seed in range(args.sweeps):
        plan = SweepPlan.generate(args.robot, n, seed=seed)
        table = simulate_delays(
            args.robot, plan.q_start_rad, plan.joint, plan.direction, t, seed=seed
        )
        z = held_out_z(table, folds=10, random_state=0)
        # folds=0: the bundle's GP std stays uncalibrated (factor 1); the rules scale it
        model = train_delay_models(table, methods="gpr", folds=0, random_state=0).model
        factors = {
            "gp": dict.fromkeys(KEYS, 1.0),
            "rms": {k: std_scale_factor(z[k], np.ones_like(z[k])) for k in KEYS},
            "q95": {k: max(1.0, float(np.quantile(np.abs(z[k]), 0.95)) / 1.959964) for k in KEYS},
        }
        parts = []
        for k in range(10):
            held = SweepPlan.generate(args.robot, n, seed=100_000 + 100 * seed + k)
            first = held.repeat == 0
            parts.append(
                (held.q_start_rad[first], held.joint[first], held.direction[first], t[first])
            )
        q, j, d, tt = (np.concatenate([p[i] for p in parts]) for i in range(4))
        truth = simulate_delays(args.robot, q, j, d, tt, seed=50_000 + seed)
        y = np.asarray(truth["actuation_delay"], float)
        pred = model.predict_many(j, d, q)
        own = np.array([model.gp_std_scale("actuation_delay", int(x)) for x in j])
        raw_std = pred.actuation_std / own
        for name, fac in factors.items():
            c = np.array([fac[str(int(x))] for x in j])
            inside = TimingBounds.around(pred.actuation_mean, raw_std * c, 0.95, period).contains(y)
            cover[name].append(
                [float(np.mean(inside))] + [float(np.mean(inside[j == x])) for x in (1, 2, 3, 5)]
            )
    load = os.getloadavg()[0]
    print(
        f"{args.robot}, {n} training trials, {args.sweeps} sweeps, {len(y)} held-out trials "
        f"each; {time.perf_counter() - start:.0f} s at load {load:.1f}"
    )
    print(f"{'std':5} {'coverage':>9} {'range':>13}   per joint (1, 2, 3, 5)")
    base = float(np.mean([c[0] for c in cover["gp"]]))
    for name, rows in cover.items():
        v = np.array(rows)
        joints = " ".join(f"{x:.3f}" for x in v[:, 1:].mean(axis=0))
        print(
            f"{name:5} {v[:, 0].mean():9.3f} {v[:, 0].min():6.3f}-{v[:, 0].max():.3f}   {joints}"
            f"   ({v[:, 0].mean() - base:+.3f} vs gp)"
        )


if __name__ == "__main__":
    main()
