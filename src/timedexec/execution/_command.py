"""One cycle's speed command: the shifted feed-forward, the position correction, the limits.

:class:`CommandStream` is the command side of the executor's loop: per cycle, joint ``j``
gets the active plan's speed where its command acts (its shift ``tau_j`` plus the ramp
later), the position correction, inside the limits; it keeps the previous command.
:class:`SmithPredictor` is the optional position correction: the back-dated reported
position is compared with the plan at the instant the package describes, and the
corrections already sent whose action is not yet visible in that package are subtracted, so
the loop's delay does not make the correction oscillate (the executor adds ``gain · error``
to the speed command, ``ExecutorSettings(position_gain_1_s=...)``). :func:`limit_command`
keeps a command inside the speed, acceleration and position limits;
:class:`FrictionFeed` is the feed-forward: the plan's speed plus what carries a tracking
model's friction offsets (:class:`~timedexec.tasks.TrackingDelays`);
:func:`ramp_acceleration` is the ``speedj`` acceleration that ramps it over one period.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.execution._plan import ExecutionLimits, JointPlan
from timedexec.execution._state import StateTracker
from timedexec.robots import RobotSpec

__all__ = [
    "FRICTION_BUILD_S",
    "FRICTION_SPEED_RAD_S",
    "CommandStream",
    "FrictionFeed",
    "SmithPredictor",
    "friction_sign",
    "limit_command",
    "ramp_acceleration",
]


#: Speed scale of the smooth sign that carries a joint's friction offset, rad/s: the offset
#: is ``friction_rad * tanh(v / FRICTION_SPEED_RAD_S)`` (96 % of it from 0.04 rad/s on).
FRICTION_SPEED_RAD_S = 0.02
#: Plan time over which a friction offset builds from a plan's start, s (a smooth step).
FRICTION_BUILD_S = 0.25


def friction_sign(v_rad_s: ArrayLike) -> FloatArray:
    """The smooth sign of a joint speed that scales its friction offset (-1..1)."""
    return np.tanh(np.asarray(v_rad_s, dtype=float) / FRICTION_SPEED_RAD_S)


class FrictionFeed:
    """The feed-forward of one plan: the planned speed, plus what carries friction offsets.

    A joint that trails its command by a position (kinetic friction over the velocity
    loop's integral gain, ``friction_rad``, a tracking model's) is put on its plan by
    commanding that much further: ``friction_rad[k] * friction_sign(v)`` (``k`` 0 moving
    positive, 1 negative), built over the plan's first :data:`FRICTION_BUILD_S` (a smooth
    step) and turning over where the joint reverses. What the limits clipped of it is
    owed, not lost (:meth:`commanded`): a time-optimal approach runs at the acceleration
    limits, and built at the speed sign's pace the offset asked 8 rad/s² more of a UR10
    than they allow.

    Parameters
    ----------
    friction_rad : array (2, 6) or (6,)
        Offset per direction (positive, negative) and joint, rad; (6,): the same both
        ways (zeros: the planned speed alone).
    """

    #: The smooth sign of a joint speed that scales its friction offset (-1..1):
    #: ``tanh(v / FRICTION_SPEED_RAD_S)``; a fit of the offsets uses the same one.
    sign = staticmethod(friction_sign)

    def __init__(self, friction_rad: ArrayLike) -> None:
        self.friction_rad = np.broadcast_to(np.asarray(friction_rad, dtype=float), (2, 6))
        self.sent_rad = np.zeros(6)  # offset commanded so far
        self._planned = np.zeros(6)
        self._active = bool(self.friction_rad.any())  # once: speed() runs every cycle

    def speed(self, plan: JointPlan, t_plan_s: FloatArray, period_s: float) -> FloatArray:
        """Joint ``j``'s speed command (6,), rad/s, for plan time ``t_plan_s[j]``: the
        plan's speed plus what brings the offset sent to where it is one period later."""
        v = self._planned = plan.velocity_per_joint(t_plan_s)
        if not self._active:
            return v
        later = t_plan_s + period_s
        x = np.clip(later / FRICTION_BUILD_S, 0.0, 1.0)
        sgn = friction_sign(plan.velocity_per_joint(later))
        e = np.where(sgn >= 0, self.friction_rad[0], self.friction_rad[1])
        due = e * sgn * x * x * (3.0 - 2.0 * x)
        return np.asarray(v + (due - self.sent_rad) / period_s)

    def commanded(self, v_rad_s: FloatArray, period_s: float) -> None:
        """Count the offset a sent feed-forward ``v_rad_s`` (after the limits) carries."""
        if self._active:
            self.sent_rad = self.sent_rad + (np.asarray(v_rad_s) - self._planned) * period_s


