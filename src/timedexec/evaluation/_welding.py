"""Conveyor welding on the simulator: the physical torch error of each compensation strategy.

Here, beside the onset evaluation, and not in :mod:`timedexec.tasks`: it runs the simulator
(its physical joint angles are the truth at the torch), which real-robot code never imports.

The task (:func:`timedexec.tasks.track_conveyor_seam`): a straight belt at
``speed_m_s`` carries a part; the torch, orientation held, meets a seam on it (straight or
curved, across the belt), welds along it at 0.05 m/s relative to the part, every joint
moving, streamed through the :class:`~timedexec.execution.TimedExecutor` on ``sim://``. The
error is the torch tip from the simulator's *physical* joint angles minus the seam point at
the same instant, over the cruise (from ``settle_s`` after the meeting, ``cruise_s`` long):
mean, RMS and max of the distance, and along / across the seam.

What each strategy shifts joint ``j``'s command stream by — the **tracking delay**, the
lag a moving arm keeps (:class:`timedexec.tasks.TrackingDelays`):

``none``      0 (no compensation);
``constant``  one latency for all joints: the median of every joint's measured tracking
              delay over the calibration runs (MoveIt Servo's single latency);
``median``    per joint, the median over the calibration runs;
``model``     the tracking model fitted on the calibration runs: a dead time per joint
              and a friction offset per direction and joint, the offsets added to the
              command stream (:class:`~timedexec.tasks.TrackingDelays`);
``oracle``    the true mean tracking delay of each joint *on this very path*: the shift that
              best aligns the physical joint with its command (least squares over the
              cruise), averaged over ``oracle_draws`` runs with fresh publisher phases (none
              of them an evaluated run). It knows the path, the pose and the physics, but not
              the evaluated run's phase: the best any per-joint constant shift can do.

Calibration runs are uncompensated welds of the same seam at other work points (the cell's
work point moved by up to 5 cm), measured from the *reported* positions back-dated by the
model's response delay (what a real cell gives; phase-free, see the tracking module).
Evaluated: ``cells`` work points x ``seeds`` publisher phases per strategy, the phases
stratified over their range (:func:`phase_seeds`; the oracle's draws too).

``onset_strategies`` (optional) runs the same welds with the *onset* delays (what
:func:`timedexec.evaluation.evaluate` compares: overall and per-joint medians of simulated
calibration trials, the model's prediction, and :class:`SimulatedOracle`'s conditional mean):
the torch then leads the seam. ``feedback`` adds ``model + feedback``: the tracking shift
plus the executor's Smith-predictor position correction.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from timedexec._progress import Progress
from timedexec._types import FloatArray
from timedexec._validation import check_counts
from timedexec.effects import EffectSet, default_effects
from timedexec.errors import ConfigError
from timedexec.evaluation._onset import STRATEGIES, SimulatedOracle
from timedexec.execution import (
    DelayPredictor,
    ExecutorSettings,
    IntakeFix,
    StalenessLimits,
    TimedExecutor,
    check_model_robot,
    load_delay_model,
)
from timedexec.recording import SweepPlan, calibration_ranges
from timedexec.robots import get_robot, get_robot_entry
from timedexec.sim import simulate_delays
from timedexec.tasks import (
    MAX_CALIBRATION_RUNS,
    SEAM_KINDS,
    SEAM_POSITION_GAIN_1_S,
    ConveyorRun,
    Seam,
    SeamPlan,
    TrackingDelays,
    TrackingPhases,
    WeldCell,
    default_cell,
    fit_joint_lags,
    measure_tracking_delays,
    plan_seam,
    run_tracking_phases,
    track_conveyor_seam,
)

__all__ = [
    "TRACKING_SOURCES",
    "ConveyorEvaluation",
    "conveyor_cells",
    "evaluate_conveyor",
    "phase_seeds",
    "physical_tracking_delays",
    "run_weld",
    "sweep_tracking_model",
    "weld_on_twin",
]


#: Parts welded before each measured weld by default (:func:`run_weld`,
#: :func:`weld_on_twin`, :func:`evaluate_conveyor`): none, every weld from a fresh start,
#: so calibration and evaluation share a history. A weld's lag depends on the motions
#: before it (the velocity loop's integrator is held at rest; the approach ends where
#: friction lets it): the first weld after a start differs from later ones by up to
#: 2.4 ms (UR10) and 5.5 ms (the KR 5's reversing joints); docs/welding.md, "Weld after
#: weld", for what ``previous_welds`` > 0 gives and why it is not yet trustworthy.
PREVIOUS_WELDS = 0
#: Seed offsets so that evaluated runs, oracle draws and calibration never share a phase.
_ORACLE_SEED = 5_000
_CAL_SEED = 9_000
_PHASE_SEED = 11_000
#: Where the ``model`` strategy's tracking model of :func:`evaluate_conveyor` may come from.
TRACKING_SOURCES = ("sweep", "dry runs")
#: Warm robot time for the onset oracle and calibration trials (4 h into a sweep), s.
_WARM_S = 4 * 3600.0


def warm(robot: str) -> EffectSet:
    """The robot's default effects, warmed up (no cold-start friction)."""
    return default_effects(robot).without("thermal_drift")


