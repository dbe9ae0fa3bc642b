"""The ROS 2 environment the node needs, and a clear error where rclpy is missing."""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from typing import Any

from timedexec.errors import ConfigError

__all__ = ["INSTALL_HINT", "import_rclpy", "ros_environment"]

#: How to get what the node needs.
INSTALL_HINT = "pip install 'timedexec[ros]'"

#: The middleware the ``[ros]`` extra installs (ros-rmw-fastrtps-cpp).
DEFAULT_RMW = "rmw_fastrtps_cpp"
#: ROS 2 domain ids valid with Fast DDS's port mapping (0 .. 232).
DOMAIN_ID_MAX = 232


def ros_environment(
    env: MutableMapping[str, str] | None = None,
    *,
    domain_id: int | None = None,
    localhost_only: bool = False,
) -> MutableMapping[str, str]:
    """Set the variables rclpy reads when it starts, in ``env`` (default ``os.environ``).

    ``RMW_IMPLEMENTATION`` defaults to Fast DDS (the extra's middleware; a value already
    set is kept); ``domain_id`` sets ``ROS_DOMAIN_ID``; ``localhost_only`` sets
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (Jazzy and later; it replaces the
    deprecated ``ROS_LOCALHOST_ONLY=1``, which is removed so the two cannot disagree).

    Raises
    ------
    ConfigError
        ``domain_id`` outside 0 .. 232.
    """
    env = os.environ if env is None else env
    env.setdefault("RMW_IMPLEMENTATION", DEFAULT_RMW)
    if domain_id is not None:
        if isinstance(domain_id, bool) or not 0 <= int(domain_id) <= DOMAIN_ID_MAX:
            raise ConfigError(
                f"domain_id={domain_id!r} is outside 0 .. {DOMAIN_ID_MAX} (the ROS 2 domain "
                "ids Fast DDS maps to ports); choose one in range"
            )
        env["ROS_DOMAIN_ID"] = str(int(domain_id))
    if localhost_only:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def import_rclpy() -> Any:
    """``rclpy``, imported on first use.

    Raises
    ------
    ConfigError
        rclpy (or the message packages) is not installed; the message says to
        ``pip install 'timedexec[ros]'``.
    """
    try:
        import diagnostic_msgs.msg  # noqa: F401
        import rclpy
        import sensor_msgs.msg  # noqa: F401
        import trajectory_msgs.msg  # noqa: F401
    except ImportError as exc:
        raise ConfigError(
            f"the ROS 2 node needs rclpy and the ROS message packages ({exc.name or exc} is "
            f"missing): {INSTALL_HINT} (ROS 2 Kilted wheels for Python 3.11), or source a "
            "ROS 2 installation"
        ) from exc
    return rclpy
