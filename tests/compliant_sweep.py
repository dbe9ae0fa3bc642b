"""An independent generator of recordings from compliant joints read by motor-side encoders.

Real UR and KUKA arms drive each joint through a compliant gear (harmonic drive or cycloidal)
and report the angle of an encoder on the *motor* side, divided by the gear ratio; a gyro on
the flange sees the *link*, which deflects against the gear under gravity and under the
torque that accelerates it. This generator (issue 37) makes such recordings, to test what
the extraction's response delay means and how well it is measured there. Written from
``docs/recording-format.md`` alone: it imports nothing of timedexec but the public recording
writer, and shares no code with :mod:`timedexec.sim` or ``tests/independent_sweep.py``.

Physics (per trial; the actuated joint moves, the others are held rigid)
-----------------------------------------------------------------------
* **Arm.** Denavit-Hartenberg chain with point-mass links (plus a radius of gyration) and a
  payload at the flange; from the start pose: the link inertia about the moving axis, the
  gravity torque the gear must hold, exact in the joint angle (``a·cos Δ + b·sin Δ`` for a
  rotation about a fixed axis), and the gyro's axis in flange coordinates.
  UR10: Universal Robots' published DH parameters (d1 0.1273, a2 -0.612, a3 -0.5723,
  d4 0.163941, d5 0.1157, d6 0.0922 m) and link masses (7.1, 12.7, 4.27, 2.0, 2.0,
  0.365 kg), centres of mass of the order of UR's table. KR 5 sixx R650: DH of its
  data sheet's dimensions (d1 0.335, a1 0.075, a2 0.270, a3 0.090, d4 0.295, d6 0.080 m),
  its 28 kg spread over the links by judgement (no published mass table).
* **Gear.** Motor-side inertia (rotor x ratio², ratio 101 for UR's harmonic drives, 121
  for the KR 5 by judgement) and a torsional spring between motor and link with
  - the three-segment piecewise-linear stiffness harmonic-drive catalogues publish (limit
    torques T1, T2 and stiffnesses K1 < K2 < K3; Harmonic Drive AG's worked example for a
    size-32 gear: T1 = 29 N·m, T2 = 108 N·m, K1 = 6.7e4, K2 = 1.1e5, K3 = 1.2e5 N·m/rad),
    scaled per joint by gear size (UR10 shoulder and base 1, elbow 0.5, wrist 0.1);
    the KR 5's cycloidal gears with a soft zone ("lost motion" about 1.5 arcmin within
    ±3 % of the rated torque) and a rigidity of the order of a Nabtesco RV-6E
    (20 N·m/arcmin, 6.9e4 N·m/rad), elbow 0.5 and wrist 0.1 of that;
  - hysteresis as a Dahl element in parallel (rate-independent: the loop's width at the
    rated torque is the catalogue's "hysteresis loss", drawn 0.3-1 arcmin for the
    harmonic drives, 0.2-0.6 arcmin for the cycloidal gears; its pre-sliding stiffness
    twice the gear's K3, so a loop closes within a quarter of its width; tooth friction
    grows with the load, so the loop narrows to a quarter of that at no load: its friction
    torque is 0.25 + 0.75·min(|τ|/τ_rated, 1) of the rated one, τ_rated 108 N·m x size
    (harmonic; the size-32 example's T2) or 58 N·m x size (cycloidal));
  - light structural damping (ζ 0.03-0.08 of the link on the spring) and a viscous link
    bearing.
  The link's gravity preload sets where on the stiffness curve a trial works, so the
  deflection and the resonance change with the pose; the heavy joints (2, 3) deflect most.
* **Drive.** Motor Coulomb and viscous friction with stiction (breakaway 1.4x Coulomb), a
  PI velocity loop on the *motor* encoder's speed at 4 kHz (quantised encoder, 2^17
  counts per motor revolution), gravity feed-forward from a model 0-5 % off (the
  integrator holds the rest), the commanded speed sampled per controller cycle and
  interpolated linearly by the servo.
* **State.** The controller latches the motor encoder 0.1-0.4 ms before each cycle boundary
  and reports ``encoder / ratio``; packages leave after the cycle's work (UR: within the
  cycle; KR 5: one cycle later) over a network with log-normal latency.

Ground truth (``docs/architecture.md``, "What the response delay means on a compliant
joint"): the actuation delay is the instant the *link's* speed (what the gyro sees) reaches
10 % of the commanded speed minus the instant the commanded ramp reaches that speed after
the send; the response delay is the mean age, on arrival, of the *motor-side* sample the
package carries (arrival minus the encoder's latch instant). The reported position is not
the link's: it leads it by the gear's deflection.

Sensor, clock, USB (our own models, not the simulator's nor independent_sweep's)
--------------------------------------------------------------------------------
* Gyro sampled internally at 32 kHz, a 4-sample average decimating to 8 kHz, then a
  first-order low-pass (its DC group delay, with the average's, is the stated constant);
  white noise (the "1x" density 0.005 °/s/√Hz), a slowly wandering zero-rate, ±3 % scale
  and ±2 % cross-axis sensitivity, int16 at 65.5 LSB/(°/s); mounted on the flange at a
  random orientation (the joint's axis reaches it through the pose's rotation).
* Oscillator: an offset, a linear drift over the sweep and a slow thermal wander.
* USB: the device sends transfers of 16 samples (two recorded blocks of 8 share one
  arrival); a minimum latency, gamma jitter, host stalls, lost and duplicated transfers.

Usage (as a library)::

    from compliant_sweep import CompliantConditions, write_compliant_sweep
    write_compliant_sweep("rec.h5", "ur10", 300, CompliantConditions(noise_factor=2), seed=1)
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from timedexec.recording import Field, RecordingWriter

FloatArray = NDArray[np.float64]

#: The "1x" gyro noise density, °/s/√Hz (the simulator's default; MPU-6000 data sheet 0.005).
BASE_NOISE_DPS_RTHZ = 0.005
ONSET_FRACTION = 0.1  # docs/architecture.md: onset at 10 % of the commanded speed
ARCMIN = math.pi / (180 * 60)
GRAVITY = np.array([0.0, 0.0, -9.81])
FS_GYRO = 8000.0
OVERSAMPLE = 4  # internal 32 kHz, averaged over 4 samples
TRANSFER = 16  # samples per USB transfer
BLOCK = 8  # recorded block (header gyro.block_samples)
SERVO_HZ = 4000.0
DT_PHYS = 1.0 / 32000.0  # physics step: the sensor's internal rate


@dataclass(frozen=True)
class Arm:
    """One robot: kinematics, masses, gears, controller timing."""

    #: DH (standard): d, a, alpha per joint, m and rad.
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    #: Link masses, kg, and centres of mass in each link's DH frame, m.
    mass: tuple[float, ...]
    com: tuple[tuple[float, float, float], ...]
    #: Radius of gyration of each link about its own centre, m.
    gyration_m: float
    payload_kg: tuple[float, float]
    #: Gear size factor per joint (stiffness and limit torques scale with it).
    size: tuple[float, ...]
    #: Reflected motor inertia at size 1 (kg·m², link side) and Coulomb friction (N·m).
    rotor_kgm2: float
    coulomb_nm: float
    kind: str  # "harmonic" or "cycloidal"
    ratio: float
    period_s: float
    pipeline: int
    extra_cycle: int
    bw_hz: float
    vendor: str


ARMS: dict[str, Arm] = {
    "ur10": Arm(
        d=(0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922),
        a=(0.0, -0.612, -0.5723, 0.0, 0.0, 0.0),
        alpha=(math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0),
        mass=(7.1, 12.7, 4.27, 2.0, 2.0, 0.365),
        com=(
            (0.021, 0.0, 0.027),
            (0.38, 0.0, 0.158),
            (0.24, 0.0, 0.068),
            (0.0, 0.007, 0.018),
            (0.0, 0.007, 0.018),
            (0.0, 0.0, -0.026),
        ),
        gyration_m=0.06,
        payload_kg=(0.0, 5.0),
        size=(1.0, 1.0, 0.5, 0.1, 0.1, 0.1),
        rotor_kgm2=2.5,
        coulomb_nm=8.0,
        kind="harmonic",
        ratio=101.0,
        period_s=0.008,
        pipeline=2,
        extra_cycle=0,
        bw_hz=15.0,
        vendor="universal_robots",
    ),
    "kr5": Arm(
        d=(0.335, 0.0, 0.0, 0.295, 0.0, 0.080),
        a=(0.075, 0.270, 0.090, 0.0, 0.0, 0.0),
        alpha=(-math.pi / 2, 0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, 0.0),
        mass=(9.0, 7.0, 5.0, 3.5, 2.0, 1.5),
        com=(
            (0.03, 0.0, 0.05),
            (-0.13, 0.0, 0.03),
            (-0.04, 0.0, 0.02),
            (0.0, -0.05, 0.0),
            (0.0, 0.0, 0.02),
            (0.0, 0.0, -0.02),
        ),
        gyration_m=0.05,
        payload_kg=(0.0, 3.0),
        size=(1.0, 1.0, 0.5, 0.1, 0.1, 0.1),
        rotor_kgm2=0.5,
        coulomb_nm=3.0,
        kind="cycloidal",
        ratio=121.0,
        period_s=0.012,
        pipeline=7,
        extra_cycle=1,
        bw_hz=12.0,
        vendor="kuka",
    ),
}


@dataclass(frozen=True, kw_only=True)
class CompliantConditions:
    """What is hard about a recording.

    Parameters
    ----------
    noise_factor : float
        Gyro white-noise density relative to 0.005 °/s/√Hz.
    clock_offset_ppm, clock_drift_ppm : float
        Oscillator error at the sweep's start and its linear change over the sweep, ppm.
    transfer_loss, transfer_dup : float
        Probability that a USB transfer (16 samples) is lost / delivered twice.
    package_loss : float
        Probability that a state package is lost.
    stiffness_scale : float
        Multiplies every gear stiffness (large: a nearly rigid gear; for studies).
    hysteresis_scale : float
        Multiplies the gears' hysteresis (0: none; for studies).
    gravity : bool
        Gravity load on the links (False: none; for studies).
    hysteresis_load : bool
        The gear's friction (its hysteresis loop's width) grows with the transmitted
        torque (default); False: the rated torque's loop at every load.
    """

    noise_factor: float = 1.0
    clock_offset_ppm: float = 2000.0
    clock_drift_ppm: float = 0.0
    transfer_loss: float = 0.0
    transfer_dup: float = 0.0
    package_loss: float = 0.002
    stiffness_scale: float = 1.0
    hysteresis_scale: float = 1.0
    gravity: bool = True
    hysteresis_load: bool = True


# ---- arm --------------------------------------------------------------------------------------


def _frames(arm: Arm, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Homogeneous transforms of the base and of each link frame (7, 4, 4) and the centres
    of mass in the base frame (6, 3), for one pose q (6,)."""
    t = np.eye(4)
    frames = [t.copy()]
    coms = []
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(arm.alpha[i]), math.sin(arm.alpha[i])
        step = np.array([[ct, -st * ca, st * sa, arm.a[i] * ct],
                         [st, ct * ca, -ct * sa, arm.a[i] * st],
                         [0.0, sa, ca, arm.d[i]],
                         [0.0, 0.0, 0.0, 1.0]])  # fmt: skip
        t = t @ step
        frames.append(t.copy())
        coms.append((t @ np.r_[arm.com[i], 1.0])[:3])
    return np.array(frames), np.array(coms)


