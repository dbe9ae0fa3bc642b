"""The delay a tracking arm keeps: measuring it from reported positions, and a model of it.

Onset delay and tracking delay
------------------------------
The delay models learn the **actuation (onset) delay**: from the command leaving the host to
the joint's speed reaching 10 % of the commanded speed, starting from rest. It holds the
controller's dead time (intake wait, command pipeline, drive offset) *and* the time the
velocity loop needs to break the joint free (static friction) and to raise its speed.

A joint that already moves has no breakaway to wait for, and the velocity loop's integrator
recovers most of the motion lost to the start: the **tracking delay** — the time shift that
aligns the physical joint position with the command stream during a cruise — is the dead
time plus the loop's residual lag (kinetic friction / integral gain, divided by the joint
speed, plus viscous friction / integral gain). On the simulated KR 5 it is ~10 ms shorter
than the onset delay, on the UR10 ~2 ms (docs/welding.md): an onset-compensated stream
therefore puts the torch *ahead* of a seam by ``speed x difference``.

Measuring it without a gyro
---------------------------
The reported joint positions of a run, at the instants they were sampled, aligned with the
plan per joint. Answering each package at once, the dead time ``A`` moves with the
publisher's phase (where in its cycle the controller sends the state) and, back-dated by a
mean response ``R^``, so does the measurement (``L_m = A + l + R - R^``: phase-free only if
``A + R`` is, which it is not once the commands are cycle-locked). With the executor's
``cycle_lock`` and its probed intake both are phase-free: every command lands half a period
before a deadline (``A`` fixed), and each package is dated at the cycle boundary it was
sampled at (:meth:`~timedexec.execution.IntakeFix.sampled_s`, used by
:func:`sampling_times_s`). On the KR 5 over four phases: joint 1's measured lag 78.2-78.4
ms, within 0.27 ms of the physical one on every joint; dated by ``R^`` 74.0-81.3 ms
(``tests/test_welding.py``).

The model
---------
A cruising joint trails its command by a dead time ``D`` *and a position* ``e`` (kinetic
friction over the velocity loop's integral gain; it differs with the direction): its
time lag ``D + e / |v|`` changes with its speed, so one constant shift per joint fits one
speed only (the "median" strategy's limit, and the oracle's). :class:`TrackingDelays`
holds ``D`` per joint and ``e`` per direction and joint, fitted jointly on the cruises of
calibration runs (:func:`fit_dead_time_and_friction`, :meth:`TrackingDelays.calibrate_runs`);
the executor shifts each joint's stream by ``D`` and adds ``e * FrictionFeed.sign(v)`` to it
(:class:`~timedexec.execution.FrictionFeed`). On the uncompensated UR10 weld (straight
seam) the fit leaves 0.0004-0.003 mrad RMS on joints 1-3, 5 and 6 where the best constant
shift leaves 0.07-0.33 mrad (0.25-0.33 on joints 1-3 and 6).

From the calibration sweep (issue 39): the sweep's trial holds its speed 50 ms, and a KR 5's
lag settles only ~0.3 s after the command (joint 1: 88.7 ms 0.15 s after the send, 75.7 ms
steady); and one speed cannot tell ``D`` from ``e / |v|`` (UR10 joint 2: 19.7 ms at 0.4
rad/s, 26.0 ms at 0.1 rad/s). So ``calibrate`` ends with **tracking phases**
(:class:`TrackingPhases`, :func:`run_tracking_phases`): per joint, 0.05 and 0.25 rad/s both
ways, each held 0.8 s (the last 0.4 s fitted), each from rest reached by a short move the
other way (the rest the velocity loop holds depends on how the joint got there: UR10 joint
1 at 0.05 rad/s lags 26.8 ms from a fresh start, 35.3 ms after a phase the other way);
:meth:`TrackingDelays.calibrate_phases` fits ``D`` and ``e±`` per joint on them
(:func:`fit_tracking_phases`, the same pooled fit as the runs'). Calibration runs of the
task (dry runs of the weld at other work points, :meth:`TrackingDelays.calibrate_runs`)
remain: they see the task's own speeds and rest states (docs/welding.md compares both).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._files import write_atomic
from timedexec._types import FloatArray
from timedexec._validation import DictMixin, check_non_negative, check_positive
from timedexec.errors import ConfigError
from timedexec.execution import (
    DelayPredictions,
    DelayPredictor,
    FrictionFeed,
    JointPlan,
    TimedExecutor,
    load_delay_model,
    predict_delays,
)
from timedexec.tasks._conveyor import _ruckig_velocity
from timedexec.tasks._lag_fit import (
    TrackingFit,
    cruise_positions,
    fit_joint_lags,
    fit_tracking,
    sampling_times_s,
)
from timedexec.tasks._truth import physical_probe

__all__ = [
    "MAX_CALIBRATION_RUNS",
    "PHASE_SPEEDS_RAD_S",
    "RUN_AGREEMENT_RAD",
    "RUN_AGREEMENT_S",
    "TRACKING_FILE",
    "PhaseRun",
    "TrackingDelays",
    "TrackingPhases",
    "fit_tracking_phases",
    "run_tracking_phases",
]


#: Largest difference, s, between one calibration run's lag (best constant shift) on any
#: joint and the runs' median that still counts as the same task's lag: work points apart
#: by 5 cm differ by up to 1.2 ms (3 ms on a joint that reverses in the cruise); a run
#: whose approach ended off its start, or that a disturbed machine delayed, reads 15-20 ms
#: off (the independent peer: 31-36 ms where its lag is 16.2).
RUN_AGREEMENT_S = 0.005
#: ... and the position that difference is worth at the joint's mean speed, rad, beyond
#: which a run disagrees (both must be exceeded): a joint's time lag is ``D + e / |v|``, so
#: on a slow belt work points 5 cm apart differ by 5-10 ms on a joint that barely moves
#: (UR10 at 0.05 m/s, joint 4: 33.9-43.3 ms at 0.016-0.033 rad/s) while the position,
#: what the torch feels, differs by 0.1-0.2 mrad. 0.5 mrad is ~0.5 mm at a 1 m reach.
RUN_AGREEMENT_RAD = 5e-4
#: The file beside a model bundle's manifest that holds its tracking model
#: (:meth:`TrackingDelays.save`, :meth:`TrackingDelays.of_bundle`).
TRACKING_FILE = "tracking.json"
#: The most calibration runs :meth:`TrackingDelays.calibrate_runs` welds in all when it may
#: add runs to settle a disagreement.
MAX_CALIBRATION_RUNS = 7


@dataclass(frozen=True, kw_only=True)
class TrackingDelays:
    """A tracking-delay model: a dead time per joint and a friction offset per direction and
    joint, fitted on calibration runs (:meth:`calibrate_runs`).

    ``predict_many`` answers as the base (onset) model for the response delay and the
    uncertainties, with ``actuation_mean`` replaced by the joint's dead time: the shift a
    velocity stream needs once the arm moves. The friction offsets go into the command
    stream itself (:func:`~timedexec.tasks.prepare_shifted`,
    :class:`~timedexec.execution.FrictionFeed`). A joint the base model does not cover
    (a sweep of joints 1, 2, 3, 5) gets the covered joints' mean uncertainty and response.
    Hand it to :class:`~timedexec.execution.TimedExecutor` for tracking tasks.

    The onset model's pose dependence is not used: it is mostly the breakaway's, which a
    moving joint does not have; applied to the dead time it cost 0.13 mm at the KR 5's
    torch and 0.12 mm at the UR10e's (docs/welding.md).

    Parameters
    ----------
    base : DelayPredictor
        The onset-delay model (or a bundle path / bundled name).
    dead_time_s : 6 floats
        Dead time per joint, s (>= 0).
    friction_rad : 2 x 6 floats, optional
        Friction offset per direction (positive, negative) and joint, rad (>= 0; 6 floats:
        the same both ways): the position a cruising joint trails its command by beyond the
        dead time (:func:`fit_dead_time_and_friction`). None: a pure shift.
    fit_rms_rad : 6 floats, optional
        How far the calibration positions scatter about the fit, per joint, rad (RMS): the
        model's own uncertainty in position (a joint that reverses in the cruise sticks
        there, which neither ``D`` nor ``e`` describes: 0.8-0.9 mrad on the KR 5's joints 2
        and 3 in a one-offset fit of one weld, 0.39-0.45 mrad on the friction peer's joint
        4, against 0.001-0.007 mrad for joints that do not reverse).
    notes : tuple of str
        What the calibration set aside and why (:meth:`calibrate_runs`).
    source : str
        Where the dead times and offsets came from: ``"dry runs"`` (:meth:`calibrate_runs`,
        runs of the task), ``"sweep"`` (:meth:`calibrate_phases`, the calibration sweep's
        constant-speed phases) or ``"given"``.
    echo_depth_cycles : int, optional
        The controller's echo depth (cycles from the intake that takes a command to the
        first state package showing it; ``ExecutorSettings.echo_depth_cycles``) where the
        calibration measured it (``calibrate``'s tracking phases: the sweep's gyro and
        :meth:`~timedexec.execution.IntakeFix.echo_depth_at`): the executor then dates the
        states by counting packages, whatever the publisher's phase. None: not measured.
    """

    base: Any
    dead_time_s: tuple[float, ...]
    friction_rad: tuple[tuple[float, ...], ...] | None = None
    fit_rms_rad: tuple[float, ...] | None = None
    notes: tuple[str, ...] = ()
    source: str = "given"
    echo_depth_cycles: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "base", load_delay_model(self.base))
        depth = self.echo_depth_cycles
        if depth is not None and (
            isinstance(depth, bool) or not isinstance(depth, int) or depth < 0
        ):
            raise ConfigError(
                f"TrackingDelays.echo_depth_cycles={depth!r} must be a whole number of "
                "cycles >= 0, or None (not measured)"
            )
        d = np.asarray(self.dead_time_s, dtype=float).reshape(-1)
        if d.shape != (6,) or not np.all(d >= 0) or not np.all(np.isfinite(d)):
            raise ConfigError(
                f"TrackingDelays.dead_time_s={self.dead_time_s!r} needs 6 finite delays >= 0 s"
            )
        object.__setattr__(self, "dead_time_s", tuple(map(float, d)))
        if self.friction_rad is not None:
            f = np.asarray(self.friction_rad, dtype=float)
            if f.shape not in ((6,), (2, 6)) or not np.all(f >= 0) or not np.all(np.isfinite(f)):
                raise ConfigError(
                    f"TrackingDelays.friction_rad={self.friction_rad!r} must be 2 x 6 (or 6) "
                    "offsets >= 0 rad, per direction (positive, negative) and joint"
                )
            rows = np.broadcast_to(f, (2, 6))
            object.__setattr__(self, "friction_rad", tuple(tuple(map(float, r)) for r in rows))
        if self.fit_rms_rad is not None:
            r = np.asarray(self.fit_rms_rad, dtype=float).reshape(-1)
            if r.shape != (6,) or np.any(r < 0):
                raise ConfigError(
                    f"TrackingDelays.fit_rms_rad={self.fit_rms_rad!r} needs 6 values >= 0 rad"
                )
            object.__setattr__(self, "fit_rms_rad", tuple(map(float, r)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe: ``{"dead_time_s", "friction_rad", "fit_rms_rad", "notes", "source",
        "echo_depth_cycles"}`` (the base model is not included: :meth:`from_dict` takes
        it)."""
        return {
            "dead_time_s": list(self.dead_time_s),
            "friction_rad": None if self.friction_rad is None else [list(r) for r in self.friction_rad],
            "fit_rms_rad": None if self.fit_rms_rad is None else [
                None if not math.isfinite(x) else x for x in self.fit_rms_rad],
            "notes": list(self.notes),
            "source": self.source,
            "echo_depth_cycles": self.echo_depth_cycles,
        }  # fmt: skip

    @classmethod
    def from_dict(cls, base: DelayPredictor | Any, data: dict[str, Any]) -> TrackingDelays:
        """The model :meth:`to_dict` wrote, on the onset model ``base``.

        Raises
        ------
        ConfigError
            A key missing or unknown, or a value out of range.
        """
        known = {"dead_time_s", "friction_rad", "fit_rms_rad", "notes", "source",
                 "echo_depth_cycles"}  # fmt: skip
        if not isinstance(data, dict) or "dead_time_s" not in data or set(data) - known:
            raise ConfigError(
                f"a tracking model needs the keys {sorted(known)} (dead_time_s required), got "
                f"{sorted(data) if isinstance(data, dict) else type(data).__name__}"
            )
        rms = data.get("fit_rms_rad")
        return cls(
            base=base,
            dead_time_s=tuple(data["dead_time_s"]),
            friction_rad=data.get("friction_rad"),
            fit_rms_rad=None if rms is None else tuple(math.nan if x is None else x for x in rms),
            notes=tuple(data.get("notes", ())),
            source=str(data.get("source", "given")),
            echo_depth_cycles=data.get("echo_depth_cycles"),
        )

    def save(self, bundle_dir: str | os.PathLike[str]) -> Path:
        """Write :meth:`to_dict` as ``TRACKING_FILE`` into a model bundle's folder (atomic);
        return its path."""
        path = Path(bundle_dir) / TRACKING_FILE
        write_atomic(path, json.dumps(self.to_dict(), indent=1) + "\n")
        return path

    @classmethod
    def of_bundle(cls, base: DelayPredictor | Any) -> TrackingDelays | None:
        """The tracking model stored beside an onset model's bundle (``TRACKING_FILE`` in
        its folder, :meth:`save`), on that model (a loaded bundle, its folder or a shipped
        name); None when it has none.

        Raises
        ------
        ConfigError
            The file is there but not a tracking model.
        """
        base = load_delay_model(base)
        folder = getattr(base, "path", None)
        if folder is None or not (Path(folder) / TRACKING_FILE).is_file():
            return None
        path = Path(folder) / TRACKING_FILE
        try:
            data = json.loads(path.read_text())
        except ValueError as exc:
            raise ConfigError(
                f"{path}: not JSON ({exc}); rewrite it with TrackingDelays.save"
            ) from exc
        return cls.from_dict(base, data)

    @property
    def robot(self) -> str:
        """The base model's robot."""
        return str(self.base.robot)

    @property
    def joints(self) -> tuple[int, ...]:
        """All six: every joint has its dead time."""
        return (1, 2, 3, 4, 5, 6)

    @property
    def controller_period_s(self) -> float:
        """The base model's controller period, s."""
        base = self.base
        return float(getattr(base, "controller_period_s", 0.0) or getattr(base, "period_s", 0.0))

    def tracking_delay_s(self, joint: int, v_rad_s: ArrayLike) -> FloatArray:
        """The time lag joint ``joint`` keeps at speed ``v_rad_s`` without the friction
        offsets in its command, as the model compensates it: ``D + e · |sign(v)| / |v|``,
        s, with the executor's smooth sign (:attr:`FrictionFeed.sign`): ``D + e / |v|``
        once the joint moves, bounded as the speed goes to 0 (at rest ``D + e`` over the
        sign's slope). The offset ``e`` itself, a position, is bounded at every speed."""
        v = np.abs(np.asarray(v_rad_s, dtype=float))
        f = np.zeros((2, 6)) if self.friction_rad is None else np.asarray(self.friction_rad)
        e = np.where(np.asarray(v_rad_s, dtype=float) >= 0, f[0, joint - 1], f[1, joint - 1])
        tiny = 1e-9  # below it, the sign's slope at 0 (its limit over the speed)
        ratio = np.abs(FrictionFeed.sign(np.maximum(v, tiny))) / np.maximum(v, tiny)
        return np.asarray(self.dead_time_s[joint - 1] + e * ratio)

    def predict_many(self, joint: Any, direction: Any, q: Any) -> DelayPredictions:
        """The base model's predictions with the dead time as the actuation delay."""
        j = np.atleast_1d(np.asarray(joint, dtype=np.int64))
        d = np.atleast_1d(np.asarray(direction, dtype=np.int64))
        qq = np.asarray(q, dtype=float).reshape(-1, 6)
        n = max(len(j), len(d), len(qq))
        j, d = np.broadcast_to(j, (n,)), np.broadcast_to(d, (n,))
        qq = np.broadcast_to(qq, (n, 6))
        covered = np.array([int(k) for k in getattr(self.base, "joints", (1, 2, 3, 5))])
        names = ("actuation_std", "response_mean", "response_std")
        out = {name: np.empty(n) for name in names}
        inside = np.isin(j, covered)
        if inside.any():
            p = predict_delays(self.base, j[inside], d[inside], qq[inside])
            for name in names:
                out[name][inside] = getattr(p, name)
        for r in np.flatnonzero(~inside):
            k = len(covered)
            p = predict_delays(self.base, covered, np.full(k, d[r]), np.tile(qq[r], (k, 1)))
            for name in names:
                out[name][r] = float(np.mean(getattr(p, name)))
        return DelayPredictions(actuation_mean=np.asarray(self.dead_time_s)[j - 1], **out)

    @classmethod
    def calibrate_runs(
        cls,
        base: DelayPredictor | Any,
        runs: Sequence[Any],
        *,
        more: Callable[[int], Any] | None = None,
        max_runs: int = MAX_CALIBRATION_RUNS,
    ) -> TrackingDelays:
        """Dead time and friction offsets from calibration runs (uncompensated or shifted
        tracking runs, e.g. welds at other work points): the pooled fit of
        :func:`fit_dead_time_and_friction` over each run's cruise, the reported positions at
        their sampling instants (:func:`sampling_times_s`). A joint no run moves gets the
        median dead time of the others and no offset. A run whose lag on some joint is
        more than :data:`RUN_AGREEMENT_S` (and :data:`RUN_AGREEMENT_RAD` of position) off
        the runs' median is set aside (``notes`` says which and why).

        Runs that disagree with no majority to side with (two runs, or as many outliers as
        agreeing runs): with ``more`` (``more(i)`` makes the ``i``-th calibration run,
        counting from 0 over all runs, e.g. a weld at yet another work point), runs are
        added one at a time until a majority agrees, up to ``max_runs`` in all (``notes``
        says how many were added).

        Raises
        ------
        ConfigError
            No run; a run that carried friction offsets (its positions would need them
            undone); runs that still disagree with no majority (without ``more``, or at
            ``max_runs``).
        """
        if not runs:
            raise ConfigError("calibrate_runs needs at least one calibration run")
        runs = list(runs)
        added = 0
        while True:
            if any(np.any(np.asarray(r.plan.meta.get("friction_rad", 0.0)) != 0) for r in runs):
                raise ConfigError(
                    "calibrate_runs takes runs without friction offsets (compensate=False, or "
                    "an explicit shift_s); one of these ran a model's offsets"
                )
            samples = [(run.plan, *cruise_positions(run), run.shifts_s) for run in runs]
            lags = np.array([fit_joint_lags(p, t, q) + shift for p, t, q, shift in samples])
            speeds = np.array([_mean_speed(p, t) for p, t, *_ in samples])
            agreement = _agreeing(lags, speeds)
            if agreement is not None:
                break
            if more is None or len(runs) >= max_runs:
                raise ConfigError(_disagreement(lags, len(runs), more is not None))
            runs.append(more(len(runs)))
            added += 1
        keep, notes = agreement
        if added:
            notes = (
                f"calibration runs disagreed with no majority: {added} more welded "
                f"automatically ({len(runs)} in all)",
                *notes,
            )
        fit = fit_tracking([x for x, k in zip(samples, keep, strict=True) if k])
        advice = (
            "calibrate at a second belt speed, or from a sweep with constant-speed phases, "
            "to use the model at other speeds"
        )
        return cls._from_fit(base, fit, notes, advice, source="dry runs")

    @classmethod
    def calibrate_phases(
        cls, base: DelayPredictor | Any, runs: Sequence[PhaseRun]
    ) -> TrackingDelays:
        """Dead time and friction offsets from constant-speed phases
        (:func:`run_tracking_phases`, :func:`fit_tracking_phases`): no run of the task
        needed. A joint no phase moves gets the median dead time of the others and no
        offset.

        Raises
        ------
        ConfigError
            No phase.
        """
        advice = "run the phases at two or more distinct speeds with longer holds"
        return cls._from_fit(base, fit_tracking_phases(runs), (), advice, source="sweep")

    @classmethod
    def _from_fit(
        cls,
        base: DelayPredictor | Any,
        fit: TrackingFit,
        notes: tuple[str, ...],
        advice: str,
        *,
        source: str,
    ) -> TrackingDelays:
        """The model of a fit; a note names the joints whose dead time was not separable
        (with ``advice``)."""
        dead = fit.dead_time_s
        moved = np.isfinite(dead)
        if (moved & ~fit.separable).any():
            lo, hi = fit.speed_rad_s
            shown = ", ".join(
                f"{j + 1} ({lo[j]:.3f}-{hi[j]:.3f} rad/s)"
                for j in np.flatnonzero(moved & ~fit.separable)
            )
            notes += (
                f"dead time not separable from friction on joints {shown}: speeds too "
                "alike for the positions' scatter about the fit; dead time taken from the "
                f"other joints (or the shortest lag), exact at these speeds only: {advice}",
            )
        fallback = float(np.nanmedian(dead)) if moved.any() else 0.0
        return cls(
            base=base,
            dead_time_s=tuple(np.maximum(np.where(moved, dead, fallback), 0.0)),
            friction_rad=np.where(np.isfinite(fit.friction_rad), fit.friction_rad, 0.0),  # type: ignore[arg-type]
            fit_rms_rad=tuple(float(x) for x in fit.rms_rad),
            notes=notes,
            source=source,
        )


