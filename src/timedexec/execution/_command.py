"""One cycle's speed command: the position correction and the limits.

:class:`SmithPredictor` is the optional position correction: the back-dated reported
position is compared with the plan at the instant the package describes, and the
corrections already sent whose action is not yet visible in that package are subtracted, so
the loop's delay does not make the correction oscillate (the executor adds ``gain · error``
to the speed command, ``TimedExecutor(position_gain_1_s=...)``). :func:`limit_command`
keeps a command inside the speed, acceleration and position limits;
:func:`ramp_acceleration` is the ``speedj`` acceleration that ramps it over one period.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

from timedexec.execution._plan import ExecutionLimits, JointPlan
from timedexec.robots import RobotSpec

__all__ = ["SmithPredictor", "limit_command", "ramp_acceleration"]

FloatArray = NDArray[np.float64]


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
