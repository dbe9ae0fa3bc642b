"""A simulated KUKA controller speaking Ethernet RSI XML over UDP (the robot side of RSI).

The twin plays ``RSI_ON(#ABSOLUTE)`` (or ``#RELATIVE``) followed by ``RSI_MOVECORR()`` on a
simulated KR 5: every controller cycle (12 ms ``#IPO``; 4 ms ``#IPO_FAST``) it sends a
``<Rob TYPE="KUKA">`` frame from an ephemeral source port to the PC's RSI port, waits for the
``<Sen>`` answer echoing the frame's IPOC, and feeds the correction to the stepped simulated
controller (:class:`timedexec.sim.ControllerSim`). It behaves like KSS where it matters for
timing:

* **Clock.** Controller time ``t`` happens at host time ``t0_host_s + t``
  (:func:`time.monotonic`, shared by every process of the machine). Cycle ``k`` starts at
  ``k * period_s``.
* **State on the wire.** Frame ``k`` carries the state sampled at boundary ``k``
  (``AIPos`` = physical joint angles, ``ASPos`` = the controller's set-point, ``RIst`` = the
  flange pose from forward kinematics) and leaves at the simulated controller's send time
  (packing phase, plus one period with the ``response_extra_cycle`` effect), so the
  response delay, including KUKA's extra cycle, reaches the PC.
* **IPOC.** ``ipoc_start + k * ipoc_step``; the default step is the period in milliseconds
  (KR C4: 12 per 12 ms frame, 4 per 4 ms); ``ipoc_step=1`` mimics KR C2 / RSI 2.x.
* **Answers and the late counter.** An answer counts if it echoes the IPOC of the latest
  frame and arrives before the next frame leaves. Otherwise the cycle is late: the counter
  (sent as ``<Delay D>``) goes up and the correction of the previous cycle stays in force
  (absolute mode) or nothing is added (relative mode). When the counter reaches
  ``timeout_packets`` (KSS's ETHERNET object ``Timeout``, default 100) RSI stops with
  "RSITimeout" (KSS29002) and the robot brakes. KUKA's documentation does not say whether
  the counter restarts after an answer in time; ``late_counter="cumulative"`` (default)
  never resets it, ``"consecutive"`` resets it on every answer in time.
* **Corrections.** Absolute mode: the correction is the total offset from the pose at RSI
  start; relative mode: increments are summed. The commanded joint position (start pose +
  total correction) goes to the simulated controller as a :class:`~timedexec.sim.ServoJ`
  reached linearly over one period, i.e. a position reference that is updated once per
  cycle, which is what RSI does to the KSS set-point. Only a changed correction is
  submitted. A correction beyond ``max_correction_deg`` (the AXISCORR limits) stops RSI
  ("correction_limit"), and so does a commanded position outside the joint limits
  ("software_limit", the software limit switches).

  Why ServoJ and not SpeedJ from the increments: RSI corrections *are* positions; the
  simulated controller takes a ServoJ through the same register, intake at the next cycle
  boundary and command pipeline as any command, so the actuation delay is the simulator's
  own, and the position loop follows the reference without the drift a sequence of speed
  commands accumulates (each SpeedJ restarts the reference from the measured position, so
  lost time is never caught up).
* **Processes and threads.** The twin runs in its own process (``backend="process"``, the
  default; ``"thread"`` runs it in the caller's process for debugging, with less honest
  timing). Inside, one thread steps the physics once per period and another sends frames
  at their send times and receives answers, so a frame never waits for the physics of the
  cycle being computed (the state of boundary ``k`` is read before ``cycle()`` computes
  ``k -> k+1`` and checked against the packet ``cycle()`` returns). The process lowers its
  own GIL switch interval to 0.2 ms so that the I/O thread gets the interpreter promptly.
  How late frames left against their scheduled send time is recorded
  (:meth:`RSITwin.status`), so a run on an overloaded machine can be recognised.

Ground truth: :meth:`ControllerSim.truth_records` (one record per command, controller time)
goes to the JSON-lines file ``truth_path`` when the twin stops (a ``"meta"`` line with
``t0_monotonic_s``, then ``"command"`` lines, then an ``"rsi"`` line with the stop reason),
and is returned by :meth:`RSITwin.truth`; the frames sent and the answers received are
returned by :meth:`RSITwin.frames` and :meth:`RSITwin.answers`.

Fault injection for tests: :meth:`RSITwin.pause` (frames are lost for a while),
:meth:`RSITwin.drop_frames` and :meth:`RSITwin.drop_answers`.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import heapq
import importlib
import json
import math
import multiprocessing
import os
import select
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.effects import EffectSet
from timedexec.errors import ConfigError, ProtocolError
from timedexec.robots import forward_kinematics, get_robot

__all__ = [
    "STOP_REASONS",
    "RSITwin",
    "RSITwinConfig",
    "RSITwinStatus",
    "free_udp_port",
    "read_rsi_truth",
]

FloatArray = NDArray[np.float64]

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

_LATE_SEND_S = 0.001  # a frame leaving more than this after its send time counts as late
_SWITCH_INTERVAL_S = 0.0002
_T0_LEAD_S = 0.02  # controller time 0 lies this far after the twin is ready

# Shared status slots (a multiprocessing double array).
_S_FRAMES, _S_DROPPED, _S_ANSWERS, _S_STALE, _S_LATE, _S_PROTO = 0, 1, 2, 3, 4, 5
_S_REASON, _S_LATE_SENDS, _S_MAX_LATENESS, _S_CYCLES, _S_T0, _S_PORT = 6, 7, 8, 9, 10, 11
_S_STOP_TIME, _S_PEEK_MISMATCH, _S_LATE_TOTAL, _S_DONE = 12, 13, 14, 15
_N_SLOTS = 16


# --------------------------------------------------------------------------- configuration


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
        Robot spec name (``"kr5"``).
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
    settle_s: float = 1.0
    truth_path: str | None = None
    controller_factory: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.port, int) or not 1 <= self.port <= 65535:
            raise ConfigError(f"port={self.port!r} must be an integer in 1..65535")
        spec = get_robot(self.robot, period_s=self.period_s)  # validates robot and period
        if spec.vendor != "kuka":
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
        for name in ("max_duration_s", "settle_s"):
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
        Answers with an old IPOC, or arriving after the next frame (ignored).
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


def read_rsi_truth(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a twin's ground-truth file.

    Returns
    -------
    dict
        ``meta`` (robot, period_s, t0_monotonic_s, ipoc_start, ipoc_step, start pose),
        ``commands`` (list of :meth:`ControllerSim.truth_records` rows, controller time,
        s) and ``rsi`` (stop reason, detail and counters).
    """
    out: dict[str, Any] = {"meta": {}, "commands": [], "rsi": {}}
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.strip()
            if not line:
                continue
            record = json.loads(line)
            event = record.pop("event", "")
            if event == "meta":
                out["meta"] = record
            elif event == "command":
                out["commands"].append(record)
            elif event == "rsi":
                out["rsi"] = record
    return out


