"""Robot URLs, parsed once: ``sim://ROBOT``, ``ur://HOST``, ``rsi://[LISTEN_IP:]PORT``.

:meth:`RobotURL.parse` turns a URL into one validated, frozen object; :func:`open_driver`,
the command line (``calibrate``) and the fleet manifest (a simulated sweep,
``sim://ROBOT?trials=N``) all take that object, so no one parses a robot URL again.

Grammar (every part means something or is refused: an unknown scheme, query parameter or
robot, a repeated parameter, a malformed value, a port, path or fragment where none belongs
is a :class:`~timedexec.errors.ConfigError` naming the part and what is allowed; a typo
never falls back silently to a default)::

    sim://[ROBOT][?realtime=0|1][&seed=N][&warm=0|1]   ROBOT: ur10 (the default), ur10e, kr5
    sim://[ROBOT]?trials=N[&seed=S][&repeats=R][&effects=E]    a simulated sweep (fleet)
    ur://HOST[?external_control=0|1][&ur_cap_port=P][&program=/programs/X.urp]
    rsi://[LISTEN_IP:]PORT[?listen=IP][&robot=IP][&period=S][&ipoc_tick_ms=MS|auto]
                          [&first_frame_timeout_s=S][&max_correction_deg=D|D1,...,D6]

Flags take 1/0, true/false, yes/no, on/off; an empty field (``?seed=1&``) is ignored, a
name without ``=`` is refused. The path-only forms ``sim:ur10`` and ``ur:HOST`` mean the
same as ``sim://ur10`` and ``ur://HOST``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any
from urllib.parse import SplitResult, unquote_plus, urlsplit

from timedexec.drivers._base import RobotDriver
from timedexec.errors import ConfigError
from timedexec.robots import ROBOT_NAMES, get_robot

__all__ = [
    "DEFAULT_SIM_ROBOT",
    "SCHEMES",
    "SWEEP_PARAMS",
    "URL_PARAMS",
    "RobotURL",
    "open_driver",
]

SCHEMES = ("sim", "ur", "rsi")

#: Query parameters each scheme accepts when the URL names a robot to drive.
URL_PARAMS: dict[str, tuple[str, ...]] = {
    "sim": ("realtime", "seed", "warm"),
    "ur": ("external_control", "ur_cap_port", "program"),
    "rsi": (
        "period",
        "listen",
        "robot",
        "ipoc_tick_ms",
        "first_frame_timeout_s",
        "max_correction_deg",
    ),
}
#: Query parameters of a simulated sweep (``sim://`` only; a fleet manifest's source).
SWEEP_PARAMS = ("trials", "seed", "repeats", "effects")
#: The robot ``sim://`` simulates when the URL names none.
DEFAULT_SIM_ROBOT = "ur10"

#: Largest seed (32-bit unsigned, as the command line's ``--seed``).
_MAX_SEED = 2**32 - 1
_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off", "")
_RSI_FORM = "rsi://PORT or rsi://LISTEN_IP:PORT, e.g. rsi://49152 or rsi://0.0.0.0:49152"
_UR_FORM = "ur://HOST, e.g. ur://192.168.1.10"


@dataclass(frozen=True, kw_only=True)
class RobotURL:
    """A robot URL, parsed and validated once (:meth:`parse`).

    Attributes
    ----------
    text : str
        The URL as given (for messages and a recording's ``source``).
    scheme : str
        ``"sim"``, ``"ur"`` or ``"rsi"``.
    host : str or None
        ``ur://``: the controller's host; ``rsi://``: the address this PC listens on (None:
        loopback); ``sim://``: None.
    port : int or None
        ``rsi://``: the PC's UDP port; None otherwise (ur_rtde uses the controller's fixed
        ports).
    robot : str or None
        ``sim://``: the simulated robot model as named (None: not named, the driver
        simulates :data:`DEFAULT_SIM_ROBOT`, the fleet the manifest's robot column); None
        for ``ur://`` and ``rsi://`` (the controller or the ``robot=`` option says).
    options : Mapping[str, Any]
        The query's parameters, validated, in SI units, under the driver's keyword names:
        ``sim://`` ``realtime`` (bool), ``seed`` (int), ``warm`` (bool: powered on
        hours before, :data:`~timedexec.sim.WARM_START_S`; default cold); ``ur://`` ``external_control``
        (bool), ``ur_cap_port`` (int), ``program`` (str); ``rsi://`` ``robot_ip`` (str),
        ``period_s`` (float, s), ``ipoc_tick_s`` (float, s, or ``"auto"``),
        ``first_frame_timeout_s`` (float, s), ``max_correction_deg`` (float or 6 floats,
        degrees); a sweep ``trials``, ``seed``, ``repeats``
        (int), ``effects`` (str). Only what the URL gives.
    sweep : bool
        Parsed as a simulated sweep (``sim://ROBOT?trials=N``), not a robot to drive.
    """

    text: str
    scheme: str
    host: str | None = None
    port: int | None = None
    robot: str | None = None
    options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    sweep: bool = False

    def __str__(self) -> str:
        return self.text

    def __reduce__(self) -> tuple[Any, ...]:
        # pickled as its text (the read-only options mapping itself cannot be), parsed again
        return (_parse, (self.text, self.sweep))

    @classmethod
    def parse(cls, url: str | RobotURL, *, sweep: bool = False) -> RobotURL:
        """Parse and validate a robot URL (see the module docstring for the grammar).

        Parameters
        ----------
        url : str or RobotURL
            The URL (a :class:`RobotURL` is returned as it is, unless ``sweep`` asks for
            another grammar than the one it was parsed with).
        sweep : bool
            Parse a simulated sweep (``sim://ROBOT?trials=N[&seed=S][&repeats=R]
            [&effects=E]``, :data:`SWEEP_PARAMS`) instead of a robot to drive.

        Raises
        ------
        ConfigError
            Naming the part of the URL that is wrong and what is allowed.
        """
        if isinstance(url, RobotURL):
            return url if url.sweep == sweep else cls.parse(url.text, sweep=sweep)
        if not isinstance(url, str):
            raise ConfigError(
                f"robot URL must be a string such as 'sim://ur10', 'ur://HOST' or 'rsi://PORT', "
                f"got {type(url).__name__} {url!r}"
            )
        try:
            parts = urlsplit(url)
        except ValueError as exc:
            raise ConfigError(f"robot URL {url!r} is malformed ({exc})") from None
        scheme = parts.scheme.lower()
        allowed = ("sim",) if sweep else SCHEMES
        if scheme not in allowed:
            raise ConfigError(
                f"robot URL {url!r} has an unknown scheme {parts.scheme!r}; use "
                + (
                    "sim://ROBOT?trials=N for a simulated sweep"
                    if sweep
                    else f"one of sim://ROBOT ({', '.join(ROBOT_NAMES)}), ur://HOST, rsi://PORT"
                )
            )
        if parts.fragment:
            raise ConfigError(f"robot URL {url!r}: unexpected fragment #{parts.fragment}")
        params = SWEEP_PARAMS if sweep else URL_PARAMS[scheme]
        what = f"{scheme}:// sweep" if sweep else f"{scheme}://"
        query = _query(url, what, params, parts.query)
        if scheme == "sim":
            robot = _sim_robot(url, parts)
            options = _sweep_options(url, query) if sweep else _sim_options(url, query)
            return cls(
                text=url, scheme=scheme, robot=robot, options=MappingProxyType(options), sweep=sweep
            )
        if scheme == "ur":
            return cls(
                text=url,
                scheme=scheme,
                host=_ur_host(url, parts),
                options=MappingProxyType(_ur_options(url, query)),
            )
        host, port = _rsi_address(url, parts, query)
        return cls(
            text=url,
            scheme=scheme,
            host=host,
            port=port,
            options=MappingProxyType(_rsi_options(url, query)),
        )


def open_driver(url: str | RobotURL, **options: Any) -> RobotDriver:
    """A (not yet connected) driver for ``url``.

    ``sim://ur10`` (in-process simulator, virtual time; ``sim://ur10?realtime=1`` real
    time, ``?seed=N`` its seed, which wins over a ``seed=`` option, ``?warm=1`` a robot
    powered on hours before the sweep instead of a cold one), ``ur://192.168.1.10``
    (ur_rtde; a UR twin: ``ur://127.0.0.2``; through the External Control URCap:
    ``?external_control=1``, ``?ur_cap_port=50002``, ``?program=/programs/x.urp`` which the
    dashboard then plays; see docs/ur-twin.md), ``rsi://49152`` (the PC side
    of KUKA RSI listening on that UDP port of the loopback interface;
    ``rsi://0.0.0.0:49152`` or ``?listen=192.168.1.5`` listens where a real robot can
    reach it; ``?robot=IP`` answers only that controller, ``?period=0.004``,
    ``?ipoc_tick_ms=1|12|auto``, ``?first_frame_timeout_s=10``; see docs/rsi.md). Extra
    keyword options go to the driver's constructor (URL parameters win).

    Parameters
    ----------
    url : str or RobotURL
        The robot's URL, or one parsed already (:meth:`RobotURL.parse`).
    **options
        Keyword arguments of the driver's constructor.

    Raises
    ------
    ConfigError
        ``url`` not a string, an unknown scheme, a missing host or port, an unknown or
        repeated parameter (:data:`URL_PARAMS`), or a malformed value; the message names
        the part and what is allowed.
    """
    parsed = url if isinstance(url, RobotURL) else RobotURL.parse(url)
    if parsed.sweep:
        raise ConfigError(
            f"robot URL {parsed.text!r} describes a simulated sweep (trials=...), not a "
            "robot to drive; give sim://ROBOT[?realtime=1&seed=N]"
        )
    if parsed.scheme == "sim":
        from timedexec.drivers._sim import SimDriver

        option_seed = options.pop("seed", 0)  # the URL's seed wins
        seed = (
            parsed.options["seed"] if "seed" in parsed.options else _seed(parsed.text, option_seed)
        )
        realtime = bool(parsed.options.get("realtime", False))
        if "warm" in parsed.options:
            options["warm"] = parsed.options["warm"]
        return SimDriver(
            parsed.robot or DEFAULT_SIM_ROBOT, virtual=not realtime, seed=seed, **options
        )
    if parsed.scheme == "ur":
        from timedexec.drivers._ur import URDriver

        assert parsed.host is not None  # parse refuses a ur:// URL without a host
        return URDriver(parsed.host, **{**options, **parsed.options})
    from timedexec.drivers._rsi import KukaRSIDriver

    assert parsed.port is not None  # parse refuses an rsi:// URL without a port
    address = {} if parsed.host is None else {"host": parsed.host}
    return KukaRSIDriver(parsed.port, **{**options, **address, **parsed.options})


# ----------------------------------------------------------------------------- the parts


def _parse(text: str, sweep: bool) -> RobotURL:
    """Unpickle a :class:`RobotURL`."""
    return RobotURL.parse(text, sweep=sweep)


def _query(url: str, what: str, allowed: tuple[str, ...], query: str) -> dict[str, str]:
    """The query's ``name=value`` fields (percent-decoded), each allowed and given once."""
    out: dict[str, str] = {}
    for item in query.split("&") if query else ():
        if not item:
            continue  # ?a=1& or ?a=1&&b=2: an empty field says nothing
        name, sep, value = item.partition("=")
        key = unquote_plus(name)
        if key not in allowed:
            raise ConfigError(
                f"robot URL {url!r}: unknown parameter {key!r} for {what} URLs "
                f"(allowed: {', '.join(allowed)})"
            )
        if not sep:
            raise ConfigError(
                f"robot URL {url!r}: parameter {key!r} has no value; write it as "
                "?name=value&name=value"
            )
        if key in out:
            raise ConfigError(f"robot URL {url!r}: parameter {key!r} is given twice; give it once")
        out[key] = unquote_plus(value)
    return out


