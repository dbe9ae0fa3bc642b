"""The response delay on compliant joints read by motor-side encoders (issue 37).

Recordings come from ``tests/compliant_sweep.py`` (a hysteretic, stiffening gear between a
motor-side encoder and a gravity-loaded link; its own sensor chain, oscillator and USB;
written in the documented format, no ``timedexec.sim``). For every condition and joint it
prints the response delay's RMSE and bias against the age of the motor-side sample, the
coverage of the per-trial 95 % intervals (``delay ± 1.96·se``) — all on the trials whose
response delay may be used (no ``flag``, no ``response_flag``) — the count of trials with
a ``response_flag`` ("rf."; "all N rf.": every one, as for a joint flagged as a whole,
``deflection_joint``) and with a ``flag`` ("fl."), and the actuation RMSE (every unflagged
trial, response-flagged ones included) — for this worktree's extractor and, in the same
run, a reference revision's
(``--ref REV``, default ``main``: checked out into a temporary ``git worktree`` and run in a
subprocess with its own ``src`` first on the path).

Conditions: UR10-like and KR 5-like arms, clean, 2x and 5x the gyro noise, 150 ppm of
clock drift on a -1500 ppm offset, 2 % lost and 0.5 % duplicated USB transfers; with
``--controls`` also the same arms with gears 100x stiffer (nothing to separate), without
hysteresis, and with a hysteresis loop as wide at every load as at the rated torque.

Targets (issue 37): response RMSE <= 0.2 ms and |bias| <= 0.1 ms on every joint (or the
affected trials flagged with a reason), 95 % intervals covering the truth on 90-98 % of
trials per joint and condition, actuation RMSE <= 0.15 ms clean. A cell that misses the
accuracy target is marked "!", one whose coverage is outside 90-98 % "~" (with ~40-60
trials per joint, a perfectly calibrated interval lands outside that band on about one
cell in eight by chance: the binomial sd is ~3 %).

Usage: python benchmarks/bench_extract_compliant.py [--trials 200] [--seed 1]
       [--only ur10,kr5] [--ref main | --ref none] [--cache DIR] [--controls]
"""

from __future__ import annotations

import argparse
import hashlib
import math
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from compliant_sweep import CompliantConditions, write_compliant_sweep  # noqa: E402

CONDITIONS: list[tuple[str, CompliantConditions]] = [
    ("clean", CompliantConditions()),
    ("noise 2x", CompliantConditions(noise_factor=2.0)),
    ("noise 5x", CompliantConditions(noise_factor=5.0)),
    ("drift 150 ppm", CompliantConditions(clock_offset_ppm=-1500.0, clock_drift_ppm=150.0)),
    ("2 % lost, 0.5 % dup", CompliantConditions(transfer_loss=0.02, transfer_dup=0.005)),
]
CONTROLS: list[tuple[str, CompliantConditions]] = [
    ("gears 100x stiffer", CompliantConditions(stiffness_scale=100.0)),
    ("no hysteresis", CompliantConditions(hysteresis_scale=0.0)),
    ("hysteresis not load-dependent", CompliantConditions(hysteresis_load=False)),
]
COLUMNS = ("trial", "joint", "flag", "actuation_delay", "true_actuation_delay",
           "response_delay", "true_response_delay", "response_delay_se")  # fmt: skip
#: The response-only verdict (absent from an older extractor's table: nothing flagged).
RESPONSE_FLAG = "response_flag"
JOINTS = (1, 2, 3, 5)

#: Runs a revision's extractor on one recording; its columns to an .npz (subprocess).
_RUNNER = """
import sys, numpy as np
from timedexec.extraction import extract_recording
t = extract_recording(sys.argv[1], progress=False).table
cols = {k: np.asarray(t[k]) for k in sys.argv[3].split(",") if k in t}
cols["flag"] = np.array([str(f) for f in t["flag"]])
cols["response_flag"] = np.array([str(f) for f in t["response_flag"]] if "response_flag" in t
                                 else [""] * len(t))
np.savez(sys.argv[2], **cols)
"""