# --------------------------------------------------------------------------- inside the twin


@dataclass(order=True)
class _Frame:
    send_time_s: float
    cycle: int
    ipoc: int = dataclasses.field(compare=False)
    sample_time_s: float = dataclasses.field(compare=False)
    q_rad: FloatArray = dataclasses.field(compare=False)
    q_set_rad: FloatArray = dataclasses.field(compare=False)
    cart: FloatArray | None = dataclasses.field(compare=False)
    cart_set: FloatArray | None = dataclasses.field(compare=False)
    ready_s: float = dataclasses.field(compare=False, default=math.nan)


def _flange_pose(spec: Any, q: FloatArray) -> FloatArray:
    """Flange X, Y, Z (m) and KUKA A, B, C (ZYX Euler, rad) in the DH base frame."""
    t = forward_kinematics(spec, q)[-1]
    r = t[:3, :3]
    a = math.atan2(r[1, 0], r[0, 0])
    b = math.atan2(-r[2, 0], math.hypot(r[0, 0], r[1, 0]))
    c = math.atan2(r[2, 1], r[2, 2])
    return np.array([t[0, 3], t[1, 3], t[2, 3], a, b, c])


def _default_factory(
    robot: str, *, effects: EffectSet | None, q0_rad: Any, seed: int, period_s: float
) -> Any:
    from timedexec.sim import ControllerSim

    # 4 kHz physics: a real-time twin must finish each cycle well inside it (8 kHz cost
    # 4-8 ms of a 12 ms cycle on this class of machine); the truth is unchanged in kind.
    return ControllerSim(
        robot, effects=effects, q0_rad=q0_rad, seed=seed, period_s=period_s, physics_rate_hz=4000.0
    )


def _resolve_factory(name: str | None) -> Callable[..., Any]:
    if name is None:
        return _default_factory
    module, _, attr = name.partition(":")
    try:
        obj: Any = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(
            f"controller_factory={name!r} cannot be imported ({exc}); use 'module:function'"
        ) from exc
    if not callable(obj):
        raise ConfigError(f"controller_factory={name!r} is not callable")
    return obj  # type: ignore[no-any-return]