def arm_loads(arm: Arm, q: FloatArray, joint: int, payload_kg: float) -> dict[str, Any]:
    """Link inertia about joint ``joint`` (1-based) at pose q (kg·m²), the gravity torque the
    gear must hold as ``a·cos Δ + b·sin Δ`` of the joint's excursion Δ (N·m), and the
    rotation axis in flange coordinates."""
    frames, coms = _frames(arm, np.asarray(q, dtype=np.float64))
    axis = frames[joint - 1][:3, 2]
    origin = frames[joint - 1][:3, 3]
    flange = frames[6][:3, 3]
    masses = [*arm.mass[joint - 1 :], payload_kg]
    points = [*coms[joint - 1 :], flange]
    inertia = 0.0
    hold = 0.0  # torque the gear supplies about the axis to hold the links still
    lever = 0.0  # d(hold)/dΔ
    for m, p in zip(masses, points, strict=True):
        r = p - origin
        r_perp = r - axis * (axis @ r)
        inertia += m * (r_perp @ r_perp + arm.gyration_m**2)
        # gravity's torque about the axis: axis·(r × m g) = m g·(axis × r_perp); the gear
        # holds its negative; rotating by Δ: r_perp -> cosΔ r_perp + sinΔ axis × r_perp.
        g = m * GRAVITY
        hold -= g @ np.cross(axis, r_perp)
        lever -= g @ np.cross(axis, np.cross(axis, r_perp))
    return {"inertia": inertia, "grav_a": hold, "grav_b": lever,
            "axis_flange": frames[6][:3, :3].T @ axis}  # fmt: skip


