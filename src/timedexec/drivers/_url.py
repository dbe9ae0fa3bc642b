"""Drivers chosen by URL: ``sim://ROBOT``, ``ur://HOST``, ``rsi://PORT``.

Every part of a URL means something or is refused: an unknown query parameter, a repeated
one, a malformed value or a path where none belongs is a
:class:`~timedexec.errors.ConfigError` naming it and what is allowed (a typo never falls
back silently to a default).
"""

from __future__ import annotations

import math
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from timedexec.drivers._base import RobotDriver
from timedexec.errors import ConfigError
from timedexec.robots import ROBOT_NAMES

__all__ = ["SCHEMES", "URL_PARAMS", "open_driver"]

SCHEMES = ("sim", "ur", "rsi")

#: Query parameters each scheme accepts (anything else is an error).
URL_PARAMS: dict[str, tuple[str, ...]] = {
    "sim": ("realtime", "seed"),
    "ur": ("external_control", "ur_cap_port", "program"),
    "rsi": ("period", "listen", "robot", "ipoc_tick_ms", "first_frame_timeout_s"),
}

#: Largest seed (32-bit unsigned, as the command line's ``--seed``).
_MAX_SEED = 2**32 - 1
_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off", "")


def _query(url: str, scheme: str, query: str) -> dict[str, str]:
    allowed = URL_PARAMS[scheme]
    out: dict[str, str] = {}
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise ConfigError(
            f"robot URL {url!r}: malformed query {query!r}; write it as ?name=value&name=value"
        ) from None
    for key, value in pairs:
        if key not in allowed:
            what = f"allowed: {', '.join(allowed)}" if allowed else "it takes none"
            raise ConfigError(
                f"robot URL {url!r}: unknown parameter {key!r} for {scheme}:// URLs ({what})"
            )
        if key in out:
            raise ConfigError(f"robot URL {url!r}: parameter {key!r} is given twice; give it once")
        out[key] = value
    return out


def _seed(url: str, value: Any) -> int:
    try:
        seed = int(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"robot URL {url!r}: seed={value!r} is not an integer; use 0 .. {_MAX_SEED}, "
            "e.g. sim://ur10?seed=1"
        ) from None
    if isinstance(value, float) or not 0 <= seed <= _MAX_SEED:
        raise ConfigError(f"robot URL {url!r}: seed={value!r} must be an integer 0 .. {_MAX_SEED}")
    return seed


def _no_path(url: str, path: str, form: str) -> None:
    if path not in ("", "/"):
        raise ConfigError(f"robot URL {url!r}: unexpected path {path!r}; use {form}")


def open_driver(url: str, **options: Any) -> RobotDriver:
    """A (not yet connected) driver for ``url``.

    ``sim://ur10`` (in-process simulator, virtual time; ``sim://ur10?realtime=1`` real
    time, ``?seed=N`` its seed, which wins over a ``seed=`` option), ``ur://192.168.1.10``
    (ur_rtde; a UR twin: ``ur://127.0.0.2``; through the External Control URCap:
    ``?external_control=1``, ``?ur_cap_port=50002``, ``?program=/programs/x.urp`` which the
    dashboard then plays; see docs/ur-twin.md), ``rsi://49152`` (the PC side
    of KUKA RSI listening on that UDP port of the loopback interface;
    ``rsi://0.0.0.0:49152`` or ``?listen=192.168.1.5`` listens where a real robot can
    reach it; ``?robot=IP`` answers only that controller, ``?period=0.004``,
    ``?ipoc_tick_ms=1|12|auto``, ``?first_frame_timeout_s=10``; see docs/rsi.md). Extra
    keyword options go to the driver's constructor (URL parameters win).

    Raises
    ------
    ConfigError
        ``url`` not a string, an unknown scheme, a missing host or port, an unknown or
        repeated parameter (:data:`URL_PARAMS`), or a malformed value; the message names
        the part and what is allowed.
    """
    if not isinstance(url, str):
        raise ConfigError(
            f"robot URL must be a string such as 'sim://ur10', 'ur://HOST' or 'rsi://PORT', "
            f"got {type(url).__name__} {url!r}"
        )
    try:
        parts = urlsplit(url)
    except ValueError as exc:
        raise ConfigError(f"robot URL {url!r} is malformed ({exc})") from None
    scheme = parts.scheme
    if scheme not in SCHEMES:
        raise ConfigError(
            f"robot URL {url!r} has an unknown scheme {scheme!r}; use one of "
            f"sim://ROBOT ({', '.join(ROBOT_NAMES)}), ur://HOST, rsi://PORT"
        )
    if parts.fragment:
        raise ConfigError(f"robot URL {url!r}: unexpected fragment #{parts.fragment}")
    query = _query(url, scheme, parts.query)
    if scheme == "sim":
        from timedexec.drivers._sim import SimDriver

        _no_path(url, parts.path if parts.netloc else "", "sim://ROBOT, e.g. sim://ur10")
        where = parts.netloc or parts.path.strip("/")
        realtime = _flag(url, query, "realtime")
        option_seed = options.pop("seed", 0)
        seed = _seed(url, query["seed"]) if "seed" in query else _seed(url, option_seed)
        return SimDriver(where or "ur10", virtual=not realtime, seed=seed, **options)
    if scheme == "ur":
        from timedexec.drivers._ur import URDriver

        where = parts.netloc or parts.path
        if not where:
            raise ConfigError(
                f"robot URL {url!r} names no host; use ur://HOST, e.g. ur://192.168.1.10"
            )
        if parts.netloc:
            _no_path(url, parts.path, "ur://HOST, e.g. ur://192.168.1.10")
        options.update(_ur_options(url, query))
        return URDriver(where, **options)
    from timedexec.drivers._rsi import KukaRSIDriver

    options.update(_rsi_options(url, parts, query))
    port = options.pop("port")
    return KukaRSIDriver(port, **options)


