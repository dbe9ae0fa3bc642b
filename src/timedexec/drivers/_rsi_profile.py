"""The speedj velocity profile of the KUKA RSI driver, integrated per controller cycle.

:class:`SpeedProfile` turns :class:`SpeedCommand` (speedj / stop) into an absolute joint
correction, one controller cycle per received frame: every joint ramps towards its target
speed (the leading axis at the command's acceleration, the others scaled to arrive
together), holds for the command's duration, ramps down; it brakes at the spec's
acceleration limit before a joint or correction limit and clamps as a last resort. See
:mod:`timedexec.drivers._rsi` for the conventions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from timedexec._types import FloatArray
from timedexec.robots import RobotSpec

__all__ = ["SpeedCommand", "SpeedProfile"]


_LIMIT_MARGIN_RAD = math.radians(0.5)  # stay this far inside the joint position limits


@dataclass
class SpeedCommand:
    kind: str
    qd: FloatArray
    accel: float
    duration_s: float
    call_host_s: float
    index: int


class SpeedProfile:
    """speedj velocity profile integrated per controller cycle (absolute correction, rad)."""

    def __init__(self, spec: RobotSpec, max_correction_rad: FloatArray) -> None:
        self.qd_max = np.asarray(spec.qd_max_rad_s, dtype=np.float64)
        self.qdd_max = np.asarray(spec.qdd_max_rad_s2, dtype=np.float64)
        self.q_min = np.asarray(spec.q_min_rad, dtype=np.float64) + _LIMIT_MARGIN_RAD
        self.q_max = np.asarray(spec.q_max_rad, dtype=np.float64) - _LIMIT_MARGIN_RAD
        self.max_corr = max_correction_rad
        self.reset(np.zeros(6))

    def reset(self, q_start: FloatArray) -> None:
        self.q_start = q_start.copy()
        # Allowed correction interval: joint limits and the RSI correction limit together.
        self.lo = np.maximum(self.q_min - q_start, -self.max_corr)
        self.hi = np.minimum(self.q_max - q_start, self.max_corr)
        self.corr = np.zeros(6)
        self.v = np.zeros(6)
        self.target = np.zeros(6)
        self.rate = np.zeros(6)  # per-joint |acceleration| towards target, rad/s²
        self.accel = 0.0
        self.hold_s = math.inf
        self.moving_command = False

    @staticmethod
    def _scaled_rates(delta: FloatArray, accel: float) -> FloatArray:
        lead = float(np.max(np.abs(delta)))
        if lead <= 0.0:
            return np.full(6, accel)
        return accel * np.abs(delta) / lead

    def apply(self, cmd: SpeedCommand) -> None:
        self.target = cmd.qd.copy()
        self.accel = cmd.accel
        self.rate = self._scaled_rates(self.target - self.v, cmd.accel)
        self.hold_s = cmd.duration_s
        self.moving_command = cmd.kind == "speedj"

    def step(self, dt: float) -> bool:
        """Advance one cycle; return True if a limit held the correction this cycle."""
        if self.moving_command and self.hold_s <= 1e-9:  # 1 ns: float residue of -= dt
            # Hold time over: ramp down, leading axis at the command's acceleration.
            self.target = np.zeros(6)
            self.rate = self._scaled_rates(self.v, self.accel)
            self.moving_command = False
        self.hold_s -= dt
        target = self.target
        # Brake before a limit: stopping distance at the spec's acceleration limit.
        v = self.v
        stop_dist = v * v / (2.0 * self.qdd_max) + np.abs(v) * dt
        braking = ((v > 0) & (self.corr + stop_dist >= self.hi)) | (
            (v < 0) & (self.corr - stop_dist <= self.lo)
        )
        toward = ((target > 0) & (self.corr >= self.hi)) | ((target < 0) & (self.corr <= self.lo))
        limited = braking | toward
        rate = self.rate
        if np.any(limited):
            target = np.where(limited, 0.0, target)
            rate = np.where(braking, self.qdd_max, rate)
        step = np.clip(target - v, -rate * dt, rate * dt)
        v_new = v + step
        corr = self.corr + 0.5 * (v + v_new) * dt
        clamped = (corr > self.hi) | (corr < self.lo)
        if np.any(clamped):
            corr = np.clip(corr, self.lo, self.hi)
            v_new = np.where(clamped, 0.0, v_new)
        self.corr = corr
        self.v = v_new
        return bool(np.any(limited | clamped))
