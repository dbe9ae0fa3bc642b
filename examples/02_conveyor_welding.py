"""Conveyor welding as on a factory floor: a straight belt, a seam across it, every joint moving.

A belt carries a part at 0.5 m/s past the simulated robot; the torch (held at a fixed
tilt) meets a seam on the part and welds along it at 0.05 m/s, following it through the
robot's inverse kinematics, streamed through the TimedExecutor (virtual time, headless).
For each strategy the command streams are shifted by a delay; the table is the *physical*
torch tip (the simulator's joint angles) against the seam over 0.6 s of cruise:

* none      - no shift: the torch trails the seam by belt speed x the arm's lag (KR 5 ~4 cm);
* constant  - one latency for all joints (MoveIt Servo's setting);
* median    - one per joint (the published baseline);
* model     - the tracking model fitted on a calibration weld: a dead time per joint and a
              friction offset per direction, the offsets added to the command stream;
* oracle    - the true mean tracking delay of each joint on this path.

With --onset the same welds run shifted by the *onset* delay (what the delay models learn):
the torch then leads the seam by several millimetres, because a moving arm keeps less lag
than the time it takes to start (docs/welding.md).

With --twin the same seam is then welded once per strategy, with the shifts of the table's
first weld (the model with its offsets too), through the real client against the robot's protocol twin in its own process
(UR: ur_rtde against the UR twin; KR 5: RSI XML against the RSI twin, whose position
corrections keep a lag of their own), the torch measured from the twin's truth; beside each
row the simulator's per-run range (one twin weld is one publisher phase).

    python examples/02_conveyor_welding.py [--robot ROBOT] [--seam straight|curved]
        [--runs N] [--onset] [--twin] [--figure weld.png]
"""

from __future__ import annotations

import argparse

from timedexec.evaluation import ConveyorEvaluation, evaluate_conveyor, weld_on_twin
from timedexec.robots import ROBOT_NAMES, get_robot_entry


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--robot", default="kr5", choices=ROBOT_NAMES)
    p.add_argument("--seam", default="straight", choices=("straight", "curved"))
    p.add_argument("--speed", type=float, default=0.5, help="belt speed, m/s")
    p.add_argument("--runs", type=int, default=2, help="publisher phases per strategy (stratified)")
    p.add_argument("--onset", action="store_true", help="also shift by the onset delay")
    p.add_argument("--figure", help="write the welder's figure (PNG) here")
    p.add_argument(
        "--twin", action="store_true", help="also weld through the real client against the twin"
    )
    args = p.parse_args()
    # The model bundled for this simulated robot (or a folder from `timedexec train`).
    result = evaluate_conveyor(
        args.robot,
        get_robot_entry(args.robot).shipped_model,
        seam=args.seam,
        speed_m_s=args.speed,
        cells=1,
        seeds=args.runs,
        oracle_draws=args.runs,
        calibration_runs=1,
        onset=args.onset,
        feedback=False,
    )
    print(result.table())
    if args.twin:
        twin_table(result, args.robot)
    if args.figure:
        from timedexec.report import fig_welding

        print(f"figure: {fig_welding(result.figure_data(), args.figure)}")


def twin_table(result: ConveyorEvaluation, robot: str) -> None:
    """One weld per strategy through the real client against the twin, with the shifts of
    the simulator's first weld; the simulator's per-run range beside it."""
    names = [n for n in ("none", "constant", "median", "model", "oracle") if n in result.examples]
    seam_plan = result.examples[names[0]].seam_plan
    # The model compensates by itself (its shifts and friction offsets), the others by shift.
    shifts: dict[str, object] = {n: result.examples[n].shifts_s for n in names}
    shifts.update(none=None, model=result.tracking_model)
    entry = get_robot_entry(robot)
    runs = weld_on_twin(seam_plan, entry.shipped_model, shifts)
    client = "ur_rtde" if entry.twin.interface == "ur_rtde" else "RSI XML"
    print(f"\nthrough {client} against the {robot} twin, one weld per strategy (mm):")
    print(f"{'strategy':10} {'mean':>6} {'RMS':>6} {'max':>6}   simulator, per run")
    for name, run in runs.items():
        st = run.errors().stats()
        sim = result.strategies[name]
        print(
            f"{name:10} {st['torch_mean_mm']:6.2f} {st['torch_rms_mm']:6.2f} "
            f"{st['torch_max_mm']:6.2f}   {sim['run_mean_mm_min']:.2f}-{sim['run_mean_mm_max']:.2f}"
        )


if __name__ == "__main__":
    main()
