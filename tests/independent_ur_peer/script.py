"""The ``rtde_control`` script's semantics, re-implemented (not interpreted): the command
register sampled once per cycle, the acknowledgement register, realtime and one-shot
commands, and the script threads that re-issue a blocking motion call.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, Protocol

from .physics import Arm, Motion, MoveJMotion, ServoMotion, SpeedMotion, StopMotion

# Commands of the rtde_control script (ids from librtde.so.1.6.5's embedded script).
MOVEJ, SPEEDJ, SPEEDL, SERVOJ = 1, 9, 10, 11
SPEED_STOP, SERVO_STOP, STOPL, STOPJ = 15, 16, 33, 34
SET_WATCHDOG, IS_STEADY, WATCHDOG, STOP_SCRIPT = 35, 47, 99, 255
GET_STEPTIME = 26
REALTIME_CMDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
# Commands that have no effect on motion here and are simply acknowledged.
NOOP_CMDS = frozenset({8, 17, 20, 21, 29, 59, 65, WATCHDOG})


class Cell(Protocol):
    """What the script reads and writes of its controller (:class:`.controller.Controller`):
    the arm, the output registers, the truth log's events, program stop and watchdogs."""

    arm: Arm
    out_int: list[int]
    out_double: list[float]

    def event(self, kind: str, **fields: Any) -> None: ...

    def program_stop(self, reason: str) -> None: ...

    def set_watchdog(self, var: str, freq: float, action: str) -> None: ...


@dataclasses.dataclass
class _ScriptThread:
    """A URScript thread re-issuing a blocking motion call; ``left`` cycles until it returns."""

    kind: str  # "speed", "servo", "move", "stop"
    left: int = 0
    motion: Motion | None = None
    until_reached: bool = False


