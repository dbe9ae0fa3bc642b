"""Universal Robots UR10e (e-Series), RTDE at 500 Hz."""

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
    name="ur10e",
    description="Universal Robots UR10e (e-Series), RTDE at 500 Hz",
    vendor="universal_robots",
    controller_period_s=0.002,
    period_options_s=(0.002,),
    dh_a_m=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
    dh_d_m=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
    dh_alpha_rad=(HALF_PI, 0.0, 0.0, HALF_PI, -HALF_PI, 0.0),
    dh_offset_rad=(0.0,) * 6,
    joint_sign=(1.0,) * 6,
    link_mass_kg=(7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
    link_com_m=(
        (0.021, 0.0, 0.027),
        (0.38, 0.0, 0.158),
        (0.24, 0.0, 0.068),
        (0.0, 0.007, 0.018),
        (0.0, 0.007, 0.018),
        (0.0, 0.0, -0.026),
    ),
    link_inertia_kgm2=(
        cylinder(7.369, 0.075, 0.18, 2),
        cylinder(13.051, 0.06, 0.6127, 0),
        cylinder(3.989, 0.045, 0.57155, 0),
        cylinder(2.1, 0.05, 0.12, 2),
        cylinder(1.98, 0.05, 0.12, 2),
        cylinder(0.615, 0.045, 0.04, 2),
    ),
    # The UR10's joint sizes (4, 4, 3, 2, 2, 2), hence its rotor estimates.
    rotor_inertia_kgm2=(1.2, 1.2, 0.45, 0.10, 0.10, 0.10),
    torque_max_nm=(330.0, 330.0, 150.0, 56.0, 56.0, 56.0),
    q_min_rad=(-_LIMIT_RAD,) * 6,
    q_max_rad=(_LIMIT_RAD,) * 6,
    qd_max_rad_s=(120 * DEG, 120 * DEG, 180 * DEG, 180 * DEG, 180 * DEG, 180 * DEG),
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -HALF_PI, HALF_PI, -HALF_PI, -HALF_PI, 0.0),
    sources=(
        "UR10e (e-Series). "
        "DH parameters, link masses and centres of mass: Universal Robots, 'DH parameters for "
        "calculations of kinematics and dynamics' (universal-robots.com support article). "
        "Joint limits (±360°) and speeds (120°/s base and shoulder, 180°/s the others) from "
        "the UR data sheet. ESTIMATES: link inertias (solid cylinders along each link or "
        "joint housing, radii from the housing sizes); rotor inertias (J_m·N² with harmonic "
        "drive ratio N = 101 and J_m from the motor size); acceleration limits (working "
        "values, not published: 10 rad/s² base/shoulder, 12 elbow, 15 wrists)."
        " Peak torques (330, 330, 150, 56, 56, 56) N·m from UR's e-Series joint sizes. "
        "Controller: 2 ms (RTDE at 500 Hz). Rated payload 12.5 kg (not included by default)."
    ),
)

ROBOT = RobotEntry(
    spec=_SPEC,
    joint_names=UR_JOINT_NAMES,
    # e-Series: a longer pipeline in cycles than the CB3 (4 against 1) but a 4x shorter
    # cycle; RTDE samples and sends within the cycle. Drive loop as the UR10's.
    timing=ControllerTiming(
        pipeline_cycles=4,
        packing_phase_periods=(0.02, 0.97),
        cycle_jitter_s=20e-6,
        bandwidth_hz=(25.0, 25.0, 25.0, 40.0, 40.0, 40.0),
        breakaway_time_s=(0.0045,) * 6,
        state_velocity=True,
    ),
    # PolyScope 5 reports the model as "UR10"; the client knows the e-Series by the major.
    twin=TwinIdentity(
        interface="ur_rtde",
        controller="e-Series",
        model_name="UR10",
        controller_version=(5, 11, 1, 108318),
        serial_number="20215000001",
    ),
    # As the UR10's (1.3 m reach): the belt 0.80 m out.
    cell=WorkCell(
        seed_q_rad=(0.0, -HALF_PI, HALF_PI, -HALF_PI, -HALF_PI, 0.0),
        work_point_m=(-0.80, 0.20, 0.20),
    ),
    sweep_q_min_rad=UR_SWEEP_Q_MIN_RAD,
    sweep_q_max_rad=UR_SWEEP_Q_MAX_RAD,
    # RTDE samples and sends in one cycle: no response_extra_cycle.
    rated_payload_kg=12.5,
    default_effects=(
        "gravity_load",
        "gravity_direction",
        "direction",
        "inertia",
        "thermal_drift",
        "joint_offset",
    ),
    shipped_model="ur10e-sim",
    paper_family="ur",
)
