"""The built-in robots: UR10 (CB3), UR10e and KUKA KR 5 sixx, and :func:`get_robot`.

Data only (one :class:`~timedexec.robots.RobotSpec` per robot, with the sources of every
number); the kinematics and dynamics live in :mod:`timedexec.robots._dynamics`.
"""

from __future__ import annotations

import math

from timedexec.errors import ConfigError
from timedexec.robots._spec import ROBOT_NAMES, RobotSpec

__all__ = ["get_robot"]

# --------------------------------------------------------------------------------------
# Built-in robots
# --------------------------------------------------------------------------------------


def _cylinder(
    mass_kg: float, radius_m: float, length_m: float, axis: int
) -> tuple[float, float, float]:
    """Principal inertia (Ixx, Iyy, Izz) of a solid cylinder along ``axis`` (0=x, 1=y, 2=z)."""
    along = 0.5 * mass_kg * radius_m**2
    across = mass_kg * (3.0 * radius_m**2 + length_m**2) / 12.0
    out = [across, across, across]
    out[axis] = along
    return (out[0], out[1], out[2])


_DEG = math.pi / 180.0
_PI = math.pi
_HALF_PI = math.pi / 2.0

# UR joints: harmonic drives, ratio about 101 in every joint. Rotor inertias are not
# published; J_m is estimated from the frameless-motor size of each joint (size 4 base and
# shoulder, size 3 elbow, size 2 wrists): J_m about 1.2e-4, 4.4e-5, 1.0e-5 kg·m².
_UR_ROTOR_KGM2 = (1.2, 1.2, 0.45, 0.10, 0.10, 0.10)
_UR_LIMIT_RAD = 2.0 * math.pi
_UR_SOURCES_COMMON = (
    "DH parameters, link masses and centres of mass: Universal Robots, 'DH parameters for "
    "calculations of kinematics and dynamics' (universal-robots.com support article). "
    "Joint limits (±360°) and speeds (120°/s base and shoulder, 180°/s the others) from "
    "the UR data sheet. ESTIMATES: link inertias (solid cylinders along each link or "
    "joint housing, radii from the housing sizes); rotor inertias (J_m·N² with harmonic "
    "drive ratio N = 101 and J_m from the motor size); acceleration limits (working "
    "values, not published: 10 rad/s² base/shoulder, 12 elbow, 15 wrists)."
)

_UR10 = RobotSpec(
    name="ur10",
    description="Universal Robots UR10 (CB3), RTDE at 125 Hz",
    vendor="universal_robots",
    controller_period_s=0.008,
    period_options_s=(0.008,),
    dh_a_m=(0.0, -0.612, -0.5723, 0.0, 0.0, 0.0),
    dh_d_m=(0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922),
    dh_alpha_rad=(_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0),
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
        _cylinder(7.1, 0.075, 0.18, 2),  # shoulder housing, along the joint-2 axis
        _cylinder(12.7, 0.06, 0.612, 0),  # upper arm tube, along x2
        _cylinder(4.27, 0.045, 0.5723, 0),  # forearm tube, along x3
        _cylinder(2.0, 0.05, 0.12, 2),  # wrist housings, along their joint axes
        _cylinder(2.0, 0.05, 0.12, 2),
        _cylinder(0.365, 0.045, 0.03, 2),  # flange disc
    ),
    rotor_inertia_kgm2=_UR_ROTOR_KGM2,
    torque_max_nm=(330.0, 330.0, 150.0, 54.0, 54.0, 54.0),
    q_min_rad=(-_UR_LIMIT_RAD,) * 6,
    q_max_rad=(_UR_LIMIT_RAD,) * 6,
    qd_max_rad_s=(120 * _DEG, 120 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG),
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -_HALF_PI, _HALF_PI, -_HALF_PI, -_HALF_PI, 0.0),
    sources=(
        "UR10 (CB3). "
        + _UR_SOURCES_COMMON
        + " Peak torques (330, 330, 150, 54, 54, 54) N·m from UR's joint sizes. "
        "Controller: 8 ms (RTDE at 125 Hz). Rated payload 10 kg (not included by default)."
    ),
)

_UR10E = RobotSpec(
    name="ur10e",
    description="Universal Robots UR10e (e-Series), RTDE at 500 Hz",
    vendor="universal_robots",
    controller_period_s=0.002,
    period_options_s=(0.002,),
    dh_a_m=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
    dh_d_m=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
    dh_alpha_rad=(_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0),
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
        _cylinder(7.369, 0.075, 0.18, 2),
        _cylinder(13.051, 0.06, 0.6127, 0),
        _cylinder(3.989, 0.045, 0.57155, 0),
        _cylinder(2.1, 0.05, 0.12, 2),
        _cylinder(1.98, 0.05, 0.12, 2),
        _cylinder(0.615, 0.045, 0.04, 2),
    ),
    rotor_inertia_kgm2=_UR_ROTOR_KGM2,
    torque_max_nm=(330.0, 330.0, 150.0, 56.0, 56.0, 56.0),
    q_min_rad=(-_UR_LIMIT_RAD,) * 6,
    q_max_rad=(_UR_LIMIT_RAD,) * 6,
    qd_max_rad_s=(120 * _DEG, 120 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG),
    qdd_max_rad_s2=(10.0, 10.0, 12.0, 15.0, 15.0, 15.0),
    home_q_rad=(0.0, -_HALF_PI, _HALF_PI, -_HALF_PI, -_HALF_PI, 0.0),
    sources=(
        "UR10e (e-Series). "
        + _UR_SOURCES_COMMON
        + " Peak torques (330, 330, 150, 56, 56, 56) N·m from UR's e-Series joint sizes. "
        "Controller: 2 ms (RTDE at 500 Hz). Rated payload 12.5 kg (not included by default)."
    ),
)

