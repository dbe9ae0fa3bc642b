"""An independently written Universal Robots controller peer for the real ``ur_rtde`` client.

Run it as a process::

    python tests/independent_ur_peer.py --host 127.0.0.171 --model UR10 --version 5.11.1 \\
        --truth /tmp/truth.csv

It listens on the ports the ``ur_rtde`` 1.6.5 client uses (fixed by the client, so one peer per
loopback address): 30004 RTDE (protocol v2), 29999 dashboard and 30003 script upload, prints
``ready`` on stdout once listening, and exits cleanly on SIGTERM.

What it emulates, from UR's public documentation and the control script embedded in
``librtde.so.1.6.5`` (never from this project's own simulator):

* RTDE output recipes streamed at the requested frequency (500 Hz controller cycle for an
  e-Series, version 5.x; 125 Hz for a CB3, version 3.x), packed with the controller's types;
  unknown names answered ``NOT_FOUND``; input recipes numbered 1, 2, 3 ... per connection; an
  input already owned by another connection answered ``IN_USE``.
* The uploaded ``rtde_control`` script's main loop, *not* by interpreting URScript but by
  re-implementing its semantics: command id in ``input_int_register_0`` (or 24), sampled once per
  controller cycle; acknowledgement in ``output_int_register_0`` (1 ready, 2 done); realtime
  commands (9 speedj, 11 servoj, ...) processed every cycle; the others once, until the client
  clears the register; blocking commands (synchronous movej, stopj, speed_stop) keep the main
  loop busy until the motion ends.
* The speed "thread": ``speedj(target, a, t)`` re-issued with the latest target each time the
  previous call returns (after ``t``, or when the target speed is reached when ``t`` is 0), so
  ``t`` never ends the motion; only speed_stop, another motion command or a program stop does.
* ``rtde_set_watchdog(var, f, "stop")``: when no RTDE input package containing ``var`` arrives
  for ``1/f`` s the program is stopped (runtime_state 1) and the arm decelerates to rest;
  watchdogs are removed on program stop.

Physics (deliberately unlike a first-order model): per joint a reference velocity, acceleration
limited to the commanded ``a`` with the leading axis scaling all joints (so a joint-space
straight line), joint speed limits by the same scaling, and a fixed 3-cycle actuation pipeline
(actual velocity = reference velocity 3 cycles earlier); with ``--servo-friction F`` the
actual joint instead follows that delayed reference through a PD position servo (8 Hz,
damping 0.9) against Coulomb friction ``F`` and viscous friction, sticking where the drive
cannot overcome static friction (``Arm``). A program stop decelerates the
reference at ``--stop-decel`` (default 3 rad/s^2, leading axis). The controller clock is a
fixed-rate loop on absolute ``time.monotonic`` deadlines; timestamps are ``cycles * period``.

Truth log (``--truth``): a header comment with ``t0_monotonic``, then the line
``time_s,runtime_state,q0..q5,qd0..qd5`` and one row per controller cycle (actual joint
positions in rad, velocities in rad/s, time in controller seconds), flushed every ~50 ms, plus
``#event,time_s,kind,key=value;...`` lines (program start/stop, watchdog trips, at_rest, ...).

The pendant program with the External Control URCap (``--urcap HOST:PORT``, default
``127.0.0.1:50002``; ``--external-control-program PATH``, default
``/programs/external_control.urp``): for cells where remote control is forbidden the operator
plays a pendant program holding the URCap's *External Control* node. The URCap's installation
names a PC address and port; when the program starts the URCap connects there, sends
``request_program\n`` and reads back a URScript text, which it splits at the markers
``# HEADER_BEGIN`` / ``# HEADER_END`` (function definitions, inserted once) and runs the rest
(``# NODE_CONTROL_LOOP_BEGINS`` ... ``# NODE_CONTROL_LOOP_ENDS``) at its node
(UniversalRobots/Universal_Robots_ExternalControl_URCap, README and ``RequestProgram.java``;
the script is requested anew at every program start). Here:

* The dashboard knows exactly one installed program, that path: ``load`` of it answers
  ``Loading program: <path>``, any other path ``File not found: <path>`` (PolyScope 3.4+ / 5.x
  replies); ``get loaded program`` answers ``Loaded program: <path>`` (``No program loaded``
  before); ``programState`` names the loaded program's file (``<unnamed>`` without one).
* ``play`` with it loaded (and the program stopped) fetches the script as the URCap does, with
  bounds (connect ``URCAP_CONNECT_TIMEOUT_S``; the whole exchange ``URCAP_FETCH_TIMEOUT_S``;
  lines of at most ``MAX_URCAP_LINE`` bytes, ``MAX_URCAP_SCRIPT`` in all). The text is complete
  at the ``# NODE_CONTROL_LOOP_ENDS`` line (ur_rtde's script server keeps the connection open
  after it) or when the PC closes the connection with no marked part left open. Then the program
  starts through the same path as an uploaded script and ``play`` answers ``Starting program``.
  Nobody listening, a timeout, an oversized or incomplete text: ``Failed to execute: play``, a
  ``urcap_fetch_failed`` event, and the program stays STOPPED. (The real URCap instead runs a
  blocking popup program saying "Receive program failed"; for a client either way the program
  never runs.) ``play`` while PAUSED resumes; while PLAYING it changes nothing.
* A fetched text is run with the ``rtde_control`` semantics when it is ur_rtde's control script:
  the four markers in order, a header defining ``rtde_cmd``, ``signal_ready`` and
  ``process_cmd``, and a control loop calling ``rtde_cmd`` and ``process_cmd`` (the uploaded
  form is recognised as before, by its ``rtde_control`` name). Register offsets are read from
  the ``global reg_offset_int = # int register offset`` line, whose value ur_rtde 1.6.5 writes on
  the next line (in the uploaded script too).
* ``load`` while a program runs is refused (``Error while loading program: <path>``, event
  ``load_refused``): the documented failure reply, for a case the document does not describe.

Deliberate simplifications: no kinematics (TCP fields are zero; speedl, movel and other
Cartesian commands stop the program with an ``unsupported_command`` event rather than pretend);
stopl is executed as a joint-space stop; when a new motion command arrives while another
script thread is moving the arm, the newest command takes the arm and the older thread is ended
(the real controller's behaviour with two moving threads is not documented).

For tests, :func:`run_peer` starts the peer in a subprocess and yields a :class:`PeerHandle`::

    from independent_ur_peer import run_peer  # with tests/ on sys.path

    with run_peer("127.0.0.181", model="UR10", version="5.11.1") as peer:
        ...  # point rtde_control / rtde_receive, or the code under test, at peer.host
        trip = peer.wait_event("watchdog_trip", timeout=3.0)  # PeerEvent(time_s, kind, fields)
        truth = peer.wait_truth_until(trip.time_s + 0.3)  # Truth: t, runtime_state, q, qd
        rest = truth.rest_time_after(trip.time_s)  # controller s, None if still moving
        t_peer = peer.to_peer_time(time.monotonic())  # this machine's clock -> controller s

Pick a distinct loopback address per concurrently running peer (the client fixes the ports).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import math
import os
import posixpath
import queue
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

MAX_RTDE_PACKAGE = 16384  # bytes; larger declared sizes close the connection
MAX_DASHBOARD_LINE = 1024  # bytes
MAX_SCRIPT_BYTES = 2 * 1024 * 1024  # bytes buffered from one script connection
MAX_CONNECTIONS = 16  # concurrent connections per port
MAX_RECIPES = 255  # recipe ids are one byte; more setups close the connection
OUTPUT_QUEUE_PACKAGES = 64  # data packages queued per RTDE connection before dropping

# The External Control URCap's script request (see the module docstring).
URCAP_REQUEST = b"request_program\n"
URCAP_CONNECT_TIMEOUT_S = 2.0  # s to connect to the PC (the URCap itself waits 5 s)
URCAP_FETCH_TIMEOUT_S = 3.0  # s for the whole request, connect included
MAX_URCAP_LINE = 4096  # bytes in one line of the received script (ur_rtde 1.6.5: 218)
MAX_URCAP_SCRIPT = 1024 * 1024  # bytes in the whole received script (ur_rtde 1.6.5: 42 kB)
DEFAULT_URCAP = "127.0.0.1:50002"  # the URCap installation's PC address (port 50002 default)
DEFAULT_EXTERNAL_CONTROL_PROGRAM = "/programs/external_control.urp"
HEADER_BEGIN, HEADER_END = "# HEADER_BEGIN", "# HEADER_END"
LOOP_BEGINS, LOOP_ENDS = "# NODE_CONTROL_LOOP_BEGINS", "# NODE_CONTROL_LOOP_ENDS"

STOPPED, PLAYING, PAUSED = 1, 2, 3
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
JOINT_MODE_RUNNING = 253

PIPELINE_CYCLES = 3

# ---------------------------------------------------------------------------------------------
# RTDE type tables (names and types as in UR's RTDE guide)
# ---------------------------------------------------------------------------------------------

_TYPE_FMT = {
    "DOUBLE": "d",
    "UINT64": "Q",
    "UINT32": "I",
    "INT32": "i",
    "UINT8": "B",
    "BOOL": "?",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}


def _output_types() -> dict[str, str]:
    """Return the controller's output variable types by name."""
    v6 = "VECTOR6D"
    t: dict[str, str] = {
        "timestamp": "DOUBLE",
        "target_q": v6,
        "target_qd": v6,
        "target_qdd": v6,
        "target_current": v6,
        "target_moment": v6,
        "actual_q": v6,
        "actual_qd": v6,
        "actual_current": v6,
        "actual_current_window": v6,
        "actual_current_as_torque": v6,
        "joint_control_output": v6,
        "actual_TCP_pose": v6,
        "actual_TCP_speed": v6,
        "actual_TCP_force": v6,
        "target_TCP_pose": v6,
        "target_TCP_speed": v6,
        "actual_digital_input_bits": "UINT64",
        "joint_temperatures": v6,
        "actual_execution_time": "DOUBLE",
        "robot_mode": "INT32",
        "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32",
        "safety_status": "INT32",
        "actual_tool_accelerometer": "VECTOR3D",
        "speed_scaling": "DOUBLE",
        "target_speed_fraction": "DOUBLE",
        "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE",
        "actual_robot_voltage": "DOUBLE",
        "actual_robot_current": "DOUBLE",
        "actual_joint_voltage": v6,
        "actual_digital_output_bits": "UINT64",
        "runtime_state": "UINT32",
        "elbow_position": "VECTOR3D",
        "elbow_velocity": "VECTOR3D",
        "robot_status_bits": "UINT32",
        "safety_status_bits": "UINT32",
        "analog_io_types": "UINT32",
        "standard_analog_input0": "DOUBLE",
        "standard_analog_input1": "DOUBLE",
        "standard_analog_output0": "DOUBLE",
        "standard_analog_output1": "DOUBLE",
        "io_current": "DOUBLE",
        "euromap67_input_bits": "UINT32",
        "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": "DOUBLE",
        "euromap67_24V_current": "DOUBLE",
        "tool_mode": "UINT32",
        "tool_analog_input_types": "UINT32",
        "tool_analog_input0": "DOUBLE",
        "tool_analog_input1": "DOUBLE",
        "tool_output_voltage": "INT32",
        "tool_output_current": "DOUBLE",
        "tool_temperature": "DOUBLE",
        "tcp_force_scalar": "DOUBLE",
        "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "tool_output_mode": "UINT8",
        "tool_digital_output0_mode": "UINT8",
        "tool_digital_output1_mode": "UINT8",
        "payload": "DOUBLE",
        "payload_cog": "VECTOR3D",
        "payload_inertia": v6,
        "script_control_line": "UINT32",
        "ft_raw_wrench": v6,
        "joint_position_deviation_ratio": v6,
        "collision_detection_ratio": "DOUBLE",
        "time_scale_source": "UINT32",
    }
    for i in range(64, 128):
        t[f"output_bit_register_{i}"] = "BOOL"
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"output_int_register_{i}"] = "INT32"
        t[f"output_double_register_{i}"] = "DOUBLE"
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


