"""How well *could* the actuation onset be timed on the independent recordings?

The extractor models the speed near the onset locally (a cubic; ``timedexec.extraction``)
and reports the Cramér-Rao bound of *that* model. This script computes the bound of an
estimator that knows the independent generator's physics exactly
(``tests/independent_sweep.py``: PI velocity loop, two-mass joint, stiction, Butterworth
sensor filter, white noise) and sees the whole trial (out and back pulse at 8 kHz). With
the trial's own joint unknown (``+joint``: no estimator can know it) it bounds the error
of every unbiased estimator of the 10 % crossing on those recordings — even one built on
that generator's physics, which the extractor deliberately is not.

For each drawn joint the Fisher information of the gyro samples is ``JᵀJ/σ²`` (J: the
derivatives of the sensor's output with respect to the unknowns, central differences of
the generator's own simulation on a 64 kHz grid), and the bound of the crossing time T is
``∇Tᵀ F⁻¹ ∇T``. The unknowns, from most to least known:

* ``shift``: only the dead time (everything else about the joint known);
* ``+gain``: and the gyro's gain (the extraction calibrates it to ~1 %);
* ``+joint``: and the trial's own joint (load inertia, resonance, damping, stiction:
  they change with the pose and from trial to trial, so no estimator knows them);
* ``+loop``: and the velocity loop's bandwidth (a robot constant, unknown to a user).

Usage: python benchmarks/crb_independent_physics.py [--robot ur10] [--joints 24]
       [--noise 1,10,20]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from scipy import signal

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from independent_sweep import (  # noqa: E402
    BASE_NOISE_DPS_RTHZ,
    ONSET_FRACTION,
    ROBOTS,
    joint_params,
    joint_response,
)

FS = 8000.0
PROF = {"speed_rad_s": 0.4, "acceleration_rad_s2": 8.0, "hold_s": 0.05, "pause_s": 0.15,
        "pre_s": 0.05, "record_s": 0.65}  # fmt: skip
DT_PHYS = 1.0 / 64000  # finer than the generator's 16 kHz: stiction's release is a grid step
#: Central-difference steps of the unknowns (absolute; t_break spans several grid steps).
STEPS = {"shift": 2e-5, "gain": 1e-3, "jl": 5e-3, "f_res": 0.05, "zeta": 2e-3,
         "t_break": 2e-4, "bw": 0.05}  # fmt: skip
SETS = {
    "shift": ("shift",),
    "+gain": ("shift", "gain"),
    "+joint": ("shift", "gain", "jl", "f_res", "zeta", "t_break"),
    "+loop": ("shift", "gain", "jl", "f_res", "zeta", "t_break", "bw"),
}


def observe(
    par: dict[str, np.ndarray], shift: np.ndarray, gain: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sensor output at 8 kHz (rad/s, before noise) and the 10 % crossing time (s)."""
    grid = -0.01 + np.arange(round(0.7 / DT_PHYS)) * DT_PHYS
    n = shift.size
    w, _ = joint_response(par, shift, np.ones(n), grid, PROF)
    level = ONSET_FRACTION * PROF["speed_rad_s"]
    above = (w >= level) & (grid > 0)
    k = np.argmax(above, axis=1)
    r = np.arange(n)
    w0, w1 = w[r, k - 1], w[r, k]
    onset = grid[k - 1] + (level - w0) / (w1 - w0) * DT_PHYS
    t_s = np.arange(0.0, 0.66, 1.0 / FS)
    ws = np.array([np.interp(t_s, grid, row) for row in w])
    b, a = signal.butter(2, 230.0, fs=FS)
    return gain[:, None] * signal.lfilter(b, a, ws, axis=1), onset


def bounds(robot: str, n_joints: int, seed: int) -> dict[str, np.ndarray]:
    """sqrt(CRB) of the crossing at unit noise (σ = 1 rad/s per sample), per set, per joint."""
    rng = np.random.default_rng(seed)
    base = joint_params(rng, n_joints, float(ROBOTS[robot]["bw"]), PROF)
    base["shift"] = np.full(n_joints, 0.02)
    base["gain"] = np.ones(n_joints)
    names = SETS["+loop"]
    jac, grad = {}, {}
    for name in names:
        h = STEPS[name]
        sides = []
        for sgn in (1.0, -1.0):
            p = {k: v.copy() for k, v in base.items()}
            p[name] = p[name] + sgn * h
            sides.append(observe(p, p["shift"], p["gain"]))
        jac[name] = (sides[0][0] - sides[1][0]) / (2 * h)
        grad[name] = (sides[0][1] - sides[1][1]) / (2 * h)
    out = {}
    for label, unknowns in SETS.items():
        sd = np.empty(n_joints)
        for i in range(n_joints):
            j = np.stack([jac[u][i] for u in unknowns], axis=1)
            g = np.array([grad[u][i] for u in unknowns])
            fisher = j.T @ j
            sd[i] = math.sqrt(float(g @ np.linalg.solve(fisher, g)))
        out[label] = sd
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--robot", default="ur10", choices=sorted(ROBOTS))
    ap.add_argument("--joints", type=int, default=24)
    ap.add_argument("--noise", default="1,10,20")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    unit = bounds(args.robot, args.joints, args.seed)
    print(f"{args.robot}: bound of the 10 % crossing time (RMS over {args.joints} joints), ms")
    print("| noise | σ per sample (rad/s) | " + " | ".join(SETS) + " |")
    print("|---" * (len(SETS) + 2) + "|")
    for k in (float(x) for x in args.noise.split(",")):
        sigma = math.radians(BASE_NOISE_DPS_RTHZ * k * math.sqrt(FS / 2))
        cells = [f"{1e3 * sigma * math.sqrt(np.mean(unit[s] ** 2)):.3f}" for s in SETS]
        print(f"| {k:g}x | {sigma:.4f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