def phase_seeds(robot: str, n: int, start: int) -> list[int]:
    """``n`` simulator seeds whose state publishers' phases stratify their range.

    The publisher's phase (sampling to sending, drawn per seed, drifting over 47 s) moves
    time between the actuation and the response delay and dominates a single run's torch
    error; one seed per ``1/n`` of its range (the first from ``start`` on that falls in each
    bin) estimates the mean over phases with far less variance than ``n`` random seeds
    (stratified sampling).
    """
    from timedexec.sim import ControllerSim

    picked: dict[int, int] = {}
    s = int(start)
    while len(picked) < n:
        ctrl = ControllerSim(robot, seed=s)
        lo, hi = ctrl.settings.timing.packing_phase_s
        frac = (ctrl.packing_phase_s(0.0) - lo) / (hi - lo) if hi > lo else 0.0
        picked.setdefault(min(int(frac * n), n - 1), s)
        s += 1
    return [picked[k] for k in sorted(picked)]


def conveyor_cells(
    robot: str, n: int, seed: int, *, speed_m_s: float = 0.5, spread_m: float = 0.05
) -> list[WeldCell]:
    """``n`` weld cells: the built-in one (first) and work points moved by up to
    ``spread_m`` (m) in x and y, seeded."""
    base = default_cell(robot, speed_m_s=speed_m_s)
    rng = np.random.default_rng([seed, 0xCE11])
    cells = [base]
    while len(cells) < n:
        dx, dy = rng.uniform(-spread_m, spread_m, 2)
        p = np.asarray(base.work_point_m) + np.array([dx, dy, 0.0])
        cells.append(
            WeldCell(
                robot=base.robot,
                work_point_m=(float(p[0]), float(p[1]), float(p[2])),
                torch_rotation=base.torch_rotation,
                tool_m=base.tool_m,
                seed_q_rad=base.seed_q_rad,
                conveyor=base.conveyor,
            )
        )
    return cells


def _weld_in_turn(
    ex: TimedExecutor,
    seam_plan: SeamPlan,
    shift_s: Any,
    settle_s: float,
    cruise_s: float,
    previous_welds: int,
) -> ConveyorRun:
    """``previous_welds`` welds of ``seam_plan`` through ``ex`` (not measured), then the one
    returned.

    Raises
    ------
    ConfigError
        ``previous_welds`` is not an integer >= 0.
    """
    if (
        isinstance(previous_welds, bool)
        or not isinstance(previous_welds, int | np.integer)
        or previous_welds < 0
    ):
        raise ConfigError(f"previous_welds={previous_welds!r} must be an integer >= 0")
    for _ in range(int(previous_welds) + 1):
        run = track_conveyor_seam(ex, seam_plan.cell, seam_plan.seam, seam_plan=seam_plan,
                                  shift_s=shift_s, settle_s=settle_s, cruise_s=cruise_s)  # fmt: skip
    return run


def run_weld(
    seam_plan: SeamPlan,
    model: Any,
    *,
    seed: int,
    shift_s: Any = None,
    compensate: bool = True,
    position_gain_1_s: float = 0.0,
    effects: EffectSet | None = None,
    settle_s: float = 0.15,
    cruise_s: float = 0.6,
    previous_welds: int = PREVIOUS_WELDS,
) -> ConveyorRun:
    """One weld on ``sim://`` (virtual time): the arm starts at rest where the weld ends,
    welds ``previous_welds`` parts the same way (not measured), then the one returned; each
    weld begins with the move to the approach's start.

    ``seed`` sets the controller's publisher phase and the network jitter; ``shift_s``
    (6,), s, the command shifts (None: the model's onset prediction).
    """
    from timedexec.drivers import SimDriver

    cell = seam_plan.cell
    drv = SimDriver(
        cell.robot,
        q0_rad=seam_plan.plan.q_end_rad,
        effects=effects if effects is not None else warm(cell.robot),
        seed=seed,
    )
    settings = ExecutorSettings(
        compensate=compensate, position_gain_1_s=position_gain_1_s, cycle_lock=True
    )
    with TimedExecutor(drv, model, settings) as ex:
        return _weld_in_turn(ex, seam_plan, shift_s, settle_s, cruise_s, previous_welds)


