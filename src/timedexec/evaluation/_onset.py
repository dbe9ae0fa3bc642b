"""Evaluation of delay-compensation strategies on the simulator, with ground truth.

On start configurations held out of training (a Sobol plan drawn with a fresh seed, laid out
in time like a full calibration sweep so the robot is as warm as during training), every
condition (configuration, joint 1/2/3/5, direction) gets one true trial delay from the
simulator. Each strategy predicts the actuation delay:

``none``      0 (no compensation);
``constant``  one latency for every joint: the overall median of a calibration sample (as
              MoveIt Servo's single latency setting);
``median``    the per-joint median of that sample (the published baseline);
``model``     the learned delay model;
``oracle``    the true conditional mean: the mean of ``draws`` further simulated trials of
              the same condition (only the cycle-phase and jitter randomness differ).

Reported per strategy: the RMS of (true - predicted) onset timing (ms) and the seam error at
``speed_m_s``: a velocity-interface stream that starts ``δ`` late leaves the tool ``speed ·
δ`` behind a moving seam, so the error is ``speed · RMS δ`` (cm). ``coverage_95`` is the
fraction of trials whose true onset lies in the model's 95 % bounds. Optionally the seam
error is verified by running the stepped physics (:func:`timedexec.tasks.track_seam` on
``sim://``) on a subset of held-out configurations with each strategy's shift.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._progress import Progress
from timedexec._types import FloatArray
from timedexec._validation import check_counts
from timedexec.effects import EffectSet, ThermalDrift, default_effects
from timedexec.errors import ConfigError
from timedexec.execution import (
    DelayPredictions,
    DelayPredictor,
    FixedDelays,
    TimingBounds,
    check_model_robot,
    load_delay_model,
    model_period_s,
    predict_delays,
)
from timedexec.recording import FULL_SWEEP_TRIALS, SweepPlan
from timedexec.robots import get_robot, get_robot_entry
from timedexec.sim import default_settings, simulate_delays, sweep_clock

__all__ = [
    "STRATEGIES",
    "Evaluation",
    "SimulatedOracle",
    "evaluate",
    "held_out_capacity",
    "warm_effects",
]


#: The strategies compared, in report order.
STRATEGIES = ("none", "constant", "median", "model", "oracle")

#: Seed offsets: the true trials, the oracle's draws and the calibration sample never share
#: random streams.
_CALIBRATION_SEED_OFFSET = 7919


def warm_effects(robot: str, t_start_s: float, effects: EffectSet | None = None) -> EffectSet:
    """The robot's effects with thermal drift as it stands ``t_start_s`` into a sweep.

    The stepped simulator starts its clock at 0 (cold); replacing ``cold_excess`` by its
    value at ``t_start_s`` gives the friction a sweep has at that time.
    """
    eff = effects if effects is not None else default_effects(robot)
    out: list[Any] = []
    for e in eff.effects:
        if isinstance(e, ThermalDrift):
            excess = e.cold_excess * math.exp(-t_start_s / e.time_constant_s)
            out.append(ThermalDrift(cold_excess=excess, time_constant_s=e.time_constant_s))
        else:
            out.append(e)
    return EffectSet(tuple(out))


class SimulatedOracle:
    """The simulator's true conditional mean delays as a delay model.

    ``predict_many`` simulates every condition ``draws`` times (fresh cycle phases and
    jitter) at sweep time ``t_start_s`` and returns the mean and standard deviation. It is
    exact up to ``std / sqrt(draws)`` and exists only for simulated robots: the ``oracle``
    strategy of :func:`evaluate`, and a stand-in model for tests and examples.
    """

    def __init__(
        self,
        robot: str,
        *,
        draws: int = 20,
        t_start_s: float = 4 * 3600.0,
        effects: EffectSet | None = None,
        seed: int = 1,
    ) -> None:
        spec = get_robot(robot)
        if draws < 2:
            raise ConfigError(f"draws={draws!r} must be >= 2")
        self.robot = spec.name
        self.controller_period_s = spec.controller_period_s
        self.draws = int(draws)
        self.t_start_s = float(t_start_s)
        self.effects = effects
        self.seed = int(seed)

    def predict_many(
        self, joint: ArrayLike, direction: ArrayLike, q: ArrayLike
    ) -> DelayPredictions:
        """Mean and std of ``draws`` simulated trials per row."""
        j = np.atleast_1d(np.asarray(joint, dtype=np.int64))
        d = np.atleast_1d(np.asarray(direction, dtype=np.int64))
        qq = np.asarray(q, dtype=float).reshape(-1, 6)
        n = len(j)
        t = np.full(n, self.t_start_s)
        act = np.empty((self.draws, n))
        resp = np.empty((self.draws, n))
        for k in range(self.draws):
            tab = simulate_delays(
                self.robot, qq, j, d, t, effects=self.effects, seed=self.seed * 1000 + k
            )
            act[k] = tab["actuation_delay"]
            resp[k] = tab["response_delay"]
        # Predictive std of a new trial: the spread of the draws plus the uncertainty of
        # their mean (sqrt(1 + 1/draws)).
        inflate = math.sqrt(1.0 + 1.0 / self.draws)
        return DelayPredictions(
            actuation_mean=act.mean(axis=0),
            actuation_std=act.std(axis=0, ddof=1) * inflate,
            response_mean=resp.mean(axis=0),
            response_std=resp.std(axis=0, ddof=1) * inflate,
        )

    def predict(self, *, joint: int, direction: int, q: ArrayLike) -> DelayPredictions:
        """One prediction (arrays of length 1)."""
        return self.predict_many([joint], [direction], np.asarray(q, float).reshape(1, 6))


@dataclass
class Evaluation:
    """Result of :func:`evaluate` (see :meth:`to_dict` for the JSON layout)."""

    robot: str
    strategies: dict[str, dict[str, float]]
    coverage_95: float
    n_trials: int
    n_configurations: int
    speed_m_s: float
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """``{"robot", "strategies": {name: {"timing_rms_ms", "seam_error_cm", ...}},
        "coverage_95", ...}``."""
        return {
            "robot": self.robot,
            "strategies": self.strategies,
            "coverage_95": self.coverage_95,
            "n_trials": self.n_trials,
            "n_configurations": self.n_configurations,
            "speed_m_s": self.speed_m_s,
            **self.details,
        }

    def ratio(self, strategy: str, metric: str = "seam_error_cm") -> float:
        """How many times smaller ``strategy``'s error is than with no compensation."""
        return float(self.strategies["none"][metric] / self.strategies[strategy][metric])

    def table(self) -> str:
        """Human-readable table."""
        phys = any("seam_physics_cm" in s for s in self.strategies.values())
        head = f"{'strategy':<10} {'timing RMS':>11} {'seam error':>11} {'vs none':>8}"
        if phys:
            head += f" {'seam (physics)':>15}"
        lines = [
            f"{self.robot}: {self.n_trials} held-out trials on {self.n_configurations} "
            f"configurations; seam at {self.speed_m_s} m/s",
            head,
        ]
        for name, s in self.strategies.items():
            row = (
                f"{name:<10} {s['timing_rms_ms']:>8.2f} ms {s['seam_error_cm']:>8.3f} cm "
                f"{self.ratio(name):>7.1f}x"
            )
            if phys:
                row += f" {s.get('seam_physics_cm', math.nan):>12.3f} cm"
            lines.append(row)
        lines.append(f"model 95 % bounds cover {self.coverage_95 * 100:.1f} % of true onsets")
        lines += [f"note: {text}" for text in self.details.get("notes", [])]
        return "\n".join(lines)


