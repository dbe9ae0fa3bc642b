"""Fitting the lag a tracking arm keeps: per joint, the time shift that aligns its
positions with the plan (:func:`fit_joint_lags`), or a dead time and friction offsets per
direction (:func:`fit_dead_time_and_friction`, :func:`fit_tracking` -> :class:`TrackingFit`),
and the instants a run's reported positions describe (:func:`sampling_times_s`). The
model built on them and its calibrations: :mod:`timedexec.tasks._tracking`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError
from timedexec.execution import FrictionFeed, JointPlan

__all__ = [
    "DEAD_TIME_SE_S",
    "POSITION_FLOOR_RAD",
    "TrackingFit",
    "cruise_positions",
    "fit_dead_time_and_friction",
    "fit_joint_lags",
    "fit_tracking",
    "measure_tracking_delays",
    "sampling_times_s",
]


def fit_joint_lags(
    plan: JointPlan,
    times_s: ArrayLike,
    q_rad: ArrayLike,
    *,
    iterations: int = 4,
) -> FloatArray:
    """Per joint, the time lag ``L`` (s) that best aligns ``q`` with the plan: ``q(t) ≈
    plan(t - L)`` in the least-squares sense.

    Gauss-Newton on ``L`` per joint from 0 (``iterations`` steps; the lag's error after
    four is below a microsecond for lags up to 0.1 s on these paths).

    Parameters
    ----------
    plan : JointPlan
        Scheduled (``start_time_s`` host time).
    times_s : array (n,)
        Host times the positions describe, s.
    q_rad : array (n, 6)
        Joint positions, rad.

    Returns
    -------
    ndarray (6,)
        Lag per joint, s (positive: the joint is late). NaN for a joint that does not move
        in the window.

    Raises
    ------
    ConfigError
        Fewer than 3 samples, or shapes that do not match.
    """
    t = np.asarray(times_s, dtype=float).reshape(-1)
    q = np.asarray(q_rad, dtype=float).reshape(-1, 6)
    if len(t) != len(q) or len(t) < 3:
        raise ConfigError(
            f"fit_joint_lags needs >= 3 samples with one time each, got {len(t)} times and "
            f"{len(q)} positions"
        )
    lag = np.zeros(6)
    tp = t - plan.start_time_s
    for _ in range(int(iterations)):
        q_p = np.empty((len(t), 6))
        v_p = np.empty((len(t), 6))
        # Each joint at its own shifted times.
        for j in range(6):
            qq, vv = plan.sample_many(tp - lag[j])
            q_p[:, j], v_p[:, j] = qq[:, j], vv[:, j]
        den = np.sum(v_p**2, axis=0)
        ok = den > 1e-12
        step = np.where(ok, np.sum((q_p - q) * v_p, axis=0) / np.where(ok, den, 1.0), 0.0)
        lag = lag + step
    return np.where(den > 1e-12, lag, np.nan)


def fit_dead_time_and_friction(
    samples: Sequence[tuple[JointPlan, ArrayLike, ArrayLike, ArrayLike]],
    *,
    iterations: int = 6,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per joint, the dead time ``D`` (s) and the friction offsets ``e+``, ``e-`` (rad,
    >= 0; moving in the positive and in the negative direction) that best explain cruising
    positions over one or more runs: ``q(t) ≈ plan(t + s - D) - e± · FrictionFeed.sign(v)``,
    ``s`` the shift the run's commands carried.

    A joint that trails its command by a position (kinetic friction over the velocity
    loop's integral gain; gravity makes it differ with the direction) keeps a time lag
    ``D + e / |v|``: one constant shift fits it at one speed only. Gauss-Newton on ``D``
    and the offsets pooled over the runs, from ``e = 0``, with ``D >= 0`` and ``e >= 0``
    (a bound that binds is held there and the rest refitted); a direction no run moves in
    gets the other direction's offset.

    Where a joint's speeds are too alike to tell ``D`` from ``e / |v|`` (a slow belt: every
    joint near one speed; :data:`DEAD_TIME_SE_S`), its dead time is not fitted but taken
    from the joints where it is separable (their median), or, where none is, the shortest
    lag of any joint (the dead time can be no longer: every offset is >= 0); either way no
    longer than the joint's own lag, and its offset is fitted with it. The lag at the
    speeds the runs saw is the data's either way; :func:`fit_tracking` says which joints
    were separable.

    Parameters
    ----------
    samples : sequence of (plan, times_s (n,), q_rad (n, 6), shift_s (6,))
        Per run: the scheduled plan, the instants the positions describe (host time, s),
        the joint positions (rad) and the command shifts that ran (s).

    Returns
    -------
    (ndarray (6,), ndarray (2, 6), ndarray (6,))
        Dead time (s) per joint; friction offset (rad) per direction (row 0: positive,
        row 1: negative) and joint; the RMS of the positions about the fit per joint (rad:
        how well ``D`` and ``e`` explain the joint). NaN for a joint no run moves.
    """
    fit = fit_tracking(samples, iterations=iterations)
    return fit.dead_time_s, fit.friction_rad, fit.rms_rad


