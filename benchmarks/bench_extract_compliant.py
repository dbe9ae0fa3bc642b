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
accuracy target is marked "!", one whose coverage is outside 90-98 % "~"; beside each
coverage, the binomial 90 % range of a calibrated interval on as many trials (with ~50
trials per joint a calibrated interval lands outside 90-98 % on about one cell in eight by
chance; with the default 1000 trials per condition, ~130-270 per joint, on 0.2-1.6 %). Part of
the error is one draw per joint and sweep (``response_delay_shared_se``), so coverage is
pooled over the seeds given (``--seed 1,5``) at the end, and the shared part is checked on
its own: per chunk of the extraction (512 trials), z = the joint's mean error over its
standard error (|z| <= 1.96 on 95 % of them if honest), and the trials' own part's
coverage about that mean.

Usage: python benchmarks/bench_extract_compliant.py [--trials 1000] [--seed 1,5]
       [--only ur10,kr5] [--ref main | --ref none] [--cache DIR] [--dump DIR] [--controls]
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
           "response_delay", "true_response_delay", "response_delay_se",
           "response_delay_shared_se")  # fmt: skip
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


#: Trials per vectorised chunk of the extraction (``extract_recording``'s default): the
#: joint-wide statistics (the shrinkage's median, the deflection decision) are a chunk's.
CHUNK_TRIALS = 512


def binomial_range(n: int, p: float = 0.95, mass: float = 0.90) -> tuple[float, float]:
    """The central ``mass`` range (%) of the share of n trials a calibrated ``p`` interval
    covers (binomial): where a cell's coverage lands by chance alone."""
    from scipy.stats import binom

    lo = binom.ppf((1 - mass) / 2, n, p) / n
    hi = binom.ppf(1 - (1 - mass) / 2, n, p) / n
    return 100 * float(lo), 100 * float(hi)


def score(t: dict[str, Any], joint: int | None) -> dict[str, Any]:
    """Response RMSE, bias (ms) and 95 % coverage (%) of one joint's (None: all) trials
    without a flag or a response flag, the counts of response-flagged and flagged trials,
    and the actuation RMSE (ms) of the unflagged ones; and the shared error's check (one
    joint only): per chunk of the extraction, z = the joint's mean error over its
    standard error (the shared part's rms and the trials' own parts averaged), and the
    coverage of each trial's own part (``response_delay_se`` without the shared part)
    about its chunk's mean error."""
    sel = np.ones(t["joint"].size, bool) if joint is None else t["joint"] == joint
    ok = sel & (t["flag"] == "")
    rf = ok & (t[RESPONSE_FLAG] != "")
    use = ok & ~rf
    err = (t["response_delay"] - t["true_response_delay"])[use] * 1e3
    act = (t["actuation_delay"] - t["true_actuation_delay"])[ok] * 1e3
    nan_col = np.full(t["joint"].size, np.nan)
    se = t.get("response_delay_se", nan_col)[use] * 1e3
    shared = t.get("response_delay_shared_se", np.zeros(t["joint"].size))[use] * 1e3
    own = np.sqrt(np.maximum(se**2 - shared**2, 0.0))
    nan = math.nan
    z: list[float] = []
    own_hit = np.zeros(err.size, bool)
    if joint is not None:
        chunk = t["trial"][use] // CHUNK_TRIALS
        for c in np.unique(chunk):
            m = chunk == c
            if m.sum() < 10:
                continue
            mean = float(np.mean(err[m]))
            sd = math.sqrt(float(np.mean(shared[m] ** 2) + np.mean(own[m] ** 2) / m.sum()))
            z.append(mean / sd if sd > 0 else math.inf)
            own_hit[m] = np.abs(err[m] - mean) <= 1.96 * own[m]
    return {
        "rmse": float(np.sqrt(np.mean(err**2))) if err.size else nan,
        "bias": float(np.mean(err)) if err.size else nan,
        "cover": float(100 * np.mean(np.abs(err) <= 1.96 * se)) if err.size else nan,
        "hits": int(np.sum(np.abs(err) <= 1.96 * se)),
        "used": int(err.size),
        "own_cover": float(100 * np.mean(own_hit)) if err.size and z else nan,
        "own_hits": int(np.sum(own_hit)) if z else 0,
        "z": z,
        "shared_ms": float(np.sqrt(np.mean(shared**2))) if err.size else nan,
        "response_flagged": float(np.sum(rf)),
        "flagged": float(np.sum(sel & (t["flag"] != ""))),
        "n": float(np.sum(sel)),
        "act": float(np.sqrt(np.mean(act**2))) if act.size else nan,
    }


