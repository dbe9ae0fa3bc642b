"""timedexec.robots: the single source of truth for every number about a robot.

A :class:`RobotSpec` (``_spec``) holds a robot's standard Denavit-Hartenberg kinematics, its
inertial data, its joint limits and its controller period. Each built-in robot is one data
module in :mod:`timedexec.robots.catalog`: a :class:`RobotEntry` (``_entry``) with its spec,
controller timing (:class:`ControllerTiming`), twin identity (:class:`TwinIdentity`), weld
cell (:class:`WorkCell`), joint names, calibration ranges, default effects and shipped
model. The registry (``_registry``: :data:`ROBOT_NAMES`, :func:`get_robot`,
:func:`get_robot_entry`) is built from the catalog, and every other layer reads robots from
it. The kinematics and rigid-body quantities are plain vectorised functions in
``_dynamics``; the pose of a tool on the flange, its Jacobian and the inverse kinematics in
``_ik``.

Conventions
-----------
* Joint angles ``q`` are the **vendor's** angles, the numbers a user types on the teach
  pendant (UR: rad as shown by PolyScope; KUKA: A1..A6). The DH joint angle is
  ``theta = joint_sign * q + dh_offset_rad``.
* The base frame (frame 0) has z up, against gravity; frame 6 is the flange (tool) frame.
  Joint ``j`` (1-based) turns about the z axis of frame ``j - 1``.
* Batches: every function accepts one configuration, shape (6,), or ``N`` of them, shape
  (N, 6), and answers with the matching leading shape.
* SI units: m, kg, kg·m², rad, rad/s, rad/s², N·m, s.
"""

from __future__ import annotations

from timedexec.robots._dynamics import (
    forward_kinematics,
    gravity_torque,
    gravity_torque_coefficients,
    joint_axis_in_tool,
    joint_inertia,
)
from timedexec.robots._entry import (
    INTERFACES,
    PAPER_FAMILIES,
    ControllerTiming,
    RobotEntry,
    TwinIdentity,
    WorkCell,
)
from timedexec.robots._ik import rotation_error, solve_ik, tool_jacobian, tool_pose
from timedexec.robots._registry import ROBOT_NAMES, get_robot, get_robot_entry
from timedexec.robots._spec import N_JOINTS, RobotSpec, check_configuration

__all__ = [
    "INTERFACES",
    "N_JOINTS",
    "PAPER_FAMILIES",
    "ROBOT_NAMES",
    "ControllerTiming",
    "RobotEntry",
    "RobotSpec",
    "TwinIdentity",
    "WorkCell",
    "check_configuration",
    "forward_kinematics",
    "get_robot",
    "get_robot_entry",
    "gravity_torque",
    "gravity_torque_coefficients",
    "joint_axis_in_tool",
    "joint_inertia",
    "rotation_error",
    "solve_ik",
    "tool_jacobian",
    "tool_pose",
]
