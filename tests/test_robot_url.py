"""The one robot URL grammar (``timedexec.drivers.RobotURL``): every URL the drivers, the
``calibrate`` command and the fleet manifest accept parses into one validated object, and
every wrong part is one ConfigError naming the part and what is allowed."""

from __future__ import annotations

import pickle
import re

import pytest

from timedexec.drivers import (
    DEFAULT_SIM_ROBOT,
    SCHEMES,
    SWEEP_PARAMS,
    URL_PARAMS,
    RobotURL,
    open_driver,
)
from timedexec.errors import ConfigError


@pytest.mark.parametrize(
    ("url", "scheme", "host", "port", "robot", "options"),
    [
        ("sim://ur10", "sim", None, None, "ur10", {}),
        ("sim://", "sim", None, None, None, {}),
        ("sim:ur10e", "sim", None, None, "ur10e", {}),  # the path-only form, as before
        ("sim:///kr5", "sim", None, None, "kr5", {}),
        ("sim://UR10?seed=3&realtime=yes&", "sim", None, None, "ur10", {"seed": 3, "realtime": True}),
        ("sim://ur10e?warm=1", "sim", None, None, "ur10e", {"warm": True}),
        ("ur://192.168.1.10", "ur", "192.168.1.10", None, None, {}),
        ("ur:192.168.1.10", "ur", "192.168.1.10", None, None, {}),
        ("ur://h?ur_cap_port=50010", "ur", "h", None, None,
         {"ur_cap_port": 50010, "external_control": True}),
        ("ur://h?external_control=0&program=/programs/x.urp", "ur", "h", None, None,
         {"external_control": False, "program": "/programs/x.urp"}),
        ("rsi://49152", "rsi", None, 49152, None, {}),
        ("rsi://0.0.0.0:49152", "rsi", "0.0.0.0", 49152, None, {}),
        ("rsi://49152?listen=192.168.1.5&robot=192.168.1.10&period=0.004&ipoc_tick_ms=12"
         "&first_frame_timeout_s=30", "rsi", "192.168.1.5", 49152, None,
         {"robot_ip": "192.168.1.10", "period_s": 0.004, "ipoc_tick_s": 0.012,
          "first_frame_timeout_s": 30.0}),
        ("rsi://49152?ipoc_tick_ms=auto", "rsi", None, 49152, None, {"ipoc_tick_s": "auto"}),
    ],
)  # fmt: skip
def test_urls_parse_into_one_object(url, scheme, host, port, robot, options) -> None:  # type: ignore[no-untyped-def]
    """Each documented form parses once into scheme, host, port, robot and typed options in SI
    units under the driver's keyword names (the URL kept as written)."""
    parsed = RobotURL.parse(url)
    assert (parsed.scheme, parsed.host, parsed.port, parsed.robot) == (scheme, host, port, robot)
    assert dict(parsed.options) == options  # 12 ms / 1000 is the double nearest 0.012: exact
    assert str(parsed) == parsed.text == url
    assert RobotURL.parse(parsed) is parsed  # parsed once: an object passes through


def test_the_grammar_tables_name_every_scheme() -> None:
    """The tables the messages quote cover the schemes, and the sweep form is sim:// only."""
    assert set(URL_PARAMS) == set(SCHEMES) == {"sim", "ur", "rsi"}
    assert SWEEP_PARAMS == ("trials", "seed", "repeats", "effects")
    assert DEFAULT_SIM_ROBOT == "ur10"


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("http://h", "unknown scheme 'http'; use one of sim://ROBOT (ur10, ur10e, kr5, ur5e), ur://HOST"),
        ("sim://ur11", "unknown robot 'ur11'; choose one of ur10, ur10e, kr5, ur5e"),
        ("sim://ur10/x", "unexpected path '/x'; use sim://ROBOT"),
        ("sim://ur10#frag", "unexpected fragment #frag"),
        (
            "sim://ur10?trials=4",
            "unknown parameter 'trials' for sim:// URLs (allowed: realtime, seed, warm)",
        ),
        ("sim://ur10?realtime", "parameter 'realtime' has no value"),
        ("sim://ur10?realtime=maybe", "realtime='maybe' must be 1 or 0"),
        ("sim://ur10?warm=hot", "warm='hot' must be 1 or 0"),
        ("sim://ur10?seed=1&seed=2", "parameter 'seed' is given twice"),
        ("ur://", "names no host; use ur://HOST"),
        ("ur://h:30004", "ur:// takes no port (ur_rtde uses the controller's fixed ports"),
        ("rsi://x", "the RSI port 'x' is not a number; use rsi://PORT or rsi://LISTEN_IP:PORT"),
        ("rsi://70000", "port 70000 outside 1..65535"),
        ("rsi://49152?period=-1", "period='-1' must be a controller period in s > 0"),
    ],
)
def test_a_wrong_part_is_named_with_what_is_allowed(url: str, message: str) -> None:
    """One ConfigError per wrong part, naming the URL, the part and the allowed values; the
    same from open_driver (it parses through RobotURL)."""
    for parse in (RobotURL.parse, open_driver):
        with pytest.raises(ConfigError, match=re.escape(message)) as err:
            parse(url)
        assert repr(url) in str(err.value)