def cell(s: dict[str, Any]) -> str:
    """One joint's figures: RMSE (bias) ms, coverage % [the binomial 90 % range of a
    calibrated interval on as many trials], flags."""
    if not s["response_flagged"] < s["n"] - s["flagged"]:  # nothing left to score
        return f"all {s['response_flagged']:.0f} rf." + (
            f", {s['flagged']:.0f} fl." if s["flagged"] else ""
        )
    miss = "!" if s["rmse"] > 0.2 or abs(s["bias"]) > 0.1 else ""
    off = "~" if not 89.5 <= s["cover"] <= 98.5 else ""
    lo, hi = binomial_range(s["used"])
    return (f"{s['rmse']:.3f} ({s['bias']:+.3f}){miss} {s['cover']:.1f} %{off} "
            f"[{lo:.0f}-{hi:.0f}]"
            + (f", {s['response_flagged']:.0f} rf." if s["response_flagged"] else "")
            + (f", {s['flagged']:.0f} fl." if s["flagged"] else ""))  # fmt: skip


def shared_cell(s: dict[str, Any]) -> str:
    """The shared error's check of one joint: the shared part's rms (ms), z of the joint's
    mean error per chunk, and the coverage (%) of the trials' own part about it."""
    if not s["z"]:
        return "-"
    zs = "/".join(f"{z:+.1f}" for z in s["z"])
    return f"{s['shared_ms']:.3f}, z {zs}, own {s['own_cover']:.1f} %"


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--seed", default="1", help="seed, or a comma list: pooled at the end")
    ap.add_argument("--only", default="ur10,kr5", help="comma list of arms")
    ap.add_argument("--ref", default="main", help="revision to compare with ('none': skip)")
    ap.add_argument("--cache", type=Path, help="keep generated recordings here")
    ap.add_argument("--dump", type=Path, help="keep each extracted table (.npz) here")
    ap.add_argument("--controls", action="store_true", help="also stiff and hysteresis-free gears")
    args = ap.parse_args()
    conditions = CONDITIONS + (CONTROLS if args.controls else [])
    seeds = [int(x) for x in args.seed.split(",")]
    # Pooled over the seeds, per extractor, arm, condition and joint: covered, used, z.
    pooled: dict[tuple[str, str, str, int], list[Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp_p = Path(tmp)
        cache = args.cache or tmp_p
        cache.mkdir(parents=True, exist_ok=True)
        if args.dump:
            args.dump.mkdir(parents=True, exist_ok=True)
        ref_src = None
        if args.ref != "none":
            wt = tmp_p / "ref"
            repo = HERE.parent
            subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", str(wt),
                            args.ref], check=True, capture_output=True)  # fmt: skip
            ref_src = wt / "src"
        try:
            print(
                f"compliant recordings, {args.trials} trials each (seeds {args.seed}); "
                "response RMSE (bias) in ms, 95 % coverage [binomial 90 % range of a "
                "calibrated interval] (trials without a flag or a response flag), "
                "response-flagged (rf.), flagged (fl.); actuation RMSE ms"
            )
            head = "| arm | condition | seed | extractor | " + " | ".join(
                f"joint {j}" for j in JOINTS
            )
            print(head + " | all | actuation |")
            print("|---" * (len(JOINTS) + 6) + "|")
            shared_rows = []
            for arm in args.only.split(","):
                for label, cond in conditions:
                    for seed in seeds:
                        key = hashlib.sha1(f"{arm}|{args.trials}|{seed}|{cond!r}".encode())
                        path = cache / f"compliant-{arm}-{key.hexdigest()[:12]}.h5"
                        if not path.exists():
                            write_compliant_sweep(path, arm, args.trials, cond, seed=seed)
                        runs = [("this", None)] + ([(args.ref, ref_src)] if ref_src else [])
                        for name, src in runs:
                            out = tmp_p / "t.npz"
                            if args.dump:
                                out = args.dump / f"{name}-{arm}-{seed}-{label}.npz".replace(
                                    " ", "_").replace("/", "_").replace("%", "pc")  # fmt: skip
                            t = extract_with(src, path, out)
                            scores = {j: score(t, j) for j in JOINTS}
                            for j, sc in scores.items():
                                acc = pooled.setdefault((name, arm, label, j), [0, 0, []])
                                acc[0] += sc["hits"]
                                acc[1] += sc["used"]
                                acc[2] += sc["z"]
                            whole = score(t, None)
                            print(f"| {arm} | {label} | {seed} | {name} | "
                                  + " | ".join(cell(scores[j]) for j in JOINTS)
                                  + f" | {cell(whole)} | {whole['act']:.3f} |", flush=True)  # fmt: skip
                            shared_rows.append(f"| {arm} | {label} | {seed} | {name} | "
                                               + " | ".join(shared_cell(scores[j])
                                                            for j in JOINTS) + " |")  # fmt: skip
            print(
                "\nthe shared error per joint: its rms (ms); z of the joint's mean error "
                "per chunk of the extraction (|z| <= 1.96 on 95 % of them if honest); "
                "coverage of the trials' own part about their chunk's mean error"
            )
            print(
                "| arm | condition | seed | extractor | "
                + " | ".join(f"joint {j}" for j in JOINTS)
                + " |"
            )
            print("|---" * (len(JOINTS) + 4) + "|")
            print("\n".join(shared_rows))
            print_pooled(pooled)
        finally:
            if ref_src is not None:
                subprocess.run(["git", "-C", str(HERE.parent), "worktree", "remove", "--force",
                                str(tmp_p / "ref")], check=False, capture_output=True)  # fmt: skip


