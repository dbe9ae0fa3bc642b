"""timedexec.drivers: one RobotDriver interface over ur_rtde, KUKA RSI and the simulator.

Drivers are chosen by URL with :func:`open_driver`; a robot URL is parsed once, into a
:class:`RobotURL` (the one grammar of ``sim://``, ``ur://`` and ``rsi://``, also read by the
command line and the fleet manifest). The vendor drivers import their client libraries only
when used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from timedexec.drivers._base import RobotDriver, RobotState
from timedexec.drivers._step import EARLY_WEIGHT, LatencyStep, find_latency_step
from timedexec.drivers._tap import HostTimeTap
from timedexec.drivers._url import (
    DEFAULT_SIM_ROBOT,
    SCHEMES,
    SWEEP_PARAMS,
    URL_PARAMS,
    RobotURL,
    open_driver,
)

if TYPE_CHECKING:
    from timedexec.drivers._rsi import KukaRSIDriver
    from timedexec.drivers._rsi_intake import RSIIntake
    from timedexec.drivers._sim import SimDriver, VirtualGyro
    from timedexec.drivers._ur import URDriver, ur_robot_named

__all__ = [
    "DEFAULT_SIM_ROBOT",
    "EARLY_WEIGHT",
    "SCHEMES",
    "SWEEP_PARAMS",
    "URL_PARAMS",
    "HostTimeTap",
    "KukaRSIDriver",
    "LatencyStep",
    "RSIIntake",
    "RSIState",
    "RobotDriver",
    "RobotState",
    "RobotURL",
    "SimDriver",
    "URDriver",
    "VirtualGyro",
    "find_latency_step",
    "open_driver",
    "ur_robot_named",
]

_LAZY = {
    "RSIIntake": "timedexec.drivers._rsi_intake",
    "RSIState": "timedexec.drivers._rsi",
    "SimDriver": "timedexec.drivers._sim",
    "VirtualGyro": "timedexec.drivers._sim",
    "URDriver": "timedexec.drivers._ur",
    "ur_robot_named": "timedexec.drivers._ur",
    "KukaRSIDriver": "timedexec.drivers._rsi",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'timedexec.drivers' has no attribute {name!r}")
