"""Conveyor welding as on a factory floor: a straight belt, a seam across it, every joint moving.

A belt carries a part at 0.5 m/s past the simulated robot; the torch (held at a fixed
tilt) meets a seam on the part and welds along it at 0.05 m/s, following it through the
robot's inverse kinematics, streamed through the TimedExecutor (virtual time, headless).
For each strategy the command streams are shifted by a delay; the table is the *physical*
torch tip (the simulator's joint angles) against the seam over 0.6 s of cruise:

* none      - no shift: the torch trails the seam by belt speed x the arm's lag (KR 5 ~4 cm);
* constant  - one latency for all joints (MoveIt Servo's setting);
* median    - one per joint (the published baseline);
* model     - the learned per-joint model, turned into a tracking delay;
* oracle    - the true mean tracking delay of each joint on this path.

With --onset the same welds run shifted by the *onset* delay (what the delay models learn):
the torch then leads the seam by several millimetres, because a moving arm keeps less lag
than the time it takes to start (docs/welding.md).

    python examples/02_conveyor_welding.py [--robot kr5|ur10|ur10e] [--seam straight|curved]
        [--runs N] [--onset] [--figure weld.png]
"""

from __future__ import annotations

import argparse

from timedexec.welding import evaluate_conveyor


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--robot", default="kr5", choices=("kr5", "ur10", "ur10e"))
    p.add_argument("--seam", default="straight", choices=("straight", "curved"))
    p.add_argument("--speed", type=float, default=0.5, help="belt speed, m/s")
    p.add_argument("--runs", type=int, default=2, help="publisher phases per strategy (stratified)")
    p.add_argument("--onset", action="store_true", help="also shift by the onset delay")
    p.add_argument("--figure", help="write the welder's figure (PNG) here")
    args = p.parse_args()
    # The model bundled for this simulated robot (or a folder from `timedexec train`).
    result = evaluate_conveyor(
        args.robot,
        f"{args.robot}-sim",
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
    if args.figure:
        from timedexec.report import fig_welding

        print(f"figure: {fig_welding(result.figure_data(), args.figure)}")


if __name__ == "__main__":
    main()