def _mean_speed(plan: JointPlan, times_s: FloatArray) -> FloatArray:
    """Mean absolute planned speed per joint over the instants ``times_s`` (host), rad/s."""
    return np.asarray(np.mean(np.abs(plan.sample_many(times_s - plan.start_time_s)[1]), axis=0))


def _agreeing(
    lags_s: FloatArray, speeds_rad_s: FloatArray
) -> tuple[NDArray[np.bool_], tuple[str, ...]] | None:
    """Which calibration runs (rows of per-joint lags, s; and mean joint speeds, rad/s)
    agree with the others, and a note for each one set aside: a run disagrees where a
    joint's lag is off the runs' median by more than :data:`RUN_AGREEMENT_S` and by more
    than :data:`RUN_AGREEMENT_RAD` of position at its speed. None: two runs that
    disagree, or as many outliers as agreeing runs, cannot be told apart."""
    n = len(lags_s)
    if n < 2:
        return np.ones(n, bool), ()
    off = np.abs(lags_s - np.nanmedian(lags_s, axis=0))
    off = np.where(np.isfinite(off) & (off * speeds_rad_s > RUN_AGREEMENT_RAD), off, 0.0)
    worst = np.max(off, axis=1)
    far = worst > RUN_AGREEMENT_S
    if not far.any():
        return ~far, ()
    if 2 * int(far.sum()) >= n:
        return None
    notes = tuple(
        f"calibration run {i} set aside: joint {int(np.nanargmax(off[i])) + 1} lags "
        f"{worst[i] * 1e3:.1f} ms off the runs' median"
        for i in np.flatnonzero(far)
    )
    return ~far, notes