def extract_with(src: Path | None, path: Path, out: Path) -> dict[str, Any]:
    """The table's columns from the extractor under ``src`` (None: this worktree's)."""
    env = None
    if src is not None:
        import os

        env = dict(os.environ, PYTHONPATH=str(src))
    subprocess.run([sys.executable, "-c", _RUNNER, str(path), str(out), ",".join(COLUMNS)],
                   check=True, env=env)  # fmt: skip
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def score(t: dict[str, Any], joint: int | None) -> dict[str, float]:
    """Response RMSE, bias (ms) and 95 % coverage (%) of one joint's (None: all) trials
    without a flag or a response flag, the counts of response-flagged and flagged trials,
    and the actuation RMSE (ms) of the unflagged ones."""
    sel = np.ones(t["joint"].size, bool) if joint is None else t["joint"] == joint
    ok = sel & (t["flag"] == "")
    rf = ok & (t[RESPONSE_FLAG] != "")
    use = ok & ~rf
    err = (t["response_delay"] - t["true_response_delay"])[use] * 1e3
    act = (t["actuation_delay"] - t["true_actuation_delay"])[ok] * 1e3
    se = (
        t["response_delay_se"][use] * 1e3 if "response_delay_se" in t else np.full(err.size, np.nan)
    )
    nan = math.nan
    return {
        "rmse": float(np.sqrt(np.mean(err**2))) if err.size else nan,
        "bias": float(np.mean(err)) if err.size else nan,
        "cover": float(100 * np.mean(np.abs(err) <= 1.96 * se)) if err.size else nan,
        "response_flagged": float(np.sum(rf)),
        "flagged": float(np.sum(sel & (t["flag"] != ""))),
        "n": float(np.sum(sel)),
        "act": float(np.sqrt(np.mean(act**2))) if act.size else nan,
    }


def cell(s: dict[str, float]) -> str:
    if not s["response_flagged"] < s["n"] - s["flagged"]:  # nothing left to score
        return f"all {s['response_flagged']:.0f} rf." + (
            f", {s['flagged']:.0f} fl." if s["flagged"] else ""
        )
    miss = "!" if s["rmse"] > 0.2 or abs(s["bias"]) > 0.1 else ""
    off = "~" if not 89.5 <= s["cover"] <= 98.5 else ""
    return (f"{s['rmse']:.3f} ({s['bias']:+.3f}){miss} {s['cover']:.0f} %{off}"
            + (f", {s['response_flagged']:.0f} rf." if s["response_flagged"] else "")
            + (f", {s['flagged']:.0f} fl." if s["flagged"] else ""))  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", default="ur10,kr5", help="comma list of arms")
    ap.add_argument("--ref", default="main", help="revision to compare with ('none': skip)")
    ap.add_argument("--cache", type=Path, help="keep generated recordings here")
    ap.add_argument("--controls", action="store_true", help="also stiff and hysteresis-free gears")
    args = ap.parse_args()
    conditions = CONDITIONS + (CONTROLS if args.controls else [])
    with tempfile.TemporaryDirectory() as tmp:
        tmp_p = Path(tmp)
        cache = args.cache or tmp_p
        cache.mkdir(parents=True, exist_ok=True)
        ref_src = None
        if args.ref != "none":
            wt = tmp_p / "ref"
            repo = HERE.parent
            subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", str(wt),
                            args.ref], check=True, capture_output=True)  # fmt: skip
            ref_src = wt / "src"
        try:
            print(
                f"compliant recordings, {args.trials} trials each (seed {args.seed}); "
                "response RMSE (bias) in ms, 95 % coverage (trials without a flag or a "
                "response flag), response-flagged (rf.), flagged (fl.); actuation RMSE ms"
            )
            head = "| arm | condition | extractor | " + " | ".join(f"joint {j}" for j in JOINTS)
            print(head + " | all | actuation |")
            print("|---" * (len(JOINTS) + 5) + "|")
            for arm in args.only.split(","):
                for label, cond in conditions:
                    key = hashlib.sha1(f"{arm}|{args.trials}|{args.seed}|{cond!r}".encode())
                    path = cache / f"compliant-{arm}-{key.hexdigest()[:12]}.h5"
                    if not path.exists():
                        write_compliant_sweep(path, arm, args.trials, cond, seed=args.seed)
                    runs = [("this", None)] + ([(args.ref, ref_src)] if ref_src else [])
                    for name, src in runs:
                        t = extract_with(src, path, tmp_p / "t.npz")
                        cells = [cell(score(t, j)) for j in JOINTS]
                        whole = score(t, None)
                        print(f"| {arm} | {label} | {name} | " + " | ".join(cells)
                              + f" | {cell(whole)} | {whole['act']:.3f} |", flush=True)  # fmt: skip
        finally:
            if ref_src is not None:
                subprocess.run(["git", "-C", str(HERE.parent), "worktree", "remove", "--force",
                                str(tmp_p / "ref")], check=False, capture_output=True)  # fmt: skip


if __name__ == "__main__":
    main()
