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

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.effects import EffectSet, Pose
from timedexec.robots import RobotSpec, gravity_torque_coefficients, joint_inertia
from timedexec.sim._drive import _drive_step

if TYPE_CHECKING:
    from timedexec.sim._settings import SimSettings

__all__ = [
    "JointBank",
    "JointChain",
    "JointParams",
    "drive_delay_s",
    "joint_params",
    "pulse_derivative",
    "pulse_profile",
    "response_delay_s",
]


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


class _Coefficients(NamedTuple):
    """The step's constants, per element: arrays of shape (n,) or floats (one joint)."""

    grav_a: Any
    grav_b: Any
    kp: Any
    ki: Any
    alpha: Any
    inv_j: Any
    torque_max: Any
    breakaway_pos: Any
    breakaway_neg: Any
    kinetic_pos: Any
    kinetic_neg: Any
    viscous: Any


def _coefficients(params: JointParams, dt_s: float) -> _Coefficients:
    """Loop gains and friction constants of ``params`` as float arrays of shape (n,)."""
    f = lambda x: np.asarray(x, dtype=float)  # noqa: E731
    omega = 2.0 * np.pi * f(params.bandwidth_hz)
    kp = f(params.inertia_nominal_kgm2) * omega
    return _Coefficients(
        grav_a=f(params.grav_a_nm),
        grav_b=f(params.grav_b_nm),
        kp=kp,
        ki=kp * omega / f(params.integral_ratio),
        alpha=1.0 - np.exp(-dt_s / f(params.current_time_constant_s)),
        inv_j=1.0 / f(params.inertia_kgm2),
        torque_max=f(params.torque_max_nm),
        breakaway_pos=f(params.breakaway_pos_nm),
        breakaway_neg=f(params.breakaway_neg_nm),
        kinetic_pos=f(params.kinetic_pos_nm),
        kinetic_neg=f(params.kinetic_neg_nm),
        viscous=f(params.viscous_nms),
    )


def _raise_interrupt_inside(exc: BaseException) -> None:
    """Raise the KeyboardInterrupt (or SystemExit) at the root of ``exc``'s causes, if any.

    A Ctrl-C that lands while Numba's first call of a kernel in a process loads its cached
    constants surfaces as a chain of ``SystemError("... returned a result with an exception
    set")`` whose root cause is the KeyboardInterrupt (seen once in `simulate`'s Ctrl-C
    test: a traceback and exit 1 instead of exit 130 and the resume command)."""
    root: BaseException = exc
    while root.__cause__ is not None:
        root = root.__cause__
    if isinstance(root, KeyboardInterrupt | SystemExit):
        raise root.with_traceback(None) from None


@functools.cache
def _bank_step() -> Any:
    """The compiled bank step (:mod:`timedexec.sim._kernel`), imported on first use: Numba
    and the compiled code load only in processes that step a bank (~0.3 s import, ~0.6 s
    to load the cached machine code, ~2 s to compile it the first time on a machine)."""
    from timedexec.sim._kernel import bank_step

    return bank_step


def _crossing_time(v, v_new, t_s, threshold: float, dt: float):  # type: ignore[no-untyped-def]
    """When within a step that started at ``t_s`` the speed crossed ``threshold`` (linear);
    arrays (a bank) or floats (a chain: numpy's scalars give the same bits)."""
    a0, a1 = abs(v), abs(v_new)
    frac = (threshold - a0) / np.maximum(a1 - a0, 1e-300)
    return t_s + np.clip(frac, 0.0, 1.0) * dt


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
        self.p = params
        self._c = _coefficients(params, self.dt_s)
        n = self.q.shape[0]
        self._c_arrays = np.array([np.broadcast_to(f, (n,)) for f in self._c], dtype=np.float64)

    def arm_onset(self, mask: NDArray[np.bool_]) -> None:
        """Start watching the elements in ``mask`` for their next motion onset."""
        self.onset_s[mask] = np.nan
        self._armed |= mask

    def step(self, v_ref_rad_s: FloatArray, t_s: float | FloatArray) -> None:
        """Advance one step with velocity reference ``v_ref_rad_s`` (n,); ``t_s`` is the time
        at the start of the step (scalar or (n,)), used to time-stamp onsets."""
        v = self.v
        v_ref = v_ref_rad_s
        if not (
            isinstance(v_ref, np.ndarray) and v_ref.shape == v.shape and v_ref.dtype == np.float64
        ):
            v_ref = np.ascontiguousarray(np.broadcast_to(v_ref, v.shape), dtype=np.float64)
        try:
            self.q, v_new, self.tau_m, self.integ, self.stuck = _bank_step()(
                self._c_arrays, self.dt_s, self.q, v, self.tau_m, self.integ, self.stuck, v_ref
            )
        except SystemError as exc:
            _raise_interrupt_inside(exc)
            raise
        if self._armed.any():
            crossed = self._armed & (np.abs(v_new) >= self.threshold)
            if crossed.any():
                t0 = np.broadcast_to(np.asarray(t_s, dtype=float), v.shape)[crossed]
                self.onset_s[crossed] = _crossing_time(
                    v[crossed], v_new[crossed], t0, self.threshold, self.dt_s
                )
                self._armed &= ~crossed
        self.v = v_new