def _disagreement(lags_s: FloatArray, n_runs: int, automatic: bool) -> str:
    """The message for calibration runs that disagree with no majority (lags per run and
    joint, s)."""
    table = "; ".join(
        f"run {i}: " + " ".join(f"{x * 1e3:.1f}" for x in row) for i, row in enumerate(lags_s)
    )
    head = (
        f"calibration runs disagree by more than {RUN_AGREEMENT_S * 1e3:g} ms "
        f"({RUN_AGREEMENT_RAD * 1e3:g} mrad at the joint's speed) on some joint (lags per "
        f"joint, ms: {table})"
    )
    if automatic:
        return (
            f"{head}, with no majority after {n_runs} runs (the most calibrate_runs welds): "
            "the task's lag changes from run to run; check that nothing disturbs the arm "
            "and that each run starts at rest on the approach's start"
        )
    return (
        f"{head}; weld at least three calibration runs, each starting at rest on the "
        "approach's start, so that an outlier can be set aside"
    )


# ---------------------------------------------------------------- from constant-speed phases
#: Joint speeds of the tracking phases by default, rad/s: a slow one, where the friction
#: offset dominates the lag (``e / |v|``: a 0.05 m/s belt moves the joints at 0.01-0.05
#: rad/s), and a fast one, where the dead time does (a 0.5 m/s belt: 0.1-0.8 rad/s).
PHASE_SPEEDS_RAD_S = (0.05, 0.25)
#: The move the other way before each phase, rad (:func:`run_tracking_phases`).
PRELOAD_RAD = 0.02