def _stiffness_curve(arm: Arm, joint: int, scale: float) -> tuple[float, ...]:
    """(T1, T2, K1, K2, K3) of the joint's gear: N·m and N·m/rad."""
    s = arm.size[joint - 1]
    if arm.kind == "harmonic":  # Harmonic Drive AG's size-32 example, scaled
        return (29.0 * s, 108.0 * s, 6.7e4 * s * scale, 1.1e5 * s * scale, 1.2e5 * s * scale)
    # Cycloidal: a soft zone (lost motion 1.5 arcmin within ±3 % of 58 N·m), then the rigidity.
    k = 6.9e4 * s * scale
    t1 = 0.03 * 58.0 * s
    k1 = t1 / (0.75 * ARCMIN)
    return (t1, 4 * t1, min(k1 * scale, k), 0.8 * k, k)


def spring_torque(delta: FloatArray, curve: tuple[FloatArray, ...]) -> FloatArray:
    """Piecewise-linear odd stiffness curve: torque (N·m) at deflection ``delta`` (rad)."""
    t1, t2, k1, k2, k3 = curve
    d1 = t1 / k1
    d2 = d1 + (t2 - t1) / k2
    x = np.abs(delta)
    mag = np.where(x <= d1, k1 * x, np.where(x <= d2, t1 + k2 * (x - d1), t2 + k3 * (x - d2)))
    return np.asarray(np.sign(delta) * mag)


def spring_deflection(torque: FloatArray, curve: tuple[FloatArray, ...]) -> FloatArray:
    """Inverse of :func:`spring_torque`."""
    t1, t2, k1, k2, k3 = curve
    x = np.abs(torque)
    mag = np.where(x <= t1, x / k1, np.where(x <= t2, t1 / k1 + (x - t1) / k2,
                                             t1 / k1 + (t2 - t1) / k2 + (x - t2) / k3))  # fmt: skip
    return np.asarray(np.sign(torque) * mag)