def _input_types() -> dict[str, str]:
    """Return the controller's input variable types by name."""
    t: dict[str, str] = {
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(64, 128):
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


OUTPUT_TYPES = _output_types()
INPUT_TYPES = _input_types()

# Joint speed limits in rad/s per model family (UR data sheets: base/shoulder of the big arms
# 120 deg/s, the others 180 deg/s; UR3 wrists 360 deg/s).
_SPEED_LIMITS = {
    "UR3": (math.pi,) * 3 + (2 * math.pi,) * 3,
    "UR5": (math.pi,) * 6,
    "UR10": (2.0944, 2.0944) + (math.pi,) * 4,
    "UR16": (2.0944, 2.0944) + (math.pi,) * 4,
}
JOINT_POSITION_LIMIT = 2 * math.pi  # rad, +-360 deg on every joint of these models
DEFAULT_Q0 = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)  # rad

# Commands of the rtde_control script (ids from librtde.so.1.6.5's embedded script).
MOVEJ, SPEEDJ, SPEEDL, SERVOJ = 1, 9, 10, 11
SPEED_STOP, SERVO_STOP, STOPL, STOPJ = 15, 16, 33, 34
SET_WATCHDOG, IS_STEADY, WATCHDOG, STOP_SCRIPT = 35, 47, 99, 255
GET_STEPTIME = 26
REALTIME_CMDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
# Commands that have no effect on motion here and are simply acknowledged.
NOOP_CMDS = frozenset({8, 17, 20, 21, 29, 59, 65, WATCHDOG})


