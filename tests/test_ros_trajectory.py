"""JointTrajectory points interpolated as joint_trajectory_controller does, as a JointPlan
(timedexec.ros.plan_from_points; no rclpy needed)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

from timedexec.errors import ConfigError
from timedexec.robots import get_robot, get_robot_entry
from timedexec.ros import PointsTrajectory, order_joints, plan_from_points, spline_kind

SPEC = get_robot("ur10")
Q0 = np.array(SPEC.home_q_rad)


def sample(traj: PointsTrajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out = [traj.at_time(float(x)) for x in t]
    return tuple(np.array([o[k] for o in out]) for k in range(3))  # type: ignore[return-value]


def test_kind_follows_the_fields_the_points_carry() -> None:
    """Positions only: linear; with velocities: cubic; with accelerations too: quintic
    (accelerations without velocities: cubic is impossible, JTC falls back to linear)."""
    assert spline_kind(False, False) == "linear"
    assert spline_kind(True, False) == "cubic"
    assert spline_kind(True, True) == "quintic"
    assert spline_kind(False, True) == "linear"


def test_cubic_is_the_hermite_spline_through_positions_and_speeds() -> None:
    """With positions and velocities the segments are cubic Hermite polynomials: equal to
    SciPy's CubicHermiteSpline through the same knots (an independent implementation) to
    1e-12 rad, and the start state (at rest) joins the first point at time 0.2 s."""
    rng = np.random.default_rng(3)
    t = np.array([0.2, 0.5, 0.9, 1.4])
    q = Q0 + rng.uniform(-0.1, 0.1, (4, 6))
    v = rng.uniform(-0.3, 0.3, (4, 6))
    traj = PointsTrajectory(Q0, t, q, v)
    ref = CubicHermiteSpline(np.r_[0.0, t], np.vstack([Q0, q]), np.vstack([np.zeros(6), v]))
    grid = np.linspace(0.0, 1.4, 301)
    qs, vs, acc = sample(traj, grid)
    # Rounding of a degree-3 polynomial in seconds around 1 rad: 1e-12.
    np.testing.assert_allclose(qs, ref(grid), atol=1e-12)
    np.testing.assert_allclose(vs, ref(grid, 1), atol=1e-11)
    np.testing.assert_allclose(acc[1:-1], ref(grid[1:-1], 2), atol=1e-9)


def test_quintic_meets_position_speed_and_acceleration_at_every_point() -> None:
    """With accelerations the segments are quintics: position, speed and acceleration are
    continuous and equal the points' at each knot (which fixes a quintic), the arm holds the
    last point afterwards."""
    rng = np.random.default_rng(4)
    t = np.array([0.0, 0.3, 0.7])
    q = Q0 + np.vstack([np.zeros(6), rng.uniform(-0.1, 0.1, (2, 6))])
    v = np.vstack([np.zeros(6), rng.uniform(-0.2, 0.2, (1, 6)), np.zeros(6)])
    a = np.vstack([np.zeros(6), rng.uniform(-1, 1, (1, 6)), np.zeros(6)])
    traj = PointsTrajectory(Q0, t, q, v, a)
    assert traj.kind == "quintic"
    eps = 1e-7
    for k in (1,):
        for side in (-eps, eps):
            qk, vk, ak = (np.array(x) for x in traj.at_time(t[k] + side))
            # 1e-7 s from the knot: position moves by <= 3e-8 rad, speed by 1e-6 rad/s.
            np.testing.assert_allclose(qk, q[k], atol=1e-7)
            np.testing.assert_allclose(vk, v[k], atol=1e-5)
            np.testing.assert_allclose(ak, a[k], atol=1e-4)
    after = traj.at_time(5.0)
    np.testing.assert_array_equal(after[0], q[-1])
    np.testing.assert_array_equal(after[1], np.zeros(6))


def test_linear_points_have_constant_speed_per_segment() -> None:
    """Positions only: the speed is constant within a segment (the distance over the
    duration), including the segment from the start state to the first point."""
    q1 = Q0 + 0.01
    q2 = Q0 + 0.03
    traj = PointsTrajectory(Q0, [0.5, 1.0], [q1, q2])
    np.testing.assert_allclose(traj.at_time(0.25)[1], np.full(6, 0.02))
    np.testing.assert_allclose(traj.at_time(0.75)[1], np.full(6, 0.04))
    np.testing.assert_allclose(traj.at_time(0.75)[0], Q0 + 0.02)


def test_plan_from_points_gives_an_executable_plan() -> None:
    """The plan starts at the arm's position, ends at the last point at rest, moves the
    joints the points move, and its 10 % onset is where the profile's speed reaches 10 % of
    its peak (a 0.4 rad/s trapezoid with 8 rad/s² ramps: 5 ms)."""
    t = np.round(np.arange(0.0, 0.3 + 1e-9, 0.01), 9)
    v1 = np.minimum.reduce([8 * t, np.full_like(t, 0.4), 8 * (0.3 - t)]).clip(0)
    x1 = np.concatenate([[0.0], np.cumsum((v1[1:] + v1[:-1]) / 2 * np.diff(t))])
    q = np.tile(Q0, (len(t), 1))
    q[:, 0] += x1
    v = np.zeros_like(q)
    v[:, 0] = v1
    plan = plan_from_points(SPEC, Q0, t, q, v)
    np.testing.assert_array_equal(plan.q_start_rad, Q0)
    np.testing.assert_array_equal(plan.q_end_rad, q[-1])
    assert plan.moving_joints().tolist() == [True] + [False] * 5
    # The onset search samples every 0.2 ms and interpolates linearly: exact on a ramp.
    assert plan.onset_times()[0] == pytest.approx(0.005, abs=1e-6)


@pytest.mark.parametrize(
    ("points", "words"),
    [
        ({"times_s": [0.1], "positions_rad": [Q0 + np.array([10.0, 0, 0, 0, 0, 0])]}, "joint 1 position"),
        ({"times_s": [1.0], "positions_rad": [Q0 + np.array([0, 0, 0, 0, 0, 5.0])]}, "joint 6 speed"),
        ({"times_s": [0.5], "positions_rad": [Q0 + np.array([0, 0.5, 0, 0, 0, 0])]}, "joint 2 acceleration"),
        ({"times_s": [0.5, 0.4], "positions_rad": [Q0, Q0]}, "strictly increasing"),
        ({"times_s": [0.5], "positions_rad": [Q0 + 0.01], "velocities_rad_s": [np.full(6, 0.1)]}, "must end at rest"),
        ({"times_s": [0.5], "positions_rad": [np.full(6, np.nan)]}, "not finite"),
    ],
)
def test_what_the_robot_cannot_follow_is_refused_with_the_reason(points: dict, words: str) -> None:
    """A position outside the joint range, a speed above the limit, a linear segment that
    steps the speed from rest beyond the acceleration limit, times out of order, a
    trajectory ending in motion, NaN: ConfigError naming the joint (or field) and limit."""
    with pytest.raises(ConfigError, match=words):
        plan_from_points(SPEC, Q0, **points)


def test_joint_order_maps_message_columns_onto_the_robot() -> None:
    """A message may list the joints in any order; every one of the robot's, once."""
    names = list(get_robot_entry("ur10").joint_names)
    shuffled = [names[k] for k in (2, 0, 1, 5, 4, 3)]
    idx = order_joints(shuffled, names)
    assert [shuffled[i] for i in idx] == names
    with pytest.raises(ConfigError, match="each once"):
        order_joints(names[:5], names)
    with pytest.raises(ConfigError, match="each once"):
        order_joints(list(get_robot_entry("kr5").joint_names), names)