def joint_params(
    rng: np.random.Generator,
    arm: Arm,
    q_start: FloatArray,
    joint: NDArray[np.int64],
    cond: CompliantConditions,
) -> dict[str, FloatArray]:
    """Per-trial physical parameters (drawn in a fixed order)."""
    n = len(joint)
    payload = rng.uniform(*arm.payload_kg, n)
    loads = [arm_loads(arm, q_start[i], int(joint[i]), float(payload[i])) for i in range(n)]
    curve = np.array([_stiffness_curve(arm, int(j), cond.stiffness_scale) for j in joint]).T
    size = np.array([arm.size[j - 1] for j in joint])
    if arm.kind == "harmonic":
        hyst = rng.uniform(0.3, 1.0, n) * ARCMIN
    else:
        hyst = rng.uniform(0.2, 0.6, n) * ARCMIN
    # Dahl element: saturates at T_h, the loop's half-width in torque at the K3 branch.
    t_h = 0.5 * hyst * curve[4] * cond.hysteresis_scale
    inertia = np.array([ld["inertia"] for ld in loads])
    g_on = 1.0 if cond.gravity else 0.0
    rotor = arm.rotor_kgm2 * np.maximum(size, 0.1) * rng.uniform(0.8, 1.2, n)
    zeta = rng.uniform(0.03, 0.08, n)
    return {
        "payload": payload,
        "jl": inertia,
        "jm": rotor,
        "grav_a": g_on * np.array([ld["grav_a"] for ld in loads]),
        "grav_b": g_on * np.array([ld["grav_b"] for ld in loads]),
        "axis": np.array([ld["axis_flange"] for ld in loads]),
        "t1": curve[0], "t2": curve[1], "k1": curve[2], "k2": curve[3], "k3": curve[4],
        "t_h": t_h,
        "t_rated": np.where(arm.kind == "harmonic", 108.0, 58.0) * size,
        "load_share": np.full(n, 0.75 if cond.hysteresis_load else 0.0),
        "sigma_h": 2.0 * curve[4],
        "c_gear": 2 * zeta * np.sqrt(curve[4] * inertia),
        "b_link": rng.uniform(0.2, 1.0, n) * size,
        "f_c": arm.coulomb_nm * size * rng.uniform(0.7, 1.3, n),
        "b_m": 4.0 * size * rng.uniform(0.7, 1.3, n),
        "ff_error": rng.uniform(-0.05, 0.05, n),
        "hyst0": rng.uniform(-0.5, 0.5, n),
        "bw": np.full(n, arm.bw_hz),
    }  # fmt: skip


def _profile(x: FloatArray, speed: float, accel: float, hold: float, pause: float) -> FloatArray:
    """Commanded speed of the out-and-back trapezoid (x: time since it started, s)."""
    ramp = speed / accel
    pulse = 2 * ramp + hold

    def one(u: FloatArray) -> FloatArray:
        return np.where(
            (u > 0) & (u < pulse),
            np.minimum(np.clip(u, 0, ramp), np.clip(pulse - u, 0, ramp)) * accel,
            0.0,
        )

    return one(x) - one(x - pulse - pause)


def simulate_joints(
    par: dict[str, FloatArray],
    t_ref: FloatArray,
    direction: FloatArray,
    period_s: float,
    ratio: float,
    grid: FloatArray,
    prof: dict[str, float],
) -> dict[str, FloatArray]:
    """Link speed, link angle and motor angle (link side) relative to the start, on ``grid``
    (uniform, DT_PHYS), of the joints ``par`` following the profile from ``t_ref``.

    Semi-implicit Euler at 32 kHz; the velocity loop runs every 8 steps (4 kHz)."""
    n = len(t_ref)
    dt = float(grid[1] - grid[0])
    curve = (par["t1"], par["t2"], par["k1"], par["k2"], par["k3"])
    jl, jm = par["jl"], par["jm"]
    jt = jl + jm
    w_bw = 2 * np.pi * par["bw"]
    kp = jt * w_bw
    ki = kp * w_bw / 4.0
    quantum = 2 * np.pi / (2**17 * ratio)
    # Static equilibrium at the start: the hysteresis state from the arm's history, the
    # spring holding the rest of the gravity torque.
    h = par["hyst0"] * par["t_h"] * _load_factor(par["grav_a"], par)
    g0 = par["grav_a"]
    delta = spring_deflection(g0 - h, curve)
    ql = np.zeros(n)
    wl = np.zeros(n)
    qm = delta.copy()  # motor angle (link side) relative to the link's start
    wm = np.zeros(n)
    ff0 = (1 + par["ff_error"]) * g0
    integ = (g0 - ff0) / ki  # the integrator holds what the feed-forward misses
    stuck = np.ones(n, dtype=bool)
    f_s = 1.4 * par["f_c"]
    enc_prev = np.round(qm / quantum) * quantum
    u = g0.copy()
    steps_per_servo = round(1.0 / (SERVO_HZ * dt))
    out_wl = np.zeros((n, grid.size))
    out_wm = np.zeros((n, grid.size))
    speed, accel = prof["speed_rad_s"], prof["acceleration_rad_s2"]
    hold, pause = prof["hold_s"], prof["pause_s"]
    for i in range(grid.size):
        t = grid[i]
        if i % steps_per_servo == 0:
            # Servo tick: the reference interpolated between the controller's cycles.
            x = t - t_ref
            k = np.floor(x / period_s)
            r0 = _profile(k * period_s, speed, accel, hold, pause)
            r1 = _profile((k + 1) * period_s, speed, accel, hold, pause)
            ref = direction * np.where(x > 0, r0 + (x / period_s - k) * (r1 - r0), 0.0)
            enc = np.round(qm / quantum) * quantum
            w_meas = (enc - enc_prev) * SERVO_HZ
            enc_prev = enc
            err = ref - w_meas
            integ = integ + err / SERVO_HZ
            excursion = enc - delta  # the controller's own angle, relative to the start
            ff = (1 + par["ff_error"]) * (
                par["grav_a"] * np.cos(excursion) + par["grav_b"] * np.sin(excursion)
            )
            u = ff + kp * err + ki * integ
        d = qm - ql
        dd = wm - wl
        # Dahl hysteresis: dh = σ·dδ·(1 - h/T_h·sign(dδ)), T_h growing with the load.
        elastic = spring_torque(d, curve)
        t_h = par["t_h"] * _load_factor(elastic, par)
        h = h + par["sigma_h"] * dd * dt * (1 - h / np.maximum(t_h, 1e-9) * np.sign(dd))
        h = np.where(par["t_h"] > 0, h, 0.0)
        tau_g = elastic + h + par["c_gear"] * dd
        grav = par["grav_a"] * np.cos(ql) + par["grav_b"] * np.sin(ql)
        drive = u - tau_g
        breaks = stuck & (np.abs(drive) > f_s)
        stuck = stuck & ~breaks
        fric = np.where(stuck, 0.0, par["f_c"] * np.sign(np.where(wm != 0, wm, drive)))
        acc_m = np.where(stuck, 0.0, (drive - fric - par["b_m"] * wm) / jm)
        wm_new = wm + acc_m * dt
        crossing = ~stuck & (np.sign(wm_new) != np.sign(wm)) & (wm != 0)
        stick = crossing & (np.abs(drive) <= f_s)
        wm = np.where(stick, 0.0, wm_new)
        stuck = stuck | stick
        qm = qm + wm * dt
        acc_l = (tau_g - grav - par["b_link"] * wl) / jl
        wl = wl + acc_l * dt
        ql = ql + wl * dt
        out_wl[:, i] = wl
        out_wm[:, i] = wm
    # Angles as the trapezoid integrals of the speeds on the grid: the Euler states run half
    # a step (16 µs) ahead of the speeds, which would make every state look younger.
    return {"w_link": out_wl, "q_link": _integral(out_wl, dt),
            "q_motor": _integral(out_wm, dt), "deflection0": delta}  # fmt: skip