# ---------------------------------------------------------------------------------------------
# Small vector helpers (plain Python: faster than numpy for 6 elements)
# ---------------------------------------------------------------------------------------------


def _scale_to_limits(v: list[float], limits: tuple[float, ...]) -> list[float]:
    """Scale a joint velocity vector (rad/s) uniformly so no joint exceeds its limit."""
    s = 1.0
    for vi, lim in zip(v, limits, strict=True):
        if abs(vi) > lim:
            s = min(s, lim / abs(vi))
    return v if s == 1.0 else [vi * s for vi in v]


def _ramp(cur: list[float], goal: list[float], accel: float, dt: float) -> list[float]:
    """Move velocity ``cur`` toward ``goal`` (rad/s) by at most ``accel*dt`` on the leading axis.

    All joints are scaled by the same factor, so they arrive together (linear in joint space).
    """
    delta = [g - c for g, c in zip(goal, cur, strict=True)]
    m = max(abs(d) for d in delta)
    step = max(accel, 0.0) * dt
    if m <= step:
        return list(goal)
    s = step / m
    return [c + d * s for c, d in zip(cur, delta, strict=True)]


# ---------------------------------------------------------------------------------------------
# Motions: each computes the next reference velocity (rad/s) from the reference state
# ---------------------------------------------------------------------------------------------


class Motion:
    """A reference generator; ``step`` returns the next reference velocity in rad/s."""

    done = False

    def step(self, arm: Arm) -> list[float]:
        """Return the reference joint velocity (rad/s) for the next cycle."""
        raise NotImplementedError


class SpeedMotion(Motion):
    """speedj: accelerate at ``accel`` (rad/s^2, leading axis) to ``target`` (rad/s), hold."""

    def __init__(self, target: list[float], accel: float) -> None:
        self.target = target
        self.accel = accel

    def step(self, arm: Arm) -> list[float]:
        """Ramp toward the (speed-limited) target velocity."""
        goal = _scale_to_limits(self.target, arm.speed_limits)
        return _ramp(arm.qd_ref, goal, self.accel, arm.dt)

    def reached(self, arm: Arm) -> bool:
        """Whether the reference velocity equals the target velocity."""
        goal = _scale_to_limits(self.target, arm.speed_limits)
        return all(abs(a - b) < 1e-12 for a, b in zip(arm.qd_ref, goal, strict=True))


class StopMotion(Motion):
    """stopj / program stop: decelerate at ``decel`` rad/s^2 (leading axis) to zero."""

    def __init__(self, decel: float) -> None:
        self.decel = decel

    def step(self, arm: Arm) -> list[float]:
        """Ramp the reference velocity to zero."""
        qd = _ramp(arm.qd_ref, [0.0] * 6, self.decel, arm.dt)
        if all(v == 0.0 for v in qd):
            self.done = True
        return qd


class MoveJMotion(Motion):
    """movej: stop first if moving, then a synchronised trapezoid along a joint-space line.

    ``vel`` in rad/s and ``accel`` in rad/s^2 apply to the leading axis.
    """

    def __init__(self, goal: list[float], vel: float, accel: float) -> None:
        self.goal = goal
        self.vel = max(vel, 1e-6)
        self.accel = max(accel, 1e-6)
        self.stopping: StopMotion | None = None
        self.start: list[float] | None = None
        self.k = 0

    def _plan(self, arm: Arm) -> None:
        self.start = list(arm.q_ref)
        dq = [g - s for g, s in zip(self.goal, self.start, strict=True)]
        self.dist = max(abs(d) for d in dq)
        if self.dist == 0.0:
            self.u = [0.0] * 6
            self.t_total = 0.0
            return
        self.u = [d / self.dist for d in dq]
        v = self.vel
        for ui, lim in zip(self.u, arm.speed_limits, strict=True):
            if abs(ui) > 0:
                v = min(v, lim / abs(ui))
        a = self.accel
        if self.dist < v * v / a:  # triangular profile
            self.t_acc = math.sqrt(self.dist / a)
            self.v_peak = a * self.t_acc
            self.t_total = 2 * self.t_acc
        else:
            self.t_acc = v / a
            self.v_peak = v
            self.t_total = self.dist / v + v / a

    def _s(self, t: float) -> float:
        a, ta, tt, vp = self.accel, self.t_acc, self.t_total, self.v_peak
        if t <= ta:
            return 0.5 * a * t * t
        if t < tt - ta:
            return 0.5 * a * ta * ta + vp * (t - ta)
        r = max(tt - t, 0.0)
        return self.dist - 0.5 * a * r * r

    def step(self, arm: Arm) -> list[float]:
        """Return the velocity that moves the reference to the profile's next position."""
        if self.start is None:
            if any(v != 0.0 for v in arm.qd_ref):
                if self.stopping is None:
                    self.stopping = StopMotion(self.accel)
                return self.stopping.step(arm)
            self._plan(arm)
        assert self.start is not None
        self.k += 1
        t = self.k * arm.dt
        if t >= self.t_total:
            self.done = True
            return [(g - q) / arm.dt for g, q in zip(self.goal, arm.q_ref, strict=True)]
        s = self._s(t)
        nxt = [q0 + ui * s for q0, ui in zip(self.start, self.u, strict=True)]
        return [(n - q) / arm.dt for n, q in zip(nxt, arm.q_ref, strict=True)]


class ServoMotion(Motion):
    """servoj: velocity toward the latest target over the lookahead time (s), limited.

    Velocity is bounded by the joint limits and its change by ``SERVO_ACCEL`` (rad/s^2, leading
    axis). The gain argument is accepted but not modelled.
    """

    SERVO_ACCEL = 20.0

    def __init__(self, target: list[float], lookahead: float) -> None:
        self.target = target
        self.lookahead = lookahead

    def step(self, arm: Arm) -> list[float]:
        """Return the rate-limited velocity toward the servo target."""
        horizon = max(self.lookahead, 2 * arm.dt)
        want = [(t - q) / horizon for t, q in zip(self.target, arm.q_ref, strict=True)]
        want = _scale_to_limits(want, arm.speed_limits)
        return _ramp(arm.qd_ref, want, self.SERVO_ACCEL, arm.dt)


