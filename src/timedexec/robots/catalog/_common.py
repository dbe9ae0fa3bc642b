"""Helpers and family conventions shared by the catalog's data modules."""

from __future__ import annotations

import math

__all__ = [
    "DEG",
    "HALF_PI",
    "KUKA_JOINT_NAMES",
    "PI",
    "UR_JOINT_NAMES",
    "UR_SWEEP_Q_MAX_RAD",
    "UR_SWEEP_Q_MIN_RAD",
    "cylinder",
]

DEG = math.pi / 180.0
PI = math.pi
HALF_PI = math.pi / 2.0

#: Joint names of every UR arm (Universal Robots' ROS driver, ur_description).
UR_JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
#: Joint names of KUKA arms in ROS-Industrial (kuka_experimental): A1..A6.
KUKA_JOINT_NAMES = ("joint_a1", "joint_a2", "joint_a3", "joint_a4", "joint_a5", "joint_a6")

#: Calibration-sweep ranges of a UR arm, rad: half a turn either way; the shoulder from
#: straight out to straight up and the elbow within ±2.6 rad keep the arm above its base
#: plane (a sweep must not drive into the table).
UR_SWEEP_Q_MIN_RAD = (-PI, -PI, -2.6, -PI, -PI, -PI)
UR_SWEEP_Q_MAX_RAD = (PI, 0.0, 2.6, PI, PI, PI)


def cylinder(
    mass_kg: float, radius_m: float, length_m: float, axis: int
) -> tuple[float, float, float]:
    """Principal inertia (Ixx, Iyy, Izz) of a solid cylinder along ``axis`` (0=x, 1=y, 2=z)."""
    along = 0.5 * mass_kg * radius_m**2
    across = mass_kg * (3.0 * radius_m**2 + length_m**2) / 12.0
    out = [across, across, across]
    out[axis] = along
    return (out[0], out[1], out[2])
