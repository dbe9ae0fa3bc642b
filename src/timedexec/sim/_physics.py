"""Joint physics: a bank of independent single-axis drives, vectorised.

Each element is one joint: link-side inertia ``J``, gravity torque ``A cos x + B sin x``
(exact for a revolute joint whose neighbours are held), a PI velocity loop with gravity
feed-forward tuned for the nominal inertia, a first-order current loop with a torque limit,
and friction with breakaway (static friction above kinetic, Karnopp-style stick at velocity
reversal). The batch sweep puts one element per trial; the stepped controller one per
joint. Integration is semi-implicit Euler on a fixed step; the current loop is discretised
exactly.

Delays are not put in: a stuck joint starts to move only when its velocity loop has built
enough torque beyond gravity to break away, so the onset emerges from gravity load,
friction, inertia and gains.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from timedexec.effects import EffectSet
from timedexec.robots import RobotSpec, gravity_torque_coefficients, joint_inertia

if TYPE_CHECKING:
    from timedexec.sim._settings import SimSettings

__all__ = ["JointBank", "JointParams", "joint_params", "pulse_derivative", "pulse_profile"]

FloatArray = NDArray[np.float64]


@dataclass(kw_only=True)
class JointParams:
    """Per-element physical parameters, each an array of shape (n,).

    Attributes
    ----------
    inertia_kgm2 : true reflected inertia, kg·m².
    inertia_nominal_kgm2 : inertia the velocity loop is tuned for, kg·m².
    grav_a_nm, grav_b_nm : holding torque ``A cos x + B sin x`` at joint angle x, N·m.
    breakaway_pos_nm, breakaway_neg_nm : static friction for motion in +/-, N·m.
    kinetic_pos_nm, kinetic_neg_nm : kinetic friction for motion in +/-, N·m.
    viscous_nms : viscous friction, N·m·s/rad.
    torque_max_nm : motor torque limit at the joint, N·m.
    bandwidth_hz : velocity-loop bandwidth, Hz.
    integral_ratio : proportional/integral corner ratio (scalar or (n,)).
    current_time_constant_s : current-loop time constant, s.
    """

    inertia_kgm2: FloatArray
    inertia_nominal_kgm2: FloatArray
    grav_a_nm: FloatArray
    grav_b_nm: FloatArray
    breakaway_pos_nm: FloatArray
    breakaway_neg_nm: FloatArray
    kinetic_pos_nm: FloatArray
    kinetic_neg_nm: FloatArray
    viscous_nms: FloatArray
    torque_max_nm: FloatArray
    bandwidth_hz: FloatArray
    integral_ratio: float | FloatArray
    current_time_constant_s: float | FloatArray


class JointBank:
    """State and one-step integration of ``n`` independent joints.

    Parameters
    ----------
    params : JointParams
        Arrays of shape (n,).
    q0_rad : array, shape (n,)
        Start angles, rad. The joints start at rest, holding gravity, stuck.
    dt_s : float
        Integration step, s.
    onset_threshold_rad_s : float
        Speed at which a joint counts as moving for :attr:`onset_s` (ground truth).
    """

    def __init__(
        self, params: JointParams, q0_rad: FloatArray, dt_s: float, onset_threshold_rad_s: float
    ) -> None:
        self.dt_s = float(dt_s)
        n = np.shape(q0_rad)[0]
        self.q = np.array(q0_rad, dtype=float, copy=True)
        self.v = np.zeros(n)
        self.tau_m = params.grav_a_nm * np.cos(self.q) + params.grav_b_nm * np.sin(self.q)
        self.integ = np.zeros(n)
        self.stuck = np.ones(n, dtype=bool)
        self.set_params(params)
        self.threshold = float(onset_threshold_rad_s)
        self.onset_s = np.full(n, np.nan)
        self._armed = np.zeros(n, dtype=bool)

    def set_params(self, params: JointParams) -> None:
        """Replace the physical parameters (e.g. as the pose changes); the state is kept."""
        p = params
        self.p = p
        omega = 2.0 * np.pi * np.asarray(p.bandwidth_hz, dtype=float)
        self.kp = np.asarray(p.inertia_nominal_kgm2, dtype=float) * omega
        self.ki = self.kp * omega / np.asarray(p.integral_ratio, dtype=float)
        self.alpha = 1.0 - np.exp(-self.dt_s / np.asarray(p.current_time_constant_s, dtype=float))
        self.inv_j = 1.0 / np.asarray(p.inertia_kgm2, dtype=float)

    def arm_onset(self, mask: NDArray[np.bool_]) -> None:
        """Start watching the elements in ``mask`` for their next motion onset."""
        self.onset_s[mask] = np.nan
        self._armed |= mask

    def step(self, v_ref_rad_s: FloatArray, t_s: float | FloatArray) -> None:
        """Advance one step with velocity reference ``v_ref_rad_s`` (n,); ``t_s`` is the time
        at the start of the step (scalar or (n,)), used to time-stamp onsets."""
        p, dt = self.p, self.dt_s
        q, v = self.q, self.v
        cq, sq = np.cos(q), np.sin(q)
        tau_g = p.grav_a_nm * cq + p.grav_b_nm * sq
        err = v_ref_rad_s - v
        integ_new = self.integ + err * dt
        tau_cmd = tau_g + self.kp * err + self.ki * integ_new
        limited = np.clip(tau_cmd, -p.torque_max_nm, p.torque_max_nm)
        # Conditional integration (anti-windup): keep the integrator where the limit binds.
        self.integ = np.where(limited == tau_cmd, integ_new, self.integ)
        self.tau_m += self.alpha * (limited - self.tau_m)
        net = self.tau_m - tau_g
        # Breakaway: a stuck joint starts when the net torque beats static friction.
        breaks = self.stuck & ((net > p.breakaway_pos_nm) | (net < -p.breakaway_neg_nm))
        moving = ~self.stuck | breaks
        direction = np.where(v != 0.0, np.sign(v), np.sign(net))
        friction = np.where(direction > 0, p.kinetic_pos_nm, -p.kinetic_neg_nm) + p.viscous_nms * v
        acc = (net - friction) * self.inv_j
        v_new = np.where(moving, v + acc * dt, 0.0)
        # Stick at a velocity reversal: the joint stops and must break away again.
        reversal = moving & (v_new * direction < 0.0)
        # Coming to rest without a reversal (the loop settles asymptotically): stick once the
        # speed is negligible and the drive torque cannot break the joint free again.
        settled = (
            moving
            & (np.abs(v_new) < 1e-7)
            & (net <= p.breakaway_pos_nm)
            & (net >= -p.breakaway_neg_nm)
        )
        reversal |= settled
        v_new = np.where(reversal, 0.0, v_new)
        self.stuck = np.where(moving, reversal, self.stuck)
        self.q = q + 0.5 * (v + v_new) * dt
        if self._armed.any():
            crossed = self._armed & (np.abs(v_new) >= self.threshold)
            if crossed.any():
                a0, a1 = np.abs(v[crossed]), np.abs(v_new[crossed])
                frac = (self.threshold - a0) / np.maximum(a1 - a0, 1e-300)
                t0 = np.broadcast_to(np.asarray(t_s, dtype=float), v.shape)[crossed]
                self.onset_s[crossed] = t0 + np.clip(frac, 0.0, 1.0) * dt
                self._armed &= ~crossed
        self.v = v_new


def pulse_profile(
    t_s: FloatArray | float,
    *,
    speed_rad_s: float,
    acceleration_rad_s2: float,
    hold_s: float,
    pause_s: float,
    out_only: bool = False,
) -> FloatArray:
    """The calibration motion's commanded speed, out and back, for direction +1.

    Parameters
    ----------
    t_s : array
        Time since the motion started, s (negative: before it).
    speed_rad_s, acceleration_rad_s2, hold_s, pause_s : float
        See :class:`~timedexec.sim.TrialProfile`.
    out_only : bool
        Only the out pulse (the template the delay fit aligns).

    Returns
    -------
    ndarray
        Commanded joint speed, rad/s, same shape as ``t_s``: a trapezoid up to
        ``speed_rad_s`` and back to 0, then after ``pause_s`` its mirror image.
    """
    t = np.asarray(t_s, dtype=float)
    pulse = 2.0 * speed_rad_s / acceleration_rad_s2 + hold_s

    def trapezoid(x: FloatArray) -> FloatArray:
        ramp = np.minimum(acceleration_rad_s2 * x, acceleration_rad_s2 * (pulse - x))
        return np.clip(ramp, 0.0, speed_rad_s)

    if out_only:
        return trapezoid(t)
    return trapezoid(t) - trapezoid(t - pulse - pause_s)


def pulse_derivative(
    t_s: FloatArray | float,
    *,
    speed_rad_s: float,
    acceleration_rad_s2: float,
    hold_s: float,
    pause_s: float,
    out_only: bool = False,
) -> FloatArray:
    """Time derivative of :func:`pulse_profile` (commanded acceleration), rad/s²."""
    t = np.asarray(t_s, dtype=float)
    ramp = speed_rad_s / acceleration_rad_s2
    pulse = 2.0 * ramp + hold_s

    def d_trapezoid(x: FloatArray) -> FloatArray:
        up = (x > 0) & (x < ramp)
        down = (x > pulse - ramp) & (x < pulse)
        return np.where(up, acceleration_rad_s2, 0.0) - np.where(down, acceleration_rad_s2, 0.0)

    if out_only:
        return d_trapezoid(t)
    return d_trapezoid(t) - d_trapezoid(t - pulse - pause_s)


def joint_params(
    spec: RobotSpec,
    settings: SimSettings,
    effects: EffectSet,
    q_start: FloatArray,
    joint: NDArray[np.int64],
    t0_s: FloatArray,
) -> tuple[JointParams, FloatArray, FloatArray]:
    """Physical parameters of joint ``joint[i]`` (1-based) at configuration ``q_start[i]``.

    Applies the friction and inertia effects of ``effects``. ``t0_s`` is the time since the
    sweep (or the controller) started, for ``thermal_drift``. Returns the parameters, the
    holding torque at the start pose (N·m) and the true inertia (kg·m²), each (n,).
    """
    n = len(joint)
    rows = np.arange(n)
    col = joint - 1
    q_j = q_start[rows, col]
    a_nm, b_nm = gravity_torque_coefficients(spec, q_start, joint)
    tau_g = a_nm * np.cos(q_j) + b_nm * np.sin(q_j)
    rotor = np.asarray(spec.rotor_inertia_kgm2)[col]
    j_true_full = joint_inertia(spec, q_start)[rows, col]
    home = np.broadcast_to(np.asarray(spec.home_q_rad, dtype=float), (1, 6))
    j_nominal = joint_inertia(spec, home)[0][col]
    inertia = effects.get("inertia")
    if inertia is not None:
        j_true = rotor + inertia.scale * (j_true_full - rotor)  # type: ignore[attr-defined]
    else:
        j_true = j_nominal.copy()

    servo = settings.servo
    base = np.asarray(servo.breakaway_nm)[col]
    thermal = effects.get("thermal_drift")
    factor = thermal.friction_factor(t0_s) if thermal is not None else np.ones(n)  # type: ignore[attr-defined]
    f_pos = base.copy()
    f_neg = base.copy()
    load = effects.get("gravity_load")
    if load is not None:
        extra = load.friction_per_load * np.abs(tau_g)  # type: ignore[attr-defined]
        f_pos += extra
        f_neg += extra
    gdir = effects.get("gravity_direction")
    if gdir is not None:
        k = gdir.friction_per_load  # type: ignore[attr-defined]
        f_pos += k * tau_g  # moving in + against a positive holding torque lifts the load
        f_neg -= k * tau_g
    f_pos = np.maximum(f_pos, 0.2 * base)
    f_neg = np.maximum(f_neg, 0.2 * base)
    direction = effects.get("direction")
    if direction is not None:
        asym = np.asarray(direction.asymmetry)[col]  # type: ignore[attr-defined]
        f_pos *= 1.0 + asym
        f_neg *= 1.0 - asym
    f_pos *= factor
    f_neg *= factor
    # The drive schedules its gains on part of the pose-dependent inertia.
    j_tuned = j_nominal + settings.servo.inertia_scheduling * (j_true - j_nominal)
    params = JointParams(
        inertia_kgm2=j_true,
        inertia_nominal_kgm2=j_tuned,
        grav_a_nm=a_nm,
        grav_b_nm=b_nm,
        breakaway_pos_nm=f_pos,
        breakaway_neg_nm=f_neg,
        kinetic_pos_nm=servo.kinetic_ratio * f_pos,
        kinetic_neg_nm=servo.kinetic_ratio * f_neg,
        viscous_nms=np.asarray(servo.viscous_nms)[col] * factor,
        torque_max_nm=np.asarray(spec.torque_max_nm)[col],
        bandwidth_hz=np.asarray(servo.bandwidth_hz)[col],
        integral_ratio=servo.integral_ratio,
        current_time_constant_s=servo.current_time_constant_s,
    )
    return params, tau_g, j_true
