"""DelayMonitor through the real ur_rtde client against the UR twin, with a drive that
changes in service.

Each run: a UR10e twin (its own process, default effects without thermal drift) and a
TimedExecutor over ur_rtde; executions move joints 1, 2 and 3 together out and back (0.05
rad, rests of 0.35 s), the monitor follows the executor's log with a 20-move warm-up per
joint. After ``--warmup`` executions the twin's joint 2 drive takes its setpoint
``--step-ms`` later (``ControllerSim.set_joint_offsets``, switched by a flag file the twin
checks every 50 cycles); ``--after`` executions follow. Printed per run: alarms before the
change (false), the first alarm after it (joint, moves of that joint since the change,
the estimated shift and its 95 % interval), and the residual spread per joint. With
``--step-ms 0`` the run measures false alarms only.

    nice -n 5 python benchmarks/bench_monitor_twin.py [--runs 3] [--warmup 50] [--after 80]
        [--step-ms 2] [--joint 2]

A real-time twin on a shared two-core VM: the executor's send times wander with the load,
which the monitor sees as timing noise common to the joints of a move.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def stepped_sim(robot: str, *, effects: Any, q0_rad: Any, seed: int) -> Any:
    """The twin's simulated controller; its ``joint`` drive gets ``extra_s`` more offset
    once the file named by TIMEDEXEC_BENCH_STEP_FLAG exists (env: path, joint, extra_s)."""
    from timedexec.sim import ControllerSim

    flag = os.environ["TIMEDEXEC_BENCH_STEP_FLAG"]
    joint = int(os.environ["TIMEDEXEC_BENCH_STEP_JOINT"])
    extra_s = float(os.environ["TIMEDEXEC_BENCH_STEP_S"])

    class Stepped(ControllerSim):
        stepped = False

        def cycle(self):  # type: ignore[no-untyped-def]
            if not self.stepped and self.cycle_index % 50 == 0 and os.path.exists(flag):
                off = np.array(self._offset_s)
                off[joint - 1] += extra_s
                self.set_joint_offsets(off)
                self.stepped = True
            return super().cycle()

    return Stepped(robot, effects=effects, q0_rad=q0_rad, seed=seed, physics_rate_hz=4000.0)


class Tally:
    """The alerts of one run: false before the change (the joint re-baselined, as an
    operator would), every one after it, and the first joint alarm after it (a common-shift
    alert names no changed joint)."""

    def __init__(self) -> None:
        self.false_before: list[str] = []
        self.after_all: list[str] = []
        self.first_after: Any = None

    def take(self, mon: Any, alerts: list[Any], moves_at_step: dict[int, int]) -> None:
        for a in alerts:
            if not moves_at_step:
                self.false_before.append(a.message())
                if a.test != "common":
                    mon.rebaseline(a.joint)
                continue
            moves = a.move - moves_at_step.get(a.joint, 0)
            self.after_all.append(
                f"joint {a.joint} ({a.test}) after {moves} of its moves: {a.shift_ms:+.2f} ms"
            )
            if self.first_after is None and a.test != "common":
                self.first_after = a


def one_run(seed: int, args: argparse.Namespace) -> dict[str, Any]:
    from timedexec.drivers import URDriver
    from timedexec.effects import EffectSet, default_effects
    from timedexec.errors import ConfigError
    from timedexec.execution import (
        ExecutorSettings,
        StalenessLimits,
        TimedExecutor,
        predict_delays,
    )
    from timedexec.learning import DelayModel
    from timedexec.monitoring import DelayMonitor
    from timedexec.robots import get_robot
    from timedexec.twins import URTwin

    host = f"127.0.0.{60 + seed}"
    flag = Path(tempfile.mkdtemp()) / "step"
    os.environ.update(
        TIMEDEXEC_BENCH_STEP_FLAG=str(flag),
        TIMEDEXEC_BENCH_STEP_JOINT=str(args.joint),
        TIMEDEXEC_BENCH_STEP_S=str(args.step_ms * 1e-3),
    )
    effects = EffectSet(tuple(e for e in default_effects("ur10e") if e.name != "thermal_drift"))
    q0 = np.array(get_robot("ur10e").home_q_rad)
    q0[1] += 0.3
    model = DelayModel.load("ur10e-sim")
    for d in (1, -1):  # build the GP predictors before connecting (the watchdog)
        predict_delays(model, [1, 2, 3], [d] * 3, np.tile(q0, (3, 1)))
    mon = DelayMonitor(model, warmup_moves=args.warmup_moves, reference_k=args.k)
    # Tolerant limits (200 periods) and watchdog (1 s): the monitor, not the faults.
    settings = ExecutorSettings(
        staleness=StalenessLimits.from_stale_periods(200), watchdog_timeout_s=1.0
    )
    moves_at_step: dict[int, int] = {}
    tally = Tally()
    rows_at_step = 0
    with (
        URTwin("ur10e", host, seed=seed, effects=effects, q0_rad=q0, sim_factory=stepped_sim),
        TimedExecutor(URDriver(host), model, settings) as ex,
    ):
        start = ex.estimate().q_rad
        for k in range(args.warmup + args.after):
            if k == args.warmup:
                mon.follow(ex)
                moves_at_step = {s.joint: s.moves for s in mon.states()}
                rows_at_step = len(ex.log)
                flag.touch()
                ex.idle(ex.now() + 0.2)  # the twin checks the flag every 50 cycles
            target = start.copy()
            target[:3] += 0.05 if k % 2 == 0 else 0.0
            ex.idle(ex.now() + 0.35)
            try:
                ex.execute(ex.plan(target), start_time_s=ex.now() + 0.5)
            except ConfigError as exc:  # the VM stalled past the start time
                if "too soon" not in str(exc):
                    raise
                continue
            tally.take(mon, mon.follow(ex), moves_at_step)
            if tally.first_after is not None and not args.full:
                break
        ex.idle(ex.now() + 0.5)
        tally.take(mon, mon.follow(ex), moves_at_step)
        if args.save is not None:
            from timedexec.monitoring import save_cycle_log

            save = Path(args.save)
            save.mkdir(parents=True, exist_ok=True)
            save_cycle_log(save / f"run{seed}.npz", ex.log.arrays(0), period_s=ex.period_s)
            meta = {"rows_at_step": rows_at_step, "step_ms": args.step_ms, "joint": args.joint}
            (save / f"run{seed}.json").write_text(json.dumps(meta))
    return _result(seed, mon, moves_at_step, tally)


def replay(path: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One saved run through this checkout's monitor, fed as the live run fed it (a
    chunk of rows per execution)."""
    from timedexec.learning import DelayModel
    from timedexec.monitoring import DelayMonitor, load_cycle_log

    arrays, _ = load_cycle_log(path)
    rows_at_step = json.loads(path.with_suffix(".json").read_text())["rows_at_step"]
    mon = DelayMonitor(
        DelayModel.load("ur10e-sim"), warmup_moves=args.warmup_moves, reference_k=args.k
    )
    # chunk bounds: the executions' first commands (a send after >= 0.3 s without one)
    sent = np.flatnonzero(np.isfinite(arrays["send_s"]))
    starts = sent[np.flatnonzero(np.diff(arrays["arrival_s"][sent], prepend=-1e9) > 0.3)]
    bounds = sorted({0, rows_at_step, len(arrays["send_s"]), *(int(i) for i in starts)})
    moves_at_step: dict[int, int] = {}
    tally = Tally()
    for lo, hi in itertools.pairwise(bounds):
        alerts = mon.feed_log({k: v[lo:hi] for k, v in arrays.items()})
        if hi == rows_at_step:
            moves_at_step = {s.joint: s.moves for s in mon.states()}
        tally.take(mon, alerts, moves_at_step)
    seed = int(path.stem.removeprefix("run")) if path.stem.startswith("run") else 0
    return _result(seed, mon, moves_at_step, tally)