def physical_tracking_delays(run: ConveyorRun) -> FloatArray:
    """Per joint, the shift that would have aligned the *physical* joint with its command
    over the run's cruise (the truth behind :func:`measure_tracking_delays`), s (6,)."""
    t = run.truth_s - run.sync_time_s
    keep = (t >= run.settle_s) & (t <= run.settle_s + run.cruise_s)
    return np.asarray(fit_joint_lags(run.plan, run.truth_s[keep], run.truth_q[keep]) + run.shifts_s)


def sweep_tracking_model(
    robot: str,
    model: Any,
    *,
    seed: int,
    phases: TrackingPhases | None = None,
    q_rad: Any = None,
    effects: EffectSet | None = None,
) -> TrackingDelays:
    """The tracking model from a simulated sweep's constant-speed phases alone
    (:func:`~timedexec.tasks.run_tracking_phases`,
    :meth:`~timedexec.tasks.TrackingDelays.calibrate_phases`): the phases run on ``sim://``
    (virtual time, warm, uncompensated, cycle-locked) from ``q_rad`` (default: the middle of
    the sweep's calibration ranges), measured from the reported positions as a real sweep
    would be."""
    from timedexec.drivers import SimDriver

    spec = get_robot(robot)
    if q_rad is None:
        lo, hi = calibration_ranges(spec)
        q_rad = 0.5 * (lo + hi)
    drv = SimDriver(spec.name, q0_rad=np.asarray(q_rad, dtype=float),
                    effects=effects if effects is not None else warm(spec.name), seed=seed)  # fmt: skip
    settings = ExecutorSettings(compensate=False, cycle_lock=True)
    with TimedExecutor(drv, model, settings) as ex:
        runs = run_tracking_phases(ex, phases)
    return TrackingDelays.calibrate_phases(model, runs)


@dataclass
class ConveyorEvaluation:
    """Result of :func:`evaluate_conveyor` (see :meth:`to_dict`)."""

    robot: str
    seam: str
    speed_m_s: float
    strategies: dict[str, dict[str, float]]
    onset_strategies: dict[str, dict[str, float]] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    examples: dict[str, ConveyorRun] = field(default_factory=dict, repr=False)
    #: The tracking model the "model" strategy ran (fitted on the calibration welds).
    tracking_model: TrackingDelays | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """``{"robot", "task": "conveyor", "seam", "speed_m_s", "strategies": {name:
        {"torch_mean_mm", "torch_rms_mm", "torch_max_mm", "along_*", "across_*", ...}},
        "onset_strategies": {...}, ...details}`` (distances over the cruise, physical
        torch against the seam)."""
        return {
            "robot": self.robot,
            "task": "conveyor",
            "seam": self.seam,
            "speed_m_s": self.speed_m_s,
            "strategies": self.strategies,
            "onset_strategies": self.onset_strategies,
            **self.details,
        }

    def ratio(self, strategy: str) -> float:
        """How many times smaller ``strategy``'s mean torch distance is than with none."""
        return float(
            self.strategies["none"]["torch_mean_mm"] / self.strategies[strategy]["torch_mean_mm"]
        )

    def figure_data(self) -> dict[str, Any]:
        """JSON-safe time series of one run per strategy (the first cell and seed) for
        :func:`timedexec.report.fig_welding`: ``runs: {name: {times_s, torch_xy_m,
        seam_xy_m, along_mm, across_mm}}``."""
        runs = {}
        for name, run in self.examples.items():
            err = run.errors(window=False)
            q = run.truth_q
            t = run.truth_s - run.sync_time_s
            keep = (t >= 0) & (t <= run.seam_plan.weld_s)
            torch = run.seam_plan.torch_m(q[keep])
            point, _, _ = run.seam_plan.target(t[keep])
            runs[name] = {
                "times_s": t[keep].round(5).tolist(),
                "torch_xy_m": torch[:, :2].round(6).tolist(),
                "seam_xy_m": point[:, :2].round(6).tolist(),
                "along_mm": (err.along_m * 1e3).round(4).tolist(),
                "across_mm": (err.across_m * 1e3).round(4).tolist(),
            }
        first = next(iter(self.examples.values()), None)
        return {
            "robot": self.robot,
            "seam": self.seam,
            "speed_m_s": self.speed_m_s,
            "settle_s": first.settle_s if first else math.nan,
            "cruise_s": first.cruise_s if first else math.nan,
            "runs": runs,
        }

    def table(self) -> str:
        """Human-readable table (mm)."""
        d = self.details
        lines = [
            f"{self.robot}: conveyor at {self.speed_m_s:g} m/s, {self.seam} seam welded at "
            f"{d.get('weld_speed_m_s', math.nan):g} m/s; physical torch over "
            f"{d.get('cruise_s', math.nan):g} s of cruise, {d.get('n_runs', 0)} runs per "
            "strategy",
            f"{'strategy':<18} {'mean':>7} {'RMS':>7} {'max':>7} {'along':>7} {'across':>7} "
            f"{'vs none':>8}   (mm; along/across: mean, signed)",
        ]

        def row(name: str, s: dict[str, float]) -> str:
            base = self.strategies["none"]["torch_mean_mm"]
            return (
                f"{name:<18} {s['torch_mean_mm']:>7.2f} {s['torch_rms_mm']:>7.2f} "
                f"{s['torch_max_mm']:>7.2f} {s['along_mean_mm']:>+7.2f} "
                f"{s['across_mean_mm']:>+7.2f} {base / s['torch_mean_mm']:>7.1f}x"
            )

        lines += [row(name, s) for name, s in self.strategies.items()]
        if self.onset_strategies:
            lines.append("shifted by the onset (actuation) delay instead:")
            lines += [row(f"  {name}", s) for name, s in self.onset_strategies.items()]
        shifts = d.get("shift_ms", {})
        if shifts:
            lines.append("command shifts (ms, joints 1-6, first cell):")
            for name, v in shifts.items():
                lines.append(f"  {name:<16} " + " ".join(f"{x:6.1f}" for x in v))
        lines += [f"note: {text}" for text in d.get("notes", [])]
        return "\n".join(lines)


