"""Inside the simulated KUKA RSI controller: the physics thread, the UDP I/O loop and the
entry point of the twin's process (or thread). See :mod:`timedexec.twins._rsi` for what it
emulates; :class:`~timedexec.twins.RSITwin` is the handle that starts it.

The engine talks to its handle through a pipe (``ready``, control messages, ``done`` with
the results) and a shared array of live counters (the ``_S_*`` slots).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import heapq
import importlib
import json
import math
import os
import select
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._types import FloatArray
from timedexec.effects import EffectSet
from timedexec.errors import ConfigError, ProtocolError
from timedexec.robots import forward_kinematics, get_robot
from timedexec.twins._rsi_config import STOP_REASONS, RSITwinConfig

_LATE_SEND_S = 0.001  # a frame leaving more than this after its send time counts as late
#: The physics of a cycle waits for frames due up to this long after its boundary to leave
#: first, s. Computing a cycle takes the twin's interpreter for 2-5 ms right after the
#: boundary; where the packing phase was small (a frame due 0.5-3 ms after it) the I/O
#: thread then sent 11 % of the frames 1-7 ms late on a loaded machine (a real controller
#: sends on time). The physics' result does not change: its intake is by arrival time.
_SEND_GUARD_S = 0.003
_SWITCH_INTERVAL_S = 0.0002
_T0_LEAD_S = 0.02  # controller time 0 lies this far after the twin is ready
#: Below this joint speed (max over the joints, mean over a cycle) the arm is at rest, rad/s
#: (1.1 deg/s): above the stick-slip hunting of a held position loop (up to 0.011 rad/s in
#: short bursts, a fraction of a mrad), an order of magnitude under commanded motion.
_REST_SPEED_RAD_S = 0.02

# Shared status slots (a multiprocessing double array).
_S_FRAMES, _S_DROPPED, _S_ANSWERS, _S_STALE, _S_LATE, _S_PROTO = 0, 1, 2, 3, 4, 5
_S_REASON, _S_LATE_SENDS, _S_MAX_LATENESS, _S_CYCLES, _S_T0, _S_PORT = 6, 7, 8, 9, 10, 11
_S_STOP_TIME, _S_PEEK_MISMATCH, _S_LATE_TOTAL, _S_DONE = 12, 13, 14, 15
_N_SLOTS = 16


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
        # (ipoc, host time it left) of the latest frames the controller sent, lost or not:
        # an answer echoing an older IPOC than one sent before it arrived is late (KSS).
        self.sent_ipocs: collections.deque[tuple[int, float, bool]] = collections.deque(maxlen=64)
        self.stale_late = 0
        self.last_motion_s = math.nan
        self._q_prev: FloatArray | None = None
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
            self._track_motion()
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
            self._track_motion()
            self._inc(_S_CYCLES)
            if sim.is_steady():
                break

    def _track_motion(self) -> None:
        """Note the controller time of the last cycle in which the arm moved (truth)."""
        q = np.array(self.sim.q_rad, dtype=float)
        prev = self._q_prev
        if prev is not None and float(np.max(np.abs(q - prev))) > _REST_SPEED_RAD_S * self.period_s:
            self.last_motion_s = float(self.sim.time_s)
        self._q_prev = q

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
                if self.heap and self.heap[0].send_time_s < boundary + _SEND_GUARD_S:
                    # A frame due before the boundary, or just after it, is about to leave:
                    # let it go before the cycle's physics takes the interpreter.
                    wait = 0.0002
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
        while True:
            self._poll_control()
            if self.reason != "running":
                break
            # Answers already waiting are taken before any expiry or the next frame, so the
            # order of events on the wire decides (an answer is stale only if it truly
            # arrived after a newer frame left).
            self._receive()
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
            self._count_late()
            if self.reason != "running":
                return

    def _count_late(self) -> None:
        """One more late cycle; RSI stops with RSITimeout at ``timeout_packets``."""
        if not self.pc_seen:
            return  # wait_for_pc: the robot program has not "started" yet
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

    def _newer_frame_sent(self, ipoc: int, departed_s: float, now: float) -> bool:
        """Whether a frame with a later IPOC than ``ipoc`` (which left at host time
        ``departed_s``) had left by ``now``: the answer then echoes a stale IPOC.

        Only a newer frame that left on time and at least half a period after this one
        counts: when the twin itself fell behind real time and sends late or back to back,
        an answer to the earlier frame is not held against the PC (the twin's lag is never
        passed on; a real controller never sends late).
        """
        for sent_ipoc, left_s, on_time in reversed(self.sent_ipocs):
            if sent_ipoc <= ipoc:
                return False
            if on_time and left_s <= now and left_s - departed_s >= 0.5 * self.period_s:
                return True
        return False

    def _send(self, frame: _Frame) -> None:
        if self.reason != "running":
            return
        if self.cfg.legacy_empty_frame and not self.frame_log:  # RSI <= 2.3, before frame 0
            with contextlib.suppress(OSError):
                self.sock.sendto(self._build_rob(None), self.dest)
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
        on_time = sent_s is None or sent_s - frame.send_time_s <= _LATE_SEND_S
        self.sent_ipocs.append((frame.ipoc, now, on_time))
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
            # KSS takes only an answer echoing the latest IPOC: once a newer frame has left,
            # this one's cycle is late (counted now, its correction not applied).
            stale = entry is not None and self._newer_frame_sent(sen.ipoc, entry[1], now)
            in_time = in_time and not stale
            self.answer_log.append(
                {
                    "ipoc": sen.ipoc,
                    "arrival_s": arrival_s,
                    "arrival_host_s": now,
                    "in_time": in_time,
                    "stale_ipoc": stale,
                    "correction_rad": sen.correction_rad.tolist(),
                }
            )
            if not in_time:
                self._inc(_S_STALE)
                if stale:
                    with self.lock:
                        self.pending.pop(sen.ipoc, None)
                    self.stale_late += 1
                    self._count_late()
                    if self.reason != "running":
                        return
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
        self.t0 = time.monotonic() + _T0_LEAD_S + float(self.cfg.first_frame_delay_s)
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
            "stale_ipoc_late": self.stale_late,
            "last_motion_s": None if math.isnan(self.last_motion_s) else self.last_motion_s,
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
