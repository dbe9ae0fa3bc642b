"""Find what the simulation is missing: the discrepancy workflow on a simulated robot.

A "measured" delay table is made by the simulated UR10 with all its default effects on
(2,000 trials: 200 conditions, each repeated 10 times, as a calibration sweep runs them),
plus a dependence of joint 1's actuation delay on q1 that no effect of the vocabulary can
express. The analysis starts from a model that lacks gravity_load: it should name
gravity_load, and instead of forcing the q1 dependence onto a name, discover it as a term
of its own (joint 1, following q1; issue 36), add it to the simulator and close the gap to
the noise floor.

Runs headless in a few seconds; writes a report (markdown + PNG) into a temporary folder
unless a folder is given:  python examples/04_discrepancy.py [REPORT_DIR]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from timedexec.delays import DelayTable
from timedexec.discrepancy import analyse_discrepancy
from timedexec.effects import default_effects
from timedexec.recording import SweepPlan
from timedexec.sim import simulate_delays


def measured_table() -> DelayTable:
    robot = "ur10"
    plan = SweepPlan.generate(robot, 2000, seed=1)  # 10 repeats per condition
    new_config = np.r_[True, plan.config_index[1:] != plan.config_index[:-1]]
    t_start_s = 10.0 + np.cumsum(1.0 + np.where(new_config, 3.0, 0.0))  # ~1 s per trial
    table = simulate_delays(
        robot,
        plan.q_start_rad,
        plan.joint,
        plan.direction,
        t_start_s,
        effects=default_effects(robot),
        seed=1,
    )
    cols = dict(table.columns)
    # Something outside the vocabulary: joint 1 is 1 ms slower around q1 = +90°.
    cols["actuation_delay"] = cols["actuation_delay"] + 1e-3 * np.sin(plan.q_start_rad[:, 0]) * (
        plan.joint == 1
    )
    return DelayTable(cols, source="simulated UR10 sweep (2,000 trials)")


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="disc-"))
    table = measured_table()
    start = default_effects("ur10").without("gravity_load")
    result = analyse_discrepancy(table, start=start)

    print(f"robot {result.robot}: {result.n_trials:,} trials, {result.n_conditions} conditions")
    print(f"start model: {', '.join(result.start_effects)}")
    for d in ("actuation_delay", "response_delay"):
        print(
            f"{d:16s} gap {result.gap_before_ms[d]:.2f} ms -> {result.gap_after_ms[d]:.2f} ms "
            f"(noise floor {result.noise_floor_ms[d]:.2f} ms)"
        )
    for k, step in enumerate(result.steps, 1):
        print(f"step {k}: added {step.effect}")
        print(f"  {step.explanation}")
        print(f"  fitted: {step.parameters}")
    for term in result.discovered:
        print(f"discovered: {term.description}")
        print(f"  {term.formula}")
    for entry in result.unexplained:
        print(f"unexplained: {entry['description']}")
    report = result.write_report(out)
    result.write_json(out / "discrepancy.json")
    print(f"report: {report}")
    assert result.added_effects == ["gravity_load"], result.added_effects
    assert [(t.joints, t.inputs) for t in result.discovered] == [([1], ["q1"])]


if __name__ == "__main__":
    main()