def _pool(runs: list[ConveyorRun]) -> dict[str, float]:
    """Statistics over the cruise samples of every run (and per-run spread)."""
    errs = [r.errors() for r in runs]
    d = np.concatenate([e.distance_m for e in errs])
    along = np.concatenate([e.along_m for e in errs])
    across = np.concatenate([e.across_m for e in errs])
    vertical = np.concatenate([e.vertical_m for e in errs])
    per_run = np.array([float(np.mean(e.distance_m)) for e in errs]) * 1e3

    def rms(x: FloatArray) -> float:
        return float(np.sqrt(np.mean(x**2))) * 1e3

    return {
        "torch_mean_mm": float(np.mean(d)) * 1e3,
        "torch_rms_mm": rms(d),
        "torch_max_mm": float(np.max(d)) * 1e3,
        "along_mean_mm": float(np.mean(along)) * 1e3,
        "along_rms_mm": rms(along),
        "along_max_mm": float(np.max(np.abs(along))) * 1e3,
        "across_mean_mm": float(np.mean(across)) * 1e3,
        "across_rms_mm": rms(across),
        "across_max_mm": float(np.max(np.abs(across))) * 1e3,
        "vertical_rms_mm": rms(vertical),
        "run_mean_mm_min": float(np.min(per_run)),
        "run_mean_mm_max": float(np.max(per_run)),
        "missed_cycles": int(sum(r.execution.missed_cycles for r in runs)),
        "runs": len(runs),
    }


def _onset_medians(
    robot: str, n: int, seed: int, effects: EffectSet
) -> tuple[float, FloatArray, float]:
    """Overall and per-joint medians of simulated onset delays (a calibration sample of
    ``n`` configurations x joints 1/2/3/5 x both directions), and the response median."""
    spec = get_robot(robot)
    plan = SweepPlan.generate(spec, 80 * n, seed=seed)
    first = plan.repeat == 0
    q, j, d = plan.q_start_rad[first], plan.joint[first], plan.direction[first]
    tab = simulate_delays(spec, q, j, d, np.full(len(j), _WARM_S), effects=effects, seed=seed)
    act = np.asarray(tab["actuation_delay"], dtype=float)
    overall = float(np.median(act))
    per_joint = np.full(6, overall)
    for k in np.unique(j):
        per_joint[k - 1] = float(np.median(act[j == k]))
    return overall, per_joint, float(np.median(tab["response_delay"]))


#: The cruise windows :func:`evaluate_conveyor` tries in turn when none is given, s: a
#: weld spans ``speed x (settle + cruise + 0.05 s)`` of belt, centred on the work point,
#: which a small arm cannot reach on a fast belt (KR 5, 850 mm: 0.8 m of belt at 1 m/s).
CRUISE_CHOICES_S = (0.6, 0.45, 0.3, 0.2)