def print_pooled(pooled: dict[tuple[str, str, str, int], list[Any]]) -> None:
    """Coverage pooled over the seeds per joint and condition, with the binomial range,
    and per extractor the share of joint-chunks whose mean error is within 1.96 and 1
    shared standard errors."""
    print("\npooled over the seeds: coverage % [binomial 90 % range] (cells outside 90-98 %: ~)")
    names = sorted({k[0] for k in pooled})
    for name in names:
        print(f"\n{name}:\n| arm | condition | " + " | ".join(f"joint {j}" for j in JOINTS)
              + " |\n" + "|---" * (len(JOINTS) + 2) + "|")  # fmt: skip
        rows: dict[tuple[str, str], list[str]] = {}
        zs: list[float] = []
        out_band = cells = 0
        for (n_, arm, label, _j), (hits, used, z) in pooled.items():
            if n_ != name:
                continue
            zs += z
            if used == 0:
                rows.setdefault((arm, label), []).append("-")
                continue
            cover = 100 * hits / used
            lo, hi = binomial_range(used)
            off = not 89.5 <= cover <= 98.5
            out_band += off
            cells += 1
            rows.setdefault((arm, label), []).append(
                f"{cover:.1f}{'~' if off else ''} [{lo:.0f}-{hi:.0f}] ({used})"
            )
        for (arm, label), c in rows.items():
            print(f"| {arm} | {label} | " + " | ".join(c) + " |")
        za = np.abs(np.array(zs))
        print(
            f"{out_band} of {cells} cells outside 90-98 %; joint-chunks' mean error within "
            f"1.96 shared se: {100 * np.mean(za <= 1.96):.0f} %, within 1: "
            f"{100 * np.mean(za <= 1):.0f} % (of {za.size}; a calibrated shared error "
            "gives 95 and 68 %)"
        )


if __name__ == "__main__":
    main()