def test_the_sweep_form_is_its_own_grammar() -> None:
    """``sim://ROBOT?trials=N...`` (a fleet manifest's source) parses with sweep=True: trials
    required, repeats >= 2, driver options refused; open_driver refuses a sweep."""
    sweep = RobotURL.parse("sim://kr5?trials=40&seed=2&repeats=3&effects=base", sweep=True)
    assert (sweep.robot, dict(sweep.options)) == (
        "kr5", {"trials": 40, "seed": 2, "repeats": 3, "effects": "base"}
    )  # fmt: skip
    for url, message in {
        "sim://ur10": "a simulated sweep needs trials=N",
        "sim://ur10?trials=4&realtime=1": "unknown parameter 'realtime' for sim:// sweep URLs "
        "(allowed: trials, seed, repeats, effects)",
        "sim://ur10?trials=4&repeats=1": "repeats=1 must be >= 2",
        "sim://ur10?trials=zero": "trials='zero' is not an integer",
        "ur://h?trials=4": "use sim://ROBOT?trials=N for a simulated sweep",
    }.items():
        with pytest.raises(ConfigError, match=re.escape(message)):
            RobotURL.parse(url, sweep=True)
    with pytest.raises(ConfigError, match="describes a simulated sweep"):
        open_driver(sweep)
    assert RobotURL.parse(sweep, sweep=True) is sweep
    with pytest.raises(ConfigError, match="unknown parameter 'trials' for sim:// URLs"):
        RobotURL.parse(sweep)  # read as a robot to drive: the driver grammar refuses it
    for parsed in (sweep, RobotURL.parse("rsi://0.0.0.0:49152?period=0.004")):
        assert pickle.loads(pickle.dumps(parsed)) == parsed  # e.g. to a worker process


def _arrivals(url: str | RobotURL, **options: object) -> list[float]:
    with open_driver(url, **options) as robot:
        return [robot.read_state().host_time_s for _ in range(5)]


def test_open_driver_takes_the_parsed_object() -> None:
    """The object reaches the driver with its meaning: the sim robot and seed (the URL's
    seed wins over the option's: the seeded arrival jitter is the same with either option,
    and another seed changes it), the RSI address and period, the UR host and options."""
    sim = open_driver(RobotURL.parse("sim://kr5?realtime=0"))
    assert (sim.robot, sim.virtual) == ("kr5", True)  # type: ignore[attr-defined]
    assert open_driver("sim://").robot == DEFAULT_SIM_ROBOT
    seeded = _arrivals(RobotURL.parse("sim://ur10?seed=7"), seed=3)
    assert seeded == _arrivals("sim://ur10?seed=7", seed=4) == _arrivals("sim://ur10", seed=7)
    assert seeded != _arrivals("sim://ur10", seed=8)
    rsi = open_driver(RobotURL.parse("rsi://0.0.0.0:49152?period=0.004"))
    assert (rsi.host, rsi.port, rsi.controller_period_s) == ("0.0.0.0", 49152, 0.004)  # type: ignore[attr-defined]
    ur = open_driver(RobotURL.parse("ur://127.0.0.9?ur_cap_port=50010"), robot="ur10e")
    assert (ur.host, ur.external_control, ur.ur_cap_port, ur.robot) == (  # type: ignore[attr-defined]
        "127.0.0.9", True, 50010, "ur10e"
    )  # fmt: skip
