"""ExecutorSettings: the executor's options in one object — defaults, validation, round trip."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from timedexec.drivers import SimDriver
from timedexec.errors import ConfigError
from timedexec.execution import (
    ExecutionLimits,
    ExecutorSettings,
    FixedDelays,
    StalenessLimits,
    TimedExecutor,
)

MODEL = FixedDelays(robot="ur10e", actuation_s=0.019, response_s=0.0011, actuation_std_s=6e-4)


def test_defaults_are_the_constructor_defaults_they_replace() -> None:
    """``ExecutorSettings()`` holds exactly the defaults ``TimedExecutor``'s keyword
    arguments had (none changed by moving them), but for the cycle lock and coasting, which
    since issue 34 are the driver's choice (None): the executor built without settings runs
    with these."""
    s = ExecutorSettings()
    assert s.confidence == 0.95
    assert s.staleness == StalenessLimits()
    assert s.watchdog_timeout_s == 0.1
    assert s.cycle_lock is None  # the driver's choice: on for a UR (issue 34), else off
    assert s.round_trip_s == 4e-4
    assert s.realtime_priority is None
    assert s.limits == ExecutionLimits()
    assert s.position_gain_1_s == 0.0
    assert s.compensate is True
    assert s.stop_deceleration_rad_s2 is None
    assert s.coast is None
    assert TimedExecutor(SimDriver("ur10e"), MODEL).settings == s


def test_round_trip_through_json() -> None:
    """``to_dict`` is JSON-safe (nested limits as dicts) and ``from_dict`` reads it back to
    an equal object; missing keys take their defaults."""
    s = ExecutorSettings(
        confidence=0.9,
        staleness=StalenessLimits.from_stale_periods(25),
        watchdog_timeout_s=None,
        cycle_lock=True,
        round_trip_s=7e-4,
        realtime_priority=5,
        limits=ExecutionLimits(velocity_fraction=0.5, acceleration_cap_rad_s2=None),
        position_gain_1_s=20.0,
        compensate=False,
        stop_deceleration_rad_s2=2.0,
        coast=True,
    )
    d = json.loads(json.dumps(s.to_dict()))
    assert d["staleness"]["stall_periods"] == 25.0
    assert d["limits"]["velocity_fraction"] == 0.5
    assert ExecutorSettings.from_dict(d) == s
    assert ExecutorSettings.from_dict({"coast": True}) == ExecutorSettings(coast=True)
    assert StalenessLimits.from_dict(StalenessLimits().to_dict()) == StalenessLimits()
    assert s.replace(coast=False).coast is False


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"confidence": 1.5}, r"confidence=1.5 outside \(0, 1\); give a probability"),
        ({"watchdog_timeout_s": 20.0}, r"watchdog_timeout_s=20.0 outside \(0, 10\] s; e.g. 0.1"),
        ({"watchdog_timeout_s": math.nan}, r"watchdog_timeout_s=nan outside"),
        ({"round_trip_s": -1e-4}, r"round_trip_s=-0.0001 is not a time >= 0 s; measure it"),
        ({"realtime_priority": 0}, r"realtime_priority=0 outside the SCHED_FIFO range 1..99"),
        ({"realtime_priority": 5.0}, r"realtime_priority=5.0 outside"),
        ({"position_gain_1_s": -1.0}, r"position_gain_1_s=-1.0 is not a gain >= 0 1/s"),
        ({"stop_deceleration_rad_s2": 0.0}, r"stop_deceleration_rad_s2=0.0 is not a dec"),
        ({"cycle_lock": 1}, r"cycle_lock=1 is not a bool or None; give True, False or None"),
        ({"limits": {"velocity_fraction": 0.5}}, r"limits=.* is not an ExecutionLimits"),
        ({"staleness": 3}, r"staleness=3 is not a StalenessLimits.*from_stale_periods"),
        ({"echo_depth_cycles": -1}, r"echo_depth_cycles=-1 is not a whole number of cycles"),
        ({"echo_depth_cycles": 2.0}, r"echo_depth_cycles=2.0 is not a whole number.*twin's"),
        ({"echo_depth_cycles": True}, r"echo_depth_cycles=True is not a whole number"),
    ],
)
def test_a_bad_value_is_refused_where_the_settings_are_built(
    changes: dict[str, object], message: str
) -> None:
    """Each option is checked once, when the settings are built: a ConfigError naming the
    field, the value, the range and what to give."""
    with pytest.raises(ConfigError, match=message):
        ExecutorSettings(**changes)  # type: ignore[arg-type]


def test_unknown_keys_and_a_settings_of_the_wrong_type_are_refused() -> None:
    """A misspelt key in a dict (also a nested one) is a ConfigError listing the known
    keys; the executor takes an ExecutorSettings only (a dict goes through from_dict)."""
    with pytest.raises(ConfigError, match=r"unknown ExecutorSettings keys \['cycle_locks'\]"):
        ExecutorSettings.from_dict({"cycle_locks": True})
    with pytest.raises(ConfigError, match=r"unknown StalenessLimits keys \['floor'\]"):
        ExecutorSettings.from_dict({"staleness": {"floor": 0.05}})
    with pytest.raises(ConfigError, match=r"unknown ExecutionLimits keys \['cap'\]"):
        ExecutorSettings.from_dict({"limits": {"cap": 8.0}})
    with pytest.raises(ConfigError, match=r"not an ExecutorSettings; .*from_dict"):
        TimedExecutor(SimDriver("ur10e"), MODEL, {"coast": True})  # type: ignore[arg-type]


def test_idle_until_rest_returns_once_the_arm_is_still() -> None:
    """``idle(until, until_rest=True)`` reads (never commands) and returns after the third
    package in a row with every joint below 0.01 rad/s: at once for an arm at rest, long
    before ``until``."""
    with TimedExecutor(SimDriver("ur10e", seed=1, physics_rate_hz=2000), MODEL) as ex:
        rows = len(ex.log)
        start = ex.now()
        ex.idle(start + 5.0, until_rest=True)
        assert len(ex.log) - rows == 3
        assert ex.now() - start < 0.1
        assert np.all(np.isnan(ex.log.arrays(rows)["send_s"]))  # no command went out
