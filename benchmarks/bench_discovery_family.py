"""Discovery beyond the vocabulary on an independent randomised family (issue 36): per-case
outcomes and the rates the issue asks for.

The cases come from ``tests/discovery_cases.py``: terms outside the vocabulary (cables,
periodic drive terms, local bumps in one or two angles, one-direction terms, terms shared
by two joints, the gravity torque of another joint, steps and products the library does
not hold), simulated through run-time registered effects with trial noise (per-trial noise 0.6-1.4 ms,
the issue's regime; ``--regime floor``: the noise floor of a condition mean 0.6-1.4 ms,
3.2x more noise), 3,200-4,800 trials per table, nulls and vocabulary controls.

Acceptance (issue 36): out of vocabulary, no vocabulary name, a discovered term whose
joints and inputs contain the true ones and an actuation gap after <= 1.25 x the floor or
<= 0.4 x the gap before in >= 80 %; nulls: nothing named and nothing discovered in >= 7 of
8; controls named right with nothing discovered; the discovered size within 20 % of the
generator's where the form is in the library.

Usage: python benchmarks/bench_discovery_family.py [--outside 30] [--nulls 10]
       [--controls 8] [--seed 36] [--only d003,d017] [--json out.json] [--verbose]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from threadpoolctl import threadpool_limits

from discovery_cases import KINDS, discovery_family, judge
from timedexec.discrepancy import analyse_discrepancy


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--outside", type=int, default=30, help="out-of-vocabulary tables (30)")
    ap.add_argument("--nulls", type=int, default=10, help="null tables (10)")
    ap.add_argument("--controls", type=int, default=8, help="vocabulary controls (8)")
    ap.add_argument("--seed", type=int, default=36, help="family seed (default 36)")
    ap.add_argument(
        "--regime",
        default="trial",
        choices=("trial", "floor"),
        help="trial: per-trial noise 0.6-1.4 ms (the issue's); floor: noise floor of a "
        "condition mean 0.6-1.4 ms (harder)",
    )
    ap.add_argument("--only", default="", help="comma list of case ids to run")
    ap.add_argument("--json", default="", help="write per-case results to this file")
    ap.add_argument("--verbose", action="store_true", help="print every case as it ends")
    args = ap.parse_args()
    cases = discovery_family(
        args.outside, args.nulls, args.controls, seed=args.seed, regime=args.regime
    )
    if args.only:
        keep = set(args.only.split(","))
        cases = [c for c in cases if c.case_id in keep]
    print(
        f"discovery family: {len(cases)} tables (seed {args.seed}, regime {args.regime})",
        flush=True,
    )
    per_kind: dict[str, list[bool]] = defaultdict(list)
    rows: list[dict[str, Any]] = []
    misses: list[str] = []
    walls: list[float] = []
    pinned = 0
    size_errors: list[tuple[str, float]] = []
    t_all = time.perf_counter()
    for case in cases:
        table = case.table()
        t0 = time.perf_counter()
        with threadpool_limits(1):
            result = analyse_discrepancy(table, start=case.start_effects, seed=0)
        wall = time.perf_counter() - t0
        walls.append(wall)
        v = judge(case, result)
        per_kind[case.kind].append(v.right)
        pinned += v.pinned
        if v.size_error is not None:
            size_errors.append((case.case_id, v.size_error))
        a = "actuation_delay"
        line = (
            f"{case.describe()}\n      -> named {list(v.named) or '-'}; discovered "
            f"{list(v.discovered) or '-'}; act gap {result.gap_before_ms[a]:.2f} -> "
            f"{result.gap_after_ms[a]:.2f} ms (floor {result.noise_floor_ms[a]:.2f}, "
            f"{v.gap_ratio:.2f} x)"
            + (f"; size error {100 * v.size_error:.0f} %" if v.size_error is not None else "")
            + f"; {wall:.1f} s"
        )
        if not v.right:
            misses.append(line + "\n      MISS: " + "; ".join(v.reasons))
        if args.verbose:
            print(("ok   " if v.right else "MISS ") + line, flush=True)
        rows.append(
            {
                "case": case.case_id,
                "kind": case.kind,
                "description": case.describe(),
                "named": list(v.named),
                "discovered": result.to_dict().get("discovered", []),
                "unexplained": [
                    {k: u[k] for k in ("delay", "joints", "variable")} for u in result.unexplained
                ],
                "gap_before_ms": result.gap_before_ms,
                "gap_after_ms": result.gap_after_ms,
                "noise_floor_ms": result.noise_floor_ms,
                "right": v.right,
                "pinned": v.pinned,
                "located": v.located,
                "size_error": v.size_error,
                "reasons": list(v.reasons),
                "trials": result.n_trials,
                "runtime_s": wall,
            }
        )
    print()
    for kind in KINDS:
        res = per_kind.get(kind, [])
        if res:
            print(f"  {kind:8s} right {sum(res):3d}/{len(res):3d} = {100 * sum(res) / len(res):5.1f} %")
    n_out = len(per_kind.get("outside", []))
    if n_out:
        print(f"  outside pinned on a vocabulary name: {pinned}/{n_out}")
    if size_errors:
        within = sum(e <= 0.2 for _, e in size_errors)
        print(
            f"  fitted size within 20 % (form in the library): {within}/{len(size_errors)}; "
            + ", ".join(f"{c} {100 * e:.0f} %" for c, e in size_errors)
        )
    walls_sorted = sorted(walls)
    print(
        f"analysis time per table: median {walls_sorted[len(walls) // 2]:.1f} s, max "
        f"{max(walls):.1f} s; total with generation {time.perf_counter() - t_all:.0f} s"
    )
    if misses:
        print(f"\nmisses ({len(misses)}):")
        for m in misses:
            print("  " + m)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