def _load_factor(torque: FloatArray, par: dict[str, FloatArray]) -> FloatArray:
    """The gear friction's (hysteresis loop's) share of its rated-torque width at
    ``torque`` (N·m): 1 - s + s·min(|τ|/τ_rated, 1), s = ``load_share``."""
    s = par["load_share"]
    return np.asarray(1.0 - s + s * np.minimum(np.abs(torque) / par["t_rated"], 1.0))


def _integral(w: FloatArray, dt: float) -> FloatArray:
    out = np.zeros_like(w)
    out[:, 1:] = np.cumsum(0.5 * (w[:, 1:] + w[:, :-1]), axis=1) * dt
    return out


# ---- sensor, clock, USB -----------------------------------------------------------------------


def sensor_filter(cutoff_hz: float = 400.0) -> tuple[float, float]:
    """The first-order low-pass after the 4-sample average: its coefficient α
    (y += α·(x - y) per 8 kHz sample) and the chain's DC group delay, s."""
    alpha = 1.0 - math.exp(-2 * math.pi * cutoff_hz / FS_GYRO)
    delay = 1.5 / (FS_GYRO * OVERSAMPLE) + (1.0 - alpha) / alpha / FS_GYRO
    return alpha, delay


class Oscillator:
    """The gyro's clock: rate f0·(1 + 1e-6·ppm(t)), ppm(t) = offset + drift·t/T + a slow
    thermal wander (1 ppm, 170 s period); sample 0 taken at host time ``t_origin``."""

    def __init__(self, offset_ppm: float, drift_ppm: float, sweep_s: float, phase: float):
        self.off, self.drift, self.T = offset_ppm, drift_ppm, max(sweep_s, 1.0)
        self.wander, self.period, self.phi = 1.0, 170.0, phase
        self.t_origin = -0.81

    def ppm(self, t: FloatArray) -> FloatArray:
        w = 2 * math.pi / self.period
        return np.asarray(
            self.off + self.drift * t / self.T + self.wander * np.sin(w * t + self.phi)
        )

    def index(self, t: FloatArray) -> FloatArray:
        """Fractional sample index at host time t."""
        t = np.asarray(t, dtype=np.float64)
        w = 2 * math.pi / self.period
        s = t - self.t_origin
        integral = (self.off * s + self.drift * (t**2 - self.t_origin**2) / (2 * self.T)
                    - self.wander / w * (np.cos(w * t + self.phi)
                                         - math.cos(w * self.t_origin + self.phi)))  # fmt: skip
        return np.asarray(FS_GYRO * (s + 1e-6 * integral))

    def time_of(self, k: FloatArray) -> FloatArray:
        """Host time at which (fractional) sample index k is taken."""
        k = np.asarray(k, dtype=np.float64)
        t = self.t_origin + k / FS_GYRO
        for _ in range(4):
            t = t - (self.index(t) - k) / (FS_GYRO * (1 + 1e-6 * self.ppm(t)))
        return t


