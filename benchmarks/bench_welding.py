"""Per-cycle cost of online conveyor tracking: IK + delay model + Ruckig for six joints.

Issue 19 target: the work of one 500 Hz cycle (UR10e) — the inverse kinematics of the moving
seam point, a delay-model query for the current configuration and an online Ruckig update
towards the IK state — at p99 <= 0.5 ms.

What one cycle does here (the online variant of :func:`timedexec.tasks.plan_seam`, for
a seam not known in advance):

1. ``solve_ik`` of the torch pose at the cycle's time, warm-started from the previous
   cycle's solution (2 ms earlier on the belt), to ``--ik-tol-um`` (default 1 µm and
   1 µrad, 500 times below a weld's 0.5 mm: one damped Newton step from the warm start;
   0.1 µm takes a second step, the planner's default 1 nm a third);
2. the bundled ``ur10e-sim`` model's ``predict`` (the single-query fast path a control
   loop calls) for *one* joint at that configuration (GP mean and std of both delays; BLAS
   pinned to one thread, as the executor holds it), the joints in turn: each joint's delay
   is refreshed every 4 cycles (8 ms, 4 mm of belt at 0.5 m/s, over which the prediction
   moves by microseconds). ``--all-joints`` queries the four modelled joints every cycle
   instead (``predict_many``, one vectorised call);
3. ``Ruckig(6, 0.002).update`` towards the IK position and its finite-difference velocity.

Wall clock and thread CPU time per cycle and per step (CPU time excludes the time the
scheduler gives other processes on a shared machine; the load average is printed).

Then the executor's feed-forward on the planned seam (what ``track_conveyor_seam`` runs
per cycle): the planned speed alone (``velocity_per_joint``) against the tracking model's
:class:`~timedexec.execution.FrictionFeed` (one more spline sample, the offsets owed), and
their ratio.

Usage: python benchmarks/bench_welding.py [--robot ur10e] [--cycles 5000] [--ik-tol-um 1]
"""

from __future__ import annotations

import argparse
import gc
import os
import time

import numpy as np

from timedexec.execution import FrictionFeed, load_delay_model
from timedexec.robots import ROBOT_NAMES, get_robot_entry, solve_ik
from timedexec.tasks import Seam, default_cell, plan_seam