class Arm:
    """Joint state: reference (target_*) and actual (pipeline-delayed) positions/velocities.

    Positions in rad, velocities in rad/s, ``dt`` in s. With ``friction`` > 0 (rad/s²,
    Coulomb friction per unit inertia) the actual joint is not the delayed reference itself
    but follows it through a servo: a PD *position* loop (stiffness :attr:`SERVO_KP`,
    damping :attr:`SERVO_KD`) against Coulomb and viscous friction, sticking while the
    drive cannot overcome static friction, integrated in :attr:`SERVO_SUBSTEPS` steps per
    cycle. A cruising joint then trails the delayed reference by ``(friction + viscous · v)
    / SERVO_KP`` (the textbook servo error), and sticks where it reverses.
    """

    SERVO_KP = 2500.0  # 1/s²: 8 Hz
    SERVO_KD = 90.0  # 1/s: damping ratio 0.9
    SERVO_VISCOUS = 5.0  # 1/s
    SERVO_SUBSTEPS = 8

    def __init__(
        self, q0: list[float], dt: float, speed_limits: tuple[float, ...], friction: float = 0.0
    ) -> None:
        self.dt = dt
        self.speed_limits = speed_limits
        self.q_ref = list(q0)
        self.qd_ref = [0.0] * 6
        self.qdd_ref = [0.0] * 6
        self.q = list(q0)
        self.qd = [0.0] * 6
        self.pipe: deque[list[float]] = deque([[0.0] * 6] * PIPELINE_CYCLES)
        self.motion: Motion | None = None
        self.friction = friction
        self.q_cmd = list(q0)  # the delayed reference, integrated (servo only)

    def step(self) -> None:
        """Advance one controller cycle."""
        qd = self.motion.step(self) if self.motion is not None else [0.0] * 6
        self.qdd_ref = [(n - o) / self.dt for n, o in zip(qd, self.qd_ref, strict=True)]
        self.qd_ref = qd
        self.q_ref = [q + v * self.dt for q, v in zip(self.q_ref, qd, strict=True)]
        self.pipe.append(qd)
        qd_cmd = self.pipe.popleft()
        if self.friction <= 0.0:
            self.qd = qd_cmd
            self.q = [q + v * self.dt for q, v in zip(self.q, self.qd, strict=True)]
            return
        h = self.dt / self.SERVO_SUBSTEPS
        fc, fs = self.friction, 1.2 * self.friction
        for j in range(6):
            q, v, ref, v_ref = self.q[j], self.qd[j], self.q_cmd[j], qd_cmd[j]
            for _ in range(self.SERVO_SUBSTEPS):
                ref += v_ref * h
                drive = self.SERVO_KP * (ref - q) + self.SERVO_KD * (v_ref - v)
                if v == 0.0 and abs(drive) <= fs:
                    continue  # stuck
                sign = (v > 0.0) - (v < 0.0) or (drive > 0.0) - (drive < 0.0)
                v_new = v + (drive - fc * sign - self.SERVO_VISCOUS * v) * h
                if v != 0.0 and v_new * v < 0.0:
                    v_new = 0.0  # friction stops the joint; it sticks until driven again
                v = v_new
                q += v * h
            self.q[j], self.qd[j], self.q_cmd[j] = q, v, ref

    def at_rest(self) -> bool:
        """True when reference and actual velocities and the whole pipeline are zero."""
        return (
            all(v == 0.0 for v in self.qd_ref)
            and all(v == 0.0 for row in self.pipe for v in row)
            and all(v == 0.0 for v in self.qd)
        )

    def actual_still(self) -> bool:
        """True when the actual joint velocities are all exactly zero."""
        return all(v == 0.0 for v in self.qd)


# ---------------------------------------------------------------------------------------------
# The rtde_control script's semantics
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _ScriptThread:
    """A URScript thread re-issuing a blocking motion call; ``left`` cycles until it returns."""

    kind: str  # "speed", "servo", "move", "stop"
    left: int = 0
    motion: Motion | None = None
    until_reached: bool = False


class RtdeControlProgram:
    """Emulates the main loop and threads of ur_rtde's uploaded ``rtde_control`` script."""

    def __init__(self, ctl: Controller, off_int: int, off_float: int) -> None:
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


# ---------------------------------------------------------------------------------------------
# The External Control URCap: the script request, and recognising ur_rtde's control script
# ---------------------------------------------------------------------------------------------

_MARKERS = (HEADER_BEGIN, HEADER_END, LOOP_BEGINS, LOOP_ENDS)


def _marker_positions(lines: list[str]) -> list[tuple[str, int]]:
    """(marker, line index) of every marker line; a marker stands alone on its line, blanks
    around it allowed (as the URCap's own match of these lines)."""
    return [(ln.strip(), i) for i, ln in enumerate(lines) if ln.strip() in _MARKERS]


def split_external_control(text: str) -> tuple[str, str] | None:
    """Split a fetched script into (header, control loop), the parts the URCap inserts once and
    at its node. None unless the four markers appear once each, in their order."""
    lines = text.split("\n")
    found = _marker_positions(lines)
    if [m for m, _ in found] != list(_MARKERS):
        return None
    (_, hb), (_, he), (_, lb), (_, le) = found
    return "\n".join(lines[hb + 1 : he]), "\n".join(lines[lb + 1 : le])


def _defines(text: str, name: str) -> bool:
    return re.search(rf"^[ \t]*def[ \t]+{name}[ \t]*\(", text, re.M) is not None


def _calls(text: str, name: str) -> bool:
    return re.search(rf"\b{name}[ \t]*\(", text) is not None


def is_rtde_control_script(text: str) -> bool:
    """Whether ``text`` is ur_rtde's control script, run here with its semantics.

    Uploaded on port 30003 it is ``def rtde_control(): ... end`` and is recognised, as it always
    was here, by that name. Fetched by the External Control URCap it has no ``def`` of its own
    and no such name: then the marked parts must show the script's protocol, a header defining
    ``rtde_cmd`` (reads the command register), ``signal_ready`` and ``process_cmd``, and a
    control loop that reads commands and hands them to ``process_cmd``.
    """
    if "rtde_control" in text:
        return True
    parts = split_external_control(text)
    if parts is None:
        return False
    header, loop = parts
    if not all(_defines(header, f) for f in ("rtde_cmd", "signal_ready", "process_cmd")):
        return False
    return _calls(loop, "rtde_cmd") and _calls(loop, "process_cmd")


def register_offset(text: str, kind: str) -> int:
    """``reg_offset_<kind>`` (``int`` or ``float``) assigned in the script; 0 when absent.

    ur_rtde 1.6.5 writes ``global reg_offset_int = # int register offset``, a newline, then the
    value (followed on that line by the next statement): the value may follow the ``=`` directly
    or after a comment that runs to the end of the line. ``==`` comparisons are not assignments.
    """
    m = re.search(rf"\breg_offset_{kind}[ \t]*=(?!=)[ \t]*(?:#[^\n]*)?\n?[ \t]*(\d+)", text)
    return int(m.group(1)) if m else 0


def _open_part(text: str) -> bool:
    """Whether a marked part of ``text`` was begun and not ended (or a marker is out of order)."""
    seq = [m for m, _ in _marker_positions(text.split("\n"))]
    closed = ([], [HEADER_BEGIN, HEADER_END], [LOOP_BEGINS, LOOP_ENDS], list(_MARKERS))
    return seq not in closed