class JointChain:
    """The joints of one arm stepped one joint at a time in floats: the stepped controller's
    bank. Same physics and bit-identical results as :class:`JointBank` (one code path,
    :func:`_drive_step`), at a fraction of its cost for six joints, and a joint at rest
    whose last step changed nothing is not stepped again until its input or parameters
    change (the step is a pure function of them: skipping it is exact).

    Parameters are those of :class:`JointBank`. :attr:`q`, :attr:`v`, :attr:`stuck` and
    :attr:`onset_s` read as arrays of shape (n,).
    """

    def __init__(
        self, params: JointParams, q0_rad: FloatArray, dt_s: float, onset_threshold_rad_s: float
    ) -> None:
        self.dt_s = float(dt_s)
        q0 = np.asarray(q0_rad, dtype=float)
        n = q0.shape[0]
        self._q = [float(x) for x in q0]
        self._v = [0.0] * n
        tau = params.grav_a_nm * np.cos(q0) + params.grav_b_nm * np.sin(q0)
        self._tau_m = [float(x) for x in tau]
        self._integ = [0.0] * n
        self._stuck = [True] * n
        self._onset = [math.nan] * n
        self._armed = [False] * n
        self._rest = [False] * n  # the last step, with zero input, changed nothing
        self.threshold = float(onset_threshold_rad_s)
        self.set_params(params)

    q = property(lambda self: np.array(self._q), doc="Joint angles, rad, (n,).")
    v = property(lambda self: np.array(self._v), doc="Joint speeds, rad/s, (n,).")
    stuck = property(lambda self: np.array(self._stuck), doc="Joints held by static friction.")
    onset_s = property(lambda self: np.array(self._onset), doc="Last armed onset per joint, s.")

    def set_params(self, params: JointParams) -> None:
        """Replace the physical parameters (e.g. as the pose changes); the state is kept."""
        self.p = params
        c = _coefficients(params, self.dt_s)
        n = len(self._q)
        columns = [
            [float(f)] * n if np.ndim(f) == 0 else np.broadcast_to(f, (n,)).tolist() for f in c
        ]
        self._c = [_Coefficients(*(col[j] for col in columns)) for j in range(n)]
        self._rest = [False] * len(self._q)

    def arm_onset(self, mask: NDArray[np.bool_]) -> None:
        """Start watching the joints in ``mask`` for their next motion onset."""
        for j in np.flatnonzero(mask):
            self._onset[j] = math.nan
            self._armed[j] = True

    def angle(self, j: int) -> float:
        """Joint ``j``'s angle, rad."""
        return self._q[j]

    def step_joint(self, j: int, v_ref_rad_s: float, t_s: float) -> float:
        """Advance joint ``j`` one step with speed reference ``v_ref_rad_s``; returns its
        speed at the end of the step, rad/s."""
        v = self._v[j]
        if v_ref_rad_s == 0.0 and self._rest[j]:
            return v
        q, tau_m, integ, stuck = self._q[j], self._tau_m[j], self._integ[j], self._stuck[j]
        q_new, v_new, tau_new, integ_new, stuck_new = _drive_step(
            *self._c[j], self.dt_s, q, v, tau_m, integ, stuck, v_ref_rad_s
        )
        self._rest[j] = v_ref_rad_s == 0.0 and (q_new, v_new, tau_new, integ_new, stuck_new) == (
            q,
            v,
            tau_m,
            integ,
            stuck,
        )
        if self._armed[j] and abs(v_new) >= self.threshold:
            self._onset[j] = float(_crossing_time(v, v_new, t_s, self.threshold, self.dt_s))
            self._armed[j] = False
        self._q[j], self._v[j], self._tau_m[j] = q_new, v_new, tau_new
        self._integ[j], self._stuck[j] = integ_new, stuck_new
        return v_new

    def step(self, v_ref_rad_s: ArrayLike, t_s: float) -> None:
        """Advance every joint one step (the :class:`JointBank` interface)."""
        for j, v_ref in enumerate(np.asarray(v_ref_rad_s, dtype=float)):
            self.step_joint(j, float(v_ref), float(t_s))


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


