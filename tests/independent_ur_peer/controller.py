"""The controller: a fixed-rate cycle on absolute deadlines, the registers, the program state,
watchdogs, the pendant program and the truth log.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from .codec import OUTPUT_TYPES
from .constants import (
    DEFAULT_EXTERNAL_CONTROL_PROGRAM,
    JOINT_MODE_RUNNING,
    PAUSED,
    PLAYING,
    ROBOT_MODE_RUNNING,
    SAFETY_NORMAL,
    SAFETY_PROTECTIVE_STOP,
    STOPPED,
)
from .physics import JOINT_POSITION_LIMIT, SPEED_LIMITS, Arm, StopMotion
from .script import RtdeControlProgram
from .urcap import (
    fetch_urcap_script,
    is_rtde_control_script,
    register_offset,
    split_external_control,
)


class Subscriber(Protocol):
    """A connection the controller publishes to each cycle (:class:`.rtde.RtdeConnection`)."""

    def publish(self, ctl: Controller) -> None: ...

    def close(self) -> None: ...


class Controller:
    """Fixed-rate controller; ``rate_hz`` 500 (e-Series) or 125 (CB3)."""

    def __init__(
        self,
        model: str,
        version: tuple[int, int, int, int],
        truth_path: Path | None,
        stop_decel: float,
        start_delay: float,
        q0: list[float],
        urcap: tuple[str, int] = ("127.0.0.1", 50002),
        installed_program: str = DEFAULT_EXTERNAL_CONTROL_PROGRAM,
    ) -> None:
        self.model = model
        self.version = version
        self.rate_hz = 500.0 if version[0] >= 4 else 125.0
        self.dt = 1.0 / self.rate_hz
        family = model.upper().rstrip("E")
        self.speed_limits = SPEED_LIMITS.get(family, SPEED_LIMITS["UR10"])
        self.arm = Arm(q0, self.dt, self.speed_limits)
        self.stop_decel = stop_decel
        self.start_delay_cycles = max(1, round(start_delay * self.rate_hz))
        self.lock = threading.Lock()
        self.inputs: dict[str, Any] = {}
        self.last_update: dict[str, int] = {}
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.runtime_state = STOPPED
        self.safety_mode = SAFETY_NORMAL
        self.program: RtdeControlProgram | None = None
        self.program_text: str | None = None
        self.pending_program: tuple[int, str] | None = None
        self.urcap = urcap  # where the External Control node asks for its script
        self.installed_program = installed_program  # the pendant program holding that node
        self.loaded_urp: str | None = None  # the pendant program loaded through the dashboard
        self.dashboard_lock = threading.Lock()  # one load / play of it at a time
        self.watchdogs: dict[str, tuple[float, str]] = {}
        self.cycle = 0
        self.t0 = time.monotonic()
        self.connections: list[Subscriber] = []
        self.stop_event = threading.Event()
        self._truth = open(truth_path, "a", encoding="ascii") if truth_path else None  # noqa: SIM115
        self._last_flush = 0.0
        self._was_still = True
        # Input log (benchmarks): one line per RTDE input package, when it arrived, the
        # boundary of the cycle that took it and when that cycle read it (controller s).
        self.input_log: Any = None
        self.rt_priority = 0  # SCHED_FIFO priority of the cycle thread (0: normal)
        self.publish_delay_s = 0.0  # s from the cycle boundary to sending its package
        self._arrived: list[float] = []
        if self._truth is not None:
            self._truth.write(
                f"# independent_ur_peer model={model} version={'.'.join(map(str, version))} "
                f"rate_hz={self.rate_hz:g} (clock origin: see the peer_started event)\n"
                "time_s,runtime_state,"
                + ",".join(f"q{i}" for i in range(6))
                + ","
                + ",".join(f"qd{i}" for i in range(6))
                + "\n"
            )
            self._truth.flush()

    # time ------------------------------------------------------------------------------------
    @property
    def now(self) -> float:
        """Controller time in s (cycles * period)."""
        return self.cycle * self.dt

    def event(self, kind: str, **fields: Any) -> None:
        """Append an ``#event`` line to the truth log (flushed at once)."""
        if self._truth is None:
            return
        detail = ";".join(f"{k}={v}" for k, v in fields.items())
        self._truth.write(f"#event,{self.now:.4f},{kind},{detail}\n")
        self._truth.flush()

    # inputs ----------------------------------------------------------------------------------
    def apply_inputs(self, names: list[str], values: list[Any]) -> None:
        """Store an RTDE input package (called from connection threads)."""
        with self.lock:
            c = self.cycle
            for n, v in zip(names, values, strict=True):
                self.inputs[n] = v
                self.last_update[n] = c
            if self.input_log is not None:
                self._arrived.append(time.monotonic() - self.t0)

    def set_watchdog(self, var: str, freq: float, action: str) -> None:
        """``rtde_set_watchdog(var, freq, action)``; freq in Hz."""
        if freq <= 0:
            self.watchdogs.pop(var, None)
            return
        with self.lock:
            self.last_update.setdefault(var, self.cycle)
        self.watchdogs[var] = (freq, action)
        self.event("watchdog_set", var=var, min_frequency=freq, action=action)

    # program ---------------------------------------------------------------------------------
    def load_program(self, text: str) -> None:
        """A complete ``def ... end`` block arrived on the script port."""
        if self.runtime_state != STOPPED:
            self.program_stop("new_program")
        self.pending_program = (self.cycle + self.start_delay_cycles, text)
        self.event("program_received", chars=len(text))

    def load_urp(self, path: str) -> str:
        """Dashboard ``load <path>``; returns the reply."""
        if path != self.installed_program:
            self.event("load_failed", path=path, reason="file_not_found")
            return f"File not found: {path}"
        if self.runtime_state != STOPPED:
            self.event("load_refused", path=path, reason="program_running")
            return f"Error while loading program: {path}"
        self.loaded_urp = path
        self.event("urp_loaded", path=path)
        return f"Loading program: {path}"

    def play_urp(self) -> bool:
        """Dashboard ``play`` of the loaded pendant program: its External Control node fetches
        the script from the PC, then it starts like an uploaded script. False: it did not start
        (the reason is logged)."""
        if self.runtime_state == PAUSED:
            self.runtime_state = PLAYING
            self.event("program_resumed", path=self.loaded_urp)
            return True
        if self.runtime_state == PLAYING or self.pending_program is not None:
            return True  # already running (or starting): nothing to do
        host, port = self.urcap
        self.event("urcap_request", pc=f"{host}:{port}")
        t0 = time.monotonic()
        text, reason = fetch_urcap_script(self.urcap)
        took = time.monotonic() - t0
        if text is None:
            self.event("urcap_fetch_failed", pc=f"{host}:{port}", reason=reason, s=f"{took:.3f}")
            self.event("play_failed", path=self.loaded_urp, reason="urcap_" + reason)
            return False
        self.event(
            "urcap_script_received",
            chars=len(text),
            lines=text.count("\n"),
            marked=split_external_control(text) is not None,
            s=f"{took:.3f}",
        )
        self.load_program(text)
        return True

    def _start_program(self, text: str) -> None:
        self.program_text = text
        off_i = register_offset(text, "int")
        off_f = register_offset(text, "float")
        if not is_rtde_control_script(text):
            # A foreign program cannot be interpreted here: it "runs" for one cycle.
            self.event("foreign_program_ignored")
            self.runtime_state = PLAYING
            self.program = None
            return
        self.program = RtdeControlProgram(self, off_i, off_f)
        self.runtime_state = PLAYING
        self.program.start()
        source = "upload" if "rtde_control" in text else "external_control"
        self.event("program_started", offset_int=off_i, offset_float=off_f, source=source)

    def program_stop(self, reason: str) -> None:
        """Stop the running program; the arm decelerates at ``stop_decel`` rad/s^2."""
        if self.program is not None:
            self.program.kill_threads()
        self.program = None
        if self.runtime_state != STOPPED:
            self.event("program_stopped", reason=reason)
        self.runtime_state = STOPPED
        self.watchdogs.clear()
        if not self.arm.at_rest() or (self.arm.motion is not None and not self.arm.motion.done):
            self.arm.motion = StopMotion(self.stop_decel)
        else:
            self.arm.motion = None

    def protective_stop(self, reason: str) -> None:
        """Protective stop: program stopped, safety mode 3, fast deceleration."""
        self.safety_mode = SAFETY_PROTECTIVE_STOP
        self.event("protective_stop", reason=reason)
        self.program_stop("protective_stop")
        self.arm.motion = StopMotion(max(self.stop_decel, 10.0))

    # the cycle -------------------------------------------------------------------------------
    def step(self) -> None:
        """One controller cycle: sample inputs, watchdogs, script, physics, outputs, truth."""
        with self.lock:
            regs = dict(self.inputs)
            last = dict(self.last_update)
            arrived, self._arrived = self._arrived, []
        if self.input_log is not None and arrived:
            taken = time.monotonic() - self.t0  # when this cycle read them (>= its boundary)
            self.input_log.write("".join(f"{a:.6f},{self.now:.6f},{taken:.6f}\n" for a in arrived))
        if self.pending_program is not None and self.cycle >= self.pending_program[0]:
            text = self.pending_program[1]
            self.pending_program = None
            self._start_program(text)
        elif self.runtime_state == PLAYING and self.program is None:
            self.runtime_state = STOPPED  # a foreign program has "finished"
            self.event("program_stopped", reason="finished")
        if self.runtime_state == PLAYING:
            for var, (freq, action) in list(self.watchdogs.items()):
                elapsed = (self.cycle - last.get(var, self.cycle)) * self.dt
                if elapsed > 1.0 / freq + 1e-9:
                    lu = last.get(var, self.cycle) * self.dt
                    self.event(
                        "watchdog_trip",
                        var=var,
                        action=action,
                        last_update_s=f"{lu:.4f}",
                        min_frequency=freq,
                    )
                    if action == "stop":
                        self.program_stop("watchdog")
                    elif action == "pause":
                        self.runtime_state = PAUSED
                        if self.program is not None:
                            self.program.kill_threads()
                        self.arm.motion = StopMotion(self.stop_decel)
                        self.watchdogs.clear()
                    else:
                        self.watchdogs.pop(var, None)
                    break
        if self.runtime_state == PLAYING and self.program is not None:
            self.program.cycle(regs)
            if self.program.finished:
                self.program.kill_threads()
                self.program = None
                self.runtime_state = STOPPED
                self.watchdogs.clear()
                self.event("program_stopped", reason="script_ended")
                if not self.arm.at_rest():
                    self.arm.motion = StopMotion(self.stop_decel)
        self.arm.step()
        if self.arm.motion is not None and self.arm.motion.done and self.arm.at_rest():
            self.arm.motion = None
        if any(abs(q) > JOINT_POSITION_LIMIT for q in self.arm.q_ref) and (
            self.safety_mode == SAFETY_NORMAL
        ):
            self.protective_stop("joint_position_limit")
        still = self.arm.actual_still()
        if still != self._was_still:
            self.event("at_rest" if still else "moving")
            self._was_still = still
        if self.publish_delay_s <= 0:
            self._publish()
        self._write_truth()

    def _publish(self) -> None:
        with self.lock:
            conns = list(self.connections)
        for conn in conns:
            conn.publish(self)

    def _write_truth(self) -> None:
        f = self._truth
        if f is None:
            return
        a = self.arm
        f.write(
            f"{self.now:.4f},{self.runtime_state},"
            + ",".join(f"{v:.7f}" for v in a.q)
            + ","
            + ",".join(f"{v:.7f}" for v in a.qd)
            + "\n"
        )
        if self.now - self._last_flush >= 0.05:
            f.flush()
            self._last_flush = self.now

    def run(self) -> None:
        """Fixed-rate loop on absolute monotonic deadlines ``t0 + cycle * dt``."""
        if self.rt_priority:
            # A controller's cycle runs at real-time priority; Linux with the right to it.
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
                self.event("realtime", priority=self.rt_priority)
            except (AttributeError, OSError) as exc:
                self.event("realtime_refused", reason=type(exc).__name__)
        while not self.stop_event.is_set():
            deadline = self.t0 + self.cycle * self.dt
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:
                # Far behind (process was starved): slip the clock rather than burst.
                slip = math.ceil(-delay / self.dt) * self.dt
                self.t0 += slip
                self.event("clock_slip", t0_monotonic=f"{self.t0:.6f}", slip_s=f"{slip:.4f}")
            self.step()
            if self.publish_delay_s > 0:
                # A publisher late in the cycle: the package (stamped at the boundary)
                # leaves publish_delay_s after it.
                delay = deadline + self.publish_delay_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                self._publish()
            with self.lock:
                self.cycle += 1
        if self._truth is not None:
            self._truth.flush()

    # output values ---------------------------------------------------------------------------
    def getter(self, name: str) -> Callable[[], Any]:
        """Return a callable producing the current value(s) of output ``name``."""
        a = self.arm
        z6 = (0.0,) * 6
        z3 = (0.0,) * 3
        if name.startswith("output_int_register_"):
            i = int(name.rsplit("_", 1)[1])
            return lambda: self.out_int[i]
        if name.startswith("output_double_register_"):
            i = int(name.rsplit("_", 1)[1])
            return lambda: self.out_double[i]
        if name.startswith("input_int_register_"):
            return lambda: int(self.inputs.get(name, 0))
        if name.startswith("input_double_register_"):
            return lambda: float(self.inputs.get(name, 0.0))
        table: dict[str, Callable[[], Any]] = {
            "timestamp": lambda: self.now,
            "target_q": lambda: a.q_ref,
            "target_qd": lambda: a.qd_ref,
            "target_qdd": lambda: a.qdd_ref,
            "actual_q": lambda: a.q,
            "actual_qd": lambda: a.qd,
            "joint_temperatures": lambda: (30.0,) * 6,
            "actual_execution_time": lambda: 0.2,
            "robot_mode": lambda: ROBOT_MODE_RUNNING,
            "joint_mode": lambda: (JOINT_MODE_RUNNING,) * 6,
            "safety_mode": lambda: self.safety_mode,
            "safety_status": lambda: self.safety_mode,
            "speed_scaling": lambda: 1.0,
            "target_speed_fraction": lambda: 1.0,
            "actual_main_voltage": lambda: 48.0,
            "actual_robot_voltage": lambda: 48.0,
            "actual_robot_current": lambda: 0.5,
            "actual_joint_voltage": lambda: (48.0,) * 6,
            "runtime_state": lambda: self.runtime_state,
            "robot_status_bits": lambda: 1 | (2 if self.runtime_state == PLAYING else 0),
            "safety_status_bits": lambda: 1 if self.safety_mode == SAFETY_NORMAL else 1 << 2,
            "tool_output_voltage": lambda: 0,
            "tool_temperature": lambda: 30.0,
        }
        if name in table:
            return table[name]
        typ = OUTPUT_TYPES[name]
        zero: Any = {
            "VECTOR6D": z6,
            "VECTOR3D": z3,
            "VECTOR6INT32": (0,) * 6,
            "DOUBLE": 0.0,
            "BOOL": False,
        }.get(typ, 0)
        return lambda: zero