def _authority(parts: SplitResult) -> str:
    """What names the robot or host: the netloc, or the path of ``sim:ur10``/``ur:HOST``."""
    return parts.netloc or parts.path.strip("/")


def _no_path(url: str, parts: SplitResult, form: str) -> None:
    if parts.netloc and parts.path not in ("", "/"):
        raise ConfigError(f"robot URL {url!r}: unexpected path {parts.path!r}; use {form}")


def _sim_robot(url: str, parts: SplitResult) -> str | None:
    _no_path(url, parts, "sim://ROBOT, e.g. sim://ur10")
    named = _authority(parts)
    if not named:
        return None
    try:
        return get_robot(named).name
    except ConfigError as exc:
        raise ConfigError(f"robot URL {url!r}: {exc}") from None


def _ur_host(url: str, parts: SplitResult) -> str:
    _no_path(url, parts, _UR_FORM)
    host = _authority(parts)
    if not host:
        raise ConfigError(f"robot URL {url!r} names no host; use {_UR_FORM}")
    try:
        port = parts.port
    except ValueError:
        port = -1
    if port is not None or host.endswith(":"):
        raise ConfigError(
            f"robot URL {url!r}: ur:// takes no port (ur_rtde uses the controller's fixed "
            f"ports: 30004 RTDE, 30003 script, 29999 dashboard); use {_UR_FORM}"
        )
    return host