def held_out_capacity(robot: str, sweep_trials: int, joints: Sequence[int] = (1, 2, 3, 5)) -> int:
    """Start configurations a held-out sweep of ``sweep_trials`` trials holds.

    :func:`evaluate` lays its held-out conditions out in a sweep of the training sweep's
    size (so the joints are as warm as in training); it evaluates on at most this many
    configurations, whatever ``n_configs`` asks (and says so in its notes).
    """
    plan = SweepPlan.generate(get_robot(robot), int(sweep_trials), seed=0, joints=joints)
    return int(plan.config_index.max()) + 1


def _held_out(
    robot: str, n_configs: int, seed: int, sweep_trials: int, joints: Sequence[int]
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64], FloatArray]:
    """Conditions (q, joint, direction, sweep time) of ``n_configs`` fresh configurations."""
    spec = get_robot(robot)
    settings = default_settings(spec)
    plan = SweepPlan.generate(spec, sweep_trials, seed=seed, joints=joints)
    clock = sweep_clock(plan, settings, seed)
    first = plan.repeat == 0
    configs = np.unique(plan.config_index)
    rng = np.random.default_rng([seed, 0xE7A1])
    if n_configs < len(configs):
        configs = np.sort(rng.choice(configs, n_configs, replace=False))
    rows = np.flatnonzero(first & np.isin(plan.config_index, configs))
    return plan.q_start_rad[rows], plan.joint[rows], plan.direction[rows], clock.t0_s[rows]


