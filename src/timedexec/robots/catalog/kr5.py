"""KUKA KR 5 sixx R850, RSI at 12 ms (``#IPO``) or 4 ms (``#IPO_FAST``): the paper's KUKA.

DH frames chosen so that the vendor angles A1..A6 are the inputs: frame 0 z up; A1 turns
about -z (joint_sign -1); A2 and A3 about the DH z axes; A3's offset -90° puts x3 along the
90 mm elbow offset; A4 and A6 turn about -z (joint_sign -1); the offset of 180° on A6 makes
frame 6 the ROS-Industrial tool0 frame (z out of the flange, x down at A1..A6 = 0). At
(0, -90, 90, 0, 0, 0)° the upper arm is vertical, the forearm horizontal and the flange
points forward along base +x at (0.560, 0, 0.790) m.
"""

from __future__ import annotations

from timedexec.robots._entry import ControllerTiming, RobotEntry, TwinIdentity, WorkCell
from timedexec.robots._spec import RobotSpec
from timedexec.robots.catalog._common import DEG, HALF_PI, KUKA_JOINT_NAMES, PI, cylinder

__all__ = ["ROBOT"]

_MASS_KG = (7.0, 6.5, 4.5, 2.5, 1.2, 0.3)  # + about 7 kg fixed base = 29 kg

_SPEC = RobotSpec(
    name="kr5",
    description="KUKA KR 5 sixx R850, RSI at 12 ms (IPO) or 4 ms (IPO_FAST)",
    vendor="kuka",
    controller_period_s=0.012,
    period_options_s=(0.012, 0.004),
    dh_a_m=(0.075, 0.365, 0.090, 0.0, 0.0, 0.0),
    dh_d_m=(0.335, 0.0, 0.0, 0.405, 0.0, 0.080),
    dh_alpha_rad=(-HALF_PI, 0.0, -HALF_PI, HALF_PI, -HALF_PI, 0.0),
    dh_offset_rad=(0.0, 0.0, -HALF_PI, 0.0, 0.0, PI),
    joint_sign=(-1.0, 1.0, 1.0, -1.0, 1.0, -1.0),
    link_mass_kg=_MASS_KG,
    link_com_m=(
        (-0.04, 0.10, 0.0),  # rotating column, below and behind the A2 axis
        (-0.18, 0.0, 0.0),  # rocker: halfway between A2 and A3
        (-0.04, 0.0, -0.03),  # arm housing with wrist motors, near the elbow
        (0.0, -0.19, 0.0),  # forearm, behind the wrist centre
        (0.0, 0.0, 0.01),  # wrist
        (0.0, 0.0, -0.01),  # flange
    ),
    link_inertia_kgm2=(
        cylinder(7.0, 0.10, 0.20, 1),  # column, vertical (y1 points down)
        cylinder(6.5, 0.06, 0.365, 0),  # rocker along x2
        cylinder(4.5, 0.07, 0.20, 2),  # arm housing along the forearm axis z3
        cylinder(2.5, 0.04, 0.30, 1),  # forearm along y4
        cylinder(1.2, 0.04, 0.10, 2),
        cylinder(0.3, 0.03, 0.02, 2),
    ),
    rotor_inertia_kgm2=(0.9, 0.9, 0.4, 0.06, 0.06, 0.03),
    torque_max_nm=(160.0, 220.0, 110.0, 30.0, 30.0, 20.0),
    q_min_rad=(-170 * DEG, -190 * DEG, -119 * DEG, -190 * DEG, -120 * DEG, -358 * DEG),
    q_max_rad=(170 * DEG, 45 * DEG, 165 * DEG, 190 * DEG, 120 * DEG, 358 * DEG),
    qd_max_rad_s=tuple(v * DEG for v in (375.0, 300.0, 375.0, 410.0, 410.0, 660.0)),
    qdd_max_rad_s2=(18.0, 15.0, 18.0, 28.0, 28.0, 45.0),
    home_q_rad=(0.0, -HALF_PI, HALF_PI, 0.0, 0.0, 0.0),
    sources=(
        "KUKA KR 5 sixx R850 (the paper's 'KR 5 sixx'; the R850 variant is chosen). "
        "Dimensions (a1 = 75, d1 = 335, a2 = 365, a3 = 90, d4 = 405, d6 = 80 mm), axis "
        "ranges (A1 ±170°, A2 -190°..+45°, A3 -119°..+165°, A4 ±190°, A5 ±120°, A6 ±358°) "
        "and axis speeds (375, 300, 375, 410, 410, 660 °/s) from the KUKA data sheet; joint "
        "directions as in ROS-Industrial kuka_experimental (A1, A4, A6 turn about -z). "
        "ESTIMATES (KUKA does not publish them): link masses (7.0, 6.5, 4.5, 2.5, 1.2, "
        "0.3) kg, chosen so that with a fixed base of about 7 kg the total is the data "
        "sheet's 29 kg; centres of mass from the link geometry; link inertias as solid "
        "cylinders; rotor inertias (J_m·N² for AC servos of about 3e-5..1e-4 kg·m² behind "
        "gears of ratio 100..160); peak torques (160, 220, 110, 30, 30, 20) N·m, sized to "
        "exceed the gravity torque at the rated 5 kg payload; acceleration limits (about "
        "0.3 s to full speed on A1..A3, 0.25 s on the wrist). RSI: 12 ms (#IPO) default, "
        "4 ms (#IPO_FAST) option. Rated payload 5 kg (not included by default)."
    ),
)

ROBOT = RobotEntry(
    spec=_SPEC,
    joint_names=KUKA_JOINT_NAMES,
    # RSI: the IPO cycle interpolates and a drive-bus stage follows; the pipeline is a time
    # (about 72 ms, the paper's ~7.5 periods with the velocity loop), so at 4 ms it holds
    # three times as many cycles. Sampling and sending fall in separate cycles (the
    # response_extra_cycle effect); the packing phase within one is 0.5-9.5 ms (at most
    # 80 % of the period).
    timing=ControllerTiming(
        pipeline_s=0.072,
        packing_phase_periods=(1.0, 0.8),
        packing_phase_max_s=(0.0005, 0.0095),
        cycle_jitter_s=10e-6,
        bandwidth_hz=(12.0, 12.0, 12.0, 25.0, 25.0, 25.0),
        breakaway_time_s=(0.0015,) * 6,
        state_velocity=False,
    ),
    twin=TwinIdentity(interface="kuka_rsi", controller="KR C4"),
    # The belt 0.55 m out (850 mm reach), the torch pointing down from the wrist (A5 90°).
    cell=WorkCell(
        seed_q_rad=(0.0, -HALF_PI, HALF_PI, 0.0, HALF_PI, 0.0),
        work_point_m=(0.55, 0.20, 0.30),
    ),
    # Inside the axis ranges, keeping the arm above its base plane (A2 -90°: upper arm up).
    sweep_q_min_rad=tuple(v * DEG for v in (-150, -170, -100, -170, -110, -170)),
    sweep_q_max_rad=tuple(v * DEG for v in (150, 10, 145, 170, 110, 170)),
    # The paper found the KR 5's response delay above one period: all effects.
    rated_payload_kg=5.0,
    default_effects=(
        "gravity_load",
        "gravity_direction",
        "direction",
        "inertia",
        "thermal_drift",
        "joint_offset",
        "response_extra_cycle",
    ),
    shipped_model="kr5-sim",
    paper_family="kuka",
)
