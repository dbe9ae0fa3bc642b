"""Universal Robots UR10 (CB3), RTDE at 125 Hz: the paper's UR."""

from __future__ import annotations

from timedexec.robots._entry import ControllerTiming, RobotEntry, TwinIdentity, WorkCell
from timedexec.robots._spec import RobotSpec
from timedexec.robots.catalog._common import (
    DEG,
    HALF_PI,
    PI,
    UR_JOINT_NAMES,
    UR_SWEEP_Q_MAX_RAD,
    UR_SWEEP_Q_MIN_RAD,
    cylinder,
)

__all__ = ["ROBOT"]

_LIMIT_RAD = 2.0 * PI  # ±360°

_SPEC = RobotSpec(
    name="ur10",
    description="Universal Robots UR10 (CB3), RTDE at 125 Hz",
    vendor="universal_robots",
    controller_period_s=0.008,
    period_options_s=(0.008,),
    dh_a_m=(0.0, -0.612, -0.5723, 0.0, 0.0, 0.0),
    dh_d_m=(0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922),
    dh_alpha_rad=(HALF_PI, 0.0, 0.0, HALF_PI, -HALF_PI, 0.0),
    dh_offset_rad=(0.0,) * 6,
    joint_sign=(1.0,) * 6,
    link_mass_kg=(7.1, 12.7, 4.27, 2.0, 2.0, 0.365),
    link_com_m=(
        (0.021, 0.0, 0.027),
        (0.38, 0.0, 0.158),
        (0.24, 0.0, 0.068),
        (0.0, 0.007, 0.018),
        (0.0, 0.007, 0.018),
        (0.0, 0.0, -0.026),
    ),
    link_inertia_kgm2=(
        cylinder(7.1, 0.075, 0.18, 2),  # shoulder housing, along the joint-2 axis
        cylinder(12.7, 0.06, 0.612, 0),  # upper arm tube, along x2
        cylinder(4.27, 0.045, 0.5723, 0),  # forearm tube, along x3
        cylinder(2.0, 0.05, 0.12, 2),  # wrist housings, along their joint axes
        cylinder(2.0, 0.05, 0.12, 2),
        cylinder(0.365, 0.045, 0.03, 2),  # flange disc
    ),
    # Harmonic drives, ratio about 101 in every joint. Rotor inertias are not published;
    # J_m is estimated from the frameless-motor size of each joint (size 4 base and
    # shoulder, size 3 elbow, size 2 wrists): J_m about 1.2e-4, 4.4e-5, 1.0e-5 kg·m².
    rotor_inertia_kgm2=(1.2, 1.2, 0.45, 0.10, 0.10, 0.10),
    torque_max_nm=(330.0, 330.0, 150.0, 54.0, 54.0, 54.0),
    q_min_rad=(-_LIMIT_RAD,) * 6,
    q_max_rad=(_LIMIT_RAD,) * 6,
    qd_max_rad_s=(120 * DEG, 120 * DEG, 180 * DEG, 180 * DEG, 180 * DEG, 180 * DEG),
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -HALF_PI, HALF_PI, -HALF_PI, -HALF_PI, 0.0),
    sources=(
        "UR10 (CB3). "
        "DH parameters, link masses and centres of mass: Universal Robots, 'DH parameters for "
        "calculations of kinematics and dynamics' (universal-robots.com support article). "
        "Joint limits (±360°) and speeds (120°/s base and shoulder, 180°/s the others) from "
        "the UR data sheet. ESTIMATES: link inertias (solid cylinders along each link or "
        "joint housing, radii from the housing sizes); rotor inertias (J_m·N² with harmonic "
        "drive ratio N = 101 and J_m from the motor size); acceleration limits (working "
        "values, not published: 10 rad/s² base/shoulder, 12 elbow, 15 wrists)."
        " Peak torques (330, 330, 150, 54, 54, 54) N·m from UR's joint sizes. "
        "Controller: 8 ms (RTDE at 125 Hz). Rated payload 10 kg (not included by default)."
    ),
)

ROBOT = RobotEntry(
    spec=_SPEC,
    joint_names=UR_JOINT_NAMES,
    # Calibrated so that the emerging delays match the paper's UR10 (actuation about 2.5
    # periods): the script thread takes the register one cycle after intake; RTDE samples
    # and sends within the cycle (packing phase 2-97 % of it).
    timing=ControllerTiming(
        pipeline_cycles=1,
        packing_phase_periods=(0.02, 0.97),
        cycle_jitter_s=20e-6,
        bandwidth_hz=(25.0, 25.0, 25.0, 40.0, 40.0, 40.0),
        breakaway_time_s=(0.0045,) * 6,
        state_velocity=True,
    ),
    twin=TwinIdentity(
        interface="ur_rtde",
        controller="CB3",
        model_name="UR10",
        controller_version=(3, 15, 7, 106331),
        serial_number="2018300001",
    ),
    # The belt 0.80 m out (1.3 m reach) at a work height the torch reaches over ±0.3 m of
    # belt with every joint well inside its limits.
    cell=WorkCell(
        seed_q_rad=(0.0, -HALF_PI, HALF_PI, -HALF_PI, -HALF_PI, 0.0),
        work_point_m=(-0.80, 0.20, 0.20),
    ),
    sweep_q_min_rad=UR_SWEEP_Q_MIN_RAD,
    sweep_q_max_rad=UR_SWEEP_Q_MAX_RAD,
    # RTDE samples and sends in one cycle: no response_extra_cycle.
    rated_payload_kg=10.0,
    default_effects=(
        "gravity_load",
        "gravity_direction",
        "direction",
        "inertia",
        "thermal_drift",
        "joint_offset",
    ),
    shipped_model="ur10-sim",
    paper_family="ur",
)
