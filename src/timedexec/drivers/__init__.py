"""timedexec.drivers: one RobotDriver interface over ur_rtde, KUKA RSI and the simulator."""

from __future__ import annotations

from timedexec.drivers._base import RobotDriver, RobotState

__all__ = ["RobotDriver", "RobotState"]