@dataclass(frozen=True, kw_only=True)
class TrackingPhases(DictMixin):
    """Constant-speed phases that calibrate the tracking model (dead time and friction
    offsets per direction) from a sweep: per joint, per speed, per direction (positive
    first, so the joint comes back), the joint ramps from rest to the speed (jerk-limited,
    the executor's limits), holds it for ``settle_s + hold_s`` and stops; the others stay
    still. The lag is fitted over the last ``hold_s`` of each hold (after the velocity
    loop has settled: ~0.3 s on a KR 5, docs/welding.md).

    Parameters
    ----------
    speeds_rad_s : tuple of float
        At least two distinct speeds > 0, rad/s (one speed cannot tell the dead time ``D``
        from ``e / |v|``).
    settle_s : float
        Time at speed before the fit's window, s (>= 0).
    hold_s : float
        The fit's window at speed, s (> 0).
    joints : tuple of int
        Joints to calibrate, 1-based (default all six: a tracking task moves every joint).
    """

    speeds_rad_s: tuple[float, ...] = PHASE_SPEEDS_RAD_S
    settle_s: float = 0.4
    hold_s: float = 0.4
    joints: tuple[int, ...] = (1, 2, 3, 4, 5, 6)

    def __post_init__(self) -> None:
        speeds = tuple(float(v) for v in self.speeds_rad_s)
        check_positive("TrackingPhases", **{f"speeds_rad_s[{i}]": v for i, v in enumerate(speeds)})
        if len(set(speeds)) < 2:
            raise ConfigError(
                f"TrackingPhases.speeds_rad_s={self.speeds_rad_s!r}: give at least two "
                "distinct speeds > 0 rad/s (e.g. 0.05 and 0.25): one speed cannot separate the "
                "dead time from the friction offset"
            )
        check_non_negative("TrackingPhases", settle_s=self.settle_s)
        check_positive("TrackingPhases", hold_s=self.hold_s)
        joints = tuple(int(j) for j in self.joints)
        if not joints or len(set(joints)) != len(joints) or not set(joints) <= set(range(1, 7)):
            raise ConfigError(
                f"TrackingPhases.joints={self.joints!r} must be distinct joints in 1..6"
            )
        object.__setattr__(self, "speeds_rad_s", speeds)
        object.__setattr__(self, "joints", joints)

    @property
    def count(self) -> int:
        """Phases in all (joints x speeds x 2 directions)."""
        return 2 * len(self.joints) * len(self.speeds_rad_s)

    def robot_time_s(self, acceleration_rad_s2: float = 8.0, gap_s: float = 0.3) -> float:
        """Robot time the phases take, s: per phase the ramp up and down at
        ``acceleration_rad_s2`` (the executor's default cap), the hold, and ``gap_s`` for
        the short move the other way, the lead before the send and the waits for rest
        (measured on the simulator: 30-38 s for the default phases where this says 34)."""
        per_speed = [2 * v / acceleration_rad_s2 + self.settle_s + self.hold_s + gap_s
                     for v in self.speeds_rad_s]  # fmt: skip
        return float(2 * len(self.joints) * sum(per_speed))


