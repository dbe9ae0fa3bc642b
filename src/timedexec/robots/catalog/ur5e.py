"""Universal Robots UR5e (e-Series), RTDE at 500 Hz."""

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
    name="ur5e",
    description="Universal Robots UR5e (e-Series), RTDE at 500 Hz",
    vendor="universal_robots",
    controller_period_s=0.002,
    period_options_s=(0.002,),
    dh_a_m=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
    dh_d_m=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
    dh_alpha_rad=(HALF_PI, 0.0, 0.0, HALF_PI, -HALF_PI, 0.0),
    dh_offset_rad=(0.0,) * 6,
    joint_sign=(1.0,) * 6,
    link_mass_kg=(3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
    link_com_m=(
        (0.0, -0.02561, 0.00193),
        (0.2125, 0.0, 0.11336),
        (0.15, 0.0, 0.0265),
        (0.0, -0.0018, 0.01634),
        (0.0, 0.0018, 0.01634),
        (0.0, 0.0, -0.001159),
    ),
    link_inertia_kgm2=(
        cylinder(3.761, 0.06, 0.14, 2),  # shoulder housing (size 3), along the joint-2 axis
        cylinder(8.058, 0.045, 0.425, 0),  # upper arm tube, along x2
        cylinder(2.846, 0.035, 0.3922, 0),  # forearm tube, along x3
        cylinder(1.37, 0.04, 0.10, 2),  # wrist housings (size 1), along their joint axes
        cylinder(1.3, 0.04, 0.10, 2),
        cylinder(0.365, 0.032, 0.03, 2),  # flange disc
    ),
    # Harmonic drives of ratio about 101; J_m from the motor size: size 3 (base, shoulder,
    # elbow) about 4.4e-5 kg·m² as on the UR10's elbow, size 1 (wrists) about 5e-6.
    rotor_inertia_kgm2=(0.45, 0.45, 0.45, 0.05, 0.05, 0.05),
    torque_max_nm=(150.0, 150.0, 150.0, 28.0, 28.0, 28.0),
    q_min_rad=(-_LIMIT_RAD,) * 6,
    q_max_rad=(_LIMIT_RAD,) * 6,
    qd_max_rad_s=(180 * DEG,) * 6,
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -HALF_PI, HALF_PI, -HALF_PI, -HALF_PI, 0.0),
    sources=(
        "UR5e (e-Series). DH parameters (d1 0.1625, a2 -0.425, a3 -0.3922, d4 0.1333, "
        "d5 0.0997, d6 0.0996 m), link masses (3.761, 8.058, 2.846, 1.37, 1.3, 0.365 kg) and "
        "centres of mass: Universal Robots, 'DH parameters for calculations of kinematics "
        "and dynamics' (universal-robots.com support article; it calls the UR5e's link "
        "inertias negligible and gives none). Joint limits (±360° every joint) and speeds "
        "(180°/s every joint) from the UR5e data sheet; peak torques (150, 150, 150, 28, 28, "
        "28) N·m from UR's joint sizes (size 3 base/shoulder/elbow, size 1 wrists; UR, "
        "'Max. joint torques'). Controller: 2 ms (RTDE at 500 Hz). Rated payload 5 kg (not "
        "included by default). ESTIMATES: link inertias (solid cylinders along each link or "
        "joint housing, radii from the housing sizes); rotor inertias (J_m·N² with harmonic "
        "drive ratio N = 101 and J_m from the motor size); acceleration limits (working "
        "values, not published, as the UR10e's: 10 rad/s² base/shoulder, 12 elbow, 15 "
        "wrists); the controller timing (the UR10e's: the same e-Series controller, its "
        "drive-loop bandwidths and breakaway times, never measured on a UR5e); the twin's "
        "serial number (a placeholder)."
    ),
)

ROBOT = RobotEntry(
    spec=_SPEC,
    joint_names=UR_JOINT_NAMES,
    # The e-Series controller as on the UR10e (pipeline 4 cycles of 2 ms, RTDE packs within
    # the cycle); drive loop as the UR10e's (an estimate: no UR5e data).
    timing=ControllerTiming(
        pipeline_cycles=4,
        packing_phase_periods=(0.02, 0.97),
        cycle_jitter_s=20e-6,
        bandwidth_hz=(25.0, 25.0, 25.0, 40.0, 40.0, 40.0),
        breakaway_time_s=(0.0045,) * 6,
        state_velocity=True,
    ),
    # PolyScope 5 reports the model as "UR5"; the client knows the e-Series by the major.
    twin=TwinIdentity(
        interface="ur_rtde",
        controller="e-Series",
        model_name="UR5",
        controller_version=(5, 11, 1, 108318),
        serial_number="20205500001",
    ),
    # 850 mm reach: the belt 0.55 m out (as the KR 5's, the other 850 mm arm).
    cell=WorkCell(
        seed_q_rad=(0.0, -HALF_PI, HALF_PI, -HALF_PI, -HALF_PI, 0.0),
        work_point_m=(-0.55, 0.20, 0.15),
    ),
    sweep_q_min_rad=UR_SWEEP_Q_MIN_RAD,
    sweep_q_max_rad=UR_SWEEP_Q_MAX_RAD,
    # RTDE samples and sends in one cycle: no response_extra_cycle.
    rated_payload_kg=5.0,
    default_effects=(
        "gravity_load",
        "gravity_direction",
        "direction",
        "inertia",
        "thermal_drift",
        "joint_offset",
    ),
    shipped_model="ur5e-sim",
    paper_family="ur",
)