def fetch_urcap_script(
    addr: tuple[str, int], timeout_s: float = URCAP_FETCH_TIMEOUT_S
) -> tuple[str | None, str]:
    """Request the script as the External Control URCap does; return ``(text, "ok")`` or
    ``(None, reason)``.

    Connect to the PC at ``addr`` (at most ``URCAP_CONNECT_TIMEOUT_S``), send
    ``request_program``, read lines until the ``# NODE_CONTROL_LOOP_ENDS`` line, or until the PC
    closes the connection with no marked part left open. The whole exchange is bounded by
    ``timeout_s`` (s), a line by ``MAX_URCAP_LINE`` and the text by ``MAX_URCAP_SCRIPT`` bytes.
    The connection is closed afterwards (the URCap closes its socket too).
    """
    deadline = time.monotonic() + timeout_s
    try:
        sock = socket.create_connection(addr, timeout=min(URCAP_CONNECT_TIMEOUT_S, timeout_s))
    except OSError as exc:
        return None, f"connect_failed:{type(exc).__name__}"
    lines: list[str] = []
    pending = b""
    total = 0
    try:
        sock.sendall(URCAP_REQUEST)
        while True:
            start = 0
            while (end := pending.find(b"\n", start)) >= 0:
                if end - start > MAX_URCAP_LINE:
                    return None, "line_too_long"
                line = pending[start:end].decode("utf-8", "replace").rstrip("\r")
                start = end + 1
                lines.append(line)
                if line.strip() == LOOP_ENDS:
                    text = "\n".join(lines) + "\n"
                    return (None, "incomplete") if _open_part(text) else (text, "ok")
            pending = pending[start:]
            if len(pending) > MAX_URCAP_LINE:
                return None, "line_too_long"
            left = deadline - time.monotonic()
            if left <= 0:
                return None, "timeout"
            sock.settimeout(left)
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                return None, "timeout"
            if not chunk:  # the PC closed the connection
                if pending:
                    lines.append(pending.decode("utf-8", "replace").rstrip("\r"))
                text = "\n".join(lines) + "\n"
                if not text.strip():
                    return None, "empty"
                return (None, "incomplete") if _open_part(text) else (text, "ok")
            total += len(chunk)
            if total > MAX_URCAP_SCRIPT:
                return None, "too_large"
            pending += chunk
    except OSError as exc:
        return None, f"connection_error:{type(exc).__name__}"
    finally:
        with contextlib.suppress(OSError):
            sock.close()


# ---------------------------------------------------------------------------------------------
# The controller: clock, registers, program state, watchdogs, truth log
# ---------------------------------------------------------------------------------------------


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
        self.speed_limits = _SPEED_LIMITS.get(family, _SPEED_LIMITS["UR10"])
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
        self.connections: list[RtdeConnection] = []
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


# ---------------------------------------------------------------------------------------------
# RTDE server
# ---------------------------------------------------------------------------------------------


def _fmt_for(types: list[str]) -> struct.Struct:
    return struct.Struct(">" + "".join(_TYPE_FMT[t] for t in types))


class _OutputRecipe:
    def __init__(self, rid: int, names: list[str], decim: int, ctl: Controller) -> None:
        self.rid = rid
        self.names = names
        self.decim = decim
        types = [OUTPUT_TYPES[n] for n in names]
        self.struct = _fmt_for(types)
        self.getters = [ctl.getter(n) for n in names]
        self.vector = [_TYPE_FMT[t][0].isdigit() for t in types]
        self.header = struct.pack(">HBB", 4 + self.struct.size, ord("U"), rid)

    def pack(self) -> bytes:
        vals: list[Any] = []
        for g, vec in zip(self.getters, self.vector, strict=True):
            v = g()
            if vec:
                vals.extend(v)
            else:
                vals.append(v)
        return self.header + self.struct.pack(*vals)