@dataclass(frozen=True, kw_only=True)
class PhaseRun:
    """One constant-speed phase as it ran (:func:`run_tracking_phases`): the duck type
    :func:`sampling_times_s` reads (``plan``, ``host_s``, ``controller_s``, ``intake``,
    ``clock_rate``), the joint and the fit's window.

    Attributes
    ----------
    joint : int
        The moving joint, 1-based.
    speed_rad_s : float
        Its commanded speed, signed, rad/s.
    plan : JointPlan
        The scheduled plan (``meta["actuation_s"]``: the shifts that ran).
    window_s : (float, float)
        Host times of the fit's window (the hold after the settle), s.
    host_s, controller_s : ndarray (n,)
        Arrival and controller time of each state package, s.
    reported_q : ndarray (n, 6)
        Reported joint angles, rad.
    truth_s, truth_q : ndarray (n,), (n, 6)
        Host time and physical angles (simulated driver), else the reported ones.
    intake : IntakeFix or None
        The probed command deadline (executor with ``cycle_lock``).
    clock_rate : float
        Host/controller clock drift of the executor's clock line, s per s.
    """

    joint: int
    speed_rad_s: float
    plan: JointPlan
    window_s: tuple[float, float]
    host_s: FloatArray
    controller_s: FloatArray
    reported_q: FloatArray
    truth_s: FloatArray
    truth_q: FloatArray
    intake: Any = None
    clock_rate: float = 0.0

    @property
    def shifts_s(self) -> FloatArray:
        """Per joint, the shift of the command stream that ran, s (6,)."""
        return np.asarray(self.plan.meta["actuation_s"], dtype=float)

    def window(self, *, physical: bool = False) -> tuple[FloatArray, FloatArray]:
        """The positions in the fit's window: (times (m,), s; q (m, 6), rad): the reported
        ones at their sampling instants (:func:`sampling_times_s`), or the physical truth."""
        if physical:
            t, q = self.truth_s, self.truth_q
        else:
            t, q = sampling_times_s(self), self.reported_q
        keep = (t >= self.window_s[0]) & (t <= self.window_s[1])
        return t[keep], q[keep]