def _cruise_in_reach(
    cells: list[WeldCell], seam: Seam, settle_s: float, cruise_s: float | None
) -> tuple[float, list[str]]:
    """The cruise window (s) and a note when it was shortened: ``cruise_s`` as given, or
    the longest of :data:`CRUISE_CHOICES_S` whose weld every one of ``cells`` can plan."""
    if cruise_s is not None:
        return cruise_s, []
    for choice in CRUISE_CHOICES_S:
        try:
            for cell in cells:
                plan_seam(cell, seam, weld_s=settle_s + choice + 0.05)
        except ConfigError:
            if choice == CRUISE_CHOICES_S[-1]:
                raise
            continue
        if choice == CRUISE_CHOICES_S[0]:
            return choice, []
        return choice, [
            f"the cruise is {choice:g} s instead of {CRUISE_CHOICES_S[0]:g} s: at "
            f"{cells[0].conveyor.speed_m_s:g} m/s a longer weld leaves the reach of "
            f"{cells[0].robot}"
        ]
    raise AssertionError("unreachable")  # pragma: no cover


def evaluate_conveyor(
    robot: str,
    model: DelayPredictor | str | os.PathLike[str] | None = None,
    *,
    seam: str = "straight",
    speed_m_s: float = 0.5,
    cells: int = 2,
    seeds: int = 3,
    oracle_draws: int = 4,
    calibration_runs: int = 3,
    seed: int = 20_261,
    settle_s: float = 0.15,
    cruise_s: float | None = None,
    onset: bool = True,
    feedback: bool = True,
    progress: bool = False,
    previous_welds: int = PREVIOUS_WELDS,
    tracking: str = "sweep",
    phases: TrackingPhases | None = None,
) -> ConveyorEvaluation:
    """Physical torch error of the compensation strategies on the simulated conveyor weld.

    Parameters
    ----------
    robot : str
        A name in :data:`~timedexec.robots.ROBOT_NAMES`.
    model : delay model, bundle path or None
        Default: the model shipped for the robot (its catalog entry's ``shipped_model``).
    seam : {"straight", "curved"}
    speed_m_s : float
        Belt speed, m/s.
    cells, seeds : int
        Work points (the built-in cell first) and publisher phases per work point: each
        strategy runs ``cells x seeds`` welds.
    oracle_draws : int
        Runs per work point behind the oracle's mean tracking delay (>= 1).
    calibration_runs : int
        Uncompensated welds at other work points behind constant, median and the model's
        correction (>= 1).
    seed : int
        Seeds the work points and every run's phase.
    settle_s, cruise_s : float
        The error window after the meeting, s. ``cruise_s`` None: 0.6 s, or the longest of
        :data:`CRUISE_CHOICES_S` whose weld stays in the robot's reach on a fast belt
        (the KR 5 at 1 m/s: 0.3 s; a note says so).
    onset : bool
        Also run the strategies with onset-delay shifts (``onset_strategies``).
    feedback : bool
        Also run ``model + feedback`` (tracking shift and the Smith-predictor position
        correction at :data:`~timedexec.tasks.SEAM_POSITION_GAIN_1_S`).
    previous_welds : int
        Parts welded the same way before each measured weld (:func:`run_weld`).
    tracking : {"sweep", "dry runs"}
        Where the ``model`` strategy's tracking model comes from: ``"sweep"`` (default) the
        calibration sweep's constant-speed phases alone: the model bundle's
        ``tracking.json`` (:meth:`~timedexec.tasks.TrackingDelays.of_bundle`), else the
        phases run on the simulator at the cell's seed pose (:func:`sweep_tracking_model`;
        a sweep over the task's workspace); the model fitted on the dry runs is then
        evaluated too, as ``model (dry runs)``. Or
        ``"dry runs"`` the uncompensated calibration welds of the task
        (:meth:`~timedexec.tasks.TrackingDelays.calibrate_runs`). The dry runs are welded
        either way: ``constant`` and ``median`` are their measured lags.
    phases : TrackingPhases, optional
        With ``tracking="sweep"``: run these phases on the simulator (instead of the
        bundle's ``tracking.json``; default :class:`~timedexec.tasks.TrackingPhases`).

    Raises
    ------
    ConfigError
        Bad counts, an unknown seam or tracking source, a model for another robot.
    """
    spec = get_robot(robot)
    if seam not in SEAM_KINDS:
        raise ConfigError(f"seam={seam!r}; choose one of {', '.join(SEAM_KINDS)}")
    check_counts(
        cells=(cells, 1), seeds=(seeds, 1), oracle_draws=(oracle_draws, 1),
        calibration_runs=(calibration_runs, 1), previous_welds=(previous_welds, 0),
    )  # fmt: skip
    if not (math.isfinite(speed_m_s) and speed_m_s > 0):
        raise ConfigError(f"speed_m_s={speed_m_s!r} must be a finite speed > 0 m/s")
    if tracking not in TRACKING_SOURCES:
        raise ConfigError(
            f"tracking={tracking!r}; choose one of {', '.join(map(repr, TRACKING_SOURCES))}"
        )
    sweep = tracking == "sweep"
    entry = get_robot_entry(spec.name)
    predictor = load_delay_model(entry.shipped_model if model is None else model)
    check_model_robot(predictor, spec.name, spec.controller_period_s)
    effects = warm(spec.name)
    the_seam = Seam(kind=seam)  # type: ignore[arg-type]
    t_begin = time.monotonic()
    # Runs that disagree with no majority get more, at further work points (the same
    # seeded sequence of cells: the first ones do not change with the cap).
    most = max(calibration_runs, MAX_CALIBRATION_RUNS)
    cal_cells = conveyor_cells(spec.name, most + 1, seed + _CAL_SEED, speed_m_s=speed_m_s)[1:]  # fmt: skip
    eval_cells = conveyor_cells(spec.name, cells, seed, speed_m_s=speed_m_s)
    cruise_s, cruise_note = _cruise_in_reach(
        [*eval_cells, *cal_cells], the_seam, settle_s, cruise_s
    )
    weld_s = settle_s + cruise_s + 0.05
    n_onset = 4 if onset else 0
    total = calibration_runs + cells * (
        oracle_draws + seeds * (len(STRATEGIES) + n_onset + int(feedback) + int(sweep))
    )
    bar = Progress(total, f"conveyor {spec.name}", enabled=progress)

    def plan_for(cell: WeldCell) -> SeamPlan:
        return plan_seam(cell, the_seam, weld_s=weld_s)

    def weld(sp: SeamPlan, k: int, **kw: Any) -> ConveyorRun:
        run = run_weld(sp, kw.pop("model", predictor), seed=k, effects=effects,
                       settle_s=settle_s, cruise_s=cruise_s, previous_welds=previous_welds, **kw)  # fmt: skip
        bar.update(1)
        return run

    # Calibration: uncompensated welds at other work points, measured as a real cell would.
    cal_runs: list[ConveyorRun] = []

    def calibration_weld(i: int) -> ConveyorRun:
        run = weld(plan_for(cal_cells[i]), seed + _CAL_SEED + i, compensate=False)
        cal_runs.append(run)
        return run

    for i in range(calibration_runs):
        calibration_weld(i)
    dry_model = TrackingDelays.calibrate_runs(
        predictor, list(cal_runs), more=calibration_weld, max_runs=most
    )
    tracking_model = dry_model
    source = "dry runs"
    if sweep:
        stored = TrackingDelays.of_bundle(predictor) if phases is None else None
        source = "sweep (the model bundle's tracking.json)"
        if stored is None:
            source = "sweep (constant-speed phases on the simulator)"
            # Where the task works (a sweep for this cell: its --workspace): the friction
            # offsets change with the gravity load (KR 5 at 0.5 m/s: 0.43 mm from phases
            # at the cell's pose, 0.91 mm from the middle of the calibration ranges).
            stored = sweep_tracking_model(
                spec.name,
                predictor,
                seed=seed + _PHASE_SEED,
                phases=phases,
                q_rad=eval_cells[0].seed_q_rad,
                effects=effects,
            )
        tracking_model = stored
    tracks_arr = np.asarray([measure_tracking_delays(run) for run in cal_runs])
    constant = float(np.median(tracks_arr))
    median = np.median(tracks_arr, axis=0)
    if onset:
        on_all, on_joint, _ = _onset_medians(spec.name, 40, seed + _CAL_SEED, effects)
        onset_oracle = SimulatedOracle(spec.name, draws=20, t_start_s=_WARM_S, effects=effects, seed=seed + 77)  # fmt: skip

    results: dict[str, list[ConveyorRun]] = {}
    examples: dict[str, ConveyorRun] = {}
    shift_log: dict[str, list[float]] = {}

    def add(name: str, run: ConveyorRun, first: bool) -> None:
        results.setdefault(name, []).append(run)
        if first:
            examples[name] = run
            shift_log[name] = (run.shifts_s * 1e3).round(2).tolist()

    oracle_shifts = []
    for c, cell in enumerate(eval_cells):
        sp = plan_for(cell)
        draws = [
            physical_tracking_delays(weld(sp, k, compensate=False))
            for k in phase_seeds(spec.name, oracle_draws, seed + _ORACLE_SEED + 1000 * c)
        ]
        oracle = np.mean(draws, axis=0)
        oracle_shifts.append(oracle)
        for s, k in enumerate(phase_seeds(spec.name, seeds, seed + 1000 * c)):
            first = c == 0 and s == 0
            add("none", weld(sp, k, compensate=False), first)
            add("constant", weld(sp, k, shift_s=np.full(6, constant)), first)
            add("median", weld(sp, k, shift_s=median), first)
            add("model", weld(sp, k, model=tracking_model), first)
            if sweep:
                add("model (dry runs)", weld(sp, k, model=dry_model), first)
            add("oracle", weld(sp, k, shift_s=oracle), first)
            if feedback:
                add("model + feedback", weld(sp, k, model=tracking_model,
                                             position_gain_1_s=SEAM_POSITION_GAIN_1_S), first)  # fmt: skip
            if onset:
                add("onset constant", weld(sp, k, shift_s=np.full(6, on_all)), first)
                add("onset median", weld(sp, k, shift_s=on_joint), first)
                add("onset model", weld(sp, k), first)
                add("onset oracle", weld(sp, k, model=onset_oracle), first)
    bar.close()
    pooled = {name: _pool(runs) for name, runs in results.items()}
    strategies = {name: pooled[name] for name in STRATEGIES}
    if sweep:
        strategies["model (dry runs)"] = pooled["model (dry runs)"]
    if feedback:
        strategies["model + feedback"] = pooled["model + feedback"]
    onset_rows = {n.removeprefix("onset "): pooled[n] for n in pooled if n.startswith("onset ")}
    details: dict[str, Any] = {
        "weld_speed_m_s": the_seam.weld_speed_m_s,
        "settle_s": settle_s,
        "cruise_s": cruise_s,
        "cells": cells,
        "seeds_per_cell": seeds,
        "n_runs": cells * seeds,
        "oracle_draws": oracle_draws,
        "calibration_runs": len(cal_runs),
        "previous_welds": previous_welds,
        "seed": seed,
        "tracking_source": source,
        "tracking_ms": {
            "constant": constant * 1e3,
            "median": (median * 1e3).round(3).tolist(),
            "model_dead_time": (np.asarray(tracking_model.dead_time_s) * 1e3).round(3).tolist(),
            "model_friction_mrad": (np.asarray(tracking_model.friction_rad) * 1e3)
            .round(4)
            .tolist(),
            "model_fit_rms_mrad": (np.asarray(tracking_model.fit_rms_rad) * 1e3).round(4).tolist(),
            "oracle": (np.mean(oracle_shifts, axis=0) * 1e3).round(3).tolist(),
            "calibration_measured": (tracks_arr * 1e3).round(3).tolist(),
            **(
                {
                    "dry_runs_dead_time": (np.asarray(dry_model.dead_time_s) * 1e3)
                    .round(3)
                    .tolist(),
                    "dry_runs_friction_mrad": (np.asarray(dry_model.friction_rad) * 1e3)
                    .round(4)
                    .tolist(),
                }
                if sweep
                else {}
            ),
        },
        "shift_ms": shift_log,
        "cell": conveyor_cells(spec.name, 1, seed, speed_m_s=speed_m_s)[0].to_dict(),
        "notes": [*cruise_note, *dry_model.notes, *(tracking_model.notes if sweep else ())],
    }
    details["elapsed_s"] = time.monotonic() - t_begin
    return ConveyorEvaluation(
        robot=spec.name,
        seam=seam,
        speed_m_s=float(speed_m_s),
        strategies=strategies,
        onset_strategies=onset_rows,
        details=details,
        examples=examples,
        tracking_model=tracking_model,
    )