class RtdeConnection:
    """One RTDE client connection: served in its accept thread, with a bounded writer queue.

    Data packages that do not fit the queue (a client not reading, e.g. SIGSTOPped) are
    dropped and counted rather than buffered or allowed to block the controller.
    """

    def __init__(self, sock: socket.socket, ctl: Controller, server: RtdeServer) -> None:
        self.sock = sock
        self.ctl = ctl
        self.server = server
        self.outputs: list[_OutputRecipe] = []
        self.inputs: dict[int, tuple[list[str], struct.Struct, list[bool]]] = {}
        self.next_input_id = 1
        self.next_output_id = 1
        self.started = False
        self.closed = False
        self.queue: queue.Queue[bytes | None] = queue.Queue(maxsize=OUTPUT_QUEUE_PACKAGES)
        self.dropped = 0
        threading.Thread(target=self._writer, daemon=True).start()

    def publish(self, ctl: Controller) -> None:
        """Called by the controller each cycle; enqueue due data packages (drop if full)."""
        if not self.started or self.closed:
            return
        for rec in self.outputs:
            if ctl.cycle % rec.decim == 0:
                try:
                    self.queue.put_nowait(rec.pack())
                except queue.Full:
                    self.dropped += 1

    def _reply(self, ptype: str, payload: bytes) -> None:
        pkg = struct.pack(">HB", 3 + len(payload), ord(ptype)) + payload
        with contextlib.suppress(queue.Full):
            self.queue.put(pkg, timeout=1.0)

    def _writer(self) -> None:
        while True:
            pkg = self.queue.get()
            if pkg is None or self.closed:
                return
            try:
                self.sock.sendall(pkg)
            except OSError:
                self.close()
                return

    def _recv_exact(self, n: int) -> bytes | None:
        buf = b""
        while len(buf) < n:
            try:
                chunk = self.sock.recv(n - len(buf))
            except OSError:
                return None
            if not chunk:
                return None
            buf += chunk
        return buf

    def serve(self) -> None:
        """Read and handle packages until the connection ends (runs in the accept thread)."""
        try:
            while not self.closed:
                head = self._recv_exact(3)
                if head is None:
                    break
                size, ptype = struct.unpack(">HB", head)
                if size < 3 or size > MAX_RTDE_PACKAGE:
                    self.ctl.event("rtde_abuse", size=size)
                    break
                payload = self._recv_exact(size - 3) if size > 3 else b""
                if payload is None:
                    break
                if not self._handle(chr(ptype), payload):
                    break
        finally:
            self.close()

    def _handle(self, ptype: str, p: bytes) -> bool:
        ctl = self.ctl
        if ptype == "V":
            if len(p) != 2:
                return False
            (ver,) = struct.unpack(">H", p)
            self._reply("V", struct.pack(">B", 1 if ver == 2 else 0))
            return True
        if ptype == "v":
            self._reply("v", struct.pack(">IIII", *ctl.version))
            return True
        if ptype == "O":
            if len(p) < 8:
                return False
            (freq,) = struct.unpack(">d", p[:8])
            names = [n for n in p[8:].decode("ascii", "replace").split(",") if n]
            types = [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            ok = names and "NOT_FOUND" not in types and 0 < freq <= ctl.rate_hz
            rid = 0
            if self.next_output_id > MAX_RECIPES:
                ctl.event("rtde_abuse", reason="too_many_output_recipes")
                return False
            if ok:
                rid = self.next_output_id
                self.next_output_id += 1
                decim = max(1, round(ctl.rate_hz / freq))
                self.outputs.append(_OutputRecipe(rid, names, decim, ctl))
            ctl.event(
                "rtde_output_setup",
                frequency=freq,
                recipe=rid,
                fields=len(names),
                not_found="|".join(
                    n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"
                ),
            )
            self._reply("O", struct.pack(">B", rid) + ",".join(types).encode())
            return True
        if ptype == "I":
            names = [n for n in p.decode("ascii", "replace").split(",") if n]
            types = [INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            with ctl.lock:
                owners = self.server.owners
                for i, n in enumerate(names):
                    if types[i] != "NOT_FOUND" and owners.get(n, self) is not self:
                        types[i] = "IN_USE"
                ok = bool(names) and all(t not in ("NOT_FOUND", "IN_USE") for t in types)
                if ok:
                    for n in names:
                        owners[n] = self
            rid = 0
            if self.next_input_id > MAX_RECIPES:
                ctl.event("rtde_abuse", reason="too_many_input_recipes")
                return False
            if ok:
                rid = self.next_input_id
                self.next_input_id += 1
                real = [INPUT_TYPES[n] for n in names]
                self.inputs[rid] = (
                    names,
                    _fmt_for(real),
                    [_TYPE_FMT[t][0].isdigit() for t in real],
                )
                ctl.event("rtde_input_setup", recipe=rid, fields="|".join(names))
            else:
                ctl.event("rtde_input_refused", types="|".join(types))
            self._reply("I", struct.pack(">B", rid) + ",".join(types).encode())
            return True
        if ptype == "S":
            self.started = True
            self._reply("S", b"\x01")
            return True
        if ptype == "P":
            self.started = False
            self._reply("P", b"\x01")
            return True
        if ptype == "U":
            if not p:
                return False
            rec = self.inputs.get(p[0])
            if rec is None:
                return True  # unknown recipe id: ignored, as the controller does
            names, st, vec = rec
            if len(p) - 1 != st.size:
                ctl.event("rtde_abuse", reason="input_size")
                return False
            flat = list(st.unpack(p[1:]))
            values: list[Any] = []
            for is_vec in vec:
                if is_vec:
                    values.append(tuple(flat[:6]))
                    del flat[:6]
                else:
                    values.append(flat.pop(0))
            ctl.apply_inputs(names, values)
            return True
        if ptype == "M":
            return True  # text message from client: ignored
        ctl.event("rtde_abuse", reason=f"type_{ord(ptype)}")
        return False

    def close(self) -> None:
        """Close the socket and release input ownership."""
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(OSError):
            self.sock.close()
        with contextlib.suppress(queue.Full):
            self.queue.put_nowait(None)
        with self.ctl.lock:
            owners = self.server.owners
            for n in [n for n, o in owners.items() if o is self]:
                del owners[n]
            if self in self.ctl.connections:
                self.ctl.connections.remove(self)
        self.ctl.event("rtde_disconnected", dropped=self.dropped)


class RtdeServer:
    """Accepts RTDE connections."""

    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        self.owners: dict[str, RtdeConnection] = {}

    def on_accept(self, sock: socket.socket) -> None:
        """Register a new connection and serve it until it closes."""
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = RtdeConnection(sock, self.ctl, self)
        with self.ctl.lock:
            self.ctl.connections.append(conn)
        self.ctl.event("rtde_connected")
        conn.serve()


# ---------------------------------------------------------------------------------------------
# Dashboard and script servers
# ---------------------------------------------------------------------------------------------


_STATE_NAMES = {STOPPED: "STOPPED", PLAYING: "PLAYING", PAUSED: "PAUSED"}


def _dashboard_reply(ctl: Controller, line: str) -> str | None:
    """Answer one dashboard command; None closes the connection."""
    cmd = line.strip()
    low = cmd.lower()
    major, minor, bugfix, build = ctl.version
    if low == "polyscopeversion":
        return f"URSoftware {major}.{minor}.{bugfix}.{build} (Jan 01 2024)"
    if low == "version":
        return f"Version: {major}.{minor}.{bugfix}.{build}"
    if low == "get serial number":
        return "20215500" + f"{sum(map(ord, ctl.model)) % 10000:04d}"
    if low == "get robot model":
        return ctl.model.rstrip("eE")
    if low == "robotmode":
        return "Robotmode: RUNNING"
    if low == "safetymode":
        return "Safetymode: " + (
            "NORMAL" if ctl.safety_mode == SAFETY_NORMAL else "PROTECTIVE_STOP"
        )
    if low == "safetystatus":
        return "Safetystatus: " + (
            "NORMAL" if ctl.safety_mode == SAFETY_NORMAL else "PROTECTIVE_STOP"
        )
    if low == "programstate":
        name = posixpath.basename(ctl.loaded_urp) if ctl.loaded_urp else "<unnamed>"
        return f"{_STATE_NAMES[ctl.runtime_state]} {name}"
    if low == "running":
        return "Program running: " + ("true" if ctl.runtime_state == PLAYING else "false")
    if low == "is in remote control":
        return "true"
    if low == "get loaded program":
        return f"Loaded program: {ctl.loaded_urp}" if ctl.loaded_urp else "No program loaded"
    if low.startswith("load "):
        with ctl.dashboard_lock:
            return ctl.load_urp(cmd[5:].strip())
    if low == "stop":
        if ctl.runtime_state == STOPPED:
            return "Failed to execute: stop"
        ctl.program_stop("dashboard")
        return "Stopped"
    if low == "pause":
        if ctl.runtime_state != PLAYING:
            return "Failed to execute: pause"
        ctl.runtime_state = PAUSED
        ctl.arm.motion = StopMotion(ctl.stop_decel)
        return "Pausing program"
    if low == "play" and ctl.loaded_urp is not None:
        with ctl.dashboard_lock:
            return "Starting program" if ctl.play_urp() else "Failed to execute: play"
    if low == "play":
        if ctl.program_text is None:
            return "Failed to execute: play"
        ctl.load_program(ctl.program_text)
        return "Starting program"
    if low == "power on":
        return "Powering on"
    if low == "power off":
        return "Powering off"
    if low == "brake release":
        return "Brake releasing"
    if low == "unlock protective stop":
        ctl.safety_mode = SAFETY_NORMAL
        return "Protective stop releasing"
    if low == "close popup":
        return "closing popup"
    if low == "close safety popup":
        return "closing safety popup"
    if low == "quit":
        return None
    return f"could not understand: '{cmd}'"


def _serve_dashboard(sock: socket.socket, ctl: Controller) -> None:
    buf = b""
    try:
        sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
        while not ctl.stop_event.is_set():
            chunk = sock.recv(4096)
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                reply = _dashboard_reply(ctl, raw.decode("utf-8", "replace"))
                if reply is None:
                    sock.sendall(b"Disconnected\n")
                    return
                sock.sendall(reply.encode() + b"\n")
            if len(buf) > MAX_DASHBOARD_LINE:
                ctl.event("dashboard_abuse", buffered=len(buf))
                return
    except OSError:
        return
    finally:
        with contextlib.suppress(OSError):
            sock.close()


_PROGRAM_RE = re.compile(r"^(def|sec)\s+\w+\s*\(\s*\)\s*:.*?^end\s*$", re.M | re.S)


def _serve_script(sock: socket.socket, ctl: Controller) -> None:
    buf = ""
    try:
        while not ctl.stop_event.is_set():
            chunk = sock.recv(65536)
            if not chunk:
                return
            buf += chunk.decode("utf-8", "replace").replace("\r", "")
            if len(buf) > MAX_SCRIPT_BYTES:
                ctl.event("script_abuse", buffered=len(buf))
                return
            while True:
                m = _PROGRAM_RE.search(buf)
                if m is None:
                    break
                ctl.load_program(m.group(0))
                buf = buf[m.end() :]
    except OSError:
        return
    finally:
        with contextlib.suppress(OSError):
            sock.close()


def _listen(host: str, port: int) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind((host, port))
    s.listen(8)
    s.settimeout(0.2)
    return s


def _accept_loop(
    lsock: socket.socket, ctl: Controller, handle: Callable[[socket.socket], None]
) -> None:
    """Accept connections, each handled in a thread until it ends (at most MAX_CONNECTIONS)."""
    slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
    while not ctl.stop_event.is_set():
        try:
            sock, _ = lsock.accept()
        except TimeoutError:
            continue
        except OSError:
            return
        sock.settimeout(None)
        if not slots.acquire(blocking=False):
            ctl.event("connection_refused", port=lsock.getsockname()[1], limit=MAX_CONNECTIONS)
            sock.close()
            continue

        def run(sock: socket.socket = sock) -> None:
            try:
                handle(sock)
            finally:
                slots.release()

        threading.Thread(target=run, daemon=True).start()


def _parse_version(text: str) -> tuple[int, int, int, int]:
    parts = [int(x) for x in text.split(".")]
    while len(parts) < 3:
        parts.append(0)
    if len(parts) < 4:
        parts.append(108318 if parts[0] >= 4 else 1000)
    return parts[0], parts[1], parts[2], parts[3]


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--host", default="127.0.0.171", help="loopback address to listen on")
    ap.add_argument("--model", default="UR10")
    ap.add_argument("--version", default="5.11.1", help="PolyScope version, e.g. 5.11.1, 3.15.7")
    ap.add_argument("--truth", type=Path, default=None, help="CSV truth log to append to")
    ap.add_argument(
        "--stop-decel",
        type=float,
        default=3.0,
        help="program-stop deceleration, rad/s^2 (leading axis)",
    )
    ap.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        help="SCHED_FIFO priority of the controller cycle (Linux, needs the right; 0: normal)",
    )
    ap.add_argument(
        "--input-log",
        type=Path,
        default=None,
        help="CSV of every RTDE input package: arrival_s,intake_s,read_s (controller s: "
        "arrival, the boundary of the cycle that took it, when that cycle read the inputs)",
    )
    ap.add_argument(
        "--publish-delay",
        type=float,
        default=0.0,
        help="s from the cycle boundary to sending its state package (below one period; "
        "0: as soon as the cycle is computed)",
    )
    ap.add_argument(
        "--start-delay",
        type=float,
        default=0.1,
        help="s from script upload to runtime_state PLAYING",
    )
    ap.add_argument(
        "--servo-friction",
        type=float,
        default=0.0,
        help="Coulomb friction per unit inertia, rad/s^2: the actual joints follow the "
        "delayed reference through a PD position servo against friction (0: they are it)",
    )
    ap.add_argument(
        "--q0",
        default=",".join(str(q) for q in DEFAULT_Q0),
        help="initial joint positions, rad, comma separated",
    )
    ap.add_argument(
        "--urcap",
        default=DEFAULT_URCAP,
        metavar="HOST:PORT",
        help="where the External Control URCap's installation says the PC serves the script",
    )
    ap.add_argument(
        "--external-control-program",
        default=DEFAULT_EXTERNAL_CONTROL_PROGRAM,
        metavar="PATH",
        help="the installed pendant program holding the External Control node",
    )
    args = ap.parse_args(argv)
    q0 = [float(x) for x in args.q0.split(",")]
    if len(q0) != 6:
        ap.error("--q0 needs 6 values")
    urcap_host, _, urcap_port = args.urcap.rpartition(":")
    if not urcap_host or not urcap_port.isdigit() or not 0 < int(urcap_port) < 65536:
        ap.error(f"--urcap {args.urcap!r} is not HOST:PORT")
    ctl = Controller(
        args.model,
        _parse_version(args.version),
        args.truth,
        args.stop_decel,
        args.start_delay,
        q0,
        urcap=(urcap_host, int(urcap_port)),
        installed_program=args.external_control_program,
    )
    ctl.rt_priority = args.rt_priority
    if not 0.0 <= args.servo_friction < 100.0:
        ap.error(f"--servo-friction {args.servo_friction} outside [0, 100) rad/s^2")
    ctl.arm.friction = args.servo_friction
    if not 0 <= args.publish_delay < 1.0 / ctl.rate_hz:
        ap.error(f"--publish-delay {args.publish_delay} s outside [0, one period)")
    ctl.publish_delay_s = args.publish_delay
    if args.input_log is not None:
        # line-buffered: a reader sees every package up to the last cycle
        ctl.input_log = open(args.input_log, "a", encoding="ascii", buffering=1)  # noqa: SIM115
    rtde = RtdeServer(ctl)
    listeners = [
        (_listen(args.host, RTDE_PORT), rtde.on_accept),
        (_listen(args.host, DASHBOARD_PORT), lambda s: _serve_dashboard(s, ctl)),
        (_listen(args.host, SCRIPT_PORT), lambda s: _serve_script(s, ctl)),
    ]
    signal.signal(signal.SIGTERM, lambda *_: ctl.stop_event.set())
    signal.signal(signal.SIGINT, lambda *_: ctl.stop_event.set())
    threads = [
        threading.Thread(target=_accept_loop, args=(ls, ctl, h), daemon=True) for ls, h in listeners
    ]
    for t in threads:
        t.start()
    loop = threading.Thread(target=ctl.run, name="controller")
    ctl.t0 = time.monotonic()
    ctl.event("peer_started", rate_hz=ctl.rate_hz, t0_monotonic=f"{ctl.t0:.6f}")
    loop.start()
    print("ready", flush=True)
    while not ctl.stop_event.wait(0.05):
        pass
    loop.join(timeout=2.0)
    for ls, _ in listeners:
        with contextlib.suppress(OSError):
            ls.close()
    with ctl.lock:
        conns = list(ctl.connections)
    for c in conns:
        c.close()
    ctl.event("peer_exit")
    if ctl._truth is not None:
        ctl._truth.close()
    if ctl.input_log is not None:
        ctl.input_log.close()
    return 0


# ---------------------------------------------------------------------------------------------
# Helper for tests
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Truth:
    """The truth log as arrays: ``t`` (s, controller time), ``runtime_state``, ``q`` (N x 6,
    rad), ``qd`` (N x 6, rad/s)."""

    t: Any
    runtime_state: Any
    q: Any
    qd: Any

    def rest_time_after(self, t_from: float) -> float | None:
        """First controller time >= ``t_from`` (s) from which every later row has qd == 0."""
        import numpy as np

        moving = np.any(self.qd != 0.0, axis=1)
        idx = np.nonzero(moving)[0]
        last_moving = idx[-1] if idx.size else -1
        if last_moving == len(self.t) - 1:
            return None
        return max(float(self.t[last_moving + 1]), t_from)


@dataclasses.dataclass(frozen=True)
class PeerEvent:
    """An ``#event`` line: controller time (s), kind and key=value fields."""

    time_s: float
    kind: str
    fields: dict[str, str]


class PeerHandle:
    """A running peer subprocess; see :func:`run_peer`."""

    def __init__(
        self,
        host: str,
        model: str,
        version: str,
        truth_path: Path,
        process: subprocess.Popen[bytes],
    ) -> None:
        self.host = host
        self.model = model
        self.version = version
        self.truth_path = truth_path
        self.process = process
        self.rate_hz = 500.0 if int(version.split(".")[0]) >= 4 else 125.0
        self.period_s = 1.0 / self.rate_hz

    def _lines(self) -> list[str]:
        text = self.truth_path.read_text(encoding="ascii", errors="replace")
        lines = text.split("\n")
        return lines[:-1]  # the last element is "" or a partly written line

    def read_truth(self) -> Truth:
        """Parse the truth log written so far into numpy arrays."""
        import numpy as np

        rows = [ln for ln in self._lines() if ln and ln[0].isdigit()]
        if not rows:
            e = np.zeros((0, 6))
            return Truth(np.zeros(0), np.zeros(0, dtype=int), e, e.copy())
        arr = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", ndmin=2)
        return Truth(arr[:, 0], arr[:, 1].astype(int), arr[:, 2:8], arr[:, 8:14])

    def events(self, kind: str | None = None) -> list[PeerEvent]:
        """Events logged so far, optionally only those of ``kind``."""
        out = []
        for ln in self._lines():
            if not ln.startswith("#event,"):
                continue
            _, t, k, detail = ln.split(",", 3)
            if kind is not None and k != kind:
                continue
            fields = dict(kv.split("=", 1) for kv in detail.split(";") if "=" in kv)
            out.append(PeerEvent(float(t), k, fields))
        return out

    def _clock_segments(self) -> list[tuple[float, float]]:
        """(controller time s, t0_monotonic s) from the start and from each clock slip."""
        segs = []
        for ev in self.events():
            if ev.kind in ("peer_started", "clock_slip"):
                segs.append((ev.time_s, float(ev.fields["t0_monotonic"])))
        if not segs:
            raise RuntimeError("peer has not logged its clock origin")
        return segs

    def to_peer_time(self, monotonic_s: float) -> float:
        """Convert a ``time.monotonic()`` reading (this machine) to controller time in s.

        The controller runs cycle k at monotonic ``t0 + k * dt`` or later; if it was starved for
        more than 0.1 s it logs a ``clock_slip`` with a new ``t0`` (the skipped wall interval
        maps to the controller time of the slip).
        """
        segs = self._clock_segments()
        t = monotonic_s - segs[0][1]
        for t_slip, t0 in segs[1:]:
            if monotonic_s - t0 >= t_slip:
                t = monotonic_s - t0
            elif t >= t_slip:
                t = t_slip
            else:
                break
        return t

    def to_host_times(self, peer_s: list[float]) -> list[float]:
        """Convert controller times (s) to ``time.monotonic()`` on this machine: the inverse
        of :meth:`to_peer_time`, each time by the clock segment it falls in."""
        segs = self._clock_segments()
        out = []
        for t in peer_s:
            t0 = segs[0][1]
            for t_slip, t0_slip in segs[1:]:
                if t >= t_slip:
                    t0 = t0_slip
            out.append(t + t0)
        return out

    def wait_event(self, kind: str, timeout: float = 5.0, after: float = -1.0) -> PeerEvent:
        """Wait (s) for an event of ``kind`` at controller time > ``after``."""
        end = time.monotonic() + timeout
        while True:
            for ev in self.events(kind):
                if ev.time_s > after:
                    return ev
            if time.monotonic() > end:
                raise TimeoutError(f"no {kind} event within {timeout} s")
            time.sleep(0.02)

    def wait_truth_until(self, t_peer: float, timeout: float = 5.0) -> Truth:
        """Wait until the truth log covers controller time ``t_peer`` (s); return it."""
        end = time.monotonic() + timeout
        while True:
            tr = self.read_truth()
            if len(tr.t) and tr.t[-1] >= t_peer:
                return tr
            if time.monotonic() > end:
                raise TimeoutError(f"truth log did not reach {t_peer} s")
            time.sleep(0.02)

    def stop(self, timeout: float = 5.0) -> int:
        """SIGTERM the peer and wait for it (s); returns its exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout)
        return int(self.process.returncode)


@contextlib.contextmanager
def run_peer(
    host: str,
    model: str = "UR10",
    version: str = "5.11.1",
    truth_path: str | os.PathLike[str] | None = None,
    extra_args: tuple[str, ...] = (),
    startup_timeout: float = 10.0,
) -> Iterator[PeerHandle]:
    """Start the peer on ``host`` in a subprocess; yield a :class:`PeerHandle`; stop it after.

    ``truth_path`` defaults to a temporary file removed afterwards. ``startup_timeout`` in s.
    """
    tmpdir = None
    if truth_path is None:
        tmpdir = tempfile.TemporaryDirectory(prefix="ur_peer_")
        path = Path(tmpdir.name) / "truth.csv"
    else:
        path = Path(truth_path)
    cmd = [
        sys.executable,
        "-S",  # the peer needs only the standard library; skip site-packages start-up cost
        str(Path(__file__).resolve()),
        "--host",
        host,
        "--model",
        model,
        "--version",
        version,
        "--truth",
        str(path),
        *extra_args,
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    handle = PeerHandle(host, model, version, path, proc)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], startup_timeout)
        line = proc.stdout.readline() if ready else b""
        if line.strip() != b"ready":
            proc.kill()
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"peer on {host} did not start: {line!r} {err}")
        yield handle
    finally:
        handle.stop()
        if tmpdir is not None:
            tmpdir.cleanup()


if __name__ == "__main__":
    sys.exit(main())