def _result(
    seed: int,
    mon: Any,
    moves_at_step: dict[int, int],
    tally: Tally,
) -> dict[str, Any]:
    first_after = tally.first_after
    spread = {
        s.joint: float(1.4826 * np.median(np.abs(np.diff(s.residual_s))) / np.sqrt(2) * 1e3)
        for s in mon.states()
    }
    shifts = {}
    for st in mon.states():
        n0 = moves_at_step.get(st.joint, st.moves)
        r = np.array(st.residual_s) * 1e3
        contrast = []  # against the median of the other joints moved in the same execution
        others = {o.joint: dict(zip(o.send_s, o.residual_s, strict=True)) for o in mon.states()}
        for i, (send, res) in enumerate(zip(st.send_s, st.residual_s, strict=True)):
            peers = [others[j][send] for j in others if j != st.joint and send in others[j]]
            if peers:
                contrast.append((i >= n0, res - float(np.median(peers))))
        c = np.array([x[1] for x in contrast]) * 1e3
        after = np.array([x[0] for x in contrast], bool)
        shifts[st.joint] = (
            float(np.median(r[n0:]) - np.median(r[:n0])) if len(r) > n0 else float("nan"),
            float(np.median(c[after]) - np.median(c[~after])) if after.any() else float("nan"),
            st.level.lrv,
            float(max(max(st.level.up_hist), max(st.level.down_hist))),
        )
    out: dict[str, Any] = {
        "seed": seed,
        "false_before": tally.false_before,
        "spread_ms": spread,
        "shifts": shifts,
        "threshold": mon.threshold,
        "after_all": tally.after_all,
    }
    if first_after is not None:
        out.update(
            joint=first_after.joint,
            after=first_after.move - moves_at_step.get(first_after.joint, 0),
            shift_ms=first_after.shift_ms,
            ci_ms=first_after.ci_ms,
            test=first_after.test,
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument(
        "--warmup",
        type=int,
        default=50,
        help="executions before the change (the contrasts' warm-up starts at a joint's 5th move)",
    )
    ap.add_argument("--after", type=int, default=80, help="executions after it (at most)")
    ap.add_argument("--warmup-moves", type=int, default=40, help="monitor warm-up per joint")
    ap.add_argument(
        "--k", type=float, default=0.5, help="CUSUM reference (h = 12.5 for 40 warm-up moves)"
    )
    ap.add_argument("--step-ms", type=float, default=2.0)
    ap.add_argument("--joint", type=int, default=2)
    ap.add_argument("--full", action="store_true", help="run every execution after an alarm")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--save", type=Path, help="keep each run's cycle log here")
    ap.add_argument("--replay", type=Path, help="replay the runs saved in this directory")
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.replay is not None:
        runs = sorted(args.replay.glob("run*.npz"), key=lambda p: int(p.stem[3:]))
        results = (replay(p, args) for p in runs)
    else:
        seeds = range(args.first_seed, args.first_seed + args.runs)
        results = (one_run(seed, args) for seed in seeds)
    right = alarmed = 0
    for r in results:
        seed = r["seed"]
        alarmed += "joint" in r
        right += r.get("joint") == args.joint
        spread = ", ".join(f"j{j} {v:.2f}" for j, v in sorted(r["spread_ms"].items()))
        print(f"run {seed}: false alarms before the change {len(r['false_before'])}", flush=True)
        for m in r["false_before"]:
            print("   ", m)
        if "joint" in r:
            lo, hi = r["ci_ms"]
            print(
                f"    first alarm after it: joint {r['joint']} ({r['test']}) after {r['after']} of its moves, "
                f"shift {r['shift_ms']:+.2f} ms (95 % {lo:+.2f} .. {hi:+.2f})"
            )
        else:
            print("    no alarm after the change")
        for m in r["after_all"]:
            print("    alarm after the change:", m)
        print(f"    move-to-move residual spread (ms, robust): {spread}")
        for j, (raw, con, lrv, cmax) in sorted(r["shifts"].items()):
            print(
                f"    joint {j}: median residual after - before {raw:+.2f} ms, against the "
                f"other joints of the move {con:+.2f} ms; long-run variance factor {lrv:.2f}; "
                f"largest CUSUM {cmax:.1f} (threshold {r['threshold']:.1f})"
            )
    print(f"alarmed after the change {alarmed}, joint {args.joint} first {right}")
    print(f"wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