def pct(x: np.ndarray) -> str:
    us = x * 1e6
    return (
        f"p50 {np.median(us):6.1f}  p90 {np.percentile(us, 90):6.1f}  "
        f"p99 {np.percentile(us, 99):6.1f}  max {np.max(us):7.1f} µs"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--robot", default="ur10e", choices=ROBOT_NAMES)
    p.add_argument("--cycles", type=int, default=5000)
    p.add_argument("--all-joints", action="store_true", help="query every joint every cycle")
    p.add_argument("--ik-tol-um", type=float, default=1.0, help="IK tolerance, µm and µrad")
    p.add_argument(
        "--iterative",
        action="store_true",
        help="also time the damped Newton IK (solve_ik(closed_form=False)) in the same run",
    )
    args = p.parse_args()
    from ruckig import InputParameter, OutputParameter, Result, Ruckig

    cell = default_cell(args.robot)
    period = cell.spec.controller_period_s
    sp = plan_seam(cell, Seam(), weld_s=0.8)  # the seam geometry (and a start configuration)
    model = load_delay_model(get_robot_entry(args.robot).shipped_model)
    joints = np.array(getattr(model, "joints", (1, 2, 3, 5)))
    rot = np.asarray(cell.torch_rotation)
    pose = np.eye(4)
    pose[:3, :3] = rot
    q = np.asarray(sp.plan.sample(sp.sync_s)[0])
    spec = cell.spec
    model.predict_many(joints, np.ones(len(joints), int), np.tile(q, (len(joints), 1)))  # warm
    n = args.cycles
    tol = args.ik_tol_um * 1e-6
    vmax = 0.9 * np.asarray(spec.qd_max_rad_s)

    def run(closed_form: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Wall and thread CPU time per cycle, and the wall time of its three steps, s."""
        otg = Ruckig(6, period)
        inp, out = InputParameter(6), OutputParameter(6)
        inp.current_position = q.tolist()
        inp.current_velocity = [0.0] * 6
        inp.current_acceleration = [0.0] * 6
        inp.max_velocity = list(spec.qd_max_rad_s)
        inp.max_acceleration = [8.0] * 6
        inp.max_jerk = [1600.0] * 6
        steps = np.empty((n, 3))
        cpu = np.empty(n)
        wall = np.empty(n)
        q_prev = q
        gc.collect()
        gc.freeze()  # as the executor holds it while connected (quiet_gc)
        with model.pinned():
            for i in range(n):
                t = (i % int(0.8 / period)) * period  # wrap along the 0.8 s seam
                c0 = time.thread_time_ns()
                t0 = time.perf_counter_ns()
                pose[:3, 3] = sp.target([t])[0][0]
                q_ik = solve_ik(spec, pose, q_prev, tool=cell.tool_m, tol_m=tol, tol_rad=tol,
                                closed_form=closed_form)  # fmt: skip
                t1 = time.perf_counter_ns()
                d = np.where(q_ik >= q_prev, 1, -1)[joints - 1]
                if args.all_joints:
                    model.predict_many(joints, d, np.tile(q_ik, (len(joints), 1)))
                else:
                    k = i % len(joints)
                    model.predict(joint=int(joints[k]), direction=int(d[k]), q=q_ik)
                t2 = time.perf_counter_ns()
                inp.target_position = q_ik.tolist()
                inp.target_velocity = np.clip((q_ik - q_prev) / period, -vmax, vmax).tolist()
                res = otg.update(inp, out)
                if res not in (Result.Working, Result.Finished):
                    raise RuntimeError(f"Ruckig: {res}")
                out.pass_to_input(inp)
                t3 = time.perf_counter_ns()
                cpu[i] = (time.thread_time_ns() - c0) * 1e-9
                wall[i] = (t3 - t0) * 1e-9
                steps[i] = np.array([t1 - t0, t2 - t1, t3 - t2]) * 1e-9
                q_prev = q_ik if i % int(0.8 / period) else np.asarray(sp.plan.sample(sp.sync_s)[0])
        return wall, cpu, steps

    what = "all modelled joints" if args.all_joints else "one joint in turn"
    # every robot of the catalog has a closed form (UR family, spherical wrist: the KR 5)
    variants = [("closed form", True)]
    if args.iterative:
        variants.append(("iterative", False))
    p99 = {}
    for label, closed in variants:
        wall, cpu, steps = run(closed)
        load = os.getloadavg()[0]
        print(f"{args.robot}: {n} cycles of IK ({label}, to {args.ik_tol_um:g} µm) + model "
              f"({what}) + Ruckig ({period * 1e3:g} ms period), load average {load:.1f}")  # fmt: skip
        print(f"  cycle, wall  {pct(wall)}")
        print(f"  cycle, CPU   {pct(cpu)}")
        for k, name in enumerate(("IK", "model", "Ruckig")):
            print(f"  {name:<6} wall  {pct(steps[:, k])}")
        print(f"  p99 <= 0.5 ms: {'yes' if np.percentile(wall, 99) <= 5e-4 else 'NO'} (wall), "
              f"{'yes' if np.percentile(cpu, 99) <= 5e-4 else 'NO'} (CPU)")  # fmt: skip
        p99[label] = (float(np.percentile(cpu, 50)), float(np.percentile(cpu, 99)))
    if len(p99) == 2:
        (a50, a99), (b50, b99) = p99.values()
        print(
            f"  iterative / closed form, CPU per cycle: p50 {b50 / a50:.2f}x, p99 {b99 / a99:.2f}x"
        )
    feed_forward(sp.plan.at(0.0), period, n)


def feed_forward(plan, period: float, n: int) -> None:  # type: ignore[no-untyped-def]
    """CPU per cycle of the planned speed alone and of the friction feed (same run)."""
    plain, feed = FrictionFeed(np.zeros(6)), FrictionFeed(np.full((2, 6), 1e-3))
    times = {}
    for label, f in (("planned speed", plain), ("friction feed", feed)):
        cpu = np.empty(n)
        for i in range(n):
            t = np.full(6, (i % int(plan.duration_s / period)) * period)
            c0 = time.thread_time_ns()
            f.commanded(f.speed(plan, t, period), period)
            cpu[i] = (time.thread_time_ns() - c0) * 1e-9
        times[label] = cpu
        print(f"  feed-forward, {label:<13} CPU  {pct(cpu)}")
    a, b = times["planned speed"], times["friction feed"]
    print(f"  friction feed / planned speed, CPU per cycle: p50 "
          f"{np.median(b) / np.median(a):.2f}x, p99 {np.percentile(b, 99) / np.percentile(a, 99):.2f}x")  # fmt: skip


if __name__ == "__main__":
    main()