class _Engine:
    """The twin itself: physics thread + I/O loop (runs in the twin's process or thread)."""

    def __init__(self, cfg: RSITwinConfig, shared: Any, conn: Any) -> None:
        from timedexec._rsi_xml import build_rob, parse_sen

        self._build_rob = build_rob
        self._parse_sen = parse_sen
        self.cfg = cfg
        self.shared = shared
        self.conn = conn
        self.spec = get_robot(cfg.robot, period_s=cfg.period_s)
        effects = EffectSet.from_dict(cfg.effects) if cfg.effects is not None else None
        factory = _resolve_factory(cfg.controller_factory)
        self.sim = factory(
            cfg.robot, effects=effects, q0_rad=cfg.q0_rad, seed=cfg.seed, period_s=cfg.period_s
        )
        self.period_s = float(self.sim.period_s)
        self.q_start: FloatArray = np.asarray(self.sim.q_rad, dtype=float).copy()
        self.q_min = np.asarray(self.spec.q_min_rad, dtype=float)
        self.q_max = np.asarray(self.spec.q_max_rad, dtype=float)
        self.max_corr_rad = np.radians(np.asarray(cfg.max_correction_deg, dtype=float))
        self.ipoc_step = cfg.ipoc_increment
        extra = None
        effects_obj = getattr(self.sim, "effects", None)
        if effects_obj is not None and hasattr(effects_obj, "get"):
            extra = effects_obj.get("response_extra_cycle")
        self.extra_s = self.period_s * float(getattr(extra, "cycles", 0)) if extra else 0.0

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((cfg.host, 0))  # the robot's ephemeral source port
        self.sock.setblocking(False)
        self.dest = (cfg.host, cfg.port)
        self.wake_r, self.wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self.wake_w.setblocking(False)

        self.lock = threading.Lock()
        self.stop_lock = threading.Lock()
        self.heap: list[_Frame] = []
        self.commands: collections.deque[tuple[float, FloatArray]] = collections.deque()
        self.rsi_stopped = threading.Event()
        self.physics_done = threading.Event()
        self.reason = "running"
        self.detail = ""
        self.stop_time_s = math.nan
        self.t0 = math.nan
        # I/O state
        # ipoc -> (answer deadline, host time the frame left, its scheduled send time)
        self.pending: collections.OrderedDict[int, tuple[float, float, float]] = (
            collections.OrderedDict()
        )
        self.last_applied_ipoc = -1
        self.pc_seen = not cfg.wait_for_pc
        self.late = 0
        self.late_total = 0
        self.corr_total = np.zeros(6)
        self.pause_until = -math.inf
        self.drop_out = 0
        self.drop_in = 0
        self.frame_log: list[dict[str, Any]] = []
        self.answer_log: list[dict[str, Any]] = []
        self.physics_error: BaseException | None = None

    # ---------------------------------------------------------------- helpers
    def _set(self, slot: int, value: float) -> None:
        self.shared[slot] = value

    def _inc(self, slot: int, by: float = 1.0) -> None:
        self.shared[slot] = self.shared[slot] + by

    def _now_c(self) -> float:
        return time.monotonic() - self.t0

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            self.wake_w.send(b"x")

    def stop_rsi(self, reason: str, detail: str) -> None:
        with self.stop_lock:
            if self.reason != "running":
                return
            self.reason = reason
            self.detail = detail
            self.stop_time_s = self._now_c()
            self._set(_S_STOP_TIME, self.stop_time_s)
            self._set(_S_REASON, float(STOP_REASONS.index(reason)))
        self.rsi_stopped.set()
        self._wake()

    # ---------------------------------------------------------------- peek
    def _peek(self) -> _Frame:
        sim = self.sim
        peek = getattr(sim, "peek_packet", None)
        if callable(peek):
            p = peek()
            return self._frame_from_packet(p)
        t = float(sim.time_s)
        k = int(getattr(sim, "cycle_index", round(t / self.period_s)))
        q = np.asarray(sim.q_rad, dtype=float)
        q_set = np.array(getattr(sim, "_ref_q", q), dtype=float)
        send = t + float(sim.packing_phase_s(t)) + self.extra_s
        return self._make_frame(k, t, send, q, q_set)

    def _frame_from_packet(self, p: Any) -> _Frame:
        return self._make_frame(
            int(p.cycle),
            float(p.sample_time_s),
            float(p.send_time_s),
            np.asarray(p.q_rad, dtype=float),
            np.asarray(p.q_target_rad, dtype=float),
        )

    def _make_frame(
        self, k: int, t: float, send: float, q: FloatArray, q_set: FloatArray
    ) -> _Frame:
        send_cart = self.cfg.send_cartesian
        cart = _flange_pose(self.spec, q) if send_cart else None
        cart_set = _flange_pose(self.spec, q_set) if send_cart else None
        return _Frame(
            send_time_s=send,
            cycle=k,
            ipoc=self.cfg.ipoc_start + k * self.ipoc_step,
            sample_time_s=t,
            q_rad=q.copy(),
            q_set_rad=q_set.copy(),
            cart=cart,
            cart_set=cart_set,
        )

    # ---------------------------------------------------------------- physics thread
    def physics_loop(self) -> None:
        try:
            self._physics()
        except BaseException as exc:  # surfaced as reason "error"
            self.physics_error = exc
            self.stop_rsi("error", f"physics thread failed: {exc!r}")
        finally:
            self.physics_done.set()
            self._wake()

    def _physics(self) -> None:
        from timedexec.sim import ServoJ, StopJ

        sim = self.sim
        period = self.period_s
        stop_decel = float(max(self.spec.qdd_max_rad_s2))
        while not self.rsi_stopped.is_set():
            boundary = float(sim.time_s)
            if self.cfg.max_duration_s is not None and boundary > self.cfg.max_duration_s:
                self.stop_rsi("max_duration", f"ran {self.cfg.max_duration_s} s")
                break
            frame = self._peek()
            frame.ready_s = self._now_c()
            with self.lock:
                heapq.heappush(self.heap, frame)
            self._wake()
            # Wait for the boundary (the peeked frame may be sent meanwhile).
            while True:
                remaining = self.t0 + boundary - time.monotonic()
                if remaining <= 0 or self.rsi_stopped.is_set():
                    break
                time.sleep(min(remaining, 0.002))
            if self.rsi_stopped.is_set():
                break
            self._wait_for_inputs(boundary)
            # Intake: the answers that arrived before this boundary, in arrival order. Later
            # ones wait for the next boundary: submitting them now would supersede a command
            # the register holds at this boundary (ControllerSim keeps only the last one).
            while self.commands and self.commands[0][0] <= boundary + 1e-12:
                arrival_s, q_cmd = self.commands.popleft()
                sim.submit(ServoJ(tuple(q_cmd), time_s=period), arrival_s=arrival_s)
            result = sim.cycle()
            packet = result.packet
            if int(packet.cycle) != frame.cycle or not (
                np.array_equal(np.asarray(packet.q_rad), frame.q_rad)
                and abs(float(packet.send_time_s) - frame.send_time_s) < 1e-9
            ):
                self._inc(_S_PEEK_MISMATCH)
            self._inc(_S_CYCLES)
        # RSI stopped: the robot brakes; run on (faster than real time) for the truth.
        stop_at = float(sim.time_s)
        if not math.isnan(self.stop_time_s):
            stop_at = max(stop_at, self.stop_time_s)
        with contextlib.suppress(Exception):
            sim.submit(StopJ(stop_decel), arrival_s=stop_at)
        end = float(sim.time_s) + self.cfg.settle_s
        while float(sim.time_s) < end:
            sim.cycle()
            self._inc(_S_CYCLES)
            if sim.is_steady():
                break

    def _wait_for_inputs(self, boundary: float) -> None:
        """Wait until every answer that could still reach the register before ``boundary``
        (controller time) is in.

        An answer's controller time of arrival is its frame's scheduled departure plus the
        PC's turnaround. A frame not answered yet will arrive later than
        ``send + (now - departure)``; once that passes the boundary, or the frame is
        answered or expired, it cannot concern this boundary. While the twin keeps real
        time this holds the moment the boundary is reached; if it has fallen behind, it
        keeps the command timing in controller time exact instead of racing ahead.
        """
        while not self.rsi_stopped.is_set():
            now = time.monotonic()
            wait = 0.0
            with self.lock:
                if self.heap and self.heap[0].send_time_s < boundary:
                    wait = 0.0002  # a frame due before the boundary is about to leave
                for _deadline, departed, send in self.pending.values():
                    if send >= boundary:
                        break
                    wait = max(wait, (boundary - send) - (now - departed))
            if wait <= 0.0:
                return
            time.sleep(min(wait, 0.002))

    # ---------------------------------------------------------------- I/O loop
    def io_loop(self) -> None:
        sock = self.sock
        if self.cfg.legacy_empty_frame:
            with contextlib.suppress(OSError):
                sock.sendto(self._build_rob(None), self.dest)
        while True:
            self._poll_control()
            if self.reason != "running":
                break
            self._expire(time.monotonic())
            if self.reason != "running":
                break
            now = time.monotonic()
            due: list[_Frame] = []
            with self.lock:
                while self.heap and self.t0 + self.heap[0].send_time_s <= now:
                    frame = heapq.heappop(self.heap)
                    due.append(frame)
                    # In flight from now on (the physics waits for its answer, see
                    # _wait_for_inputs); updated with the real departure in _send.
                    self.pending[frame.ipoc] = (math.inf, now, frame.send_time_s)
                next_send = self.t0 + self.heap[0].send_time_s if self.heap else now + 0.005
            for frame in due:
                self._send(frame)
            if self.reason != "running":
                break
            next_event = min(next_send, time.monotonic() + 0.005)
            if self.pending:
                next_event = min(next_event, next(iter(self.pending.values()))[0])
            timeout = max(0.0, next_event - time.monotonic())
            try:
                readable, _, _ = select.select([sock, self.wake_r], [], [], timeout)
            except (OSError, ValueError):
                break
            if self.wake_r in readable:
                with contextlib.suppress(OSError):
                    while self.wake_r.recv(4096):
                        pass
            if sock in readable:
                self._receive()

    def _poll_control(self) -> None:
        conn = self.conn
        try:
            while conn.poll():
                msg = conn.recv()
                kind = msg[0]
                if kind == "stop":
                    self.stop_rsi("stopped", "stopped by RSITwin.stop()")
                elif kind == "pause":
                    self.pause_until = time.monotonic() + float(msg[1])
                elif kind == "drop_frames":
                    self.drop_out += int(msg[1])
                elif kind == "drop_answers":
                    self.drop_in += int(msg[1])
        except (EOFError, OSError):
            self.stop_rsi("stopped", "the parent went away")

    def _expire(self, now: float) -> None:
        """Count every frame whose answer did not arrive within one period as late."""
        pending = self.pending
        while pending:
            ipoc, (deadline, _, _) = next(iter(pending.items()))
            if deadline > now:
                return
            with self.lock:
                del pending[ipoc]
            if not self.pc_seen:
                continue  # wait_for_pc: the robot program has not "started" yet
            self.late += 1
            self.late_total += 1
            self._set(_S_LATE, self.late)
            self._set(_S_LATE_TOTAL, self.late_total)
            if self.late >= self.cfg.timeout_packets:
                self.stop_rsi(
                    "RSITimeout",
                    f"KSS29002 Signal flow (running): Object ETHERNET1 returns error "
                    f"RSITimeout ({self.late} late cycles, Timeout={self.cfg.timeout_packets})",
                )
                return

    def _send(self, frame: _Frame) -> None:
        if self.reason != "running":
            return
        data = self._build_rob(
            frame.ipoc,
            frame.q_rad,
            aspos_rad=frame.q_set_rad,
            rist=frame.cart,
            rsol=frame.cart_set,
            delay=self.late,
        )
        now = time.monotonic()
        paused = now < self.pause_until
        drop = paused or self.drop_out > 0
        if self.drop_out > 0 and not paused:
            self.drop_out -= 1
        sent_s: float | None = None
        if drop:
            self._inc(_S_DROPPED)
        else:
            # OSError: nobody listening (ICMP); the answer will simply be missing.
            with contextlib.suppress(OSError):
                self.sock.sendto(data, self.dest)
            now = time.monotonic()
            sent_s = now - self.t0
            lateness = sent_s - frame.send_time_s
            if lateness > _LATE_SEND_S:
                self._inc(_S_LATE_SENDS)
            if lateness > self.shared[_S_MAX_LATENESS]:
                self._set(_S_MAX_LATENESS, lateness)
        self._inc(_S_FRAMES)
        # The PC has one period from the frame's departure to answer it. With the twin on
        # time this is the departure of the next frame, as on KSS; should the twin itself
        # fall behind real time (an overloaded machine) and send frames in a burst, the PC
        # is still judged by its own latency, not by the twin's hiccup.
        with self.lock:
            self.pending[frame.ipoc] = (now + self.period_s, now, frame.send_time_s)
        self.frame_log.append(
            {
                "cycle": frame.cycle,
                "ipoc": frame.ipoc,
                "sample_time_s": frame.sample_time_s,
                "send_time_s": frame.send_time_s,
                "sent_s": sent_s,
                "ready_s": frame.ready_s,
                "q_rad": frame.q_rad.tolist(),
                "q_set_rad": frame.q_set_rad.tolist(),
                "late_count": self.late,
            }
        )

    def _receive(self) -> None:
        while True:
            try:
                data, _addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # ICMP port unreachable from an earlier frame: no server yet
            now = time.monotonic()
            try:
                sen = self._parse_sen(
                    data, correction_tag=self.cfg.correction_tag, expected_type=self.cfg.sen_type
                )
            except ProtocolError:
                self._inc(_S_PROTO)
                continue
            if self.drop_in > 0:
                self.drop_in -= 1
                continue
            entry = self.pending.get(sen.ipoc)
            in_time = entry is not None and now <= entry[0]
            # Controller time of arrival: the frame's scheduled departure plus the PC's real
            # turnaround. Equal to the host clock while the twin keeps real time; if it lags
            # (overloaded machine), its own lag is not passed on to the robot.
            arrival_s = entry[2] + (now - entry[1]) if entry is not None else now - self.t0
            self.answer_log.append(
                {
                    "ipoc": sen.ipoc,
                    "arrival_s": arrival_s,
                    "arrival_host_s": now,
                    "in_time": in_time,
                    "correction_rad": sen.correction_rad.tolist(),
                }
            )
            if not in_time:
                self._inc(_S_STALE)
                continue
            self._inc(_S_ANSWERS)
            self.pc_seen = True
            if self.cfg.late_counter == "consecutive" and self.late:
                self.late = 0
                self._set(_S_LATE, 0)
            with self.lock:  # the physics sees the frame answered and its command at once
                del self.pending[sen.ipoc]
                if sen.ipoc > self.last_applied_ipoc:  # else superseded by a newer answer
                    self.last_applied_ipoc = sen.ipoc
                    self._apply(sen.correction_rad, arrival_s)
            if self.reason != "running":
                return

    def _apply(self, correction: FloatArray, arrival_s: float) -> None:
        total = correction if self.cfg.mode == "absolute" else self.corr_total + correction
        over = np.abs(total) > self.max_corr_rad * (1 + 1e-9)
        if np.any(over):
            j = int(np.argmax(over))
            self.stop_rsi(
                "correction_limit",
                f"correction A{j + 1} = {math.degrees(total[j]):.4f} deg exceeds the AXISCORR "
                f"limit of ±{math.degrees(self.max_corr_rad[j]):.4f} deg; RSI stopped",
            )
            return
        q_cmd = self.q_start + total
        outside = (q_cmd < self.q_min) | (q_cmd > self.q_max)
        if np.any(outside):
            j = int(np.argmax(outside))
            self.stop_rsi(
                "software_limit",
                f"A{j + 1} commanded to {math.degrees(q_cmd[j]):.4f} deg, outside the software "
                f"limits [{math.degrees(self.q_min[j]):.4f}, {math.degrees(self.q_max[j]):.4f}]"
                " deg; RSI stopped",
            )
            return
        if np.array_equal(total, self.corr_total):
            return  # unchanged (or still zero at the start pose): the reference holds
        self.corr_total = np.array(total, dtype=float)
        self.commands.append((arrival_s, q_cmd))

    # ---------------------------------------------------------------- run
    def run(self) -> None:
        # Cycle 0 is computed before the clock starts: no answer can reach boundary 0 (the
        # first frame leaves after it), so its physics does not depend on when it runs,
        # and the first-call costs (caches, imports) stay out of real time.
        first = self._peek()
        self.sim.cycle()
        self._inc(_S_CYCLES)
        self.t0 = time.monotonic() + _T0_LEAD_S
        first.ready_s = -_T0_LEAD_S
        self.heap.append(first)
        self._set(_S_T0, self.t0)
        self._set(_S_PORT, float(self.sock.getsockname()[1]))
        self.conn.send(
            (
                "ready",
                {
                    "t0_host_s": self.t0,
                    "source_port": int(self.sock.getsockname()[1]),
                    "q_start_rad": self.q_start.tolist(),
                    "period_s": self.period_s,
                },
            )
        )
        physics = threading.Thread(target=self.physics_loop, name="rsi-twin-physics", daemon=True)
        physics.start()
        try:
            self.io_loop()
        except BaseException as exc:
            self.stop_rsi("error", f"I/O loop failed: {exc!r}")
            raise
        finally:
            self.rsi_stopped.set()
            physics.join(timeout=self.cfg.settle_s * 20 + 10.0)
            with contextlib.suppress(OSError):
                self.sock.close()
            for s in (self.wake_r, self.wake_w):
                with contextlib.suppress(OSError):
                    s.close()

    def results(self) -> dict[str, Any]:
        truth = list(self.sim.truth_records()) if hasattr(self.sim, "truth_records") else []
        meta = {
            "robot": self.cfg.robot,
            "period_s": self.period_s,
            "t0_monotonic_s": self.t0,
            "ipoc_start": self.cfg.ipoc_start,
            "ipoc_step": self.ipoc_step,
            "q_start_rad": self.q_start.tolist(),
            "mode": self.cfg.mode,
            "pid": os.getpid(),
        }
        rsi = {
            "reason": self.reason,
            "detail": self.detail,
            "stop_time_s": None if math.isnan(self.stop_time_s) else self.stop_time_s,
            "late_count": self.late,
            "late_total": self.late_total,
        }
        return {
            "meta": meta,
            "truth": truth,
            "rsi": rsi,
            "frames": self.frame_log,
            "answers": self.answer_log,
        }