class SmithPredictor:
    """Position error where the next command acts, with the unseen corrections removed.

    Parameters
    ----------
    history : int
        At most this many sent corrections are kept (older ones are long visible).
    """

    def __init__(self, history: int = 4096) -> None:
        # Corrections sent: (host send time, s; correction per joint, rad/s).
        self._sent: deque[tuple[float, FloatArray]] = deque(maxlen=history)

    def __len__(self) -> int:
        return len(self._sent)

    def clear(self) -> None:
        """Forget the corrections sent (a new plan)."""
        self._sent.clear()

    def record(self, send_s: float, correction_rad_s: FloatArray) -> None:
        """Remember the correction (6,), rad/s, in the command sent at host time ``send_s``."""
        self._sent.append((send_s, correction_rad_s))

    def predicted_error(
        self,
        plan: JointPlan,
        sample_time_s: float,
        q_rad: FloatArray,
        tau_s: FloatArray,
        now_s: float,
    ) -> FloatArray:
        """Plan minus physical position where the next command acts, rad (6,).

        Parameters
        ----------
        plan : JointPlan
            The active plan (scheduled).
        sample_time_s : float
            Host time the newest package describes (back-dated), s: ``t_phys``.
        q_rad : ndarray (6,)
            Its reported joint positions, rad.
        tau_s : ndarray (6,)
            Per joint, the shift of the command stream (actuation delay), s.
        now_s : float
            Host time of the command being computed, s.

        Notes
        -----
        The package shows the error at ``t_phys``; a correction sent at ``s`` acts over
        ``[s + tau, s_next + tau]``, so the part of it after ``t_phys`` is not in the
        package yet and is subtracted.
        """
        t_phys = sample_time_s
        q_plan, _, _ = plan.sample(t_phys - plan.start_time_s)
        error = q_plan - q_rad
        sends = self._sent
        tau_max = float(np.max(tau_s))
        # A command acts until the next one is sent (plus tau): once that lies before the
        # package's instant it is fully visible, and so for every later package.
        while len(sends) > 1 and sends[1][0] + tau_max <= t_phys:
            sends.popleft()
        if not sends:
            return np.asarray(error)
        start = np.fromiter((c[0] for c in sends), float, len(sends))
        end = np.append(start[1:], now_s)
        u = np.stack([c[1] for c in sends])
        # Duration of each command's action after t_phys, per joint (tau differs).
        pending = np.clip(
            end[:, None] + tau_s - np.maximum(start[:, None] + tau_s, t_phys),
            0.0,
            (end - start)[:, None],
        )
        return np.asarray(error - np.sum(u * pending, axis=0))


def limit_command(
    target_rad_s: FloatArray,
    *,
    v_prev_rad_s: FloatArray,
    since_s: float,
    q_act_rad: FloatArray,
    spec: RobotSpec,
    limits: ExecutionLimits,
    period_s: float,
) -> FloatArray:
    """The speed command (6,), rad/s, closest to ``target_rad_s`` within the limits.

    Parameters
    ----------
    target_rad_s : ndarray (6,)
        Wanted joint speeds, rad/s.
    v_prev_rad_s : ndarray (6,)
        The previous command, rad/s.
    since_s : float
        Time since the previous command, s: the speed may change by the acceleration limit
        times that (at least one period, at most four: missed packages do not slow the ramp).
    q_act_rad : ndarray (6,)
        Estimated position of each joint where this command acts (after its delay), rad:
        the joint must still be able to stop before its position limit.
    spec : RobotSpec
        The robot (speed, acceleration and position limits).
    limits : ExecutionLimits
        Fractions of the spec's limits to command with.
    period_s : float
        Controller period, s.
    """
    vmax = limits.velocity(spec)
    amax = limits.acceleration(spec)
    v = np.clip(target_rad_s, -vmax, vmax)
    step = amax * min(max(period_s, since_s), 4.0 * period_s)
    v = np.clip(v, v_prev_rad_s - step, v_prev_rad_s + step)
    lo = np.asarray(spec.q_min_rad)
    hi = np.asarray(spec.q_max_rad)
    room_hi = np.maximum(hi - q_act_rad - v * period_s, 0.0)
    room_lo = np.maximum(q_act_rad - lo + v * period_s, 0.0)
    v = np.minimum(v, np.sqrt(2.0 * amax * room_hi))
    return np.asarray(np.maximum(v, -np.sqrt(2.0 * amax * room_lo)))


