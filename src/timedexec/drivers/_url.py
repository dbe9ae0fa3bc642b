"""Drivers chosen by URL: ``sim://ROBOT``, ``ur://HOST``, ``rsi://PORT``."""

from __future__ import annotations

from typing import Any
from urllib.parse import parse_qs, urlsplit

from timedexec.drivers._base import RobotDriver
from timedexec.errors import ConfigError

__all__ = ["SCHEMES", "open_driver"]

SCHEMES = ("sim", "ur", "rsi")


def open_driver(url: str, **options: Any) -> RobotDriver:
    """A (not yet connected) driver for ``url``.

    ``sim://ur10`` (in-process simulator, virtual time; ``sim://ur10?realtime=1`` real
    time), ``ur://192.168.1.10`` (ur_rtde; a UR twin: ``ur://127.0.0.2``), ``rsi://49152``
    (the PC side of KUKA RSI listening on that UDP port; ``rsi://49152?period=0.004``).
    Extra keyword options go to the driver's constructor.
    """
    parts = urlsplit(url)
    scheme, where = parts.scheme, parts.netloc or parts.path
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    if scheme == "sim":
        from timedexec.drivers._sim import SimDriver

        realtime = query.pop("realtime", "0") not in ("0", "", "false")
        seed = int(query.pop("seed", options.pop("seed", 0)))
        return SimDriver(where or "ur10", virtual=not realtime, seed=seed, **options)
    if scheme == "ur":
        from timedexec.drivers._ur import URDriver

        if not where:
            raise ConfigError(
                f"robot URL {url!r} names no host; use ur://HOST, e.g. ur://192.168.1.10"
            )
        return URDriver(where, **options)
    if scheme == "rsi":
        from timedexec.drivers._rsi import KukaRSIDriver

        try:
            port = int(where)
        except ValueError:
            raise ConfigError(
                f"robot URL {url!r}: the RSI port {where!r} is not a number; use rsi://49152"
            ) from None
        if not 1 <= port <= 65535:
            raise ConfigError(f"robot URL {url!r}: port {port} outside 1..65535")
        if "period" in query:
            options.setdefault("period_s", float(query.pop("period")))
        return KukaRSIDriver(port, **options)
    raise ConfigError(
        f"robot URL {url!r} has an unknown scheme {scheme!r}; use one of "
        "sim://ROBOT (ur10, ur10e, kr5), ur://HOST, rsi://PORT"
    )