@functools.lru_cache(maxsize=16)
def _nominal_inertia(spec: RobotSpec) -> FloatArray:
    """Each joint's inertia at the robot's home pose, kg·m² (6,), read-only: the pose the
    drives' gains are tuned for (constant; a stepped controller's parameter refresh
    recomputed it each time)."""
    home = np.asarray(spec.home_q_rad, dtype=float)[None, :]
    out = joint_inertia(spec, home)[0]
    out.setflags(write=False)
    return out


def joint_params(
    spec: RobotSpec,
    settings: SimSettings,
    effects: EffectSet,
    q_start: FloatArray,
    joint: NDArray[np.int64],
    t0_s: FloatArray,
) -> tuple[JointParams, FloatArray, FloatArray]:
    """Physical parameters of joint ``joint[i]`` (1-based) at configuration ``q_start[i]``.

    Asks every effect of ``effects`` for its physics (the hooks of
    :class:`timedexec.effects.Effect`, in this order): changes of the arm's mass model, the
    inertia that acts instead of the nominal one, breakaway torque added (the sum floored at
    a fifth of the drive's base breakaway), then scaled, and the viscous friction's factor.
    ``t0_s`` is the time since the sweep (or the controller) started. Returns the
    parameters, the holding torque at the start pose (N·m) and the true inertia (kg·m²),
    each (n,).
    """
    pose = Pose(spec=spec, q_start_rad=q_start, joint=joint, t_start_s=t0_s)
    n = len(joint)
    rows = np.arange(n)
    col = joint - 1
    q_j = q_start[rows, col]
    a_nm, b_nm = gravity_torque_coefficients(spec, q_start, joint)
    extra_inertia = None
    for e in effects:
        mass = e.mass_change(pose)
        if mass is not None:
            a_nm = a_nm + mass.grav_a_nm
            b_nm = b_nm + mass.grav_b_nm
            extra_inertia = mass.inertia_kgm2 + (0.0 if extra_inertia is None else extra_inertia)
    tau_g = a_nm * np.cos(q_j) + b_nm * np.sin(q_j)
    j_nominal = _nominal_inertia(spec)[col]
    j_true = None
    for e in effects:
        acting = e.acting_inertia_kgm2(pose)
        if acting is not None:
            j_true = acting
    j_true = j_nominal.copy() if j_true is None else j_true
    if extra_inertia is not None:
        j_true = j_true + extra_inertia

    servo = settings.servo
    base = np.asarray(servo.breakaway_nm)[col]
    f_pos = base.copy()
    f_neg = base.copy()
    for e in effects:
        added = e.breakaway_extra_nm(pose, tau_g)
        if added is not None:
            f_pos += added[0]
            f_neg += added[1]
    f_pos = np.maximum(f_pos, 0.2 * base)
    f_neg = np.maximum(f_neg, 0.2 * base)
    viscous = np.asarray(servo.viscous_nms)[col]
    for e in effects:
        factors = e.breakaway_factors(pose)
        if factors is not None:
            f_pos *= factors[0]
            f_neg *= factors[1]
        factor = e.viscous_factor(pose)
        if factor is not None:
            viscous = viscous * factor
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
        viscous_nms=viscous,
        torque_max_nm=np.asarray(spec.torque_max_nm)[col],
        bandwidth_hz=np.asarray(servo.bandwidth_hz)[col],
        integral_ratio=servo.integral_ratio,
        current_time_constant_s=servo.current_time_constant_s,
    )
    return params, tau_g, j_true


def drive_delay_s(effects: EffectSet, pose: Pose) -> FloatArray | float:
    """The effects' dead time between the interpolator's reference and each drive at
    ``pose``, s ((n,), or 0.0 when no effect has one)."""
    total: FloatArray | float = 0.0
    for e in effects:
        d = e.drive_delay_s(pose)
        if d is not None:
            total = total + d
    return total


def response_delay_s(effects: EffectSet, period_s: float) -> float:
    """The effects' extra wait of every state package beyond the packing phase, s."""
    total = 0.0
    for e in effects:
        total += e.response_delay_s(period_s)
    return total
