"""timedexec.ros: a ROS 2 node in front of any driver, and logs as MCAP (docs/ros2.md).

* :func:`run_node` with :class:`NodeOptions` (``timedexec ros``): ``joint_states`` stamped
  when each state was measured, ``~/joint_trajectory`` followed so that the arm is at
  point k at ``header.stamp + time_from_start_k``, ``/diagnostics`` with the predicted
  delays, the cycle lock and the drift monitor's alerts. rclpy is imported only here, on
  first use (:func:`import_rclpy` says what to install when it is missing);
  :func:`ros_environment` sets what rclpy reads at start (middleware, domain, localhost);
* :func:`plan_from_points` / :class:`PointsTrajectory`: trajectory points interpolated as
  joint_trajectory_controller does, as a :class:`~timedexec.execution.JointPlan`, checked
  against the limits (no rclpy needed);
* the node's log (:func:`save_node_log`, :func:`load_node_log`: a cycle log with the
  stamps it published) and :func:`log_to_mcap` (ROS 2 encodings; ``mcap`` and
  ``mcap-ros2-support``, no rclpy needed).

This package sits below ``execution`` and ``monitoring`` (it runs the executor and the
drift monitor) and above nothing but the command line.
"""

from __future__ import annotations

from timedexec.ros._env import INSTALL_HINT, import_rclpy, ros_environment
from timedexec.ros._mcap import (
    COMMAND_TOPIC,
    MESSAGE_DEFINITIONS,
    load_node_log,
    log_to_mcap,
    save_node_log,
    stamp_ns,
)
from timedexec.ros._node import NodeOptions, run_node
from timedexec.ros._trajectory import PointsTrajectory, order_joints, plan_from_points, spline_kind

__all__ = [
    "COMMAND_TOPIC",
    "INSTALL_HINT",
    "MESSAGE_DEFINITIONS",
    "NodeOptions",
    "PointsTrajectory",
    "import_rclpy",
    "load_node_log",
    "log_to_mcap",
    "order_joints",
    "plan_from_points",
    "ros_environment",
    "run_node",
    "save_node_log",
    "spline_kind",
    "stamp_ns",
]