def _strategy(model: Any, value: Any) -> tuple[Any, Any]:
    """The model and shift one of :func:`weld_on_twin`'s strategies runs with: a delay
    model compensates by itself (no shift), anything else is a shift (or None) for
    ``model``."""
    if hasattr(value, "predict_many"):
        return value, None
    return model, value


def weld_on_twin(
    seam_plan: SeamPlan,
    model: Any,
    shifts_s: dict[str, Any],
    *,
    seed: int = 1,
    host: str = "127.0.0.61",
    rsi_port: int | None = None,
    stale_periods: float = 25.0,
    settle_s: float = 0.15,
    cruise_s: float = 0.6,
    truth_dir: str | os.PathLike[str] | None = None,
    previous_welds: int = PREVIOUS_WELDS,
) -> dict[str, ConveyorRun]:
    """The same welds through a real client against a protocol twin, with its ground truth.

    By the robot's interface (its catalog entry's ``twin.interface``): UR robots
    (``ur_rtde``), a :class:`~timedexec.twins.URTwin` (own process, real time) on ``host``
    and the real ``ur_rtde`` client (:class:`~timedexec.drivers.URDriver`); KUKA
    (``kuka_rsi``, the KR 5): an
    :class:`~timedexec.twins.RSITwin` (own process) sending RSI XML to a
    :class:`~timedexec.drivers.KukaRSIDriver` on ``rsi_port`` (default: a free port). One
    weld per strategy in ``shifts_s`` (name -> per-joint shift (6,), s; a delay model that
    compensates by itself, e.g. a :class:`~timedexec.tasks.TrackingDelays` with its
    friction offsets; or None for no compensation), a fresh twin (same ``seed``) for each,
    started where the weld ends: every weld begins with the move to the approach's start,
    and the measured one follows ``previous_welds`` of the same strategy, as in
    :func:`run_weld` (a weld's lag depends on the motions before it:
    :data:`PREVIOUS_WELDS`). The torch truth: the reported angles are the twin's physical
    angles at each package's sampling instant, and the twin publishes the host time of its
    controller time 0 (:meth:`ConveyorRun.with_truth`).

    ``stale_periods`` is generous (25 periods) because the executor, ur_rtde's receive
    thread and the twin share a loaded two-core machine; a stale fault stops the weld.
    """
    cell = seam_plan.cell
    spec = cell.spec
    effects = warm(spec.name)
    q0 = seam_plan.plan.q_end_rad
    out: dict[str, ConveyorRun] = {}
    model = load_delay_model(model)  # once: a GP's first query takes seconds
    check_model_robot(model, spec.name, spec.controller_period_s)
    model.predict_many(np.array([1]), np.array([1]), q0.reshape(1, 6))
    # A fault stop's deceleration must suit every joint (the RSI driver checks each joint).
    settings = ExecutorSettings(
        staleness=StalenessLimits.from_stale_periods(stale_periods),
        stop_deceleration_rad_s2=float(min(spec.qdd_max_rad_s2)),
    )
    entry = get_robot_entry(spec.name)
    if entry.twin.interface == "ur_rtde":
        # The twin's echo depth is known by construction: its states are dated by counting
        # packages, not by a mean response its wandering publisher can be half a period from.
        settings = settings.replace(
            echo_depth_cycles=entry.timing.target_echo_cycles(spec.controller_period_s)
        )
        from timedexec.drivers import URDriver
        from timedexec.twins import URTwin

        for i, (name, value) in enumerate(shifts_s.items()):
            truth = None if truth_dir is None else os.path.join(truth_dir, f"ur-truth-{i}.jsonl")
            by, shift = _strategy(model, value)
            with URTwin(
                spec.name, host, seed=seed, effects=effects, q0_rad=q0, truth_path=truth
            ) as twin, TimedExecutor(URDriver(host, robot=spec.name), by,
                                     settings.replace(compensate=value is not None,
                                                      cycle_lock=True, coast=True)) as ex:  # fmt: skip
                run = _weld_in_turn(ex, seam_plan, shift, settle_s, cruise_s, previous_welds)
                out[name] = run.with_truth(twin.t0_monotonic_s)
        return out
    from timedexec.drivers import KukaRSIDriver
    from timedexec.twins import RSITwin

    for i, (name, value) in enumerate(shifts_s.items()):
        truth = None if truth_dir is None else os.path.join(truth_dir, f"rsi-truth-{i}.jsonl")
        by, shift = _strategy(model, value)
        with KukaRSIDriver(rsi_port or 0, robot=spec.name) as drv, RSITwin(
            drv.port, robot=spec.name, effects=effects, q0_rad=q0, seed=seed, truth_path=truth,
            timeout_packets=2000,
        ) as twin:  # fmt: skip
            # The controller's intake, probed at rest: commands placed and states dated
            # by the controller's cycle, not by the frames' wandering phase.
            probed = drv.probe_intake()
            ex = TimedExecutor(drv, by, settings.replace(compensate=value is not None))
            ex.connect()
            run = _weld_in_turn(ex, seam_plan, shift, settle_s, cruise_s, previous_welds)
            run = replace(run, intake=_rsi_dating(probed, float(run.plan.meta["response_s"])))
            last: Any = ex.last_state
            # Driver controller time counts from its first IPOC; the twin's from its start.
            offset = twin.controller_time_of_ipoc(int(last.ipoc)) - last.controller_time_s
            out[name] = run.with_truth(twin.t0_host_s + offset)
    return out


def _rsi_dating(probed: Any, response_s: float) -> IntakeFix:
    """The RSI intake probe as the run's dating (:meth:`IntakeFix.dated`: each frame
    sampled at its cycle boundary, the whole periods back chosen by ``response_s``)."""
    return IntakeFix(
        deadline_offset_s=probed.deadline_offset_s,
        period_s=probed.period_s,
        probed_at_s=probed.probed_at_s,
        resolution_s=probed.resolution_s,
        package_lead_s=(probed.arrival_offset_s - probed.deadline_offset_s) % probed.period_s,
        trials=probed.trials,
        mismatches=probed.mismatches,
        arrival_offset_s=probed.arrival_offset_s,
    ).dated(response_s)