def run_tracking_phases(
    executor: TimedExecutor, phases: TrackingPhases | None = None
) -> list[PhaseRun]:
    """Run the tracking phases through ``executor`` from where the robot is (at rest).

    Run uncompensated (``compensate=False``) with ``cycle_lock`` on, as the calibration
    welds are, so that the reported positions are dated by the probed intake. Each joint
    ends within a few mrad of where it started (each positive phase is followed by its
    negative mirror).

    Raises
    ------
    ConfigError
        A phase would leave a joint limit (before that phase moves), or Ruckig cannot plan
        a ramp.
    """
    phases = phases or TrackingPhases()
    return [
        _run_phase(executor, phases, joint, sign * speed)
        for joint in phases.joints
        for speed in phases.speeds_rad_s
        for sign in (1.0, -1.0)
    ]


def _run_phase(
    executor: TimedExecutor, phases: TrackingPhases, joint: int, speed_rad_s: float
) -> PhaseRun:
    """One phase of :func:`run_tracking_phases`: joint ``joint`` (1-based) at
    ``speed_rad_s`` (signed)."""
    spec, limits = executor.spec, executor.settings.limits
    lo, hi = limits.position_range(spec)
    j = joint - 1
    # Every phase starts from rest reached by a short move the other way (as a task's
    # motion after its approach): the rest the velocity loop holds depends on the side the
    # joint came from and how it stopped (UR10 joint 1 at 0.05 rad/s: 26.8 ms lag from a
    # fresh start, 35.3 after a phase the other way at 0.02 rad/s, 29.1 after this move).
    executor.idle(executor.now() + 2.0, until_rest=True)
    back = executor.estimate().q_rad.copy()
    back[j] -= np.sign(speed_rad_s) * PRELOAD_RAD
    executor.execute(executor.plan(back), start_time_s=executor.now() + 0.1)
    executor.idle(executor.now() + 2.0, until_rest=True)
    q0 = executor.estimate().q_rad
    v = np.zeros(6)
    v[j] = speed_rad_s
    what = f"the ramp of joint {joint} to {speed_rad_s:g} rad/s"
    ramp = _ruckig_velocity(spec, limits, q0, np.zeros(6), np.zeros(6), v, what=what)
    q_ramp = np.asarray(ramp.at_time(float(ramp.duration))[0])
    # Where the joint is when the stop after the hold has ended (a generous bound).
    travel = q_ramp[j] + speed_rad_s * (
        phases.settle_s + phases.hold_s + 0.1 + abs(speed_rad_s) / 4
    )
    if not lo[j] <= travel <= hi[j]:
        raise ConfigError(
            f"the tracking phase of joint {joint} at {speed_rad_s:g} rad/s would take it to "
            f"{travel:.3f} rad, beyond [{lo[j]:.3f}, {hi[j]:.3f}] rad; start from a pose "
            "farther from the limits"
        )
    prepared = executor.prepare(JointPlan(ramp, q0, np.zeros(6), q_ramp, v))
    executor.idle(executor.now() + 5 * executor.period_s)
    lead = float(np.max(prepared.meta["actuation_s"])) + 3 * executor.period_s
    scheduled = prepared.at(executor.now() + max(lead, 0.1))
    begin = scheduled.end_time_s + phases.settle_s
    end = begin + phases.hold_s
    probe = physical_probe(executor)
    rows: list[tuple[float, float, FloatArray, float, FloatArray]] = []

    def record(state: Any) -> None:
        t, q = probe() if probe is not None else (math.nan, state.q)
        rows.append((state.host_time_s, state.controller_time_s, state.q, t, q))

    executor.execute(scheduled, until_s=end + 0.05, on_step=record)
    n = len(rows)
    line = executor.clock_line
    return PhaseRun(
        joint=joint,
        speed_rad_s=speed_rad_s,
        plan=scheduled,
        window_s=(begin, end),
        host_s=np.array([r[0] for r in rows]),
        controller_s=np.array([r[1] for r in rows]),
        reported_q=np.array([r[2] for r in rows]).reshape(n, 6),
        truth_s=np.array([r[3] for r in rows]),
        truth_q=np.array([r[4] for r in rows]).reshape(n, 6),
        intake=executor.intake,
        clock_rate=line[2] if line is not None else 0.0,
    )