#: A joint's dead time counts as separable from its friction offset when its standard
#: error in the joint's own fit is below this, s: the shift of ``D`` that a systematic
#: position misfit of the fit's RMS (at least :data:`POSITION_FLOOR_RAD`) along ``D``'s
#: column, orthogonal to the offsets', would cause. Measured on three simulated
#: calibration welds (physical angles): 0.5 m/s belt, UR10e 0.1-0.6 ms (joint 4, which
#: reverses, 7.5), UR10 0.95-11, KR 5 0.8-7.5; 0.05 m/s, UR10 8.7-142 ms (joint 5 at
#: 0.013-0.015 rad/s, whose free fit put ``D`` at -6.8 s), UR10e 2.9-90, KR 5 1.6-19.
DEAD_TIME_SE_S = 0.002
#: The smallest position scatter a fit is credited with, rad (about an encoder count of a
#: 19-bit joint encoder: the simulator's positions fit to 1e-9 rad, a real joint's do not).
POSITION_FLOOR_RAD = 1e-5


@dataclass(frozen=True, kw_only=True)
class TrackingFit:
    """What :func:`fit_tracking` found, per joint (NaN: no run moves the joint).

    Attributes
    ----------
    dead_time_s : ndarray (6,)
        Dead time, s.
    friction_rad : ndarray (2, 6)
        Friction offset per direction (row 0 positive, row 1 negative), rad.
    rms_rad : ndarray (6,)
        Position scatter about the fit, rad.
    dead_time_se_s : ndarray (6,)
        Standard error of the dead time in the joint's own fit, s (see
        :data:`DEAD_TIME_SE_S`).
    separable : ndarray (6,) of bool
        The dead time came from the joint's own data (its standard error below
        :data:`DEAD_TIME_SE_S`); False: taken from the other joints (see
        :func:`fit_dead_time_and_friction`).
    speed_rad_s : ndarray (2, 6)
        Smallest and largest joint speed the fit saw, rad/s.
    """

    dead_time_s: FloatArray
    friction_rad: FloatArray
    rms_rad: FloatArray
    dead_time_se_s: FloatArray
    separable: NDArray[np.bool_]
    speed_rad_s: FloatArray


def fit_tracking(
    samples: Sequence[tuple[JointPlan, ArrayLike, ArrayLike, ArrayLike]],
    *,
    iterations: int = 6,
) -> TrackingFit:
    """:func:`fit_dead_time_and_friction` with what it knows about each joint's fit
    (:class:`TrackingFit`): the dead time's standard error and whether the joint's own
    speeds separated it from the friction offset."""
    runs = [
        (
            plan,
            np.asarray(t, dtype=float).reshape(-1) - plan.start_time_s,
            np.asarray(q, dtype=float).reshape(-1, 6),
            np.asarray(shift, dtype=float).reshape(6),
        )
        for plan, t, q, shift in samples
    ]
    if not runs or any(len(tp) < 3 or len(tp) != len(q) for _, tp, q, _ in runs):
        raise ConfigError("fit_dead_time_and_friction needs runs of >= 3 samples, one time each")
    nan6 = np.full(6, np.nan)
    dead, fric, rms, se = nan6.copy(), np.full((2, 6), np.nan), nan6.copy(), nan6.copy()
    speeds = np.full((2, 6), np.nan)
    lag = nan6.copy()
    joints: dict[int, _JointData] = {}
    for j in range(6):
        data = _JointData(runs, j, iterations)
        if not data.moves:
            continue
        joints[j] = data
        d, e, a, res = data.fit()
        r = float(np.sqrt(np.mean(res**2)))
        cov = np.linalg.pinv(a.T @ a)
        se[j] = max(r, POSITION_FLOOR_RAD) * float(np.sqrt(max(len(res) * cov[0, 0], 0.0)))
        dead[j], fric[:, j], rms[j] = d, e, r
        lag[j] = data.fit(e_free=False)[0]
        speeds[:, j] = data.speed_range
    separable = np.isfinite(se) & (se < DEAD_TIME_SE_S)
    if separable.any():
        prior = float(np.median(dead[separable]))
    else:
        prior = float(np.nanmin(lag)) if np.isfinite(lag).any() else 0.0
    for j, data in joints.items():
        if separable[j]:
            continue
        d_fixed = max(min(prior, float(lag[j])), 0.0)
        d, e, _, res = data.fit(d_fixed=d_fixed)
        dead[j], fric[:, j], rms[j] = d, e, float(np.sqrt(np.mean(res**2)))
    return TrackingFit(
        dead_time_s=dead,
        friction_rad=fric,
        rms_rad=rms,
        dead_time_se_s=se,
        separable=separable,
        speed_rad_s=speeds,
    )


