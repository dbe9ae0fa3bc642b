"""Interception: have the tool where a sliding object will be at a chosen time.

The object slides across the table on a known straight path at 0.3 m/s. The executor
solves the meeting configuration, asks plan_to_meet for the latest motion that arrives by
the meeting time with 95 % probability, and runs it on the embedded simulated robot
(virtual time, a few seconds of CPU). A second request with too short a deadline shows the
"cannot: misses by X ms" answer, before any motion.

    python examples/03_interception.py [--robot ROBOT]
"""

from __future__ import annotations

import argparse

import numpy as np

from timedexec.drivers import open_driver
from timedexec.effects import default_effects
from timedexec.errors import UnreachableError
from timedexec.execution import TimedExecutor, load_delay_model
from timedexec.robots import ROBOT_NAMES, forward_kinematics, get_robot, get_robot_entry
from timedexec.tasks import intercept


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--robot", default="kr5", choices=ROBOT_NAMES)
    args = p.parse_args()
    spec = get_robot(args.robot)
    # A warmed-up robot (the simulator's clock starts cold) and its bundled model.
    effects = default_effects(spec.name).without("thermal_drift")
    model = load_delay_model(get_robot_entry(spec.name).shipped_model)
    q0 = np.array(spec.home_q_rad)
    q0[1] += 0.3
    tool0 = forward_kinematics(spec, q0)[6, :3, 3]
    driver = open_driver(f"sim://{spec.name}", q0_rad=q0, effects=effects, seed=2)
    with TimedExecutor(driver, model) as ex:
        t_meet = ex.now() + 0.9

        def obj(t: float) -> np.ndarray:
            """Object position (m, base frame) at host time t (s)."""
            return tool0 + np.array([0.0, 0.4, -0.05]) + np.array([0.0, 0.3, 0.0]) * (t - t_meet)

        r = intercept(ex, obj, t_meet, confidence=0.95, arrival_tol_m=0.01)
        b = r.meet.arrival
        moving = np.flatnonzero(r.meet.plan.moving_joints())
        print(f"{spec.name}: meet the object at t = {t_meet:.3f} s (in 0.9 s)")
        print(
            f"  plan: {r.meet.plan.duration_s * 1e3:.0f} ms motion, first command at "
            f"{r.meet.first_send_s:.3f} s, motion start {r.meet.plan.start_time_s:.3f} s, "
            f"P(arrive by t_meet) = {r.meet.probability:.3f}"
        )
        for j in moving:
            print(
                f"  joint {j + 1}: arrives in [{b.lower_s[j]:.4f}, {b.upper_s[j]:.4f}] s "
                f"(95 %), expected {b.expected_s[j]:.4f} s"
            )
        print(
            f"  physical: within 1 cm of the meeting point at {r.arrival_s:.3f} s "
            f"({(r.meet_time_s - r.arrival_s) * 1e3:.0f} ms before t_meet); "
            f"{r.distance_m * 1e3:.1f} mm away at t_meet"
        )
        target = q0.copy()
        target[0] += 1.0
        try:
            ex.plan_to_meet(target, ex.now() + 0.3)
        except UnreachableError as exc:
            print(f"  too short a deadline: {exc}")


if __name__ == "__main__":
    main()