_RSI_FORM = "rsi://PORT or rsi://LISTEN_IP:PORT, e.g. rsi://49152 or rsi://0.0.0.0:49152"


def _flag(url: str, query: dict[str, str], name: str) -> bool:
    """A yes/no URL parameter (absent: no)."""
    flag = query.get(name, "0").strip().lower()
    if flag not in _TRUE + _FALSE:
        raise ConfigError(
            f"robot URL {url!r}: {name}={query[name]!r} must be 1 or 0 (true/false, yes/no)"
        )
    return flag in _TRUE


def _ur_options(url: str, query: dict[str, str]) -> dict[str, Any]:
    """Keyword options of :class:`URDriver` from a ``ur://`` URL's parameters."""
    out: dict[str, Any] = {}
    if "external_control" in query:
        out["external_control"] = _flag(url, query, "external_control")
    if "ur_cap_port" in query:
        raw = query["ur_cap_port"].strip()
        if not (raw.isdigit() and 1 <= int(raw) <= 65535):
            raise ConfigError(
                f"robot URL {url!r}: ur_cap_port={query['ur_cap_port']!r} must be a port "
                "1..65535 (the External Control URCap's, default 50002)"
            )
        out["ur_cap_port"] = int(raw)
        out.setdefault("external_control", True)
    if "program" in query:
        out["program"] = query["program"].strip()  # URDriver checks it (a .urp path)
    return out


def _rsi_options(url: str, parts: Any, query: dict[str, str]) -> dict[str, Any]:
    """``rsi://[LISTEN_IP:]PORT?period=&listen=&robot=&ipoc_tick_ms=&first_frame_timeout_s=``
    as the driver's keyword arguments (``port`` included)."""
    from timedexec.drivers._rsi_link import (
        check_first_frame_timeout,
        check_listen_address,
        check_robot_ip,
    )

    where = parts.netloc or parts.path
    host, sep, port_text = where.rpartition(":")
    if not sep:
        host, port_text = "", where
    try:
        port = int(port_text)
    except ValueError:
        raise ConfigError(
            f"robot URL {url!r}: the RSI port {port_text!r} is not a number; use {_RSI_FORM}"
        ) from None
    if not 1 <= port <= 65535:
        raise ConfigError(f"robot URL {url!r}: port {port} outside 1..65535")
    if parts.netloc:
        _no_path(url, parts.path, _RSI_FORM)
    out: dict[str, Any] = {"port": port}

    def checked(check: Any, value: str, name: str) -> Any:
        try:
            return check(value)
        except ConfigError as exc:
            raise ConfigError(f"robot URL {url!r}: {name}: {exc}") from None

    listen = query.get("listen")
    if host and listen is not None and host != listen:
        raise ConfigError(
            f"robot URL {url!r}: the listen address is given twice ({host!r} before the port, "
            f"listen={listen!r}); give it once"
        )
    if host or listen is not None:
        out["host"] = checked(check_listen_address, host or listen or "", "listen address")
    if "robot" in query:
        out["robot_ip"] = checked(check_robot_ip, query["robot"], "robot")
    if "first_frame_timeout_s" in query:
        out["first_frame_timeout_s"] = checked(
            check_first_frame_timeout, query["first_frame_timeout_s"], "first_frame_timeout_s"
        )
    if "ipoc_tick_ms" in query:
        tick = query["ipoc_tick_ms"].strip().lower()
        try:
            tick_ms = math.nan if tick == "auto" else float(tick)
        except ValueError:
            tick_ms = -1.0
        if tick != "auto" and not (math.isfinite(tick_ms) and 0.0 < tick_ms <= 1000.0):
            raise ConfigError(
                f"robot URL {url!r}: ipoc_tick_ms={query['ipoc_tick_ms']!r} must be auto or "
                "the milliseconds per IPOC unit in (0, 1000]: 1 on a KR C4, the period (12 or "
                "4) on a KR C2 / RSI 2.x counting frames"
            )
        out["ipoc_tick_s"] = "auto" if tick == "auto" else tick_ms / 1000.0
    if "period" in query:
        try:
            period = float(query["period"])
        except ValueError:
            period = math.nan
        if not (math.isfinite(period) and period > 0):
            raise ConfigError(
                f"robot URL {url!r}: period={query['period']!r} must be a controller period "
                "in s > 0 (KUKA RSI: 0.012 or 0.004)"
            )
        out["period_s"] = period
    return out
