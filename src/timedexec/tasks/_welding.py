"""Conveyor welding through the executor: run a seam plan, measure the torch against the seam.

:func:`track_conveyor_seam` plans the seam (:func:`~timedexec.tasks.plan_seam`),
schedules it so that the torch meets the seam ``lead_s`` from now, streams it through a
:class:`~timedexec.execution.TimedExecutor` and returns a :class:`ConveyorRun`: per state
package the host time, the reported joint angles and the executor's estimate, and for a
simulated driver (``sim://``) the physical joint angles at that instant. The torch error
(:meth:`ConveyorRun.errors`) is the torch tip (forward kinematics of the joint angles) minus
the seam point at the same host time, split along the seam (its tangent: the welding
direction), across it (horizontal normal) and vertically.

The command shift
-----------------
By default the executor shifts joint ``j``'s command stream by the delay model's predicted
*actuation* (onset) delay at the plan's start configuration. ``shift_s`` replaces it by any
per-joint shift (s): the *tracking* delays (:class:`~timedexec.tasks.TrackingDelays`), which
is what a velocity stream needs once the arm moves (docs/welding.md).

What is physical here
---------------------
With a ``sim://`` driver the torch comes from the simulator's physical joint angles (truth);
with a real driver only the executor's back-dated estimate is available: ``physical`` says
which. Against a protocol twin the truth comes from the twin: the reported angles are the
physical ones at the package's controller time stamp, and the twin publishes when
controller time 0 happened on the host clock (``ConveyorRun.with_truth``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.drivers import RobotState
from timedexec.errors import ConfigError
from timedexec.execution import ExecutionResult, IntakeFix, JointPlan, TimedExecutor
from timedexec.tasks._conveyor import Seam, SeamPlan, WeldCell, plan_seam
from timedexec.tasks._truth import physical_probe

__all__ = ["ConveyorRun", "TorchErrors", "prepare_shifted", "track_conveyor_seam"]

#: How far from the approach's start a weld may begin by the reported position, rad per
#: joint (the arm at rest; drivers that cannot read the set-point).
START_TOLERANCE_RAD = 1e-4
#: How far the controller's set-point may end from the approach's start, rad per joint
#: (0.02 mrad: 0.03 ms of tracking lag at the KR 5 weld's 0.79 rad/s, 0.02 mm at 1 m).
SETPOINT_TOLERANCE_RAD = 2e-5
#: Approach moves at most before a weld: the first, then corrections while the set-point
#: ended more than :data:`SETPOINT_TOLERANCE_RAD` off the start.
APPROACH_ATTEMPTS = 3
#: A correction move lasts at least this many controller cycles.
CORRECTION_PERIODS = 20


@dataclass(frozen=True)
class TorchErrors:
    """Torch-to-seam errors over a window, m.

    Attributes
    ----------
    times_s : ndarray (n,)
        Time since the meeting with the seam, s.
    along_m, across_m, vertical_m : ndarray (n,)
        Torch tip minus seam point, along the seam's tangent (positive: ahead in the
        welding direction), across it (positive: to the left) and vertically (up), m.
    distance_m : ndarray (n,)
        Euclidean distance, m.
    """

    times_s: FloatArray
    along_m: FloatArray
    across_m: FloatArray
    vertical_m: FloatArray
    distance_m: FloatArray

    def stats(self) -> dict[str, float]:
        """Mean, RMS and max over the window, mm: ``torch_mean_mm``, ``torch_rms_mm``,
        ``torch_max_mm`` (distance), ``along_*`` and ``across_*`` (signed mean, RMS and
        max of the absolute value), ``vertical_rms_mm``, ``samples``."""
        if not len(self.times_s):
            nan = math.nan
            keys = ("torch", "along", "across")
            out = {f"{k}_{m}_mm": nan for k in keys for m in ("mean", "rms", "max")}
            return {**out, "vertical_rms_mm": nan, "samples": 0}

        def rms(x: FloatArray) -> float:
            return float(np.sqrt(np.mean(x**2))) * 1e3

        d = self.distance_m
        out = {
            "torch_mean_mm": float(np.mean(d)) * 1e3,
            "torch_rms_mm": rms(d),
            "torch_max_mm": float(np.max(d)) * 1e3,
        }
        for name, x in (("along", self.along_m), ("across", self.across_m)):
            out[f"{name}_mean_mm"] = float(np.mean(x)) * 1e3
            out[f"{name}_rms_mm"] = rms(x)
            out[f"{name}_max_mm"] = float(np.max(np.abs(x))) * 1e3
        out["vertical_rms_mm"] = rms(self.vertical_m)
        out["samples"] = len(d)
        return out


@dataclass(frozen=True)
class ConveyorRun:
    """Outcome of :func:`track_conveyor_seam`.

    Attributes
    ----------
    seam_plan : SeamPlan
        The plan and the seam (the plan scheduled: ``plan.start_time_s`` host time).
    plan : JointPlan
        The scheduled, prepared plan that ran (``plan.meta["actuation_s"]``: the shifts).
    sync_time_s : float
        Host time at which the torch should meet the seam, s.
    settle_s, cruise_s : float
        The error window: from ``settle_s`` after the meeting, ``cruise_s`` long, s.
    host_s : ndarray (n,)
        Host arrival time of each state package, s.
    controller_s : ndarray (n,)
        Its controller time stamp, s.
    reported_q : ndarray (n, 6)
        Reported joint angles, rad.
    truth_s : ndarray (n,)
        Host time the truth row describes, s (simulator: the instant the package was
        handled; twin: the package's sampling instant).
    truth_q : ndarray (n, 6)
        Physical joint angles at ``truth_s`` (simulator or twin), else the estimate, rad.
    estimate_s : ndarray (n,)
        Host time of the executor's estimate, s (the instant each package was handled).
    estimate_q : ndarray (n, 6)
        The executor's back-dated estimate at ``estimate_s``, rad.
    physical : bool
        Whether ``truth_q`` is the physical truth.
    execution : ExecutionResult
    intake : IntakeFix or None
        The controller's probed command deadline the run was sent by (executor with
        ``cycle_lock``), None without.
    clock_rate : float
        The host/controller clock drift the executor's clock line had, s per s.
    """

    seam_plan: SeamPlan
    plan: JointPlan
    sync_time_s: float
    settle_s: float
    cruise_s: float
    host_s: FloatArray
    controller_s: FloatArray
    reported_q: FloatArray
    truth_s: FloatArray
    truth_q: FloatArray
    estimate_s: FloatArray
    estimate_q: FloatArray
    physical: bool
    execution: ExecutionResult = field(repr=False)
    intake: IntakeFix | None = None
    clock_rate: float = 0.0

    @property
    def shifts_s(self) -> FloatArray:
        """Per joint, the shift of the command stream that ran, s (6,)."""
        return np.asarray(self.plan.meta["actuation_s"], dtype=float)

    def errors(self, *, estimated: bool = False, window: bool = True) -> TorchErrors:
        """Torch errors over the cruise window (``window=False``: over the whole seam).

        ``estimated=True`` uses the executor's estimate instead of the truth.
        """
        q = self.estimate_q if estimated else self.truth_q
        t = (self.estimate_s if estimated else self.truth_s) - self.sync_time_s
        keep = np.isfinite(t) & np.all(np.isfinite(q), axis=1)
        if window:
            keep &= (t >= self.settle_s) & (t <= self.settle_s + self.cruise_s)
        else:
            keep &= (t >= 0) & (t <= self.seam_plan.weld_s)
        t = t[keep]
        torch = self.seam_plan.torch_m(q[keep]) if keep.any() else np.zeros((0, 3))
        point, tangent, normal = self.seam_plan.target(t)
        e = torch - point if len(t) else np.zeros((0, 3))
        return TorchErrors(
            times_s=t,
            along_m=np.sum(e * tangent, axis=1),
            across_m=np.sum(e * normal, axis=1),
            vertical_m=e[:, 2] if len(t) else np.zeros(0),
            distance_m=np.linalg.norm(e, axis=1),
        )

    def with_truth(self, t0_host_s: float) -> ConveyorRun:
        """This run with the twin's truth: the reported angles at their sampling instants.

        ``t0_host_s`` is the host time of the twin's controller time 0
        (``t0_monotonic_s`` of the twin's truth file; the RTDE time stamp and the RSI
        IPOC count controller time from the twin's start). ``estimate_q`` stays what the
        executor believed at the instants it handled the packages (``host_s``), so
        :meth:`errors` with ``estimated=True`` compares it with the seam at those instants.

        Raises
        ------
        ConfigError
            If ``t0_host_s`` is not finite.
        """
        if not math.isfinite(t0_host_s):
            raise ConfigError(f"t0_host_s={t0_host_s!r} must be a finite host time, s")
        return replace(
            self,
            truth_s=t0_host_s + self.controller_s,
            truth_q=self.reported_q,
            physical=True,
        )

    def summary(self) -> dict[str, Any]:
        """JSON-safe: the error statistics (physical and believed), the shifts, the seam."""
        return {
            **self.errors().stats(),
            "believed": self.errors(estimated=True).stats(),
            "physical": self.physical,
            "shift_ms": (self.shifts_s * 1e3).round(3).tolist(),
            "settle_s": self.settle_s,
            "cruise_s": self.cruise_s,
            "missed_cycles": int(self.execution.missed_cycles),
            "intake": None if self.intake is None else self.intake.summary(),
            **self.seam_plan.summary(),
        }


def prepare_shifted(
    executor: TimedExecutor, plan: JointPlan, shift_s: ArrayLike | None = None
) -> JointPlan:
    """``plan`` prepared for ``executor`` with per-joint command shifts ``shift_s`` (6,), s.

    None keeps the executor's own shift (the delay model's predicted actuation delay) and,
    when the model is a tracking model with friction offsets
    (:class:`~timedexec.tasks.TrackingDelays`), carries them on the moving joints
    (``meta["friction_rad"]``, :class:`~timedexec.execution.FrictionFeed`): a tracking
    stream only, never a point-to-point move, which the offset would leave off its end
    (a UR10e's start move ended 6.9 mrad off on joint 1). An executor whose settings say
    ``compensate=False`` never shifts. The predictions (bounds, response delay) are the
    executor's either way.

    Raises
    ------
    ConfigError
        If ``shift_s`` is not 6 finite shifts >= 0 s.
    """
    prepared = executor.prepare(plan)
    if not executor.settings.compensate:
        return prepared
    out = prepared.at(prepared.start_time_s)
    if shift_s is None:
        friction = getattr(executor.model, "friction_rad", None)
        if friction is not None:
            out.meta["friction_rad"] = np.where(prepared.meta["moving"], friction, 0.0)
        return out
    shift = np.asarray(shift_s, dtype=float).reshape(-1)
    if shift.shape != (6,) or not np.all(np.isfinite(shift)) or np.any(shift < 0):
        raise ConfigError(
            f"shift_s={np.asarray(shift_s).tolist()!r} must be 6 finite shifts >= 0 s, one "
            "per joint"
        )
    out.meta["actuation_s"] = np.where(prepared.meta["moving"], shift, 0.0)
    # The onset bounds then describe the shifted stream: the expected onset moves by what
    # the shift leaves of the predicted actuation delay.
    return out


def track_conveyor_seam(
    executor: TimedExecutor,
    cell: WeldCell,
    seam: Seam | None = None,
    *,
    settle_s: float = 0.15,
    cruise_s: float = 0.6,
    lead_s: float = 0.3,
    shift_s: ArrayLike | None = None,
    seam_plan: SeamPlan | None = None,
) -> ConveyorRun:
    """Weld a seam on the moving belt through ``executor`` and measure the torch.

    The robot must be at rest; it first moves to the approach's start configuration
    (a plain executor motion; where the driver reads the controller's set-point,
    ``commanded_q_rad``, up to :data:`APPROACH_ATTEMPTS` moves while the set-point ends
    more than :data:`SETPOINT_TOLERANCE_RAD` off), then the seam plan runs: the torch meets the seam
    ``lead_s`` after the plan is scheduled (at least the executor's lead), follows it for
    ``settle_s + cruise_s + 0.05`` s and stops.

    Parameters
    ----------
    executor : TimedExecutor
        Connected, robot at rest.
    cell : WeldCell
        Robot, belt and torch (:func:`~timedexec.tasks.default_cell`).
    seam : Seam, optional
        Default: a straight seam across the belt, welded at 0.05 m/s.
    settle_s, cruise_s : float
        The error window (s after the meeting, and its length), s.
    lead_s : float
        From scheduling to the meeting, s.
    shift_s : array (6,), optional
        Per-joint command shift, s (default: the executor's predicted actuation delay).
    seam_plan : SeamPlan, optional
        A plan from :func:`plan_seam` for this cell and seam (planning takes ~0.3 s).

    Raises
    ------
    ConfigError
        The seam is out of reach or beyond a limit (before any motion), or the robot does
        not belong to the cell.
    """
    if executor.spec.name != cell.robot:
        raise ConfigError(
            f"the weld cell is for {cell.robot!r}, the executor drives {executor.spec.name!r}"
        )
    for name, value in (("settle_s", settle_s), ("cruise_s", cruise_s), ("lead_s", lead_s)):
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{name}={value!r} must be a duration >= 0 s")
    seam = seam or Seam()
    weld_s = settle_s + cruise_s + 0.05
    sp = seam_plan or plan_seam(cell, seam, weld_s=weld_s, limits=executor.settings.limits)
    if sp.weld_s < weld_s - 1e-9:
        raise ConfigError(
            f"seam_plan covers {sp.weld_s:.3f} s of seam; settle_s + cruise_s + 0.05 = "
            f"{weld_s:.3f} s are needed"
        )
    # A previous motion may still be running out (its plan ended, the controller's
    # pipeline has not: a KR 5's is 72 ms): a speed stream cannot correct where the arm
    # ends up, so wait (reading, not commanding: a stop command would still be braking
    # when the approach's first commands arrive) until it is at rest.
    executor.idle(executor.now() + 2.0, until_rest=True)
    # Go to the approach's start (at rest), then let the state settle. The seam plan is a
    # speed stream from that start, so wherever the controller's set-point ends up stays
    # a position error through the weld: after one approach through RSI against the twin
    # the set-point ended -0.22 to +0.26 mrad off (the placement's lead; about 1.3 ms of
    # tracking lag per mrad at the weld's 0.79 rad/s), and -74 mrad (-90 ms) in one of
    # ~20 welds on a loaded machine. Where the driver reads the set-point
    # (``commanded_q_rad``: UR target_q, RSI's start pose + the correction sent) a
    # correction move follows from it while it is more than SETPOINT_TOLERANCE_RAD off;
    # the reported position is not chased: at rest it differs from the set-point by what
    # the position loop leaves (0.1-0.2 mrad on the KR 5 twin's A2/A3, 0.5 mrad on the
    # simulator), which the weld's motion takes up again.
    for attempt in range(APPROACH_ATTEMPTS):
        q_held = executor.driver.commanded_q_rad()
        q_from = executor.estimate().q_rad if q_held is None else q_held
        off = float(np.max(np.abs(q_from - sp.plan.q_start_rad)))
        if off <= (START_TOLERANCE_RAD if q_held is None else SETPOINT_TOLERANCE_RAD):
            break
        if attempt > 0 and q_held is None:
            break
        # The start is taken after the predictions (a GP's first query) and after a re-arm
        # of a watchdog that tripped while nobody stepped (a script upload: 25-50 ms);
        # taken before them, a real-time run started too late (8 ms cycles, 3 periods).
        # A correction is tiny: stretched over CORRECTION_PERIODS controller cycles, or
        # its few speed commands may share one cycle and cancel (a 0.04 mrad move
        # through RSI left the set-point where it was).
        stretch = None if attempt == 0 else CORRECTION_PERIODS * executor.period_s
        move = executor.prepare(
            executor.plan(sp.plan.q_start_rad, start_q_rad=q_from, minimum_duration_s=stretch)
        )
        executor.watchdog.rearm_if_tripped(executor.now)
        lead = executor.lead_time_s(move) + 3 * executor.period_s
        executor.execute(move, start_time_s=executor.now() + lead)
        executor.idle(executor.now() + 0.2)
    prepared = prepare_shifted(executor, sp.plan, shift_s)
    # The predictions may have kept the loop from reading (a GP's first query): drain the
    # packages queued meanwhile at rest, so the stream starts on fresh state.
    executor.idle(executor.now() + 5 * executor.period_s)
    lead = float(np.max(prepared.meta["actuation_s"])) + 3 * executor.period_s
    start = executor.now() + max(lead_s - sp.sync_s, lead)
    scheduled = prepared.at(start)
    sync = start + sp.sync_s
    probe = physical_probe(executor)
    rows: list[tuple[float, float, FloatArray, float, FloatArray, FloatArray]] = []

    def record(state: RobotState) -> None:
        if probe is not None:
            t, q = probe()
        else:
            t, q = executor.now(), np.full(6, np.nan)
        est = executor.estimate(t).q_rad
        rows.append((state.host_time_s, state.controller_time_s, state.q, t, q, est))

    result = executor.execute(scheduled, on_step=record)
    n = len(rows)
    host = np.array([r[0] for r in rows]) if n else np.zeros(0)
    ctrl = np.array([r[1] for r in rows]) if n else np.zeros(0)
    rep = np.array([r[2] for r in rows]).reshape(n, 6)
    t_truth = np.array([r[3] for r in rows]) if n else np.zeros(0)
    q_truth = np.array([r[4] for r in rows]).reshape(n, 6)
    q_est = np.array([r[5] for r in rows]).reshape(n, 6)
    if probe is None:
        q_truth = q_est
    return ConveyorRun(
        seam_plan=sp,
        plan=scheduled,
        sync_time_s=sync,
        settle_s=float(settle_s),
        cruise_s=float(cruise_s),
        host_s=host,
        controller_s=ctrl,
        reported_q=rep,
        truth_s=t_truth,
        truth_q=q_truth,
        estimate_s=t_truth.copy(),
        estimate_q=q_est,
        physical=probe is not None,
        execution=result,
        intake=executor.intake,
        clock_rate=line[2] if (line := executor.clock_line) is not None else 0.0,
    )
