"""An independent generator of executor cycle logs, for testing the DelayMonitor.

Written from the documented cycle-log format (``docs/monitor.md``, "Saved cycle log";
:meth:`timedexec.execution.CycleLog.arrays`): the columns ``arrival_s``, ``controller_s``,
``sequence``, ``send_s``, ``qd_cmd`` (n, 6), ``q`` (n, 6), ``coasted``, one row per state
package the executor handled, NaN ``send_s``/``qd_cmd`` while idle at rest, a speed command
per package while a plan streams (the plan's speed where each joint's command acts: the
send time plus a per-joint actuation shift plus one period, ``docs/execution.md``). It
imports nothing of timedexec (the log is written with the public
``timedexec.monitoring.save_cycle_log`` by the caller, if at all) and deliberately models
the physics *differently* from :mod:`timedexec.sim`, so that a monitor tuned on the
simulator is measured on data it was not built on:

====================  =============================================  =================================
part                  here                                           timedexec.sim
====================  =============================================  =================================
joint                 per-joint dead time (+ lift asymmetry on the   one mass: PI velocity loop with
                      gravity-loaded joints, + 0.15 ms per-move      gravity feed-forward, current
                      jitter) then a *linear* second-order velocity  loop, torque limit, breakaway
                      response (own natural frequency and damping    friction (onset emerges from
                      per joint; an 8-band gain schedule on a        friction and gains)
                      pose-dependent inertia factor), exact ZOH
                      discretisation at the interpolator step
                      (``scipy.signal.lfilter``; LTI, so the dead
                      time delays the output: any real value)
reference             speedj as a rate-limited follower (lead-axis   pipeline of whole cycles, then a
                      scaling, ramps carried across boundaries),     continuous ramp per substep
                      held by a 1 kHz (UR10) / 2 kHz (UR10e) drive
                      interpolator
command intake        latest command that reached the controller     register sampled at the boundary
                      an intake margin before the boundary; late
                      commands wait a whole period, earlier ones of
                      the same cycle are overwritten
clocks                controller crystal off the host's by           cycle jitter (Gaussian), phase
                      +-40 ppm; positions latched 0.5 ms (UR10) /    drifting per trial
                      0.25 ms (UR10e) before the boundary
state stream          publish phase fixed per log, gamma network     exponential latency, packing
                      latency, rare lost packages (no row, no        phase drawn per trial
                      command that cycle)
host                  read-time wander common to all joints of a     constant processing + exponential
                      plan: AR(1) over plans (default mean 1.5 ms,   jitter
                      std 1.5 ms, coefficient 0.6), gamma jitter,
                      stalls of 2-12 ms every 4 s on average
                      (packages queue, then a burst of commands)
reported position     encoder-quantised (2^19 / 2^20 counts per      float, unquantised
                      revolution)
commands              executor-like: a time-synchronised multi-      one trapezoid per trial, one
                      joint trapezoid (1-3 joints, user speed        joint, from one send
                      0.25-1 rad/s, 8 rad/s^2, jerk-limited by a
                      5 ms box), sampled per package at send +
                      shift + period, speedj acceleration clamped
                      to [4, 8] rad/s^2 as the executor does
poses                 each plan from a fresh random pose within the  Sobol sample of calibration
                      working range (default; the log's pose jumps   ranges
                      mid-rest) or a walk (``poses="walk"``);
                      0.03-0.6 rad per moving joint
====================  =============================================  =================================

Ground truth per move follows ``docs/architecture.md``: the actuation delay is the instant
the joint's physical speed reaches 10 % of the move's peak commanded speed minus the
instant the commanded ramp (each command reached one period after its send, from zero at
the first send: the ramp ``docs/monitor.md`` describes) reaches that speed; the response
delay is the median age (arrival minus sampling instant) of the packages that arrived in
the 0.2 s after the first send. ``true_lag_s`` is their sum, the quantity the monitor's
lag estimates up to a constant of the method.

The host wander shows in the lag only through the controller's cycle: the arrival and send
stamps both carry the host's read delay, so it cancels in ``arrival - t*(d)`` except where
it moves the command past an intake boundary; then the whole plan's lag jumps by a period
(UR10: 8 ms, when the wander is large; UR10e: 2 ms, often), for every joint of the plan and,
through the AR(1), for neighbouring plans too.

A step change: ``Conditions(step_joint=2, step_s=0.002, step_from_move=150)`` adds 2 ms of
dead time to joint 2 from its 150th move (0-based count of the moves this generator made
of that joint) on.

Usage (as a library)::

    from independent_cycle_log import Conditions, IndependentCycleLog
    gen = IndependentCycleLog("ur10", Conditions(), seed=1)
    arrays, truth = gen.generate(500)        # 500 plans; call again to continue the log
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

FloatArray = NDArray[np.float64]

ONSET_FRACTION = 0.1  # docs/architecture.md: onset at 10 % of the commanded speed
RESPONSE_WINDOW_S = 0.2  # packages whose age makes the response truth of a move
REPOSITION_AFTER_S = 0.12  # poses="random": the pose jumps this long after streaming ends
_TWO_PI = 2.0 * math.pi
_DEG = math.pi / 180.0


@dataclass(frozen=True)
class Arm:
    """Timing and drive constants of one robot (all times in s)."""

    period_s: float
    interp_s: float  # drive interpolator: the reference is held this long
    sample_lead_s: float  # the drives latch the position this long before the boundary
    dead_s: tuple[float, ...]  # per-joint dead time, reference to drive
    fn_hz: tuple[float, ...]  # natural frequency of the velocity response at f = f_ref
    zeta: tuple[float, ...]  # its damping at f = f_ref
    lift_s: tuple[float, ...]  # extra dead time moving against gravity (full load)
    counts_per_rev: int  # encoder
    pub_phase_s: tuple[float, float]  # package put on the wire this long after sampling
    intake_margin_s: float  # a command must be in this long before the boundary
    shift_s: tuple[float, ...]  # the executor's per-joint actuation shift (its model)
    package_loss: float
    speed_max_rad_s: tuple[float, ...]
    q_lo: tuple[float, ...]
    q_hi: tuple[float, ...]


_UR_LO = (-math.pi, -math.pi, -2.6, -math.pi, -math.pi, -math.pi)
_UR_HI = (math.pi, 0.0, 2.6, math.pi, math.pi, math.pi)  # shoulder: above the table
_UR_SPEED = (120 * _DEG, 120 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG)

ROBOTS: dict[str, Arm] = {
    "ur10": Arm(
        period_s=0.008,
        interp_s=0.001,
        sample_lead_s=0.0005,
        dead_s=(0.0062, 0.0068, 0.0060, 0.0052, 0.0054, 0.0050),
        fn_hz=(22.0, 20.0, 25.0, 32.0, 32.0, 35.0),
        zeta=(0.70, 0.72, 0.68, 0.62, 0.62, 0.60),
        lift_s=(0.0, 0.0008, 0.0005, 0.0, 0.0002, 0.0),
        counts_per_rev=2**19,
        pub_phase_s=(0.0012, 0.0032),
        intake_margin_s=0.0006,
        shift_s=(0.021, 0.022, 0.021, 0.019, 0.019, 0.019),
        package_loss=0.001,
        speed_max_rad_s=_UR_SPEED,
        q_lo=_UR_LO,
        q_hi=_UR_HI,
    ),
    "ur10e": Arm(
        period_s=0.002,
        interp_s=0.0005,
        sample_lead_s=0.00025,
        dead_s=(0.0058, 0.0063, 0.0055, 0.0047, 0.0049, 0.0046),
        fn_hz=(24.0, 22.0, 27.0, 35.0, 35.0, 38.0),
        zeta=(0.70, 0.72, 0.68, 0.62, 0.62, 0.60),
        lift_s=(0.0, 0.0007, 0.0004, 0.0, 0.0002, 0.0),
        counts_per_rev=2**20,
        pub_phase_s=(0.0002, 0.0008),
        intake_margin_s=0.0002,
        shift_s=(0.017, 0.019, 0.018, 0.016, 0.016, 0.016),
        package_loss=0.002,
        speed_max_rad_s=_UR_SPEED,
        q_lo=_UR_LO,
        q_hi=_UR_HI,
    ),
}

N_BANDS = 8  # the drive's gain schedule: 8 inertia bands per joint


@dataclass(frozen=True, kw_only=True)
class Conditions:
    """What the cell does and how loaded its host is.

    Parameters
    ----------
    joints : tuple of int
        Joints that move (1-based); each plan moves 1 to ``max_joints`` of them.
    min_joints, max_joints : int
        Fewest and most joints one plan moves (uniform in between).
    speed_rad_s : (float, float)
        Range of the user's (lead joint's) speed, drawn per plan.
    acceleration_rad_s2 : float
        Planned acceleration (the executor's default cap, 8 rad/s^2).
    jerk_time_s : float
        Time to reach the acceleration (executor: jerk = 200 x acceleration: 5 ms).
    distance_rad : (float, float)
        Range of each moving joint's distance, drawn per joint and plan.
    pre_s, idle_s : (float, float)
        Streaming before the plan starts (schedule to start) and rest after streaming ends.
    wander_mean_s, wander_std_s, wander_ar : float
        Host read-time wander common to a plan: ``max(0, mean + std x)``, ``x`` an AR(1)
        over plans with this coefficient (stationary std 1).
    host_jitter_s : float
        Mean of the per-package host read jitter (gamma, shape 1.5), s.
    stall_rate_hz : float
        Host stalls per second: the host stalls 2-12 ms before reading a package (later
        packages queue behind it).
    net_min_s, net_jitter_s : float
        Network latency: minimum and mean gamma excess (shape 3), both directions.
    processing_s : float
        Mean host time from reading a package to sending its command (gamma, shape 2).
    dead_jitter_s : float
        Per-move standard deviation of the dead time (drive bus phase), s.
    package_loss : float or None
        Probability that a package is lost (None: the robot's default).
    poses : {"random", "walk"}
        "random": every plan starts from a fresh random pose within the working range (the
        reported pose jumps to it in the middle of the rest before the plan, 0.12 s after
        streaming ended: a repositioning the log does not show; the monitor's stillness
        check looks at the last 0.15 s before a send only). "walk": each plan starts where
        the previous one ended (consecutive moves share most of the pose).
    step_joint, step_s, step_from_move : int or None, float, int
        The injected change: ``step_s`` more dead time on ``step_joint`` from its
        ``step_from_move``-th move (0-based, counting this generator's moves of it) on.
    """

    joints: tuple[int, ...] = (1, 2, 3, 5)
    min_joints: int = 1
    max_joints: int = 3
    speed_rad_s: tuple[float, float] = (0.25, 1.0)
    acceleration_rad_s2: float = 8.0
    jerk_time_s: float = 0.005
    distance_rad: tuple[float, float] = (0.03, 0.6)
    pre_s: tuple[float, float] = (0.06, 0.2)
    idle_s: tuple[float, float] = (0.35, 0.9)
    wander_mean_s: float = 0.0015
    wander_std_s: float = 0.0015
    wander_ar: float = 0.6
    host_jitter_s: float = 0.00015
    stall_rate_hz: float = 0.25
    net_min_s: float = 0.0001
    net_jitter_s: float = 0.0002
    processing_s: float = 0.00008
    dead_jitter_s: float = 0.00015
    package_loss: float | None = None
    poses: str = "random"
    step_joint: int | None = None
    step_s: float = 0.0
    step_from_move: int = 0

    def replace(self, **kw: Any) -> Conditions:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **kw)


# ----------------------------------------------------------------------------- physics
def inertia_factor(joint: int, q: FloatArray) -> FloatArray:
    """Pose-dependent inertia factor in [0.35, 1] of ``joint`` (1-based) at poses q (n, 6):
    base: the squared horizontal reach; shoulder: squared shoulder-wrist distance; the
    others constant. Own crude model (not the spec's dynamics)."""
    q = np.atleast_2d(q)
    if joint == 1:
        r = np.abs(0.612 * np.cos(q[:, 1]) + 0.572 * np.cos(q[:, 1] + q[:, 2])) / 1.184
        return 0.35 + 0.65 * r**2
    if joint == 2:
        d2 = 0.612**2 + 0.572**2 + 2 * 0.612 * 0.572 * np.cos(q[:, 2])
        return 0.35 + 0.65 * d2 / 1.184**2
    return np.full(len(q), 0.7)


def gravity_load(joint: int, q: FloatArray) -> FloatArray:
    """Signed gravity load in [-1, 1] of the shoulder and elbow (0 for the others)."""
    q = np.atleast_2d(q)
    if joint == 2:
        return (0.6 * np.cos(q[:, 1]) + 0.4 * np.cos(q[:, 1] + q[:, 2])) / 1.0
    if joint == 3:
        return np.cos(q[:, 1] + q[:, 2])
    if joint == 5:
        return 0.3 * np.sin(q[:, 1] + q[:, 2] + q[:, 3])
    return np.zeros(len(q))


def band_of(f: FloatArray) -> NDArray[np.int64]:
    """Gain-schedule band (0..7) of an inertia factor."""
    return np.clip(((np.asarray(f) - 0.35) / 0.65 * N_BANDS).astype(np.int64), 0, N_BANDS - 1)


@cache
def _filters(
    robot: str, joint: int, band: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """ZOH-exact discrete filters (velocity, position) of joint's band: the response to the
    reference speed held over each physics step."""
    arm = ROBOTS[robot]
    f = 0.35 + (band + 0.5) * 0.65 / N_BANDS
    scale = math.sqrt(0.7 / f)  # loop tuned at f = 0.7: w ~ 1/sqrt(inertia), zeta ~ 1/sqrt(inertia)
    w = _TWO_PI * arm.fn_hz[joint - 1] * scale
    z = min(arm.zeta[joint - 1] * scale, 1.3)
    dt = arm.interp_s  # the reference is held over each interpolator step: ZOH is exact
    bv, av, _ = signal.cont2discrete(([w * w], [1.0, 2 * z * w, w * w]), dt, "zoh")
    bq, aq, _ = signal.cont2discrete(([w * w], [1.0, 2 * z * w, w * w, 0.0]), dt, "zoh")
    return np.ravel(bv), np.asarray(av), np.ravel(bq), np.asarray(aq)


def _trapezoid_position(
    t: FloatArray, a: FloatArray, v: FloatArray, total: FloatArray
) -> FloatArray:
    """Distance along a trapezoid (acceleration a, peak v, duration ``total``) at time t."""
    ta = v / a
    dist = v * (total - ta)
    up = 0.5 * a * t**2
    mid = 0.5 * a * ta**2 + v * (t - ta)
    down = dist - 0.5 * a * (total - t) ** 2
    out = np.where(t < ta, up, np.where(t < total - ta, mid, down))
    return np.where(t <= 0, 0.0, np.where(t >= total, dist, out))


def plan_speed(
    t: FloatArray, a: FloatArray, v: FloatArray, total: FloatArray, tj: float
) -> FloatArray:
    """Jerk-limited speed (>= 0): the trapezoid's speed averaged over a ``tj`` box."""
    p1 = _trapezoid_position(t, a, v, total)
    p0 = _trapezoid_position(t - tj, a, v, total)
    return (p1 - p0) / tj


# ----------------------------------------------------------------------------- generator
class IndependentCycleLog:
    """A cycle log of a cell executing plans, generated in batches of plans (episodes).

    Each call of :meth:`generate` continues the same log (time, pose, host wander, the
    joints' move counts): feed the chunks one after the other.
    """

    def __init__(
        self, robot: str = "ur10", cond: Conditions | None = None, *, seed: int = 0
    ) -> None:
        if robot not in ROBOTS:
            raise ValueError(f"robot {robot!r}: use one of {sorted(ROBOTS)}")
        self.robot = robot
        self.arm = ROBOTS[robot]
        self.cond = cond or Conditions()
        self.rng = np.random.default_rng([seed, 0xC7C1E])
        arm, rng = self.arm, self.rng
        self.period_s = arm.period_s
        self.ppm = float(rng.uniform(-40.0, 40.0))
        self.tp = arm.period_s * (1.0 + 1e-6 * self.ppm)  # host-clock length of a cycle
        self.c0 = 1000.0 + float(rng.uniform(0.0, arm.period_s))  # boundary 0, host time
        self.pub_phase_s = float(rng.uniform(*arm.pub_phase_s))
        self.loss = arm.package_loss if self.cond.package_loss is None else self.cond.package_loss
        self.lsb = _TWO_PI / arm.counts_per_rev
        if self.cond.poses not in ("random", "walk"):
            raise ValueError(f"poses={self.cond.poses!r}: use 'random' or 'walk'")
        self.q_next = self._random_pose()
        self.q_plan = self.q_next.copy()
        self.q_act = self.q_plan.copy()
        self.k_next = 0  # next controller cycle to emit
        self.t_block = self.c0 + 0.6  # schedule time of the next plan
        self.x_wander = float(rng.standard_normal())
        self.moves_of = np.zeros(6, dtype=np.int64)
        self.episodes = 0
        self.rows = 0
        self.last_arrival = -math.inf
        self.last_send = -math.inf

    def _random_pose(self) -> FloatArray:
        lo, hi = np.array(self.arm.q_lo), np.array(self.arm.q_hi)
        return np.asarray(self.rng.uniform(lo + 0.05, hi - 0.05))

    # ------------------------------------------------------------------ plans
    def _plans(self, n: int) -> dict[str, Any]:
        c, arm, rng = self.cond, self.arm, self.rng
        lo, hi = np.array(arm.q_lo), np.array(arm.q_hi)
        joints = np.array(c.joints, dtype=np.int64)
        S = min(c.max_joints, len(joints))
        jt = np.full((n, S), -1, dtype=np.int64)  # 0-based joint per slot, -1 unused
        sgn = np.zeros((n, S))
        dist = np.zeros((n, S))
        q0 = np.zeros((n, 6))
        h = np.zeros(n)
        move_idx = np.full((n, S), -1, dtype=np.int64)
        for e in range(n):
            k = int(rng.integers(min(c.min_joints, S), S + 1))
            sel = rng.choice(joints, size=k, replace=False) - 1
            if c.poses == "random":
                self.q_plan = self.q_next.copy()
                self.q_next = self._random_pose()
            q0[e] = self.q_plan
            for s, j in enumerate(sel):
                d = float(rng.uniform(*c.distance_rad))
                sg = 1.0 if rng.random() < 0.5 else -1.0
                if not lo[j] <= self.q_plan[j] + sg * d <= hi[j]:
                    sg = -sg
                    if not lo[j] <= self.q_plan[j] + sg * d <= hi[j]:
                        d = 0.5 * (hi[j] - lo[j]) * 0.1
                        sg = 1.0 if self.q_plan[j] < 0.5 * (lo[j] + hi[j]) else -1.0
                jt[e, s], sgn[e, s], dist[e, s] = j, sg, d
                self.q_plan[j] += sg * d
                move_idx[e, s] = self.moves_of[j]
                self.moves_of[j] += 1
            self.x_wander = c.wander_ar * self.x_wander + math.sqrt(1.0 - c.wander_ar**2) * float(
                rng.standard_normal()
            )
            h[e] = max(0.0, c.wander_mean_s + c.wander_std_s * self.x_wander)
        used = jt >= 0
        a = c.acceleration_rad_s2
        vmax = np.array(arm.speed_max_rad_s)[np.where(used, jt, 0)]
        v_user = rng.uniform(*c.speed_rad_s, n)[:, None]
        v_lead = np.minimum(v_user, vmax)
        t_j = np.where(dist >= v_lead**2 / a, dist / v_lead + v_lead / a, 2.0 * np.sqrt(dist / a))
        total = np.max(np.where(used, t_j, 0.0), axis=1)
        disc = np.maximum((a * total[:, None]) ** 2 - 4.0 * a * dist, 0.0)
        v_peak = np.where(used, 0.5 * (a * total[:, None] - np.sqrt(disc)), 0.0)
        # per slot physics: dead time (+ lift, jitter, step) and gain-schedule band
        dead = np.zeros((n, S))
        band = np.zeros((n, S), dtype=np.int64)
        for j in np.unique(jt[used]):
            m = jt == j
            e_idx = np.nonzero(m)[0]
            load = gravity_load(int(j) + 1, q0[e_idx])
            lift = arm.lift_s[j] * np.maximum(0.0, sgn[m] * load)
            dead[m] = arm.dead_s[j] + lift + rng.normal(0.0, c.dead_jitter_s, m.sum())
            band[m] = band_of(inertia_factor(int(j) + 1, q0[e_idx]))
        stepped = np.zeros((n, S), dtype=bool)
        if c.step_joint is not None:
            stepped = (jt == c.step_joint - 1) & (move_idx >= c.step_from_move)
            dead = dead + np.where(stepped, c.step_s, 0.0)
        pre = rng.uniform(*c.pre_s, n)
        idle = rng.uniform(*c.idle_s, n)
        shift = np.array(arm.shift_s)
        settle = 3 * arm.period_s + shift.max()
        stream = pre + total + c.jerk_time_s + settle
        starts = self.t_block + np.concatenate(([0.0], np.cumsum(stream + idle)[:-1]))
        self.t_block = float(starts[-1] + stream[-1] + idle[-1])
        q_after = np.zeros((n, 6))  # the pose after the rest's repositioning (random)
        if c.poses == "random":
            q_after[:-1] = q0[1:]
            q_after[-1] = self.q_next
        return {
            "q_after": q_after, "jt": jt, "sgn": sgn, "dist": dist, "q0": q0, "h": h, "move_idx": move_idx,
            "v_peak": v_peak, "total": total, "dead": dead, "band": band, "stepped": stepped,
            "B": starts, "S": starts + pre, "Z": starts + stream, "used": used,
        }  # fmt: skip

    # ------------------------------------------------------------------ one batch
    def generate(self, n_episodes: int) -> tuple[dict[str, NDArray[Any]], dict[str, NDArray[Any]]]:
        """The next ``n_episodes`` plans of the log.

        Returns
        -------
        (dict, dict)
            The rows (the columns of ``CycleLog.arrays()``: ``arrival_s``,
            ``controller_s``, ``sequence``, ``send_s``, ``qd_cmd``, ``q``, ``coasted``) and
            the truth per move (arrays): ``episode``, ``joint`` (1-based), ``direction``,
            ``send_s`` (first command), ``row`` (its log row, counted from the log's first
            row), ``true_actuation_s``, ``true_response_s``, ``true_lag_s``, ``stepped``,
            ``joint_move`` (0-based move count of the joint), ``peak_speed_rad_s``,
            ``joints_in_plan``, ``wander_s``, ``q_start`` (n, 6) (planned).
        """
        c, arm, rng = self.cond, self.arm, self.rng
        T, tp = arm.period_s, self.tp
        P = self._plans(n_episodes)
        E, S = P["jt"].shape
        jt, used = P["jt"], P["used"]

        # ---- controller cycles of the batch; block e = cycles [kb[e], kb[e+1])
        k_end = np.ceil((np.r_[P["B"][1:], self.t_block] - self.c0) / tp).astype(np.int64)
        kb = np.r_[self.k_next, k_end[:-1]]
        kb = np.maximum(kb, self.k_next)
        k_all = np.arange(self.k_next, k_end[-1], dtype=np.int64)
        self.k_next = int(k_end[-1])
        ep = np.searchsorted(kb, k_all, side="right") - 1
        n_cyc = k_end - kb
        kmax = int(n_cyc.max())
        b = self.c0 + k_all * tp  # boundary, host time
        nr = len(k_all)

        # ---- state packages
        pub = self.pub_phase_s + rng.gamma(2.0, 1e-5, nr)
        net = c.net_min_s + rng.gamma(3.0, c.net_jitter_s / 3.0, nr)
        host = P["h"][ep] + rng.gamma(1.5, c.host_jitter_s / 1.5, nr)
        stall = rng.random(nr) < c.stall_rate_hz * T
        host = host + np.where(stall, rng.uniform(0.002, 0.012, nr), 0.0)
        arrival = np.maximum.accumulate(np.r_[self.last_arrival, b + pub + net + host])[1:]
        lost = rng.random(nr) < self.loss
        sample_t = b - arm.sample_lead_s  # latched just before the boundary
        streaming = ~lost & (arrival >= P["B"][ep]) & (arrival <= P["Z"][ep])

        # ---- commands (executor-like)
        srow = np.flatnonzero(streaming)
        sep = ep[srow]
        send = arrival[srow] + rng.gamma(2.0, c.processing_s / 2.0, len(srow))
        send = np.maximum.accumulate(np.r_[self.last_send, send])[1:]
        if len(send):
            self.last_send = float(send[-1])
        shift = np.array(arm.shift_s)[np.where(used, jt, 0)][sep]  # (ns, S)
        t_plan = send[:, None] - P["S"][sep][:, None] + shift + T
        v_slot = plan_speed(
            t_plan, c.acceleration_rad_s2, P["v_peak"][sep], P["total"][sep][:, None],
            c.jerk_time_s,
        ) * P["sgn"][sep]  # fmt: skip
        v_slot = np.where(used[sep], v_slot, 0.0)
        first = np.r_[True, sep[1:] != sep[:-1]]
        v_prev = np.where(first[:, None], 0.0, np.roll(v_slot, 1, axis=0))
        amax = 8.0  # the executor's limit: min(spec 10-15 rad/s^2, cap 8)
        acc = np.clip(np.max(np.abs(v_slot - v_prev), axis=1) / T, 0.5 * amax, amax)
        qd_cmd = np.zeros((len(srow), 6))
        for s in range(S):
            m = used[sep, s]
            qd_cmd[np.flatnonzero(m), jt[sep[m], s]] = v_slot[m, s]

        # ---- controller intake: last command in before each boundary (margin) wins
        at_ctrl = send + c.net_min_s + rng.gamma(3.0, c.net_jitter_s / 3.0, len(srow))
        at_ctrl = np.maximum.accumulate(at_ctrl) if len(at_ctrl) else at_ctrl
        k_in = np.ceil((at_ctrl + arm.intake_margin_s - self.c0) / tp).astype(np.int64)
        i_in = np.minimum(k_in - kb[sep], n_cyc[sep] - 1)
        last = np.r_[(sep[1:] != sep[:-1]) | (i_in[1:] != i_in[:-1]), True]
        new_v = np.full((E, kmax, S), np.nan)
        new_a = np.full((E, kmax), np.nan)
        new_v[sep[last], i_in[last]] = v_slot[last]
        new_a[sep[last], i_in[last]] = acc[last]

        # ---- reference: rate-limited follower, sampled by the drive interpolator
        m_int = round(T / arm.interp_s)
        di = tp / m_int  # host-clock length of an interpolator step
        r0 = np.zeros((E, S))
        tgt = np.zeros((E, S))
        t0 = np.zeros(E)
        dur = np.ones(E)
        R0 = np.zeros((E, kmax, S))
        TG = np.zeros((E, kmax, S))
        T0 = np.zeros((E, kmax))
        DUR = np.ones((E, kmax))
        has_new = np.isfinite(new_a)
        for i in np.flatnonzero(has_new.any(axis=0)):
            rows_i = np.flatnonzero(has_new[:, i])
            ti = i * tp
            # the state this cycle starts from: the last update's ramp, carried forward
            frac = np.clip((ti - t0[rows_i]) / dur[rows_i], 0.0, 1.0)
            rnow = r0[rows_i] + (tgt[rows_i] - r0[rows_i]) * frac[:, None]
            vn = new_v[rows_i, i]
            d = np.max(np.abs(vn - rnow), axis=1) / new_a[rows_i, i]
            r0[rows_i], tgt[rows_i], t0[rows_i] = rnow, vn, ti
            dur[rows_i] = np.maximum(d, 1e-9)
            R0[rows_i, i], TG[rows_i, i], T0[rows_i, i], DUR[rows_i, i] = rnow, vn, ti, dur[rows_i]
        # forward-fill the ramp state to the cycles without a new command
        last_upd = np.maximum.accumulate(np.where(has_new, np.arange(kmax)[None, :], -1), axis=1)
        ee = np.arange(E)[:, None]
        src = np.maximum(last_upd, 0)
        never = last_upd < 0
        R0 = np.where(never[..., None], 0.0, R0[ee, src])
        TG = np.where(never[..., None], 0.0, TG[ee, src])
        T0 = np.where(never, 0.0, T0[ee, src])
        DUR = np.where(never, 1.0, DUR[ee, src])
        t_sub = np.arange(kmax)[:, None] * tp + np.arange(m_int)[None, :] * di  # (kmax, m_int)
        frac = np.clip((t_sub[None] - T0[..., None]) / DUR[..., None], 0.0, 1.0)  # (E,kmax,m)
        ref = R0[..., None] + (TG - R0)[..., None] * frac[:, :, None, :]  # (E, kmax, S, m)
        ref = ref.transpose(0, 2, 1, 3).reshape(E, S, kmax * m_int)  # held over each step

        # ---- drive: the second-order response (per joint and band) to the held reference,
        # delayed by the dead time (LTI: delay the output), positions by cubic Hermite
        n_grid = kmax * m_int
        t_pk = np.arange(kmax) * tp - arm.sample_lead_s  # sampling instants, local time
        disp = np.zeros((E, S, kmax))  # displacement at each package's sampling instant
        final = np.zeros((E, S))
        onset_local = np.full((E, S), np.nan)
        peak_cmd = np.zeros((E, S))
        for s in range(S):
            m = used[sep, s]
            np.maximum.at(peak_cmd[:, s], sep[m], np.abs(v_slot[m, s]))
        level = ONSET_FRACTION * peak_cmd
        for j in np.unique(jt[used]):
            for bnd in np.unique(P["band"][(jt == j) & used]):
                ee, ss = np.nonzero((jt == j) & (P["band"] == bnd) & used)
                g = np.arange(len(ee))
                bv, av, bq, aq = _filters(self.robot, int(j) + 1, int(bnd))
                u = ref[ee, ss]
                vel = signal.lfilter(bv, av, u, axis=1)
                pos = signal.lfilter(bq, aq, u, axis=1)
                # positions at (sampling instant - dead time)
                x = (t_pk[None, :] - P["dead"][ee, ss][:, None]) / di
                i0 = np.clip(np.floor(x).astype(np.int64), 0, n_grid - 2)
                h = np.clip(x - i0, 0.0, 1.0)
                p0, p1 = np.take_along_axis(pos, i0, 1), np.take_along_axis(pos, i0 + 1, 1)
                w0, w1 = (
                    np.take_along_axis(vel, i0, 1) * di,
                    np.take_along_axis(vel, i0 + 1, 1) * di,
                )
                h2, h3 = h * h, h * h * h
                herm = (
                    (2 * h3 - 3 * h2 + 1) * p0 + (h3 - 2 * h2 + h) * w0
                    + (-2 * h3 + 3 * h2) * p1 + (h3 - h2) * w1
                )  # fmt: skip
                disp[ee, ss] = np.where(x < 0, 0.0, herm)
                final[ee, ss] = pos[g, n_cyc[ee] * m_int - 1]
                sv = vel * P["sgn"][ee, ss][:, None]
                lv = level[ee, ss][:, None]
                above = sv >= lv
                k1 = np.argmax(above, axis=1)
                ok = above[g, k1] & (k1 > 0)
                k1 = np.maximum(k1, 1)
                v0, v1 = sv[g, k1 - 1], sv[g, k1]
                t_on = (k1 - 1 + (lv[:, 0] - v0) / np.where(v1 > v0, v1 - v0, 1.0)) * di
                onset_local[ee, ss] = np.where(ok, t_on + P["dead"][ee, ss], np.nan)

        # ---- reported positions
        dq = np.zeros((E, 6))
        for s in range(S):
            m = used[:, s]
            dq[np.flatnonzero(m), jt[m, s]] += final[m, s]
        if c.poses == "random":
            q_start = P["q0"]
        else:
            q_start = self.q_act + np.concatenate((np.zeros((1, 6)), np.cumsum(dq, axis=0)[:-1]))
            self.q_act = self.q_act + dq.sum(axis=0)
        q_true = q_start[ep].copy()
        i_loc = k_all - kb[ep]
        for s in range(S):
            m = used[ep, s]
            q_true[np.flatnonzero(m), jt[ep[m], s]] += disp[ep[m], s, i_loc[m]]
        if c.poses == "random":  # repositioned (not logged as a move) mid-rest
            jumped = b >= P["Z"][ep] + REPOSITION_AFTER_S
            q_true[jumped] = P["q_after"][ep[jumped]]
        q_rep = np.round(q_true / self.lsb) * self.lsb

        # ---- the rows
        keep = ~lost
        send_col = np.full(nr, np.nan)
        send_col[srow] = send
        qd_col = np.full((nr, 6), np.nan)
        qd_col[srow] = qd_cmd
        rows = {
            "arrival_s": arrival[keep],
            "controller_s": (k_all * T)[keep],
            "sequence": k_all[keep],
            "send_s": send_col[keep],
            "qd_cmd": qd_col[keep],
            "q": q_rep[keep],
            "coasted": np.zeros(int(keep.sum()), dtype=bool),
        }
        row_of = np.cumsum(keep) - 1 + self.rows  # global log row of each cycle kept
        if nr:
            self.last_arrival = float(arrival[-1])

        # ---- truth per move (each used slot whose joint was commanded and moved)
        age = np.where(lost, np.nan, arrival - sample_t)
        n_w = round(RESPONSE_WINDOW_S / T)
        parts = []
        for s in range(S):
            vs = v_slot[:, s] * P["sgn"][sep, s]  # commanded speed in the move's direction
            pos = np.flatnonzero(vs > 0)
            e_m, first = np.unique(sep[pos], return_index=True)
            i0 = pos[first]  # streamed row of each move's first command
            lv_row = level[sep, s]
            cr = np.flatnonzero((vs >= lv_row) & (vs > 0))
            e_c, first_c = np.unique(sep[cr], return_index=True)
            kk = cr[first_c][np.searchsorted(e_c, e_m)]  # first command at the onset level
            ok = used[e_m, s] & np.isfinite(onset_local[e_m, s])
            e_m, i0, kk = e_m[ok], i0[ok], kk[ok]
            lv = level[e_m, s]
            tb, vb = send[kk] + T, vs[kk]
            at_first = kk == i0
            ta = np.where(at_first, send[i0], send[np.maximum(kk - 1, 0)] + T)
            va = np.where(at_first, 0.0, vs[np.maximum(kk - 1, 0)])
            t_cmd = ta + (lv - va) / (vb - va) * (tb - ta)
            t_on = b[np.searchsorted(ep, e_m)] + onset_local[e_m, s]  # local 0: first boundary
            send0 = send[i0]
            w0 = np.searchsorted(arrival, send0, side="left")
            widx = np.minimum(w0[:, None] + np.arange(n_w)[None, :], nr - 1)
            inwin = arrival[widx] <= send0[:, None] + RESPONSE_WINDOW_S
            resp = np.nanmedian(np.where(inwin, age[widx], np.nan), axis=1)
            act = t_on - t_cmd
            parts.append({
                "episode": self.episodes + e_m,
                "slot": np.full(len(e_m), s),
                "joint": jt[e_m, s] + 1,
                "direction": P["sgn"][e_m, s].astype(np.int64),
                "send_s": send0,
                "row": row_of[srow[i0]],
                "true_actuation_s": act,
                "true_response_s": resp,
                "true_lag_s": act + resp,
                "stepped": P["stepped"][e_m, s],
                "joint_move": P["move_idx"][e_m, s],
                "peak_speed_rad_s": peak_cmd[e_m, s],
                "joints_in_plan": used[e_m].sum(axis=1),
                "wander_s": P["h"][e_m],
                "q_start": P["q0"][e_m],
            })  # fmt: skip
        out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        order = np.lexsort((out.pop("slot"), out["episode"]))
        out = {k: v[order] for k, v in out.items()}
        self.episodes += E
        self.rows += int(keep.sum())
        return rows, out


def generate_cycle_log(
    robot: str, n_episodes: int, cond: Conditions | None = None, *, seed: int = 0
) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """A whole log of ``n_episodes`` plans: ``(arrays, meta)``; ``meta`` holds ``period_s``,
    ``robot`` (for ``save_cycle_log``) and ``truth`` (see :meth:`IndependentCycleLog.generate`)."""
    gen = IndependentCycleLog(robot, cond, seed=seed)
    chunks, truths = [], []
    left = n_episodes
    while left > 0:
        rows, truth = gen.generate(min(left, 200))
        chunks.append(rows)
        truths.append(truth)
        left -= 200
    arrays = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    truth = {k: np.concatenate([t[k] for t in truths]) for k in truths[0]}
    meta = {"period_s": gen.period_s, "robot": robot, "truth": truth, "ppm": gen.ppm,
            "publish_phase_s": gen.pub_phase_s}  # fmt: skip
    return arrays, meta