def _write_truth(path: str, results: Mapping[str, Any]) -> None:
    target = Path(path)
    tmp = target.with_name(target.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(json.dumps({"event": "meta", **results["meta"]}, sort_keys=True) + "\n")
        for record in results["truth"]:
            fh.write(json.dumps({"event": "command", **record}, sort_keys=True) + "\n")
        fh.write(json.dumps({"event": "rsi", **results["rsi"]}, sort_keys=True) + "\n")
    os.replace(tmp, target)


def _twin_main(cfg_dict: dict[str, Any], conn: Any, shared: Any, in_process: bool) -> None:
    """Entry point of the twin (process target, or thread target for backend="thread")."""
    if in_process:
        sys.setswitchinterval(_SWITCH_INTERVAL_S)
    engine: _Engine | None = None
    results: dict[str, Any] = {}
    try:
        cfg = RSITwinConfig.from_dict(cfg_dict)
        engine = _Engine(cfg, shared, conn)
        engine.run()
        results = engine.results()
        if cfg.truth_path:
            _write_truth(cfg.truth_path, results)
    except BaseException as exc:
        shared[_S_REASON] = float(STOP_REASONS.index("error"))
        detail = f"{type(exc).__name__}: {exc}"
        if engine is not None:
            with contextlib.suppress(Exception):
                results = engine.results()
        results.setdefault("rsi", {})
        results["rsi"] = {**results["rsi"], "reason": "error", "detail": detail}
    finally:
        shared[_S_DONE] = 1.0
        with contextlib.suppress(Exception):
            conn.send(("done", results))


# --------------------------------------------------------------------------- the handle


class RSITwin:
    """Simulated KUKA controller sending RSI frames to a PC port (context manager).

    Parameters
    ----------
    port : int, optional
        The PC's RSI port (where :class:`~timedexec.drivers._rsi.KukaRSIDriver` listens).
    backend : {"process", "thread"}, optional
        Run the twin in its own process (default; honest timing) or in a thread.
    effects : EffectSet, optional
        Simulated effects (default: the robot's default set).
    **settings
        Any other :class:`RSITwinConfig` field (``period_s``, ``q0_rad``, ``mode``,
        ``timeout_packets``, ``max_correction_deg``, ``truth_path`` ...).

    Examples
    --------
    >>> with KukaRSIDriver(0) as drv, RSITwin(drv.port, truth_path="truth.jsonl") as twin:
    ...     state = drv.read_state(timeout_s=1.0)          # doctest: +SKIP
    ...     drv.speedj([0, 0.3, 0, 0, 0, 0], 2.0, 0.5)      # doctest: +SKIP
    """

    def __init__(
        self,
        port: int = 49152,
        *,
        backend: Literal["process", "thread"] = "process",
        effects: EffectSet | None = None,
        q0_rad: ArrayLike | None = None,
        max_correction_deg: float | ArrayLike = 90.0,
        **settings: Any,
    ) -> None:
        if backend not in ("process", "thread"):
            raise ConfigError(f"backend={backend!r} must be 'process' or 'thread'")
        limits = np.broadcast_to(np.asarray(max_correction_deg, dtype=float), (6,))
        cfg_kwargs: dict[str, Any] = dict(settings)
        if effects is not None:
            cfg_kwargs["effects"] = tuple(effects.to_dict())
        if q0_rad is not None:
            cfg_kwargs["q0_rad"] = tuple(float(x) for x in np.asarray(q0_rad, dtype=float))
        if "truth_path" in cfg_kwargs and cfg_kwargs["truth_path"] is not None:
            cfg_kwargs["truth_path"] = os.fspath(cfg_kwargs["truth_path"])
        try:
            self.config = RSITwinConfig(
                port=port, max_correction_deg=tuple(limits.tolist()), **cfg_kwargs
            )
        except TypeError as exc:
            allowed = sorted(f.name for f in dataclasses.fields(RSITwinConfig))
            raise ConfigError(f"RSITwin: {exc}; settings are {allowed}") from None
        self.backend = backend
        self._ctx = multiprocessing.get_context("spawn")
        self._shared: Any = None
        self._conn: Any = None
        self._worker: Any = None
        self._ready: dict[str, Any] = {}
        self._results: dict[str, Any] | None = None

    # ---------------------------------------------------------------- lifecycle
    def start(self, timeout_s: float = 30.0) -> Self:
        """Start the twin and wait until its first frame is scheduled.

        Raises
        ------
        ConfigError
            If the twin could not start (the message carries its error).
        """
        if self._worker is not None:
            return self
        self._shared = self._ctx.Array("d", _N_SLOTS, lock=False)
        self._shared[_S_MAX_LATENESS] = -math.inf
        self._shared[_S_STOP_TIME] = math.nan
        parent, child = self._ctx.Pipe(duplex=True)
        self._conn = parent
        args = (self.config.to_dict(), child, self._shared, self.backend == "process")
        if self.backend == "process":
            self._worker = self._ctx.Process(
                target=_twin_main, args=args, name="rsi-twin", daemon=True
            )
        else:
            self._worker = threading.Thread(
                target=_twin_main, args=args, name="rsi-twin", daemon=True
            )
        self._worker.start()
        deadline = time.monotonic() + timeout_s
        while not parent.poll(0.05):
            if not self._worker.is_alive() or time.monotonic() > deadline:
                alive = self._worker.is_alive()
                self._kill()
                self._worker = None
                raise ConfigError(
                    f"RSI twin did not start within {timeout_s} s"
                    if alive
                    else "RSI twin process exited during start-up (with the spawn start "
                    "method the calling script needs an `if __name__ == '__main__':` guard)"
                )
        kind, payload = parent.recv()
        if kind != "ready":
            self._results = payload
            self._join()
            detail = (payload or {}).get("rsi", {}).get("detail", "unknown error")
            raise ConfigError(f"RSI twin failed to start: {detail}")
        self._ready = payload
        return self

    def stop(self, timeout_s: float = 30.0) -> RSITwinStatus:
        """Stop RSI (if still running), let the physics settle, collect the ground truth."""
        if self._worker is None:
            return self.status()
        if self._results is None:
            with contextlib.suppress(OSError, BrokenPipeError):
                self._conn.send(("stop",))
            self._collect(timeout_s)
        self._join()
        return self.status()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def _collect(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while self._results is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._conn.poll(remaining):
                self._kill()
                self._results = {"rsi": {"reason": "error", "detail": "twin did not finish"}}
                return
            try:
                kind, payload = self._conn.recv()
            except EOFError:
                self._results = {"rsi": {"reason": "error", "detail": "twin exited"}}
                return
            if kind == "done":
                self._results = payload

    def _join(self) -> None:
        if self._worker is not None:
            self._worker.join(timeout=10.0)

    def _kill(self) -> None:
        worker = self._worker
        if isinstance(worker, multiprocessing.process.BaseProcess) and worker.is_alive():
            worker.terminate()
            worker.join(timeout=5.0)

    # ---------------------------------------------------------------- fault injection
    def _control(self, *msg: Any) -> None:
        if self._conn is None:
            raise ConfigError("the twin is not running; start() it first")
        self._conn.send(msg)

    def pause(self, duration_s: float) -> None:
        """Lose every frame for ``duration_s`` (s), as a pulled cable would: the robot
        keeps running its cycles and counts them late."""
        self._control("pause", float(duration_s))

    def drop_frames(self, n: int) -> None:
        """Lose the next ``n`` frames on their way to the PC."""
        self._control("drop_frames", int(n))

    def drop_answers(self, n: int) -> None:
        """Lose the next ``n`` answers on their way to the robot."""
        self._control("drop_answers", int(n))

    # ---------------------------------------------------------------- observation
    @property
    def t0_host_s(self) -> float:
        """``time.monotonic()`` of controller time 0 (host time = t0_host_s + controller)."""
        return float(self._ready.get("t0_host_s", math.nan))

    @property
    def source_port(self) -> int:
        """The robot's ephemeral UDP source port."""
        return int(self._ready.get("source_port", 0))

    @property
    def start_pose_rad(self) -> FloatArray:
        """Pose at RSI start, rad, shape (6,)."""
        return np.asarray(self._ready.get("q_start_rad", [math.nan] * 6), dtype=float)

    @property
    def period_s(self) -> float:
        """RSI cycle period, s."""
        return float(self._ready.get("period_s", self.config.period_s))

    def controller_time_of_ipoc(self, ipoc: int) -> float:
        """Controller time (s) of the cycle boundary a frame's IPOC belongs to."""
        return (int(ipoc) - self.config.ipoc_start) / self.config.ipoc_increment * self.period_s

    def status(self) -> RSITwinStatus:
        """Live counters and, once RSI stopped, the reason."""
        sh = self._shared
        if sh is None:
            return RSITwinStatus(reason="running")
        reason = STOP_REASONS[int(sh[_S_REASON])]
        detail = ""
        if self._results is not None:
            rsi = self._results.get("rsi", {})
            reason = rsi.get("reason", reason)
            detail = rsi.get("detail", "")
        return RSITwinStatus(
            reason=reason,
            detail=detail,
            frames_sent=int(sh[_S_FRAMES]),
            frames_dropped=int(sh[_S_DROPPED]),
            answers_in_time=int(sh[_S_ANSWERS]),
            stale_answers=int(sh[_S_STALE]),
            late_count=int(sh[_S_LATE]),
            late_total=int(sh[_S_LATE_TOTAL]),
            protocol_errors=int(sh[_S_PROTO]),
            late_sends=int(sh[_S_LATE_SENDS]),
            max_send_lateness_s=max(0.0, float(sh[_S_MAX_LATENESS])),
            peek_mismatches=int(sh[_S_PEEK_MISMATCH]),
            cycles=int(sh[_S_CYCLES]),
            stop_time_s=float(sh[_S_STOP_TIME]),
            finished=bool(sh[_S_DONE]),
        )

    def wait_stopped(self, timeout_s: float) -> RSITwinStatus:
        """Wait until RSI stops by itself (RSITimeout, limits); returns the status.

        Raises
        ------
        TimeoutError
            If RSI still runs after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while self.status().running:
            if time.monotonic() > deadline:
                raise TimeoutError(f"RSI twin still running after {timeout_s} s")
            time.sleep(0.005)
        return self.status()

    def _finished_results(self, timeout_s: float = 30.0) -> dict[str, Any]:
        if self._results is None:
            if self._worker is None:
                raise ConfigError("the twin never ran; use it as a context manager")
            if self.status().running:
                raise ConfigError(
                    "ground truth is complete only once RSI stopped; call stop() (or wait "
                    "for RSITimeout) first"
                )
            self._collect(timeout_s)
        return self._results or {}

    def truth(self) -> list[dict[str, Any]]:
        """Ground truth per command (``ControllerSim.truth_records()``, controller time)."""
        return list(self._finished_results().get("truth", []))

    def frames(self) -> list[dict[str, Any]]:
        """Every frame the controller sent: cycle, ipoc, sample_time_s, send_time_s
        (scheduled), sent_s (actual, None if lost), q_rad, q_set_rad, late_count."""
        return list(self._finished_results().get("frames", []))

    def answers(self) -> list[dict[str, Any]]:
        """Every valid answer received: ipoc, arrival_s, in_time, correction_rad."""
        return list(self._finished_results().get("answers", []))


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port on ``host`` that is free right now (for a twin or a driver to bind)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])