def usb_stream(
    rng: np.random.Generator,
    first: int,
    taken: FloatArray,
    cond: CompliantConditions,
) -> tuple[NDArray[np.int64], FloatArray]:
    """The samples ``first + arange(len(taken))`` (taken at host times ``taken``) as the
    host receives them: (position in the run, arrival), in arrival order. The device sends
    transfers of TRANSFER samples ending at multiples of TRANSFER in the sample index;
    minimum latency 0.6 ms, gamma jitter (mean 0.25 ms), host stalls of 1-3 ms (0.3 % of
    transfers), lost and duplicated transfers."""
    m = taken.size
    idx = first + np.arange(m)
    tid = idx // TRANSFER
    ends = np.flatnonzero(np.r_[tid[1:] != tid[:-1], True])
    starts = np.r_[0, ends[:-1] + 1]
    nt = ends.size
    jitter = rng.gamma(2.0, 0.000125, nt)
    stall = np.where(rng.random(nt) < 0.003, rng.uniform(1e-3, 3e-3, nt), 0.0)
    arrival = np.maximum.accumulate(taken[ends] + 0.0006 + jitter + stall)
    copies = np.ones(nt, dtype=np.int64)
    copies[rng.random(nt) < cond.transfer_loss] = 0
    copies[(rng.random(nt) < cond.transfer_dup) & (copies == 1)] = 2
    pos: list[NDArray[np.int64]] = []
    times: list[FloatArray] = []
    for k in np.flatnonzero(copies).tolist():
        for c in range(int(copies[k])):
            pos.append(np.arange(starts[k], ends[k] + 1))
            times.append(np.full(ends[k] + 1 - starts[k], arrival[k] + c * 2e-4))
    p = np.concatenate(pos)
    t = np.concatenate(times)
    order = np.argsort(t, kind="stable")
    return p[order], t[order]


