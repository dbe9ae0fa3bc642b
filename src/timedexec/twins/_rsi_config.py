"""Settings and live status of the simulated KUKA RSI controller (:class:`RSITwinConfig`,
:class:`RSITwinStatus`, :data:`STOP_REASONS`); see :mod:`timedexec.twins._rsi`."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from timedexec.effects import EffectSet
from timedexec.errors import ConfigError, ProtocolError
from timedexec.robots import get_robot, get_robot_entry

__all__ = ["STOP_REASONS", "RSITwinConfig", "RSITwinStatus"]

#: Why the twin's RSI stopped; ``"running"`` while it has not.
STOP_REASONS = (
    "running",
    "stopped",  # stop() from the test / user
    "RSITimeout",  # the late counter reached timeout_packets (KSS29002)
    "correction_limit",  # a correction beyond max_correction_deg (AXISCORR limits)
    "software_limit",  # start pose + correction outside the joint limits
    "max_duration",  # the safety run-time limit elapsed
    "error",  # an exception inside the twin (see detail)
)


@dataclass(frozen=True, kw_only=True)
class RSITwinConfig:
    """Settings of the simulated KUKA controller (JSON round trip via to_dict/from_dict).

    Attributes
    ----------
    port : int
        The PC's RSI port (the driver's UDP server), default 49152.
    host : str
        The PC's address (loopback).
    robot : str
        A KUKA robot of the catalog (its entry's interface is ``kuka_rsi``), ``"kr5"``.
    period_s : float
        RSI cycle, s: 0.012 (``#IPO``) or 0.004 (``#IPO_FAST``).
    q0_rad : tuple of 6 float or None
        Pose at RSI start, rad (default: the spec's home pose).
    effects : tuple of dict or None
        :meth:`EffectSet.to_dict` of the simulated effects (default: the robot's default
        set, which for the KR 5 includes ``response_extra_cycle``).
    seed : int
        Seeds the simulated controller.
    sen_type : str
        SENTYPE expected in the answers' ``Type`` attribute.
    correction_tag : str
        Correction element read from the answers (``"AK"``).
    mode : {"absolute", "relative"}
        ``RSI_ON`` correction mode.
    ipoc_start : int
        IPOC of the first frame.
    ipoc_step : int or None
        IPOC increment per frame; ``None``: the period in ms (KR C4).
    timeout_packets : int
        Late cycles after which RSI stops with "RSITimeout" (KSS default 100).
    late_counter : {"cumulative", "consecutive"}
        Whether an answer in time resets the late counter (see the module docstring).
    max_correction_deg : tuple of 6 float
        Correction limits per axis, degrees (AXISCORR); beyond them RSI stops.
    legacy_empty_frame : bool
        Send RSI <= 2.3's empty ``<Rob>`` frame before the first real one.
    send_cartesian : bool
        Include ``RIst``/``RSol``: the flange pose of the actual / set-point axis angles
        from forward kinematics, in the spec's DH base frame (X, Y, Z and KUKA's A, B, C
        as Z-Y-X Euler angles).
    max_duration_s : float or None
        Optional safety limit: RSI stops ("max_duration") after this much controller time;
        ``None`` (default) runs until stopped.
    wait_for_pc : bool
        ``False`` (default, as KSS): late cycles count from the first frame, so a PC that is
        not up yet makes RSI stop with RSITimeout after ``timeout_packets`` cycles.
        ``True``: frames go out, but the late counter starts with the first answer in time
        (like an operator who starts the robot program once the PC is listening); for
        long-running servers such as ``timedexec serve``.
    first_frame_delay_s : float
        Time from start-up until the first frame leaves, s (default 0): a real controller
        takes seconds from the program start to ``RSI_ON`` (the public RSI simulator too);
        the PC must wait for it. The clock origin ``t0_host_s`` moves by as much.
    settle_s : float
        After RSI stops, the physics runs on (faster than real time) until the robot is
        still or this much controller time passed, so the ground truth is complete.
    truth_path : str or None
        JSON-lines ground-truth file written when the twin stops.
    controller_factory : str or None
        ``"module:function"`` building the simulated controller (called like
        ``ControllerSim(robot, effects=..., q0_rad=..., seed=..., period_s=...)``);
        default :class:`timedexec.sim.ControllerSim`.
    """

    port: int = 49152
    host: str = "127.0.0.1"
    robot: str = "kr5"
    period_s: float = 0.012
    q0_rad: tuple[float, ...] | None = None
    effects: tuple[dict[str, Any], ...] | None = None
    seed: int = 0
    sen_type: str = "ImFree"
    correction_tag: str = "AK"
    mode: Literal["absolute", "relative"] = "absolute"
    ipoc_start: int = 123645634560
    ipoc_step: int | None = None
    timeout_packets: int = 100
    late_counter: Literal["cumulative", "consecutive"] = "cumulative"
    max_correction_deg: tuple[float, ...] = (90.0,) * 6
    legacy_empty_frame: bool = False
    send_cartesian: bool = True
    max_duration_s: float | None = None
    wait_for_pc: bool = False
    first_frame_delay_s: float = 0.0
    settle_s: float = 1.0
    truth_path: str | None = None
    controller_factory: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.port, int) or not 1 <= self.port <= 65535:
            raise ConfigError(f"port={self.port!r} must be an integer in 1..65535")
        spec = get_robot(self.robot, period_s=self.period_s)  # validates robot and period
        if get_robot_entry(spec.name).twin.interface != "kuka_rsi":
            raise ConfigError(f"robot {self.robot!r} is not a KUKA robot; RSI needs one")
        if self.q0_rad is not None:
            q0 = tuple(float(x) for x in self.q0_rad)
            if len(q0) != 6:
                raise ConfigError(f"q0_rad has {len(q0)} values; expected 6")
            object.__setattr__(self, "q0_rad", q0)
        if self.effects is not None:
            object.__setattr__(self, "effects", tuple(dict(e) for e in self.effects))
            EffectSet.from_dict(self.effects)  # validates
        if self.mode not in ("absolute", "relative"):
            raise ConfigError(f"mode={self.mode!r} must be 'absolute' or 'relative'")
        if self.late_counter not in ("cumulative", "consecutive"):
            raise ConfigError(
                f"late_counter={self.late_counter!r} must be 'cumulative' or 'consecutive'"
            )
        if not isinstance(self.ipoc_start, int) or self.ipoc_start < 0:
            raise ConfigError(f"ipoc_start={self.ipoc_start!r} must be a non-negative integer")
        if self.ipoc_step is not None and (
            not isinstance(self.ipoc_step, int) or self.ipoc_step < 1
        ):
            raise ConfigError(f"ipoc_step={self.ipoc_step!r} must be a positive integer or None")
        if not isinstance(self.timeout_packets, int) or self.timeout_packets < 1:
            raise ConfigError(
                f"timeout_packets={self.timeout_packets!r} must be a positive integer "
                "(KSS default 100)"
            )
        limits = np.broadcast_to(np.asarray(self.max_correction_deg, dtype=float), (6,))
        if not np.all(np.isfinite(limits)) or np.any(limits <= 0):
            raise ConfigError(
                f"max_correction_deg={limits.tolist()} must be positive and finite per axis"
            )
        object.__setattr__(self, "max_correction_deg", tuple(float(x) for x in limits))
        for name in ("max_duration_s", "settle_s", "first_frame_delay_s"):
            value = getattr(self, name)
            if value is None and name == "max_duration_s":
                continue
            if not (isinstance(value, (int, float)) and value >= 0 and math.isfinite(value)):
                raise ConfigError(f"{name}={value!r} must be a finite number of s >= 0")
        try:
            from timedexec._rsi_xml import build_sen

            build_sen(0, np.zeros(6), sen_type=self.sen_type, correction_tag=self.correction_tag)
        except ProtocolError as exc:
            raise ConfigError(str(exc)) from None

    @property
    def ipoc_increment(self) -> int:
        """IPOC increment per frame."""
        if self.ipoc_step is not None:
            return self.ipoc_step
        return max(1, round(self.period_s * 1000.0))

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict that :meth:`from_dict` reads back."""
        out = dataclasses.asdict(self)
        for key in ("q0_rad", "max_correction_deg", "effects"):
            if out[key] is not None:
                out[key] = list(out[key])
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RSITwinConfig:
        """Inverse of :meth:`to_dict`.

        Raises
        ------
        ConfigError
            On unknown keys or invalid values.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"unknown RSITwinConfig keys {unknown}; expected {sorted(names)}")
        kwargs = dict(data)
        for key in ("q0_rad", "max_correction_deg", "effects"):
            if kwargs.get(key) is not None:
                kwargs[key] = tuple(kwargs[key])
        return cls(**kwargs)


@dataclass(frozen=True, kw_only=True)
class RSITwinStatus:
    """Live counters of the twin.

    Attributes
    ----------
    reason : str
        One of :data:`STOP_REASONS` (``"running"`` until RSI stops).
    detail : str
        Human-readable stop detail (after the twin finished; KSS-like message).
    frames_sent : int
        Frames the controller sent (including ones lost by fault injection).
    frames_dropped : int
        Frames lost by fault injection (pause, drop_frames).
    answers_in_time : int
        Answers that echoed the latest IPOC before the next frame left.
    stale_answers : int
        Answers not taken: echoing an IPOC older than the latest frame sent when they
        arrived (each counted late, as KSS does), or arriving after their period ran out.
    late_count : int
        The late counter as sent in ``<Delay D>``.
    late_total : int
        Late cycles in total (equals late_count with the cumulative counter).
    protocol_errors : int
        Datagrams that were not valid answers.
    late_sends : int
        Frames that left more than 1 ms after their scheduled send time (twin overload).
    max_send_lateness_s : float
        Largest lateness of a frame against its send time, s.
    peek_mismatches : int
        Frames whose early-read state differed from ``ControllerSim.cycle()``'s packet.
    cycles : int
        Controller cycles simulated.
    stop_time_s : float
        Controller time when RSI stopped, s (nan while running).
    finished : bool
        The twin's process has finished (ground truth is available).
    """

    reason: str
    detail: str = ""
    frames_sent: int = 0
    frames_dropped: int = 0
    answers_in_time: int = 0
    stale_answers: int = 0
    late_count: int = 0
    late_total: int = 0
    protocol_errors: int = 0
    late_sends: int = 0
    max_send_lateness_s: float = 0.0
    peek_mismatches: int = 0
    cycles: int = 0
    stop_time_s: float = math.nan
    finished: bool = False

    @property
    def running(self) -> bool:
        """True while RSI runs."""
        return self.reason == "running"
