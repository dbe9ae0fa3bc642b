"""The arm: per joint a reference velocity and a fixed actuation pipeline, the motions
(speedj, stopj, movej, servoj) that generate the reference, speed limits per model and, with
friction, a PD position servo against Coulomb and viscous friction.
"""

from __future__ import annotations

import math
from collections import deque

from .constants import PIPELINE_CYCLES

# Joint speed limits in rad/s per model family (UR data sheets: base/shoulder of the big arms
# 120 deg/s, the others 180 deg/s; UR3 wrists 360 deg/s).
SPEED_LIMITS = {
    "UR3": (math.pi,) * 3 + (2 * math.pi,) * 3,
    "UR5": (math.pi,) * 6,
    "UR10": (2.0944, 2.0944) + (math.pi,) * 4,
    "UR16": (2.0944, 2.0944) + (math.pi,) * 4,
}
JOINT_POSITION_LIMIT = 2 * math.pi  # rad, +-360 deg on every joint of these models
DEFAULT_Q0 = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)  # rad


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