def _flag(url: str, query: dict[str, str], name: str) -> bool:
    """A yes/no URL parameter."""
    flag = query[name].strip().lower()
    if flag not in _TRUE + _FALSE:
        raise ConfigError(
            f"robot URL {url!r}: {name}={query[name]!r} must be 1 or 0 (true/false, yes/no)"
        )
    return flag in _TRUE


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


def _sim_options(url: str, query: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if "realtime" in query:
        out["realtime"] = _flag(url, query, "realtime")
    if "seed" in query:
        out["seed"] = _seed(url, query["seed"])
    if "warm" in query:
        out["warm"] = _flag(url, query, "warm")
    return out


def _sweep_options(url: str, query: dict[str, str]) -> dict[str, Any]:
    """``trials`` (required, >= 1), ``seed``, ``repeats`` (>= 2: the noise floor needs
    replicates) and ``effects`` (checked against the vocabulary by whoever knows the robot)."""
    if "trials" not in query:
        raise ConfigError(
            f"robot URL {url!r}: a simulated sweep needs trials=N (e.g. sim://ur10?trials=2000)"
        )

    def integer(key: str, low: int) -> int:
        try:
            value = int(query[key])
        except ValueError:
            raise ConfigError(
                f"robot URL {url!r}: {key}={query[key]!r} is not an integer"
            ) from None
        if value < low:
            raise ConfigError(f"robot URL {url!r}: {key}={value} must be >= {low}")
        return value

    out: dict[str, Any] = {"trials": integer("trials", 1)}
    if "seed" in query:
        out["seed"] = _seed(url, query["seed"])
    if "repeats" in query:
        out["repeats"] = integer("repeats", 2)
    if "effects" in query:
        out["effects"] = query["effects"].strip()
    return out


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


def _checked(url: str, name: str, check: Callable[[str], Any], value: str) -> Any:
    try:
        return check(value)
    except ConfigError as exc:
        raise ConfigError(f"robot URL {url!r}: {name}: {exc}") from None


def _rsi_address(url: str, parts: SplitResult, query: dict[str, str]) -> tuple[str | None, int]:
    """The listen address (before the port or ``?listen=``; None: loopback) and the port."""
    from timedexec.drivers._rsi_link import check_listen_address

    _no_path(url, parts, _RSI_FORM)
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
    listen = query.get("listen")
    if host and listen is not None and host != listen:
        raise ConfigError(
            f"robot URL {url!r}: the listen address is given twice ({host!r} before the port, "
            f"listen={listen!r}); give it once"
        )
    if not host and listen is None:
        return None, port
    return _checked(url, "listen address", check_listen_address, host or listen or ""), port


def _rsi_options(url: str, query: dict[str, str]) -> dict[str, Any]:
    """``?robot=&first_frame_timeout_s=&ipoc_tick_ms=&period=&max_correction_deg=`` as the driver's keyword
    arguments (``listen`` is the address: :func:`_rsi_address`)."""
    from timedexec.drivers._rsi_link import check_first_frame_timeout, check_robot_ip

    out: dict[str, Any] = {}
    if "robot" in query:
        out["robot_ip"] = _checked(url, "robot", check_robot_ip, query["robot"])
    if "first_frame_timeout_s" in query:
        out["first_frame_timeout_s"] = _checked(
            url, "first_frame_timeout_s", check_first_frame_timeout, query["first_frame_timeout_s"]
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
    if "max_correction_deg" in query:
        out["max_correction_deg"] = _max_correction_deg(url, query["max_correction_deg"])
    return out


def _max_correction_deg(url: str, text: str) -> float | tuple[float, ...]:
    """``max_correction_deg=D`` (every axis) or ``D1,...,D6``: degrees, each in (0, 360]."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) not in (1, 6) or not all(math.isfinite(v) and 0 < v <= 360 for v in values):
        raise ConfigError(
            f"robot URL {url!r}: max_correction_deg={text!r} must be one angle in (0, 360] "
            "degrees or six separated by commas (A1..A6): the RSI configuration's AXISCORR "
            "limits, e.g. max_correction_deg=30"
        )
    return values[0] if len(values) == 1 else values