def _seam_physics(
    robot: str,
    predictors: dict[str, DelayPredictor],
    q: FloatArray,
    t_start: FloatArray,
    speed_m_s: float,
    effects: EffectSet | None,
    seed: int,
    bar: Progress,
) -> dict[str, FloatArray]:
    """Mean physical seam distance (m) per strategy and configuration (stepped simulator)."""
    from timedexec.drivers import SimDriver
    from timedexec.execution import ExecutorSettings, TimedExecutor
    from timedexec.tasks import track_seam

    out: dict[str, list[float]] = {name: [] for name in predictors}
    for i, (qi, ti) in enumerate(zip(q, t_start, strict=True)):
        eff = warm_effects(robot, float(ti), effects)
        for name, model in predictors.items():
            if isinstance(model, SimulatedOracle):
                model = SimulatedOracle(
                    robot, draws=model.draws, t_start_s=float(ti), effects=effects, seed=model.seed
                )
            drv = SimDriver(robot, q0_rad=qi, effects=eff, seed=seed + i)
            settings = ExecutorSettings(compensate=name != "none")
            with TimedExecutor(drv, model, settings) as ex:
                res = track_seam(ex, speed_m_s=speed_m_s, cruise_s=0.3)
            out[name].append(res.mean_error_m)
            bar.update(1)
    return {k: np.asarray(v) for k, v in out.items()}


def _physics_configs(
    robot: str, q: FloatArray, joint: NDArray[np.int64], t0: FloatArray, n: int, speed_m_s: float
) -> tuple[FloatArray, FloatArray]:
    """Up to ``n`` held-out configurations where the tool can follow the seam."""
    from timedexec.tasks import tool_radius_m

    spec = get_robot(robot)
    picked_q: list[FloatArray] = []
    picked_t: list[float] = []
    seen: set[bytes] = set()
    for qi, ti, ji in zip(q, t0, joint, strict=True):
        if len(picked_q) >= n:
            break
        key = qi.tobytes()
        if ji != 1 or key in seen:
            continue
        seen.add(key)
        r = tool_radius_m(spec, qi)
        if r <= 0 or speed_m_s / r > 0.5 * spec.qd_max_rad_s[0]:
            continue
        room = min(qi[0] - spec.q_min_rad[0], spec.q_max_rad[0] - qi[0])
        if max(qi[0] - spec.q_min_rad[0], spec.q_max_rad[0] - qi[0]) < 1.0 or room < 0:
            continue
        picked_q.append(qi)
        picked_t.append(float(ti))
    return np.asarray(picked_q).reshape(-1, 6), np.asarray(picked_t)