class _JointData:
    """One joint's cruising positions over the runs, and its bounded least-squares fits."""

    def __init__(self, runs: list[Any], j: int, iterations: int) -> None:
        self.runs, self.j, self.iterations = runs, j, int(iterations)
        # Start: the shift that ran (the median over runs).
        self.d0 = float(np.median([shift[j] for *_, shift in runs]))
        _, a0 = self.columns(self.d0, np.zeros(2))
        self.moves = float(a0[:, 0] @ a0[:, 0]) >= 1e-12
        # A direction moved in for less than 1 % of the samples cannot be fitted.
        self.seen = np.abs(a0[:, 1:]).sum(axis=0) >= 0.01 * len(a0)
        v = np.abs(a0[:, 0])
        self.speed_range = (float(v.min()), float(v.max()))

    def columns(self, d: float, e: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Residual (n,) and the derivatives of the fit by D, e+, e- (n, 3)."""
        res, cols = [], []
        j = self.j
        for plan, tp, q, shift in self.runs:
            qp, vp = plan.sample_many(tp + shift[j] - d)
            sgn = FrictionFeed.sign(vp[:, j])
            split = np.c_[np.maximum(sgn, 0.0), np.minimum(sgn, 0.0)]
            res.append(q[:, j] - qp[:, j] + split @ e)
            cols.append(np.c_[-vp[:, j], -split])
        return np.concatenate(res), np.concatenate(cols)

    def fit(
        self, *, d_fixed: float | None = None, e_free: bool = True
    ) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        """Gauss-Newton on D (unless ``d_fixed``) and the offsets seen (unless not
        ``e_free``: a pure shift), D and e held at 0 where they would go negative.
        Returns D, e (2,), the Jacobian (n, 3) and the residual (n,) at the solution."""
        free = np.r_[d_fixed is None, self.seen & e_free]
        while True:
            d = self.d0 if d_fixed is None else d_fixed
            e = np.zeros(2)
            for _ in range(self.iterations):
                res, a = self.columns(d, e)
                if not free.any():
                    break
                step = np.linalg.lstsq(a[:, free], res, rcond=None)[0]
                x = np.r_[d, e]
                x[free] += step
                d, e = float(x[0]), x[1:]
            x = np.r_[d, e]
            if np.all(x[free] >= 0):
                break
            free &= x >= 0  # hold what went negative at 0 and refit the rest
            d = max(d, 0.0) if d_fixed is None else d_fixed
            if not free[0] and d_fixed is None:
                d_fixed = 0.0
        res, a = self.columns(d, e)
        if self.seen.sum() == 1:
            e[~self.seen] = e[self.seen]
        return d, e, a, res


def sampling_times_s(run: Any, *, response_s: float | None = None) -> FloatArray:
    """Host time at which each state package of a run was sampled, s (n,).

    With the controller's intake probed and dated (``run.intake``): the cycle boundary each
    package was sampled at (:meth:`~timedexec.execution.IntakeFix.sampled_s`), which does
    not move with where the publisher sends in its cycle. Without: the arrival minus the
    response delay (``response_s``, default the executor's, ``run.plan.meta["response_s"]``),
    which carries the run's publisher phase.
    """
    fix = getattr(run, "intake", None)
    if fix is not None and np.isfinite(fix.sample_offset_s) and response_s is None:
        stamps = np.asarray(run.controller_s, dtype=float)
        return np.asarray(fix.sampled_s(stamps, float(getattr(run, "clock_rate", 0.0))))  # type: ignore[arg-type]
    resp = float(run.plan.meta["response_s"]) if response_s is None else float(response_s)
    return np.asarray(run.host_s, dtype=float) - resp


def measure_tracking_delays(run: Any, *, response_s: float | None = None) -> FloatArray:
    """Tracking delay per joint (6,), s, from a tracking run's reported positions.

    The reported positions over the run's cruise window, at their sampling instants
    (:func:`sampling_times_s`: by the probed intake where the run has one, else back-dated
    by ``response_s``), are aligned with the plan per joint (:func:`fit_joint_lags`); the
    shift that ran is added back, so the result is the shift that would have put the
    joints on time (see the module docstring).

    Parameters
    ----------
    run : ConveyorRun
        From :func:`~timedexec.tasks.track_conveyor_seam` (any driver).
    response_s : float, optional
        Response delay to back-date by, s (instead of the probed intake's dating).
    """
    t, q = cruise_positions(run, response_s)
    return np.asarray(fit_joint_lags(run.plan, t, q) + run.shifts_s)


def cruise_positions(run: Any, response_s: float | None = None) -> tuple[FloatArray, FloatArray]:
    """A run's reported positions over its cruise window, at their sampling instants."""
    t = sampling_times_s(run, response_s=response_s)
    since = t - run.sync_time_s
    keep = (since >= run.settle_s) & (since <= run.settle_s + run.cruise_s)
    return t[keep], np.asarray(run.reported_q)[keep]
