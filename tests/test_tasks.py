"""Applications of the timed executor on the simulated robot: seam tracking, interception."""

from __future__ import annotations

import numpy as np
import pytest

from timedexec.drivers import SimDriver
from timedexec.effects import EffectSet, default_effects
from timedexec.errors import ConfigError
from timedexec.evaluation import SimulatedOracle
from timedexec.execution import ExecutorSettings, TimedExecutor
from timedexec.robots import forward_kinematics, get_robot
from timedexec.tasks import intercept, solve_position_ik, track_seam


def warm(robot: str) -> EffectSet:
    """Default effects of a warmed-up robot (no cold-start friction)."""
    return EffectSet(tuple(e for e in default_effects(robot).effects if e.name != "thermal_drift"))


def pose(robot: str) -> np.ndarray:
    q = np.array(get_robot(robot).home_q_rad)
    q[1] += 0.3
    return q


@pytest.fixture(scope="module")
def kr5_oracle() -> SimulatedOracle:
    return SimulatedOracle("kr5", draws=8, effects=warm("kr5"), seed=11)


def seam(compensate: bool, model: SimulatedOracle, seed: int = 1, gain: float = 0.0, cruise_s: float = 0.3):  # type: ignore[no-untyped-def]  # fmt: skip
    drv = SimDriver("kr5", q0_rad=pose("kr5"), effects=warm("kr5"), seed=seed)
    settings = ExecutorSettings(compensate=compensate, position_gain_1_s=gain)
    with TimedExecutor(drv, model, settings) as ex:
        return track_seam(ex, speed_m_s=0.5, direction=1, cruise_s=cruise_s)


def test_seam_tracking_compensation_keeps_the_tool_on_the_seam(
    kr5_oracle: SimulatedOracle,
) -> None:
    """On the KR 5 (about 90 ms of actuation delay) the uncompensated tool trails a 0.5 m/s
    seam by ~4 cm (the published 4.5 cm); shifting the command stream by the predicted
    delay cuts the physical distance to under a third; the executor's back-dated estimate
    of the lag agrees with the physical lag to a few millimetres."""
    none = seam(False, kr5_oracle)
    comp = seam(True, kr5_oracle)
    assert none.physical
    assert comp.physical
    assert 0.03 < none.mean_lag_m < 0.05
    assert comp.mean_error_m < none.mean_error_m / 3
    # Residual: the velocity loop recovers part of the breakaway time in cruise (the onset
    # delay overestimates the positional lag by ~15 ms on this robot; docs/execution.md).
    assert abs(comp.mean_lag_m) < 0.012
    for r in (none, comp):
        assert abs(np.mean(r.estimated_lag_m) - r.mean_lag_m) < 0.005
    assert none.execution.missed_cycles == 0


def test_position_feedback_removes_the_lead_without_oscillating(
    kr5_oracle: SimulatedOracle,
) -> None:
    """With the Smith-predictor position correction (gain 20/s) the lead that onset
    compensation leaves on the KR 5 shrinks to what the back-dated estimate cannot see: the
    believed lag ends within 1 mm of zero and the physical one within 3 mm (the seam
    tolerance the paper reached with the median), on three seeds; a plain feedback of the
    same gain, blind to the ~100 ms loop delay, oscillates (the std over the cruise shows
    it: 8.7 mm measured before the predictor, 1.3 mm after)."""
    for seed in (1, 2, 3):
        ff = seam(True, kr5_oracle, seed=seed, cruise_s=0.6)
        fb = seam(True, kr5_oracle, seed=seed, gain=20.0, cruise_s=0.6)
        end = fb.times_s >= fb.times_s[-1] - 0.1  # the last 100 ms of the cruise
        # The believed lag is what the loop drives to zero: 1 mm leaves room for the
        # quantised reported positions.
        assert abs(np.mean(fb.estimated_lag_m[end])) < 0.001
        # Physical: the back-dating error of one run (response-delay phase, up to ~6 ms at
        # 0.5 m/s) remains; 3 mm is the paper's tolerance with the median.
        assert abs(np.mean(fb.lag_m[end])) < 0.003
        assert abs(np.mean(fb.lag_m[end])) < abs(ff.mean_lag_m)
        # No oscillation: the cruise's scatter stays a few mm (plain feedback: ~9 mm).
        assert np.std(fb.lag_m) < 0.003


def test_seam_refuses_a_tool_too_close_to_the_base(kr5_oracle: SimulatedOracle) -> None:
    """A tool near the base axis would need joint 1 beyond its speed limit: ConfigError
    before any motion."""
    drv = SimDriver("kr5", q0_rad=pose("kr5"), effects=warm("kr5"))
    with TimedExecutor(drv, kr5_oracle) as ex:
        with pytest.raises(ConfigError, match="from the base axis"):
            track_seam(ex, speed_m_s=5.0)
        assert drv.controller.truth == []


def test_interception_arrives_before_the_object(kr5_oracle: SimulatedOracle) -> None:
    """An object slides along a line; the tool must be where it will be at t_meet. With
    compensation the tool (physical truth) is within 1.5 cm of the meeting point by t_meet;
    without, the plan believes the robot moves at once and the whole motion, arrival
    included, comes about one actuation delay (~90 ms) later."""
    spec = get_robot("kr5")
    results = {}
    offset = np.array([0.0, 0.4, -0.05])
    speed = np.array([0.0, 0.3, 0.0])
    for compensate in (True, False):
        drv = SimDriver("kr5", q0_rad=pose("kr5"), effects=warm("kr5"), seed=3)
        with TimedExecutor(drv, kr5_oracle, ExecutorSettings(compensate=compensate)) as ex:
            start = forward_kinematics(spec, pose("kr5"))[6, :3, 3]
            t_meet = ex.now() + 0.9

            def obj(t: float, t_meet: float = t_meet, start: np.ndarray = start) -> np.ndarray:
                return start + offset + speed * (t - t_meet)

            results[compensate] = intercept(ex, obj, t_meet, arrival_tol_m=0.015)
    ok, late = results[True], results[False]
    assert ok.physical
    assert ok.meet.probability >= 0.95 - 1e-9  # the quantile is found by bisection (1e-15 s)
    # Open-loop speed streaming ends within about a centimetre on this 12 Hz velocity loop
    # (overshoot while braking, stiction at rest); docs/execution.md.
    assert ok.arrival_s <= ok.meet_time_s
    assert ok.distance_m < 0.015
    # Uncompensated: the same motion one actuation delay (~90 ms) later.
    assert 0.06 < late.arrival_s - ok.arrival_s < 0.12


def test_position_ik_round_trip_and_unreachable_point() -> None:
    """The position IK reproduces a reachable flange point to 10 µm and refuses a point
    5 m away."""
    spec = get_robot("ur10")
    q = pose("ur10")
    q_t = q.copy()
    q_t[:3] += [0.3, -0.2, 0.25]
    p = forward_kinematics(spec, q_t)[6, :3, 3]
    sol = solve_position_ik(spec, p, q)
    assert np.linalg.norm(forward_kinematics(spec, sol)[6, :3, 3] - p) < 1e-5
    with pytest.raises(ConfigError, match="out of reach"):
        solve_position_ik(spec, [5.0, 0.0, 0.0], q)