def ramp_acceleration(
    v_rad_s: FloatArray, v_prev_rad_s: FloatArray, amax_rad_s2: FloatArray, period_s: float
) -> float:
    """``speedj`` acceleration, rad/s²: the leading joint's change from ``v_prev_rad_s`` to
    ``v_rad_s`` over one period, clamped to [half the smallest, the largest] of
    ``amax_rad_s2`` (6,)."""
    need = float(np.max(np.abs(v_rad_s - v_prev_rad_s))) / period_s
    floor = 0.5 * float(np.min(amax_rad_s2))
    return float(min(max(need, floor), float(np.max(amax_rad_s2))))


class CommandStream:
    """The command side of the loop: the active plan's speed at each joint's shifted
    instant, the optional position correction, the limits, the previous command.

    Parameters
    ----------
    limits : ExecutionLimits
        Fractions of the spec's limits to command with.
    gain_1_s : float
        Position-correction gain, 1/s (0: feed-forward only; :class:`SmithPredictor`).

    Attributes
    ----------
    tau_s, tau_std_s : ndarray (6,)
        The active plan's per-joint shift (predicted actuation delay) and its
        single-trial std, s.
    v_prev_rad_s : ndarray (6,)
        The last command sent, rad/s (zeros: nothing moving is commanded).
    last_send_s : float
        Host time it left, s (NaN before the first).
    clip_count : int
        Commands a limit clipped.
    """

    def __init__(self, limits: ExecutionLimits, gain_1_s: float) -> None:
        self.limits, self.gain_1_s = limits, gain_1_s
        self.tau_s, self.tau_std_s, self.v_prev_rad_s = np.zeros(6), np.zeros(6), np.zeros(6)
        self.last_send_s = math.nan
        self.clip_count = 0
        self._feed = FrictionFeed(np.zeros(6))
        self._correction = SmithPredictor()

    @property
    def moving(self) -> bool:
        """Whether the last command asked any joint to move."""
        return bool(np.any(self.v_prev_rad_s != 0))

    def begin(self, plan: JointPlan, *, new: bool) -> None:
        """Stream the prepared ``plan`` from now on (its ``meta``: the shifts; a ``new``
        plan also starts its own feed, with its friction offsets, and correction)."""
        if new:
            self._correction.clear()
            self._feed = FrictionFeed(plan.meta.get("friction_rad", np.zeros(6)))
        self.tau_s = np.asarray(plan.meta["actuation_s"], float)
        self.tau_std_s = np.asarray(plan.meta["actuation_std_s"], float)

    def command(
        self,
        plan: JointPlan | None,
        now: float,
        state: StateTracker,
        last_plan: JointPlan | None,
        spec: RobotSpec,
        period: float,
    ) -> tuple[FloatArray, float, bool]:
        """This cycle's speed command (6,), rad/s, its ``speedj`` acceleration, rad/s², and
        whether a limit clipped it, for a command leaving at host time ``now`` (``plan``
        None: hold still; ``last_plan``: what the state estimate follows)."""
        tau = self.tau_s
        target = feed_forward = np.zeros(6)
        correcting = False
        if plan is not None:
            # Joint j gets the plan's speed where its command acts: tau_j plus the ramp later.
            t_act = now - plan.start_time_s + tau + period
            target = feed_forward = self._feed.speed(plan, t_act, period)
            sample = state.sample
            if self.gain_1_s > 0 and sample is not None:
                correcting = True
                t_phys, q, _ = sample
                error = self._correction.predicted_error(plan, t_phys, q, tau, now)
                target = feed_forward + self.gain_1_s * error
        since = now - self.last_send_s if math.isfinite(self.last_send_s) else period
        # Where this command acts (after each joint's delay) the joint must be able to stop.
        q_act = state.q_per_joint(now + tau + period, plan or last_plan)
        v = limit_command(
            target,
            v_prev_rad_s=self.v_prev_rad_s,
            since_s=since,
            q_act_rad=q_act,
            spec=spec,
            limits=self.limits,
            period_s=period,
        )
        if plan is not None:  # what a limit clipped is owed once: to the correction if any
            self._feed.commanded(feed_forward if correcting else v, period)
        clipped = bool(np.any(np.abs(v - target) > 1e-12))
        if clipped:
            self.clip_count += 1
        if correcting:
            self._correction.record(now, v - feed_forward)
        amax = self.limits.acceleration(spec)
        return v, ramp_acceleration(v, self.v_prev_rad_s, amax, period), clipped

    def sent(self, v_rad_s: FloatArray, now_s: float) -> None:
        """The command ``v_rad_s`` left at host time ``now_s``."""
        self.v_prev_rad_s = v_rad_s
        self.last_send_s = now_s

    def halt(self) -> None:
        """Nothing moving is commanded any more (a stop, a fault)."""
        self.v_prev_rad_s = np.zeros(6)