def evaluate(
    robot: str,
    model: DelayPredictor | str | os.PathLike[str] | None = None,
    *,
    n_configs: int = 300,
    seed: int = 20_261,
    draws: int = 20,
    sweep_trials: int | None = None,
    speed_m_s: float = 0.5,
    confidence: float = 0.95,
    physics_configs: int = 0,
    joints: Sequence[int] = (1, 2, 3, 5),
    effects: EffectSet | None = None,
    progress: bool = False,
) -> Evaluation:
    """Compare the compensation strategies on held-out simulated trials.

    Parameters
    ----------
    robot : str
        A name in :data:`~timedexec.robots.ROBOT_NAMES`.
    model : delay model, bundle path or None
        Default: the model shipped for the robot (its catalog entry's ``shipped_model``).
    n_configs : int
        Held-out configurations (each with every joint and both directions).
    seed : int
        Plan seed of the held-out configurations (keep it different from the training
        sweep's) and the seed of the true trials.
    draws : int
        Simulated trials per condition behind the oracle's conditional mean.
    sweep_trials : int, optional
        Size of the sweep the held-out trials are laid out in (their sweep time, hence the
        warm-up of the joints, follows a sweep of this size, like the training data's).
        Default: the model's training sweep (a bundle's ``training_data.trials``), else
        the paper's 33,500.
    speed_m_s : float
        Seam speed, m/s.
    confidence : float
        Confidence of the bounds whose coverage is reported (``coverage_95`` at 0.95).
    physics_configs : int
        Held-out configurations on which to verify the seam error by running the stepped
        physics (joint 1 follows a seam) for each strategy; 0 skips it.

    Notes
    -----
    Counts are reported as used: ``n_configurations`` is the number evaluated, which is
    fewer than ``n_configs`` when the held-out sweep holds fewer
    (:func:`held_out_capacity`), and ``details["physics_configurations"]`` may be fewer
    than ``physics_configs`` when fewer held-out configurations let joint 1 follow the
    seam; each shortfall adds a line to ``details["notes"]`` (printed by :meth:`table`).
    """
    spec = get_robot(robot)
    check_counts(n_configs=(n_configs, 1), draws=(draws, 2), physics_configs=(physics_configs, 0))
    if not (math.isfinite(speed_m_s) and speed_m_s > 0):
        raise ConfigError(f"speed_m_s={speed_m_s!r} must be a finite speed > 0 m/s")
    if model is None:
        model = get_robot_entry(spec.name).shipped_model  # the bundled model
    predictor = load_delay_model(model)
    check_model_robot(predictor, spec.name, spec.controller_period_s)
    t_begin = time.monotonic()
    if sweep_trials is None:
        trained_on = getattr(predictor, "manifest", {}).get("training_data", {}).get("trials")
        sweep_trials = int(trained_on) if trained_on else FULL_SWEEP_TRIALS
    notes: list[str] = []
    capacity = held_out_capacity(spec.name, sweep_trials, joints)
    if capacity < n_configs:
        notes.append(
            f"{n_configs} held-out configurations were asked for, but a held-out sweep of "
            f"{sweep_trials:,} trials (the size of the model's training sweep) holds only "
            f"{capacity}; evaluated on {capacity}"
        )
    q, joint, direction, t0 = _held_out(spec.name, n_configs, seed, sweep_trials, joints)
    n = len(joint)
    bar = Progress(
        draws + 3 + physics_configs * len(STRATEGIES), f"evaluate {spec.name}", enabled=progress
    )
    truth = simulate_delays(spec, q, joint, direction, t0, effects=effects, seed=seed)
    true_act = np.asarray(truth["actuation_delay"], dtype=float)
    true_resp = np.asarray(truth["response_delay"], dtype=float)
    bar.update(1)
    oracle = np.zeros(n)
    oracle_resp = np.zeros(n)
    for k in range(draws):
        tab = simulate_delays(spec, q, joint, direction, t0, effects=effects, seed=seed + 1 + k)
        oracle += np.asarray(tab["actuation_delay"]) / draws
        oracle_resp += np.asarray(tab["response_delay"]) / draws
        bar.update(1)
    # A calibration sample from another fresh plan gives the medians (what a calibration
    # sweep of the robot gives the constant and per-joint-median strategies).
    cq, cj, cd, ct = _held_out(
        spec.name, n_configs, seed + _CALIBRATION_SEED_OFFSET, sweep_trials, joints
    )
    cal = simulate_delays(
        spec, cq, cj, cd, ct, effects=effects, seed=seed + 2 * _CALIBRATION_SEED_OFFSET
    )
    cal_act = np.asarray(cal["actuation_delay"], dtype=float)
    cal_resp = float(np.median(cal["response_delay"]))
    overall = float(np.median(cal_act))
    per_joint = np.full(6, overall)
    for j in np.unique(cj):
        per_joint[j - 1] = float(np.median(cal_act[cj == j]))
    bar.update(1)
    # A bundle with a time input predicts for each trial's own time in the sweep (warm-up).
    timed = bool(getattr(predictor, "time_input", False))
    pred = predict_delays(predictor, joint, direction, q, t_s=t0 if timed else None)
    bar.update(1)
    predictions = {
        "none": np.zeros(n),
        "constant": np.full(n, overall),
        "median": per_joint[joint - 1],
        "model": pred.actuation_mean,
        "oracle": oracle,
    }
    responses = {
        "none": np.zeros(n),
        "constant": np.full(n, cal_resp),
        "median": np.full(n, cal_resp),
        "model": pred.response_mean,
        "oracle": oracle_resp,
    }
    strategies: dict[str, dict[str, float]] = {}
    for name in STRATEGIES:
        err = true_act - predictions[name]
        rms = float(np.sqrt(np.mean(err**2)))
        seam = speed_m_s * np.abs(err)
        strategies[name] = {
            "timing_rms_ms": rms * 1e3,
            "timing_mean_ms": float(np.mean(err)) * 1e3,
            "seam_error_cm": speed_m_s * rms * 100,
            "seam_mean_cm": float(np.mean(seam)) * 100,
            "seam_std_cm": float(np.std(seam)) * 100,
            "response_rms_ms": float(np.sqrt(np.mean((true_resp - responses[name]) ** 2))) * 1e3,
        }
    bounds = TimingBounds.around(
        pred.actuation_mean, pred.actuation_std, confidence, model_period_s(predictor)
    )
    inside = bounds.contains(true_act)
    coverage = float(np.mean(inside))
    per_joint_cov = {str(int(j)): float(np.mean(inside[joint == j])) for j in np.unique(joint)}
    details: dict[str, Any] = {
        "confidence": confidence,
        "coverage_per_joint": per_joint_cov,
        "mean_bound_width_ms": float(np.mean(bounds.width_s)) * 1e3,
        "oracle_draws": draws,
        "seed": seed,
        "medians_ms": {"overall": overall * 1e3, "per_joint": (per_joint * 1e3).tolist()},
        "n_configs_requested": int(n_configs),
    }
    if physics_configs > 0:
        pq, pt = _physics_configs(spec.name, q, joint, t0, physics_configs, speed_m_s)
        if len(pq):
            oracle_model = SimulatedOracle(
                spec.name,
                draws=draws,
                t_start_s=float(np.mean(pt)),
                effects=effects,
                seed=seed + 99,
            )
            predictors: dict[str, DelayPredictor] = {
                "none": FixedDelays(robot=spec.name),
                "constant": FixedDelays(robot=spec.name, actuation_s=overall, response_s=cal_resp),
                "median": FixedDelays(robot=spec.name, actuation_s=per_joint, response_s=cal_resp),
                "model": predictor,
                "oracle": oracle_model,
            }
            phys = _seam_physics(spec.name, predictors, pq, pt, speed_m_s, effects, seed, bar)
            for name, dist in phys.items():
                strategies[name]["seam_physics_cm"] = float(np.mean(dist)) * 100
        details["physics_configurations"] = len(pq)
        if len(pq) < physics_configs:
            notes.append(
                f"the physics check was asked for {physics_configs} configurations; "
                f"{len(pq)} of the held-out ones let joint 1 follow a seam at {speed_m_s:g} m/s"
                + (", so it ran on those" if len(pq) else ", so it did not run")
            )
    bar.close()
    details["notes"] = notes
    details["elapsed_s"] = time.monotonic() - t_begin
    return Evaluation(
        robot=spec.name,
        strategies=strategies,
        coverage_95=coverage,
        n_trials=n,
        n_configurations=len(np.unique(q, axis=0)),
        speed_m_s=speed_m_s,
        details=details,
    )
