"""The executor's options in one frozen, validated, serialisable object."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from timedexec._validation import DictMixin, check_known_keys
from timedexec.errors import ConfigError
from timedexec.execution._bounds import check_confidence
from timedexec.execution._cycle import DEFAULT_ROUND_TRIP_S
from timedexec.execution._plan import ExecutionLimits
from timedexec.execution._safety import DEFAULT_WATCHDOG_TIMEOUT_S
from timedexec.execution._state import StalenessLimits

__all__ = ["MAX_WATCHDOG_TIMEOUT_S", "ExecutorSettings"]

#: Longest controller watchdog timeout accepted, s: an arm whose host died keeps its last
#: speed for up to this long.
MAX_WATCHDOG_TIMEOUT_S = 10.0


@dataclass(frozen=True, kw_only=True)
class ExecutorSettings(DictMixin):
    """Every option of :class:`~timedexec.execution.TimedExecutor`, validated once here.

    ``TimedExecutor(driver, model, ExecutorSettings(realtime_priority=5))``; the defaults
    (``ExecutorSettings()``) are what ``TimedExecutor(driver, model)`` runs with.
    :meth:`to_dict` / :meth:`from_dict` round-trip through JSON, so a run can store the
    settings that produced it.

    Parameters
    ----------
    confidence : float
        Default confidence of the timing bounds (:meth:`TimedExecutor.onset_bounds`,
        :meth:`TimedExecutor.arrival_bounds`), in (0, 1). Default 0.95.
    staleness : StalenessLimits
        When the state is too old to command from. Default ``StalenessLimits()``: limits
        adapted to the stream's measured jitter, stall limit ``min(0.08 s, max(0.05 s, 2 x
        p99 of the recent gaps))``, the same for lateness. A fault stops the robot at once
        and raises :class:`~timedexec.errors.StaleStateError`. Fixed limits in controller
        periods (the former ``stale_periods``): ``StalenessLimits.from_stale_periods(n)``.
    watchdog_timeout_s : float or None
        Arm the controller's watchdog with this timeout on connect, s, in (0, 10]. Default
        0.1; None: do not arm. The controller stops the program, and so the arm, when no
        command or kick reaches it for that long: a killed, hung or paused host. While idle
        each handled package kicks it (at most five times per timeout); if the caller does
        not step the executor for longer while idle it trips harmlessly and the next motion
        re-arms it. A trip while moving raises :class:`~timedexec.errors.DriverError`
        (recover with :meth:`TimedExecutor.recover`). Drivers without a watchdog ignore it.
    cycle_lock : bool or None
        Send each command at a fixed phase of the controller's cycle, aimed at the middle
        of its intake window: half a period before the controller's command deadline,
        found at connect by probing it (:meth:`TimedExecutor.probe_intake`; a UR's
        ``target_qd``; 0.2-0.7 s), else the earliest arrival of the cycle's package plus
        half a period minus ``round_trip_s`` (with a :class:`RuntimeWarning` at connect
        saying why the probe failed and what that costs); in virtual time the driver waits
        (the clock jumps). Default None: the driver's choice
        (``RobotDriver.cycle_lock_default``): on for a UR (``ur://``), off for RSI and the
        simulator; True or False forces it. Against the UR10e twin through ur_rtde at
        500 Hz the default missed 0.85 % of the cycles at normal priority on a lightly
        loaded PC (ur_rtde's ``initPeriod``/``waitPeriod`` loop 7.7 %) and 0.1-0.6 % with
        ``realtime_priority=5`` at load 2-17 (ur_rtde's 2.7-37 %); at normal priority on a
        loaded PC (load 6 and more) it missed more than ur_rtde's loop (docs/execution.md,
        "The defaults on a UR").
    round_trip_s : float
        Shortest boundary-to-package-to-command-arrival time, s (>= 0, below one controller
        period, checked at connect). Default 4e-4: the loopback twin's; measure it for a
        real cell.
    realtime_priority : int or None
        SCHED_FIFO priority (1-99) for the calling thread while connected, and the driver's
        threads it starts (they inherit it), where the OS allows it (Linux, root or
        CAP_SYS_NICE; otherwise normal scheduling and ``TimedExecutor.realtime`` False).
        Default None: never ask.
    limits : ExecutionLimits
        Fractions of the spec's limits to plan and command with. Default
        ``ExecutionLimits()``: the full limits, acceleration capped at 8 rad/s² (the
        calibration sweeps' ramp).
    position_gain_1_s : float
        Gain of an optional position correction, 1/s (>= 0). Default 0: pure
        delay-compensated feed-forward. The back-dated reported position is compared with
        the plan at the instant it describes; corrections already sent but not yet visible
        in that package are subtracted (a Smith predictor, so the loop's ~100 ms delay does
        not make it oscillate) and ``gain · error`` is added to the speed command; the error
        then decays with time constant ``1/gain`` once seen. Useful for tracking, where the
        velocity loop's recovery of the motion lost to breakaway leaves an
        onset-compensated joint slightly ahead.
    compensate : bool
        Shift each joint's command stream by its predicted actuation delay. Default True;
        False streams the plan without any shift (the "none" strategy).
    stop_deceleration_rad_s2 : float or None
        Deceleration of a fault stop and of :meth:`TimedExecutor.stop`, rad/s² (> 0).
        Default None: the spec's smallest joint acceleration limit, which every joint and
        every driver accepts (a driver that checks per joint, as the RSI driver does,
        refuses a stop above a joint's own limit).
    coast : bool or None
        While streaming, send each cycle's command on the controller's clock even when its
        package is late: if none has arrived by the send time (clock model), the command
        goes out from the estimate and the late package is only read (real-time drivers; a
        virtual-time simulator has no late packages). The stall limit still counts from the
        last package. Default None: as ``cycle_lock`` (the driver's choice: on for a UR).
        With ``cycle_lock`` the send-time p99 fell from 0.40-1.15 ms to 0.24-0.35 ms
        against the independent peer (docs/execution.md).
    echo_depth_cycles : int or None
        Cycles from the intake that takes a command to the first state package whose
        ``target_qd`` shows it, where known (>= 0; a protocol twin's:
        ``ControllerTiming.target_echo_cycles``). With it the intake probe names the cycle
        the state was sampled in by counting packages, whatever the publisher's phase
        (:meth:`IntakeFix.dated`). Default None: the model's (``echo_depth_cycles`` of a
        tracking model: ``calibrate`` measures it on the robot in its tracking phases and
        ``train --tracking`` puts it into the bundle), else the mean response delay
        chooses, which a publisher phase at the far end of a wide range can put a period
        off; the probe warns where its response is that close.

    Raises
    ------
    ConfigError
        A value outside its range (the message names the field, the value, the range and
        what to give instead).
    """

    confidence: float = 0.95
    staleness: StalenessLimits = field(default_factory=StalenessLimits)
    watchdog_timeout_s: float | None = DEFAULT_WATCHDOG_TIMEOUT_S
    cycle_lock: bool | None = None
    round_trip_s: float = DEFAULT_ROUND_TRIP_S
    realtime_priority: int | None = None
    limits: ExecutionLimits = field(default_factory=ExecutionLimits)
    position_gain_1_s: float = 0.0
    compensate: bool = True
    stop_deceleration_rad_s2: float | None = None
    coast: bool | None = None
    echo_depth_cycles: int | None = None

    def __post_init__(self) -> None:
        def bad(name: str, allowed: str, fix: str) -> ConfigError:
            value = getattr(self, name)
            return ConfigError(f"ExecutorSettings.{name}={value!r} {allowed}; {fix}")

        object.__setattr__(self, "confidence", check_confidence(self.confidence))
        if not isinstance(self.staleness, StalenessLimits):
            raise bad(
                "staleness",
                "is not a StalenessLimits",
                "give StalenessLimits(...) (fixed limits: StalenessLimits.from_stale_periods(n))",
            )
        if not isinstance(self.limits, ExecutionLimits):
            raise bad("limits", "is not an ExecutionLimits", "give ExecutionLimits(...)")
        if not isinstance(self.compensate, bool):
            raise bad("compensate", "is not a bool", "give True or False")
        for name in ("cycle_lock", "coast"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), bool):
                raise bad(name, "is not a bool or None", "give True, False or None (the "
                          "driver's default: on for a UR)")
        wd = self.watchdog_timeout_s
        if wd is not None and not (_is_number(wd) and 0 < wd <= MAX_WATCHDOG_TIMEOUT_S):
            raise bad(
                "watchdog_timeout_s",
                f"outside (0, {MAX_WATCHDOG_TIMEOUT_S:g}] s",
                f"e.g. {DEFAULT_WATCHDOG_TIMEOUT_S}, or None to leave the controller's "
                "watchdog off",
            )
        if not (_is_number(self.round_trip_s) and self.round_trip_s >= 0):
            raise bad(
                "round_trip_s",
                "is not a time >= 0 s",
                f"measure it against the controller or keep the default {DEFAULT_ROUND_TRIP_S}",
            )
        prio = self.realtime_priority
        if prio is not None and not (isinstance(prio, int) and not isinstance(prio, bool)
                                     and 1 <= prio <= 99):  # fmt: skip
            raise bad(
                "realtime_priority",
                "outside the SCHED_FIFO range 1..99",
                "e.g. 5 (below the kernel's own threads at 50), or None for normal scheduling",
            )
        if not (_is_number(self.position_gain_1_s) and self.position_gain_1_s >= 0):
            raise bad(
                "position_gain_1_s",
                "is not a gain >= 0 1/s",
                "give 0 (feed-forward only) or e.g. 20 (a 50 ms time constant)",
            )
        depth = self.echo_depth_cycles
        if depth is not None and not (isinstance(depth, int) and not isinstance(depth, bool)
                                      and depth >= 0):  # fmt: skip
            raise bad(
                "echo_depth_cycles",
                "is not a whole number of cycles >= 0",
                "give the controller's intake-to-target_qd depth (a twin's: "
                "get_robot_entry(name).timing.target_echo_cycles(period)), or None",
            )
        decel = self.stop_deceleration_rad_s2
        if decel is not None and not (_is_number(decel) and decel > 0):
            raise bad(
                "stop_deceleration_rad_s2",
                "is not a deceleration > 0 rad/s²",
                "give e.g. 2.0, or None for the spec's smallest joint acceleration limit",
            )
        for name in ("round_trip_s", "position_gain_1_s"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in ("watchdog_timeout_s", "stop_deceleration_rad_s2"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, float(getattr(self, name)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ExecutorSettings:
        """Inverse of :meth:`to_dict` (missing keys take their defaults).

        Raises
        ------
        ConfigError
            On unknown keys or invalid values.
        """
        check_known_keys(cls, data)
        kwargs = dict(data)
        if isinstance(kwargs.get("staleness"), Mapping):
            kwargs["staleness"] = StalenessLimits.from_dict(kwargs["staleness"])
        if isinstance(kwargs.get("limits"), Mapping):
            kwargs["limits"] = ExecutionLimits.from_dict(kwargs["limits"])
        return cls(**kwargs)

    def replace(self, **changes: Any) -> ExecutorSettings:
        """A copy with fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)


def _is_number(value: Any) -> bool:
    """A finite real number (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