class CompliantSession:
    """One sweep's sensor, clock and USB state: the still recording and trials of any layout.

    :func:`write_compliant_sweep` draws its own layout; a caller with a plan (an adaptive
    design choosing configurations as it goes) asks for trials of given start poses,
    joints and directions at given sweep times, batch after batch, from the same session.

    Parameters
    ----------
    rng : numpy.random.Generator
        Every draw of the session, in call order.
    robot : {"ur10", "kr5"}
    cond : CompliantConditions
    sweep_end_s : float
        The sweep's host-clock length, s (the oscillator's drift runs over it).
    """

    def __init__(
        self, rng: np.random.Generator, robot: str, cond: CompliantConditions, sweep_end_s: float
    ) -> None:
        self.rng, self.robot, self.cond = rng, robot, cond
        self.arm = arm = ARMS[robot]
        self.period = arm.period_s
        self.lsb = 65.5
        self.prof = {"speed_rad_s": 0.4, "acceleration_rad_s2": 8.0, "hold_s": 0.05,
                     "pause_s": 0.15, "pre_s": 0.05, "record_s": 0.65}  # fmt: skip
        self.n_pk = math.floor(self.prof["record_s"] / self.period)
        n_g = round((self.prof["pre_s"] + self.prof["record_s"]) * FS_GYRO)
        self.n_g = n_g - n_g % BLOCK
        self.alpha, self.group_delay = sensor_filter()
        self.osc = Oscillator(cond.clock_offset_ppm, cond.clock_drift_ppm, float(sweep_end_s),
                              float(rng.uniform(0, 2 * math.pi)))  # fmt: skip
        self.sigma_lsb = BASE_NOISE_DPS_RTHZ * cond.noise_factor * math.sqrt(FS_GYRO / 2) * self.lsb
        self.bias0 = rng.uniform(-2.0, 2.0, 3)  # °/s
        mix = np.eye(3) + np.diag(rng.uniform(-0.03, 0.03, 3))
        self.mix = mix + (1 - np.eye(3)) * rng.uniform(-0.02, 0.02, (3, 3))
        self.mount, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        self.counter0 = int(rng.integers(0, 65536))

    def _bias_at(self, t: FloatArray) -> FloatArray:
        """Zero-rate, °/s: a slow wander (0.005 °/s over ~10 min), smooth at the trial scale."""
        return self.bias0 + 0.005 * np.sin(t[..., None] / 97.0 + np.arange(3))

    def _sensor_counts(self, rate_dps: FloatArray, t_host: FloatArray) -> NDArray[np.int16]:
        x = rate_dps @ self.mix.T + self._bias_at(t_host)
        x = x * self.lsb + self.rng.standard_normal(x.shape) * self.sigma_lsb
        return np.clip(np.rint(x), -32768, 32767).astype(np.int16)

    def header(self, seed: int) -> dict[str, Any]:
        """The recording header."""
        return {
            "source": "compliant_sweep (tests/compliant_sweep.py)",
            "robot": {"name": self.robot, "vendor": self.arm.vendor},
            "profile": self.prof,
            "controller_period_s": self.period,
            "gyro": {
                "full_scale_dps": 500,
                "nominal_rate_hz": FS_GYRO,
                "block_samples": BLOCK,
                "lsb_per_dps": self.lsb,
                "group_delay_s": self.group_delay,
                "transport_latency_s": 0.0006,
            },
            "conditions": json.loads(json.dumps(dataclasses.asdict(self.cond))),
            "truth": {"seed": seed, "response": "age of the motor-side sample on arrival"},
        }

    def fields(self) -> list[Field]:
        """The per-trial fields."""
        n_pk, n_g = self.n_pk, self.n_g
        return [
            Field("trial", (), "int64", "", "plan index"),
            Field("t0_s", (), "float64", "s", "host sweep time of trial time 0"),
            Field("cmd_send_time_s", (), "float64", "s", "command send time, trial time"),
            Field("cmd_qd_rad_s", (6,), "float64", "rad/s", "commanded joint speeds"),
            Field("state_host_time_s", (n_pk,), "float64", "s", "package arrival, trial time"),
            Field("state_q_rad", (n_pk, 6), "float64", "rad", "reported (motor-side) positions"),
            Field("state_qd_rad_s", (n_pk, 6), "float32", "rad/s", "reported joint speeds"),
            Field("gyro_raw", (n_g, 3), "int16", "LSB", "gyro counts"),
            Field("gyro_counter", (n_g,), "uint16", "", "sample counter"),
            Field("gyro_block_host_time_s", (n_g // BLOCK,), "float64", "s", "block arrival"),
            Field("true_actuation_delay_s", (), "float64", "s", "ground truth (link speed)"),
            Field("true_response_delay_s", (), "float64", "s", "ground truth (motor sample age)"),
            Field("true_payload_kg", (), "float64", "kg", "payload (for studies)"),
            Field("true_link_inertia_kgm2", (), "float64", "kg m2", "link inertia (for studies)"),
            Field("true_gravity_nm", (), "float64", "N m", "gravity torque held at the start"),
        ]

    def still(self, still_s: float) -> dict[str, Any]:
        """The still recording's statics (``still_gyro_*``) of ``still_s`` seconds."""
        rng, osc, cond = self.rng, self.osc, self.cond
        k_lo = int(np.ceil(osc.index(np.array(0.0))))
        m_still = int(still_s * FS_GYRO)
        taken = osc.time_of(k_lo + np.arange(m_still))
        pos_s, arr_s = usb_stream(rng, k_lo, taken, cond)
        pos_s = pos_s[: len(pos_s) - len(pos_s) % BLOCK]
        arr_s = arr_s[: len(pos_s)]
        return {
            "still_gyro_raw": self._sensor_counts(np.zeros((m_still, 3)), taken)[pos_s],
            "still_gyro_counter": ((self.counter0 + k_lo + pos_s) % 65536).astype(np.uint16),
            "still_gyro_block_host_time_s": arr_s[BLOCK - 1 :: BLOCK],
        }

    def trials(
        self,
        q_start: FloatArray,
        joint: NDArray[np.int64],
        direction: NDArray[np.int64],
        t0: FloatArray,
    ) -> dict[str, Any]:
        """Per-trial arrays (every field but ``trial``) of trials at host times ``t0``, s."""
        rng, arm, cond, prof, osc = self.rng, self.arm, self.cond, self.prof, self.osc
        period, n_pk, n_g = self.period, self.n_pk, self.n_g
        n_trials = len(joint)
        # ---- controller timing ------------------------------------------------------------------
        latch = rng.uniform(1e-4, 4e-4, n_trials)  # encoder latched this long before the boundary
        pack = (rng.uniform(0.1, 0.9, n_trials) + arm.extra_cycle) * period
        net = np.exp(rng.normal(math.log(3e-4), 0.35, (n_trials, n_pk)))
        c0 = -(pack + net[:, 0])  # cycle boundary of package 0, which arrives at t = 0
        boundary = c0[:, None] + np.arange(n_pk) * period
        sampled = boundary - latch[:, None]
        arrival = boundary + pack[:, None] + net
        arrival[:, 0] = 0.0
        arrival[:, 1:][rng.random((n_trials, n_pk - 1)) < cond.package_loss] = np.nan
        t_send = 1e-4 + rng.exponential(5e-5, n_trials)
        at_ctrl = t_send + 2e-4 + rng.gamma(2.0, 1e-4, n_trials)
        intake = c0 + np.ceil((at_ctrl - c0) / period) * period
        t_ref = intake + arm.pipeline * period + 3e-4

        # ---- physics ----------------------------------------------------------------------------
        par = joint_params(rng, arm, q_start, joint, cond)
        grid = -prof["pre_s"] - 0.02 + np.arange(
            round((prof["pre_s"] + prof["record_s"] + 0.04) / DT_PHYS)) * DT_PHYS  # fmt: skip
        phys = simulate_joints(par, t_ref, direction.astype(float), period, arm.ratio, grid, prof)
        w_link = phys["w_link"]
        level = ONSET_FRACTION * prof["speed_rad_s"]
        v_dir = w_link * direction[:, None]
        above = (v_dir >= level) & (grid > 0)
        k = np.argmax(above, axis=1)
        ii = np.arange(n_trials)
        v0, v1 = v_dir[ii, k - 1], v_dir[ii, k]
        onset = grid[k - 1] + (level - v0) / (v1 - v0) * DT_PHYS
        true_act = onset - (t_send + level / prof["acceleration_rad_s2"])
        got = np.isfinite(arrival)
        true_resp = np.sum(np.where(got, arrival - sampled, 0.0), axis=1) / got.sum(axis=1)
        quantum = 2 * np.pi / (2**17 * arm.ratio)
        q_motor = np.array([np.interp(sampled[i], grid, phys["q_motor"][i]) for i in ii])
        q_rep = q_start[ii, joint - 1][:, None] + phys["deflection0"][:, None] + q_motor
        q_rep = np.round(q_rep / quantum) * quantum  # the encoder's resolution
        qd_rep = np.diff(q_rep, axis=1, prepend=q_rep[:, :1]) / period
        state_q = np.repeat(q_start[:, None, :], n_pk, axis=1)
        state_q[ii, :, joint - 1] = q_rep
        state_qd = np.zeros_like(state_q)
        state_qd[ii, :, joint - 1] = qd_rep
        state_q[~got] = np.nan
        state_qd[~got] = np.nan

        # ---- gyro per trial ---------------------------------------------------------------------
        margin = 480 + int(n_g * 6 * cond.transfer_loss)
        warm = 64  # output samples before the window: the filter starts settled
        gyro_raw = np.empty((n_trials, n_g, 3), np.int16)
        gyro_counter = np.empty((n_trials, n_g), np.uint16)
        gyro_blocks = np.empty((n_trials, n_g // BLOCK), np.float32)
        sub = (
            np.arange(OVERSAMPLE) - (OVERSAMPLE - 1)
        ) / OVERSAMPLE  # internal samples of one output
        for i in range(n_trials):
            k_first = int(np.ceil(osc.index(np.array(t0[i] - prof["pre_s"]))))
            k_all = k_first - warm + np.arange(n_g + margin + warm)
            t_in = osc.time_of((k_all[:, None] + sub).ravel()) - t0[i]
            w_in = np.interp(t_in, grid, w_link[i], left=0.0, right=0.0)
            avg = w_in.reshape(-1, OVERSAMPLE).mean(axis=1)
            out = signal.lfilter([self.alpha], [1.0, self.alpha - 1.0], avg)
            axis = self.mount @ par["axis"][i]
            t_host = osc.time_of(k_all.astype(np.float64))
            counts = self._sensor_counts(np.degrees(out)[:, None] * axis, t_host)
            pos, arr = usb_stream(rng, int(k_all[0]), t_host, cond)
            inside = k_all[pos] >= k_first
            sel, arr = pos[inside][:n_g], arr[inside][:n_g]
            if sel.size < n_g:
                raise RuntimeError("margin too small for the transfer loss; raise it")
            gyro_raw[i] = counts[sel]
            gyro_counter[i] = (self.counter0 + k_all[sel]) % 65536
            gyro_blocks[i] = arr[BLOCK - 1 :: BLOCK] - t0[i]
        return {
            "t0_s": t0,
            "cmd_send_time_s": t_send,
            "cmd_qd_rad_s": np.where(np.arange(6) == (joint - 1)[:, None],
                                     direction[:, None] * prof["speed_rad_s"], 0.0),
            "state_host_time_s": arrival,
            "state_q_rad": state_q,
            "state_qd_rad_s": state_qd.astype(np.float32),
            "gyro_raw": gyro_raw,
            "gyro_counter": gyro_counter,
            "gyro_block_host_time_s": gyro_blocks,
            "true_actuation_delay_s": true_act,
            "true_response_delay_s": true_resp,
            "true_payload_kg": par["payload"],
            "true_link_inertia_kgm2": par["jl"],
            "true_gravity_nm": par["grav_a"],
        }  # fmt: skip


def write_compliant_sweep(
    path: str | Path,
    robot: str,
    n_trials: int,
    cond: CompliantConditions | None = None,
    *,
    seed: int = 0,
    still_s: float = 4.0,
) -> Path:
    """Write a recording of ``n_trials`` trials of a compliant arm in the documented format.

    Parameters
    ----------
    path : path
        New HDF5 file.
    robot : {"ur10", "kr5"}
        The arm (:data:`ARMS`).
    n_trials : int
        Trials (joints 1, 2, 3 and 5, both directions, 8 trials per start pose).
    cond : CompliantConditions
        Noise, clock, USB and physics conditions.
    seed : int
        Seed of every random draw.
    still_s : float
        Stationary recording before the sweep, s.

    Returns
    -------
    Path
        ``path``.
    """
    cond = cond or CompliantConditions()
    rng = np.random.default_rng([seed, 0xC0317])

    # Sweep layout.
    joint = np.array([1, 2, 3, 5])[rng.integers(0, 4, n_trials)]
    direction = rng.choice([-1, 1], n_trials)
    pose = np.arange(n_trials) // 8
    q_pose = rng.uniform(-2.0, 2.0, (pose.max() + 1, 6))
    q_pose[:, 5] = 0.0
    q_start = q_pose[pose]
    gap = 1.05 + rng.uniform(0, 0.02, n_trials) + np.where(np.arange(n_trials) % 8 == 0, 0.5, 0)
    t0 = still_s + 0.7 + np.cumsum(gap) - gap[0]
    session = CompliantSession(rng, robot, cond, float(t0[-1] + 1.0))
    still = session.still(still_s)
    arrays = session.trials(q_start, joint, direction, t0)
    path = Path(path)
    with RecordingWriter(
        path, header=session.header(seed), fields=session.fields(), fsync=False
    ) as w:
        w.write_static("plan_q_start_rad", q_start, unit="rad")
        w.write_static("plan_joint", joint.astype(np.int64))
        w.write_static("plan_direction", direction.astype(np.int64))
        w.write_static("still_gyro_raw", still["still_gyro_raw"], unit="LSB")
        w.write_static("still_gyro_counter", still["still_gyro_counter"])
        w.write_static(
            "still_gyro_block_host_time_s", still["still_gyro_block_host_time_s"], unit="s"
        )
        w.append({"trial": np.arange(n_trials, dtype=np.int64), **arrays})
    return path