# KUKA KR 5 sixx R850. DH frames chosen so that the vendor angles A1..A6 are the inputs:
# frame 0 z up; A1 turns about -z (joint_sign -1); A2 and A3 about the DH z axes; A3's
# offset -90° puts x3 along the 90 mm elbow offset; A4 and A6 turn about -z (joint_sign
# -1); the offset of 180° on A6 makes frame 6 the ROS-Industrial tool0 frame (z out of the
# flange, x down at A1..A6 = 0). At (0, -90, 90, 0, 0, 0)° the upper arm is vertical, the
# forearm horizontal and the flange points forward along base +x at (0.560, 0, 0.790) m.
_KR5_MASS_KG = (7.0, 6.5, 4.5, 2.5, 1.2, 0.3)  # + about 7 kg fixed base = 29 kg
_KR5 = RobotSpec(
    name="kr5",
    description="KUKA KR 5 sixx R850, RSI at 12 ms (IPO) or 4 ms (IPO_FAST)",
    vendor="kuka",
    controller_period_s=0.012,
    period_options_s=(0.012, 0.004),
    dh_a_m=(0.075, 0.365, 0.090, 0.0, 0.0, 0.0),
    dh_d_m=(0.335, 0.0, 0.0, 0.405, 0.0, 0.080),
    dh_alpha_rad=(-_HALF_PI, 0.0, -_HALF_PI, _HALF_PI, -_HALF_PI, 0.0),
    dh_offset_rad=(0.0, 0.0, -_HALF_PI, 0.0, 0.0, _PI),
    joint_sign=(-1.0, 1.0, 1.0, -1.0, 1.0, -1.0),
    link_mass_kg=_KR5_MASS_KG,
    link_com_m=(
        (-0.04, 0.10, 0.0),  # rotating column, below and behind the A2 axis
        (-0.18, 0.0, 0.0),  # rocker: halfway between A2 and A3
        (-0.04, 0.0, -0.03),  # arm housing with wrist motors, near the elbow
        (0.0, -0.19, 0.0),  # forearm, behind the wrist centre
        (0.0, 0.0, 0.01),  # wrist
        (0.0, 0.0, -0.01),  # flange
    ),
    link_inertia_kgm2=(
        _cylinder(7.0, 0.10, 0.20, 1),  # column, vertical (y1 points down)
        _cylinder(6.5, 0.06, 0.365, 0),  # rocker along x2
        _cylinder(4.5, 0.07, 0.20, 2),  # arm housing along the forearm axis z3
        _cylinder(2.5, 0.04, 0.30, 1),  # forearm along y4
        _cylinder(1.2, 0.04, 0.10, 2),
        _cylinder(0.3, 0.03, 0.02, 2),
    ),
    rotor_inertia_kgm2=(0.9, 0.9, 0.4, 0.06, 0.06, 0.03),
    torque_max_nm=(160.0, 220.0, 110.0, 30.0, 30.0, 20.0),
    q_min_rad=(-170 * _DEG, -190 * _DEG, -119 * _DEG, -190 * _DEG, -120 * _DEG, -358 * _DEG),
    q_max_rad=(170 * _DEG, 45 * _DEG, 165 * _DEG, 190 * _DEG, 120 * _DEG, 358 * _DEG),
    qd_max_rad_s=tuple(v * _DEG for v in (375.0, 300.0, 375.0, 410.0, 410.0, 660.0)),
    qdd_max_rad_s2=(18.0, 15.0, 18.0, 28.0, 28.0, 45.0),
    home_q_rad=(0.0, -_HALF_PI, _HALF_PI, 0.0, 0.0, 0.0),
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

_BUILTIN: dict[str, RobotSpec] = {"ur10": _UR10, "ur10e": _UR10E, "kr5": _KR5}


def get_robot(name: str, *, period_s: float | None = None) -> RobotSpec:
    """Return the built-in spec of a robot.

    Parameters
    ----------
    name : str
        One of :data:`ROBOT_NAMES` (``"ur10"``, ``"ur10e"``, ``"kr5"``); case-insensitive.
    period_s : float, optional
        Controller period, s; default: the robot's default period (see
        :meth:`RobotSpec.with_period`).

    Raises
    ------
    ConfigError
        For an unknown name or a period the controller does not offer.
    """
    key = name.strip().lower() if isinstance(name, str) else name
    spec = _BUILTIN.get(key) if isinstance(key, str) else None
    if spec is None:
        raise ConfigError(f"unknown robot {name!r}; choose one of {', '.join(ROBOT_NAMES)}")
    return spec if period_s is None else spec.with_period(period_s)