class RtdeControlProgram:
    """Emulates the main loop and threads of ur_rtde's uploaded ``rtde_control`` script."""

    def __init__(self, ctl: Cell, off_int: int, off_float: int) -> None:
        self.ctl = ctl
        self.off_i = off_int
        self.off_f = off_float
        self.executing_cmd = False
        self.busy: Callable[[], bool] | None = None  # main thread blocked until this is True
        self.busy_done: Callable[[], None] | None = None
        self.speed_thrd: _ScriptThread | None = None
        self.servo_thrd: _ScriptThread | None = None
        self.move_thrd: _ScriptThread | None = None
        self.stop_thrd: _ScriptThread | None = None
        self.is_speeding = 0
        self.is_servoing = 0
        self.speed_type = 0
        self.speed_target = [0.0] * 6
        self.speed_acc = 0.5
        self.speed_time = 0.5
        self.servo_target = [0.0] * 6
        self.servo_time = 0.002
        self.servo_lookahead = 0.1
        self.async_wr_count = 0
        self.async_op_id = 0
        self.finished = False
        self.last_cmd = -1  # for the "command" event, logged when the sampled id changes

    # registers -------------------------------------------------------------------------------
    def in_int(self, regs: dict[str, Any], i: int) -> int:
        """Read input int register ``i`` (with the script's offset) from the cycle snapshot."""
        return int(regs.get(f"input_int_register_{i + self.off_i}", 0))

    def in_float(self, regs: dict[str, Any], i: int) -> float:
        """Read input double register ``i`` (with the script's offset) from the snapshot."""
        return float(regs.get(f"input_double_register_{i + self.off_f}", 0.0))

    def q_from(self, regs: dict[str, Any], i: int) -> list[float]:
        """Read six consecutive input double registers starting at ``i``."""
        return [self.in_float(regs, i + k) for k in range(6)]

    def out_int(self, i: int, value: int) -> None:
        """Write output int register ``i`` (with offset)."""
        self.ctl.out_int[i + self.off_i] = int(value)

    def out_float(self, i: int, value: float) -> None:
        """Write output double register ``i`` (with offset)."""
        self.ctl.out_double[i + self.off_f] = float(value)

    def signal_ready(self) -> None:
        """Write 1 (ready) to output int register 0."""
        self.out_int(0, 1)

    def signal_done(self) -> None:
        """Write 2 (done) to output int register 0."""
        self.out_int(0, 2)

    def write_async_progress(self, value: int) -> None:
        """Async progress register 2: op id << 24 | count << 16 | running bit 15 | progress."""
        self.async_wr_count += 1
        if self.async_wr_count > 127:
            self.async_wr_count = 0
        if value == 0:
            self.async_op_id += 1
            if self.async_op_id > 127:
                self.async_op_id = 0
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int(2, reg)

    # lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Program start: reset async progress, signal ready."""
        self.write_async_progress(-1)
        self.signal_ready()

    def kill_threads(self) -> None:
        """Kill every script thread (program stop)."""
        self.speed_thrd = self.servo_thrd = self.move_thrd = self.stop_thrd = None
        self.is_speeding = self.is_servoing = 0
        self.busy = self.busy_done = None

    def _take_arm(self, keep: str) -> None:
        """Newest motion command takes the arm: end the other moving threads."""
        if keep != "speed" and self.speed_thrd is not None:
            self.speed_thrd = None
            self.is_speeding = 0
        if keep != "servo" and self.servo_thrd is not None:
            self.servo_thrd = None
            self.is_servoing = 0
        if keep != "move" and self.move_thrd is not None:
            self.move_thrd = None
            self.write_async_progress(-1)
        if keep != "stop" and self.stop_thrd is not None:
            self.stop_thrd = None
            self.write_async_progress(-1)

    # one controller cycle --------------------------------------------------------------------
    def cycle(self, regs: dict[str, Any]) -> None:
        """Run the main loop once (one ``sync()``), then the threads."""
        if self.busy is not None:
            if self.busy():
                done = self.busy_done
                self.busy = self.busy_done = None
                if done is not None:
                    done()
        else:
            cmd = self.in_int(regs, 0)
            if cmd != self.last_cmd:
                self.ctl.event("command", id=cmd)
                self.last_cmd = cmd
            if cmd in REALTIME_CMDS:
                keep = self.process(cmd, regs)
                self.signal_ready()
                if not keep:
                    self.finished = True
            elif cmd == 0:
                self.executing_cmd = False
                self.signal_ready()
            else:
                if not self.executing_cmd:
                    keep = self.process(cmd, regs)
                    if not keep:
                        self.finished = True
                self.executing_cmd = True
        self._run_threads()

    def _run_threads(self) -> None:
        arm = self.ctl.arm
        th = self.speed_thrd
        if th is not None:
            th.left -= 1
            reached = th.until_reached and isinstance(th.motion, SpeedMotion)
            if th.left <= 0 and (not reached or th.motion.reached(arm)):  # type: ignore[union-attr]
                # The speedj call returned: the loop re-issues it with the latest globals.
                self._issue_speedj(th)
        th = self.servo_thrd
        if th is not None:
            th.left -= 1
            if th.left <= 0:
                self._issue_servoj(th)
        th = self.move_thrd
        if th is not None and th.motion is not None and th.motion.done and arm.at_rest():
            self.move_thrd = None
            self.write_async_progress(-1)
        th = self.stop_thrd
        if th is not None and th.motion is not None and th.motion.done:
            self.stop_thrd = None
            self.write_async_progress(-1)

    def _issue_speedj(self, th: _ScriptThread) -> None:
        arm = self.ctl.arm
        target = list(self.speed_target)
        if isinstance(arm.motion, SpeedMotion) and arm.motion is th.motion:
            arm.motion.target = target
            arm.motion.accel = self.speed_acc
        else:
            th.motion = SpeedMotion(target, self.speed_acc)
            arm.motion = th.motion
        if self.speed_time > 0:
            th.left = max(1, math.ceil(self.speed_time / arm.dt - 1e-9))
            th.until_reached = False
        else:
            th.left = 1
            th.until_reached = True

    def _issue_servoj(self, th: _ScriptThread) -> None:
        arm = self.ctl.arm
        if isinstance(arm.motion, ServoMotion) and arm.motion is th.motion:
            arm.motion.target = list(self.servo_target)
            arm.motion.lookahead = self.servo_lookahead
        else:
            th.motion = ServoMotion(list(self.servo_target), self.servo_lookahead)
            arm.motion = th.motion
        th.left = max(1, math.ceil(self.servo_time / arm.dt - 1e-9))

    def _block_until(self, pred: Callable[[], bool], then: Callable[[], None] | None) -> None:
        self.busy = pred
        self.busy_done = then

    def _stop_arm(self, decel: float, asynchronous: bool) -> None:
        arm = self.ctl.arm
        motion = StopMotion(decel)
        arm.motion = motion
        if asynchronous:
            self.write_async_progress(0)
            self.stop_thrd = _ScriptThread("stop", motion=motion)
            self.signal_done()
        else:
            self._block_until(lambda: motion.done and arm.at_rest(), self.signal_done)

    def process(self, cmd: int, regs: dict[str, Any]) -> bool:
        """Process one command (``process_cmd``); return False for stop-script."""
        ctl = self.ctl
        arm = ctl.arm
        if cmd == MOVEJ:
            q = self.q_from(regs, 0)
            vel = self.in_float(regs, 6)
            acc = self.in_float(regs, 7)
            asynchronous = self.in_int(regs, 1) == 1
            self._take_arm("none")
            motion = MoveJMotion(q, vel, acc)
            arm.motion = motion
            if asynchronous:
                self.write_async_progress(0)
                self.move_thrd = _ScriptThread("move", motion=motion)
                self.signal_done()
            else:
                self._block_until(lambda: motion.done and arm.at_rest(), self.signal_done)
            return True
        if cmd == SPEEDJ:
            self.speed_type = 1
            self.speed_target = self.q_from(regs, 0)
            self.speed_acc = self.in_float(regs, 6)
            self.speed_time = self.in_float(regs, 7)
            self._take_arm("speed")
            if self.is_speeding == 0:
                self.is_speeding = 1
                if self.speed_thrd is None:
                    self.speed_thrd = _ScriptThread("speed")
                    self._issue_speedj(self.speed_thrd)
            self.signal_done()
            return True
        if cmd == SERVOJ:
            self.servo_target = self.q_from(regs, 0)
            self.servo_time = self.in_float(regs, 8)
            self.servo_lookahead = self.in_float(regs, 9)
            self._take_arm("servo")
            if self.is_servoing == 0:
                self.is_servoing = 1
                if self.servo_thrd is None:
                    self.servo_thrd = _ScriptThread("servo")
                    self._issue_servoj(self.servo_thrd)
            self.signal_done()
            return True
        if cmd == SPEED_STOP:
            self.is_speeding = 0
            self.speed_thrd = None
            self._stop_arm(self.in_float(regs, 0), asynchronous=False)
            return True
        if cmd == SERVO_STOP:
            self.is_servoing = 0
            self.servo_thrd = None
            self._stop_arm(self.in_float(regs, 0), asynchronous=False)
            return True
        if cmd in (STOPL, STOPJ):
            decel = self.in_float(regs, 0)
            asynchronous = self.in_int(regs, 1) == 1
            self._take_arm("none")
            self._stop_arm(decel, asynchronous)
            return True
        if cmd == SET_WATCHDOG:
            freq = self.in_float(regs, 0)
            var = f"input_int_register_{self.off_i}"
            ctl.set_watchdog(var, freq, "stop")
            self.signal_done()
            return True
        if cmd == IS_STEADY:
            self.out_int(1, 1 if arm.at_rest() else 0)
            self.signal_done()
            return True
        if cmd == GET_STEPTIME:
            self.out_float(0, arm.dt)
            self.signal_done()
            return True
        if cmd == STOP_SCRIPT:
            ctl.event("stop_script")
            return False
        if cmd in NOOP_CMDS:
            self.signal_done()
            return True
        ctl.event("unsupported_command", cmd=cmd)
        ctl.program_stop("unsupported_command")
        return True