def fit_tracking_phases(runs: Sequence[PhaseRun], *, physical: bool = False) -> TrackingFit:
    """The tracking fit (:func:`fit_tracking`) of constant-speed phases, per joint on the
    phases that move it (the others' still joints would only add their scatter).

    Per joint: ``q(t) ≈ plan(t + s - D) - e± · sign(v)`` over the holds at two or more
    speeds, so ``D`` and ``e±`` are separable (the joint's lag ``D + e / |v|`` differs
    between the speeds). ``physical=True`` fits the simulator's physical angles instead
    of the reported ones (the truth the reported fit is checked against).

    Raises
    ------
    ConfigError
        No phase, or a phase with fewer than 3 samples in its window.
    """
    if not runs:
        raise ConfigError("fit_tracking_phases needs at least one tracking phase")
    nan6 = np.full(6, np.nan)
    parts: dict[str, Any] = {
        "dead_time_s": nan6.copy(), "friction_rad": np.full((2, 6), np.nan),
        "rms_rad": nan6.copy(), "dead_time_se_s": nan6.copy(),
        "separable": np.zeros(6, bool), "speed_rad_s": np.full((2, 6), np.nan),
    }  # fmt: skip
    for joint in sorted({r.joint for r in runs}):
        samples = [(r.plan, *r.window(physical=physical), r.shifts_s)
                   for r in runs if r.joint == joint]  # fmt: skip
        fit = fit_tracking(samples)
        j = joint - 1
        for name, value in parts.items():
            value[..., j] = getattr(fit, name)[..., j]
    return TrackingFit(**parts)
