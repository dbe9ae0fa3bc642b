"""``timedexec ros``: the ROS 2 node in front of a robot (docs/ros2.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from timedexec.cli._common import add_command, float_arg, int_arg

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> None:
    """Add ``ros`` to the subparsers ``sub``."""
    p = add_command(
        sub,
        "ros",
        help="a ROS 2 node in front of the robot: measured-time joint states, timed trajectories",
        description=(
            "Run the ROS 2 node 'timedexec' with the delay-compensating executor in front of "
            "the robot's driver (docs/ros2.md). It publishes joint_states (sensor_msgs/"
            "JointState, stamped when each state was measured), follows "
            "~/joint_trajectory (trajectory_msgs/JointTrajectory: the arm is physically at "
            "point k at header.stamp + time_from_start; a zero stamp starts as soon as it "
            "can; a stamp too soon or a trajectory beyond the limits is refused, with the "
            "reason logged and on /diagnostics) and publishes /diagnostics (predicted "
            "delays with 95 % bounds, cycle lock, drift alerts). Needs "
            "`pip install 'timedexec[ros]'`. Ctrl-C or SIGTERM stops the arm and exits 0; a "
            "lost robot exits 3.\n\n"
            "example:\n  timedexec serve --robot ur10 &\n"
            "  timedexec ros --robot-url ur://127.0.0.1 --model ur10-sim --mcap run.mcap"
        ),
    )
    p.add_argument("--robot-url", required=True, metavar="URL", help="ur://HOST, rsi://PORT, sim://ROBOT?realtime=1")
    p.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory or shipped model name")
    p.add_argument("--namespace", default="", metavar="NS", help="the node's ROS namespace (empty: the root)")
    p.add_argument(
        "--joint-names",
        default=None,
        metavar="NAMES",
        help="six comma-separated joint names (None: the robot's conventional names)",
    )
    p.add_argument(
        "--domain-id",
        type=int_arg(0, 232),
        default=None,
        metavar="ID",
        help="ROS domain id, 0 .. 232 (None: ROS_DOMAIN_ID, else 0)",
    )
    p.add_argument(
        "--localhost-only",
        action="store_true",
        help="discover ROS peers on this machine only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)",
    )
    p.add_argument(
        "--settings",
        default=None,
        metavar="JSON",
        help="the executor's options as a JSON file of ExecutorSettings fields (e.g. "
        '{"cycle_lock": true, "compensate": false}); None: position_gain_1_s 20 and the '
        "cycle lock (docs/ros2.md)",
    )
    p.add_argument("--log", default=None, help="write the node's log here at exit (.npz)")
    p.add_argument("--mcap", default=None, help="write the log as MCAP here at exit")
    p.add_argument(
        "--diagnostics-period",
        type=float_arg(0.05, 60.0, unit="s"),
        metavar="S",
        default=1.0,
        help="seconds between /diagnostics arrays (0.05 .. 60)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the node until Ctrl-C or SIGTERM (0); a lost robot raises (exit 3)."""
    from timedexec.ros import NodeOptions, run_node

    settings = None
    if args.settings is not None:
        settings = _read_settings(args.settings)
    names = None
    if args.joint_names is not None:
        names = tuple(n.strip() for n in args.joint_names.split(","))
    options = NodeOptions(
        robot_url=args.robot_url,
        model=args.model,
        namespace=args.namespace,
        joint_names=names,
        domain_id=args.domain_id,
        localhost_only=args.localhost_only,
        log_path=args.log,
        mcap_path=args.mcap,
        diagnostics_period_s=args.diagnostics_period,
        settings=settings,
    )
    # run_node sets the ROS environment and imports rclpy before it opens the driver: a
    # missing rclpy is bad input (exit 2) naming the extra.
    return run_node(options, ready=lambda line: print(f"timedexec ros: {line}", file=sys.stderr, flush=True))  # fmt: skip


def _read_settings(path: str) -> Any:
    """ExecutorSettings from a JSON file (ConfigError naming the file otherwise)."""
    import json

    from timedexec.errors import ConfigError
    from timedexec.execution import ExecutorSettings

    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except ValueError as exc:
        raise ConfigError(f"--settings {path}: not JSON ({exc}); give an object of ExecutorSettings fields") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"--settings {path}: a {type(data).__name__}, not an object of ExecutorSettings fields")
    return ExecutorSettings.from_dict(data)
