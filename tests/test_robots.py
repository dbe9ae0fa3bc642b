"""Tests of timedexec.robots: robot specs, kinematics, gravity torque, joint inertia."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from strategies import robot_configurations
from timedexec.errors import ConfigError
from timedexec.robots import (
    ROBOT_NAMES,
    RobotSpec,
    check_configuration,
    forward_kinematics,
    get_robot,
    get_robot_entry,
    gravity_torque,
    gravity_torque_coefficients,
    joint_axis_in_tool,
    joint_inertia,
)

G = 9.81
# Deterministic Hypothesis runs: the same examples every time (seeded randomness).
HYPOTHESIS = settings(max_examples=40, deadline=None, derandomize=True)


def loaded(name: str) -> RobotSpec:
    """The built-in spec carrying its rated payload (the data sheet's, from the catalog) at
    the flange."""
    return dataclasses.replace(get_robot(name), payload_kg=get_robot_entry(name).rated_payload_kg)


def random_configurations(spec: RobotSpec, n: int, seed: int, margin: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo = np.asarray(spec.q_min_rad) + margin
    hi = np.asarray(spec.q_max_rad) - margin
    return rng.uniform(lo, hi, size=(n, 6))


def potential_energy(spec: RobotSpec, q: np.ndarray) -> float:
    """V = g Σ m z_com, computed from forward_kinematics and the link COMs (independent
    of the module's composite-moment code)."""
    frames = forward_kinematics(spec, q)
    height = 0.0
    for i in range(6):
        com = frames[i + 1] @ np.append(spec.link_com_m[i], 1.0)
        height += spec.link_mass_kg[i] * com[2]
    height += spec.payload_kg * frames[6][2, 3]
    return G * height


def rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# ----------------------------------------------------------------------------------------
# Specs
# ----------------------------------------------------------------------------------------


def test_builtin_specs_have_the_documented_periods_and_vendors() -> None:
    """The four robots exist with their controller periods (the paper's for the UR10 and
    KR 5) and their vendors."""
    assert ROBOT_NAMES == ("ur10", "ur10e", "kr5", "ur5e")
    periods = {name: get_robot(name).controller_period_s for name in ROBOT_NAMES}
    assert periods == {"ur10": 0.008, "ur10e": 0.002, "kr5": 0.012, "ur5e": 0.002}
    assert get_robot("kr5").period_options_s == (0.012, 0.004)
    assert {get_robot(n).vendor for n in ROBOT_NAMES} == {"universal_robots", "kuka"}
    for name in ROBOT_NAMES:
        spec = get_robot(name)
        assert spec.name == name
        assert "ESTIMATE" in spec.sources  # estimates are declared as such
        check_configuration(spec, spec.home_q_rad)  # home pose inside the limits


def test_get_robot_unknown_name_lists_the_choices() -> None:
    """An unknown robot name fails with a message listing every valid name."""
    with pytest.raises(
        ConfigError, match=re.escape(f"unknown robot 'x'; choose one of {', '.join(ROBOT_NAMES)}")
    ):
        get_robot("x")
    assert get_robot(" KR5 ").name == "kr5"  # names are case- and space-insensitive


def test_with_period_accepts_offered_periods_and_lists_options_otherwise() -> None:
    """kr5 runs at 4 ms (RSI IPO_FAST); 5 ms is refused with the options in the message."""
    fast = get_robot("kr5").with_period(0.004)
    assert fast.controller_period_s == 0.004
    assert dataclasses.replace(fast, controller_period_s=0.012) == get_robot("kr5")
    assert get_robot("kr5", period_s=0.004) == fast
    with pytest.raises(ConfigError, match=re.escape("choose one of 0.012, 0.004 s")):
        get_robot("kr5").with_period(0.005)
    with pytest.raises(ConfigError, match=re.escape("choose one of 0.008 s")):
        get_robot("ur10", period_s=0.002)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_to_dict_from_dict_round_trips_through_json(name: str) -> None:
    """A spec (with payload and another period) survives to_dict -> JSON -> from_dict."""
    spec = dataclasses.replace(get_robot(name), payload_kg=2.5)
    if name == "kr5":
        spec = spec.with_period(0.004)
    text = json.dumps(spec.to_dict())
    back = RobotSpec.from_dict(json.loads(text))
    assert back == spec
    assert hash(back) == hash(spec)
    assert_allclose(gravity_torque(back, spec.home_q_rad), gravity_torque(spec, spec.home_q_rad))


def test_from_dict_rejects_unknown_and_missing_keys() -> None:
    """from_dict names unknown keys and missing keys instead of failing obscurely."""
    d = get_robot("ur10").to_dict()
    with pytest.raises(ConfigError, match="unknown RobotSpec keys \\['colour'\\]"):
        RobotSpec.from_dict({**d, "colour": "blue"})
    del d["dh_a_m"]
    with pytest.raises(ConfigError, match="missing keys \\['dh_a_m'\\]"):
        RobotSpec.from_dict(d)


def test_spec_validation_rejects_inconsistent_data() -> None:
    """Building a spec validates lengths, signs, limits, home pose and period."""
    spec = get_robot("kr5")
    with pytest.raises(ConfigError, match="dh_a_m needs 6 values"):
        dataclasses.replace(spec, dh_a_m=(0.1,) * 5)
    with pytest.raises(ConfigError, match="joint_sign must be \\+1 or -1"):
        dataclasses.replace(spec, joint_sign=(1.0, 1.0, 0.5, 1.0, 1.0, 1.0))
    with pytest.raises(ConfigError, match="home_q_rad is outside the joint limits"):
        dataclasses.replace(spec, home_q_rad=(0.0, 1.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="joint 2 limits need q_min_rad < q_max_rad"):
        dataclasses.replace(
            spec, q_min_rad=(-1.0, 1.0, -1, -1, -1, -1), q_max_rad=(1.0,) * 6, home_q_rad=(0.0,) * 6
        )
    with pytest.raises(ConfigError, match="not one of the period options"):
        dataclasses.replace(spec, controller_period_s=0.005)
    with pytest.raises(ConfigError, match="payload_kg must be >= 0"):
        dataclasses.replace(spec, payload_kg=-1.0)


# ----------------------------------------------------------------------------------------
# check_configuration
# ----------------------------------------------------------------------------------------


def test_check_configuration_returns_float64_of_the_same_shape() -> None:
    """Valid (6,) lists and (N, 6) arrays come back as float64 arrays of the same shape."""
    spec = get_robot("ur10")
    one = check_configuration(spec, [0, 0, 0, 0, 0, 0])
    assert one.shape == (6,)
    assert one.dtype == np.float64
    many = check_configuration(spec, np.zeros((4, 6), dtype=np.int32))
    assert many.shape == (4, 6)
    assert many.dtype == np.float64


def test_check_configuration_out_of_range_names_row_joint_value_and_range() -> None:
    """The message names the row, the 1-based joint, rad and degrees and the allowed range."""
    spec = get_robot("kr5")
    q = np.tile(np.asarray(spec.home_q_rad), (3, 1))
    q[1, 1] = 1.0  # A2 above +45°
    with pytest.raises(ConfigError) as info:
        check_configuration(spec, q)
    msg = str(info.value)
    assert "row 1" in msg
    assert "joint 2 = 1 rad (57.30°)" in msg
    assert "[-3.31613, 0.785398] rad ([-190.00, 45.00]°)" in msg
    with pytest.raises(ConfigError, match=re.escape("joint 3 = -3 rad (-171.89°)")):
        check_configuration(spec, [0.0, -1.0, -3.0, 0.0, 0.0, 0.0])


def test_check_configuration_accepts_the_limits_themselves() -> None:
    """Angles exactly at a limit (or within 1e-9 rad round-off) are allowed."""
    spec = get_robot("kr5")
    check_configuration(spec, np.asarray(spec.q_min_rad))
    check_configuration(spec, np.asarray(spec.q_max_rad) + 5e-10)


def test_check_configuration_rejects_nan_inf_and_wrong_shapes() -> None:
    """NaN/inf name the joint; wrong lengths and ranks give the shape in the message."""
    spec = get_robot("ur10")
    with pytest.raises(ConfigError, match="joint 3 is nan"):
        check_configuration(spec, [0, 0, np.nan, 0, 0, 0])
    q = np.zeros((2, 6))
    q[1, 5] = np.inf
    with pytest.raises(ConfigError, match="row 1, joint 6 is inf"):
        check_configuration(spec, q)
    with pytest.raises(
        ConfigError, match=re.escape("incorrect configuration length: expected 6, got 5")
    ):
        check_configuration(spec, [0.0] * 5)
    with pytest.raises(
        ConfigError, match=re.escape("incorrect configuration length: expected 6, got 7")
    ):
        check_configuration(spec, np.zeros((3, 7)))
    with pytest.raises(ConfigError, match=re.escape("expected (6,) or (N, 6), got (2, 2, 6)")):
        check_configuration(spec, np.zeros((2, 2, 6)))
    with pytest.raises(ConfigError, match="must be numbers"):
        check_configuration(spec, ["a"] * 6)


# ----------------------------------------------------------------------------------------
# Forward kinematics
# ----------------------------------------------------------------------------------------


def test_ur10_zero_pose_matches_the_published_dh_geometry() -> None:
    """UR10 at q = 0: flange at (a2 + a3, -(d4 + d6), d1 - d5), axes Rx(90°) of the base."""
    spec = get_robot("ur10")
    frames = forward_kinematics(spec, np.zeros(6))
    assert frames.shape == (7, 4, 4)
    assert_allclose(frames[0], np.eye(4))
    # Tolerance: exact arithmetic on a handful of products; 1e-12 m is round-off only.
    assert_allclose(frames[6][:3, 3], [-1.1843, -0.256141, 0.0116], atol=1e-12)
    assert_allclose(frames[6][:3, :3], rot_x(math.pi / 2), atol=1e-12)
    ur10e = forward_kinematics(get_robot("ur10e"), np.zeros(6))
    assert_allclose(ur10e[6][:3, 3], [-1.18425, -0.2907, 0.06085], atol=1e-12)


def test_kr5_home_pose_follows_kuka_conventions() -> None:
    """KR 5 at (0, -90, 90, 0, 0, 0)°: upper arm vertical, forearm horizontal, flange
    forward at x = 75 + 405 + 80 mm, z = 335 + 365 + 90 mm, tool z along base +x."""
    spec = get_robot("kr5")
    frames = forward_kinematics(spec, spec.home_q_rad)
    atol = 1e-12  # exact geometry up to round-off
    assert_allclose(frames[2][:3, 3], [0.075, 0.0, 0.700], atol=atol)  # A3 axis above A2
    assert_allclose(frames[5][:3, 3], [0.480, 0.0, 0.790], atol=atol)  # wrist centre
    assert_allclose(frames[6][:3, 3], [0.560, 0.0, 0.790], atol=atol)  # flange
    assert_allclose(frames[6][:3, 2], [1.0, 0.0, 0.0], atol=atol)  # tool axis forward
    assert_allclose(frames[6][:3, 0], [0.0, 0.0, -1.0], atol=atol)  # tool0 x down
    # All zero: arm stretched forward, the 90 mm elbow offset upward (wrist at 845, 425 mm).
    zero = forward_kinematics(spec, np.zeros(6))
    assert_allclose(zero[5][:3, 3], [0.845, 0.0, 0.425], atol=atol)
    # A1 positive turns clockwise seen from above: the flange moves to -y.
    turned = forward_kinematics(spec, [math.pi / 2, -math.pi / 2, math.pi / 2, 0, 0, 0])
    assert_allclose(turned[6][:3, 3], [0.0, -0.560, 0.790], atol=atol)
    # A3 = +90° from an upper arm held horizontal (A2 = 0) points the forearm down.
    bent = forward_kinematics(spec, [0.0, 0.0, math.pi / 2, 0, 0, 0])
    assert_allclose(bent[5][:3, 3], [0.530, 0.0, 0.335 - 0.405], atol=atol)


@given(q=robot_configurations(get_robot("kr5")))
@HYPOTHESIS
def test_forward_kinematics_frames_are_rigid_transforms(q: np.ndarray) -> None:
    """Every frame has an orthonormal, right-handed rotation and a homogeneous last row."""
    frames = forward_kinematics(get_robot("kr5"), q)
    rot = frames[:, :3, :3]
    # 1e-12: six products of exact rotations accumulate only round-off.
    assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (7, 3, 3)), atol=1e-12)
    assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    assert_allclose(frames[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (7, 4)))


# ----------------------------------------------------------------------------------------
# Gravity torque
# ----------------------------------------------------------------------------------------


def test_ur10_joint2_gravity_vertical_zero_horizontal_extreme_and_sign_flipped() -> None:
    """UR10 shoulder: no holding torque with the arm straight up; the largest, with opposite
    signs, with the arm horizontal to either side; the value matches a hand computation."""
    spec = get_robot("ur10")
    upright = [0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0]
    # 1e-9 N·m: cos(pi/2) is 6e-17, not 0, times moments of ~10 kg·m.
    assert_allclose(gravity_torque(spec, upright), np.zeros(6), atol=1e-9)
    # Arm out along -x (q = 0): moments about the shoulder, from the published COMs:
    # link 2 at 0.612 - 0.38 m, link 3 at 1.1843 - 0.24 m, wrist links at 1.1843 m.
    arm_kgm = 12.7 * (0.612 - 0.38) + 4.27 * (1.1843 - 0.24) + (2.0 + 2.0 + 0.365) * 1.1843
    horizontal = gravity_torque(spec, np.zeros(6))
    # Positive q2 lowers an arm pointing along -x, so holding it needs negative torque.
    assert_allclose(horizontal[1], -G * arm_kgm, rtol=1e-12)
    flipped = gravity_torque(spec, [0.0, -math.pi, 0.0, 0.0, 0.0, 0.0])
    assert_allclose(flipped[1], -horizontal[1], rtol=1e-12)
    sweep = np.zeros((721, 6))
    sweep[:, 1] = np.linspace(-2 * math.pi, 2 * math.pi, 721)
    tau2 = np.abs(gravity_torque(spec, sweep)[:, 1])
    # The wrist COMs sit a few mm off the arm's line, so the extreme lies within a degree
    # or two of horizontal and exceeds the horizontal value by well under 0.1 %.
    assert tau2.max() == pytest.approx(abs(horizontal[1]), rel=1e-3)
    angle = sweep[np.argmax(tau2), 1]
    assert min(
        abs(math.remainder(angle, math.pi)), abs(math.remainder(angle - math.pi, math.pi))
    ) < math.radians(3)


def test_joint2_gravity_of_a_single_link_is_a_cosine() -> None:
    """With only the upper arm massive, tau2 = -m g l cos(q2) with l the shoulder-COM
    distance: zero for the vertical arm (up or down), extreme for horizontal."""
    spec = dataclasses.replace(get_robot("ur10"), link_mass_kg=(0.0, 12.7, 0.0, 0.0, 0.0, 0.0))
    q2 = np.linspace(-math.pi, math.pi, 73)
    q = np.zeros((73, 6))
    q[:, 1] = q2
    expected = -12.7 * G * (0.612 - 0.38) * np.cos(q2)
    # 1e-12 N·m: the same trigonometry evaluated along two paths.
    assert_allclose(gravity_torque(spec, q)[:, 1], expected, atol=1e-12)


@pytest.mark.parametrize("name", ROBOT_NAMES)
@given(data=st.data())
@HYPOTHESIS
def test_joint1_never_holds_gravity_torque(name: str, data: st.DataObject) -> None:
    """Joint 1 turns about the vertical: gravity does no work on it in any pose."""
    spec = loaded(name)
    q = data.draw(robot_configurations(spec))
    # 1e-9 N·m: e_z·(e_z × r) is 0 up to round-off of moments of ~30 kg·m.
    assert abs(gravity_torque(spec, q)[0]) < 1e-9


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_gravity_torque_is_the_gradient_of_potential_energy(name: str) -> None:
    """tau = dV/dq: matches a central finite difference of V = g Σ m z_com (with payload),
    in the vendor sign convention (KUKA A1, A4, A6 flipped)."""
    spec = loaded(name)
    h = 1e-6
    for q in random_configurations(spec, 25, seed=7, margin=1e-3):
        tau = gravity_torque(spec, q)
        fd = np.empty(6)
        for j in range(6):
            step = np.zeros(6)
            step[j] = h
            fd[j] = (potential_energy(spec, q + step) - potential_energy(spec, q - step)) / (2 * h)
        # Tolerance 1e-5 N·m: the O(h²) truncation error is ~1e-12·V''' ≈ 1e-10 N·m; the
        # round-off is ~eps·|V|/h ≈ 2e-16 · 400 J / 1e-6 ≈ 1e-7 N·m.
        assert_allclose(tau, fd, atol=1e-5)


@pytest.mark.parametrize("name", ROBOT_NAMES)
@given(data=st.data())
@HYPOTHESIS
def test_gravity_coefficients_reproduce_torque_at_any_angle(name: str, data: st.DataObject) -> None:
    """A cos(x) + B sin(x) equals gravity_torque with the joint moved to x, others fixed."""
    spec = loaded(name)
    q = data.draw(robot_configurations(spec))
    joint = data.draw(st.integers(1, 6))
    x = data.draw(st.floats(-2 * math.pi, 2 * math.pi))
    coef_a, coef_b = gravity_torque_coefficients(spec, q, joint)
    assert np.shape(coef_a) == ()
    moved = q.copy()
    moved[joint - 1] = x
    # 1e-9 N·m: two algebraically identical evaluations of torques up to ~300 N·m.
    assert_allclose(
        coef_a * math.cos(x) + coef_b * math.sin(x),
        gravity_torque(spec, moved)[joint - 1],
        atol=1e-9,
    )


def test_gravity_coefficients_reject_bad_joints() -> None:
    """Joint numbers are 1-based and must match the rows when given per row."""
    spec = get_robot("ur10")
    with pytest.raises(ConfigError, match="joint 7 is out of range: joints are numbered 1 to 6"):
        gravity_torque_coefficients(spec, np.zeros(6), 7)
    with pytest.raises(ConfigError, match="joint 0 is out of range"):
        joint_axis_in_tool(spec, np.zeros((2, 6)), [1, 0])
    with pytest.raises(ConfigError, match="joint has 3 entries but q has 2 rows"):
        gravity_torque_coefficients(spec, np.zeros((2, 6)), [1, 2, 3])
    with pytest.raises(ConfigError, match="must be an integer"):
        gravity_torque_coefficients(spec, np.zeros(6), 1.5)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_peak_torques_exceed_gravity_at_rated_payload(name: str) -> None:
    """The (partly estimated) peak torques can hold the rated payload in any pose."""
    spec = loaded(name)
    q = random_configurations(spec, 20_000, seed=3)
    worst = np.abs(gravity_torque(spec, q)).max(axis=0)
    assert np.all(worst < np.asarray(spec.torque_max_nm))


# ----------------------------------------------------------------------------------------
# Joint inertia
# ----------------------------------------------------------------------------------------


def kinetic_inertia(spec: RobotSpec, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """M_jj = 2 T for qd = e_j: Σ m |dc/dq_j|² + ω_bodyᵀ I ω_body (+ payload, + rotor),
    with velocities from central differences of forward_kinematics."""
    out = np.array(spec.rotor_inertia_kgm2, dtype=float)
    for j in range(6):
        step = np.zeros(6)
        step[j] = h
        plus, minus = forward_kinematics(spec, q + step), forward_kinematics(spec, q - step)
        here = forward_kinematics(spec, q)
        for i in range(6):
            com = np.append(spec.link_com_m[i], 1.0)
            v = (plus[i + 1] @ com - minus[i + 1] @ com)[:3] / (2 * h)
            w = here[i + 1][:3, :3].T @ (plus[i + 1][:3, :3] - minus[i + 1][:3, :3]) / (2 * h)
            omega = np.array([w[2, 1], w[0, 2], w[1, 0]])  # body-frame angular velocity
            out[j] += spec.link_mass_kg[i] * v @ v + omega @ (
                np.asarray(spec.link_inertia_kgm2[i]) * omega
            )
        v_flange = (plus[6][:3, 3] - minus[6][:3, 3]) / (2 * h)
        out[j] += spec.payload_kg * v_flange @ v_flange
    return out


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_joint_inertia_matches_kinetic_energy(name: str) -> None:
    """The composite-body diagonal equals 2·kinetic energy per unit joint speed, computed
    link by link from finite-difference velocities (payload and rotors included)."""
    spec = loaded(name)
    for q in random_configurations(spec, 10, seed=11, margin=1e-3):
        # rtol 1e-6: central differences with h = 1e-6 carry ~eps/h ≈ 2e-10 relative error
        # in each velocity; squared and summed it stays far below 1e-6.
        assert_allclose(joint_inertia(spec, q), kinetic_inertia(spec, q), rtol=1e-6)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_joint_inertia_is_positive_and_includes_the_rotor(name: str) -> None:
    """Every diagonal entry is positive and exactly rotor_inertia_kgm2 above the link part."""
    spec = get_robot(name)
    q = random_configurations(spec, 200, seed=5)
    total = joint_inertia(spec, q)
    links_only = joint_inertia(dataclasses.replace(spec, rotor_inertia_kgm2=(0.0,) * 6), q)
    assert np.all(links_only > 0.0)
    # 1e-12 kg·m²: the rotor term is added, nothing else changes.
    assert_allclose(
        total - links_only, np.broadcast_to(spec.rotor_inertia_kgm2, (200, 6)), atol=1e-12
    )


@pytest.mark.parametrize(
    ("name", "outstretched", "folded"),
    [
        ("ur10", [0, -math.pi / 2, 0, 0, 0, 0], [0, -math.pi / 2, 2.8, 0, 0, 0]),
        ("ur10e", [0, -math.pi / 2, 0, 0, 0, 0], [0, -math.pi / 2, 2.8, 0, 0, 0]),
        ("kr5", [0, -math.pi / 2, 0, 0, 0, 0], [0, -math.pi / 2, math.radians(160), 0, 0, 0]),
    ],
)
def test_joint2_inertia_larger_outstretched_than_folded(
    name: str, outstretched: list[float], folded: list[float]
) -> None:
    """The shoulder accelerates more inertia with the forearm stretched out than folded."""
    spec = get_robot(name)
    m_out = joint_inertia(spec, outstretched)[1]
    m_fold = joint_inertia(spec, folded)[1]
    assert m_out > 1.5 * m_fold  # forearm + wrist at ~2x the distance: well over 1.5x


# ----------------------------------------------------------------------------------------
# Joint axes seen from the flange (gyro)
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_joint_axis_in_tool_is_unit_and_matches_flange_rotation(name: str) -> None:
    """The axis is a unit vector and equals the flange's body angular velocity per rad/s of
    the joint, from a central difference of the flange orientation."""
    spec = get_robot(name)
    h = 1e-6
    for q in random_configurations(spec, 10, seed=13, margin=1e-3):
        for j in range(1, 7):
            axis = joint_axis_in_tool(spec, q, j)
            assert axis.shape == (3,)
            assert np.linalg.norm(axis) == pytest.approx(1.0, abs=1e-12)
            step = np.zeros(6)
            step[j - 1] = h
            rot = forward_kinematics(spec, q)[6][:3, :3]
            d_rot = (
                forward_kinematics(spec, q + step)[6][:3, :3]
                - forward_kinematics(spec, q - step)[6][:3, :3]
            ) / (2 * h)
            w = rot.T @ d_rot
            # 1e-8 rad/rad: O(h²) truncation ~1e-12 plus round-off eps/h ~ 2e-10.
            assert_allclose(axis, [w[2, 1], w[0, 2], w[1, 0]], atol=1e-8)


def test_kr5_joint1_axis_seen_from_the_flange_at_home() -> None:
    """KR 5 at home: A1 turns about base -z; the tool x axis points down, so the gyro sees
    A1 about +x of the flange."""
    spec = get_robot("kr5")
    assert_allclose(joint_axis_in_tool(spec, spec.home_q_rad, 1), [1.0, 0.0, 0.0], atol=1e-12)


# ----------------------------------------------------------------------------------------
# Batches
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_vectorised_batches_equal_a_loop_over_rows(name: str) -> None:
    """(N, 6) input gives exactly the stacked results of the (6,) calls, per-row joints too."""
    spec = loaded(name)
    q = random_configurations(spec, 16, seed=17)
    joints = np.arange(16) % 6 + 1
    coef_a, coef_b = gravity_torque_coefficients(spec, q, joints)
    axes = joint_axis_in_tool(spec, q, joints)
    fk = forward_kinematics(spec, q)
    tau = gravity_torque(spec, q)
    inertia = joint_inertia(spec, q)
    assert fk.shape == (16, 7, 4, 4)
    assert tau.shape == inertia.shape == (16, 6)
    assert coef_a.shape == coef_b.shape == (16,)
    assert axes.shape == (16, 3)
    for n in range(16):
        # 1e-12: the same arithmetic, vectorised or not, may differ in the last bits only.
        assert_allclose(fk[n], forward_kinematics(spec, q[n]), atol=1e-12)
        assert_allclose(tau[n], gravity_torque(spec, q[n]), atol=1e-12)
        assert_allclose(inertia[n], joint_inertia(spec, q[n]), atol=1e-12)
        a_n, b_n = gravity_torque_coefficients(spec, q[n], int(joints[n]))
        assert_allclose([coef_a[n], coef_b[n]], [a_n, b_n], atol=1e-12)
        assert_allclose(axes[n], joint_axis_in_tool(spec, q[n], int(joints[n])), atol=1e-12)
    # One configuration, several joints: one row per joint.
    per_joint = joint_axis_in_tool(spec, q[0], [1, 2, 3])
    assert per_joint.shape == (3, 3)
    assert_allclose(per_joint[2], joint_axis_in_tool(spec, q[0], 3), atol=1e-12)


def test_batches_of_33500_configurations_take_well_under_a_second() -> None:
    """Gravity torque and joint inertia for a full paper-sized sweep are vectorised."""
    spec = loaded("ur10")
    q = random_configurations(spec, 33_500, seed=19)
    gravity_torque(spec, q[:10])  # warm the spec cache
    start = time.perf_counter()
    gravity_torque(spec, q)
    joint_inertia(spec, q)
    elapsed = time.perf_counter() - start
    # Band: about 0.1 s on a 2-core CI runner; a Python loop over rows would take ~10 s.
    assert 0.0 < elapsed < 1.0
