"""Cross-validation as published and training of the per-joint and combined delay models.

Protocol (DESIGN.md §1): inputs start configuration, actuated joint and direction; one
model per joint and one combined model (joint one-hot); actuation and response delay
separately; 10-fold cross-validation with error ``sqrt(mean over folds of the fold MSE)``
in ms; baseline the median delay.

Folds split by **start configuration**: every trial of a configuration (all its joints,
both directions, every repeat) falls in one fold. Splitting by trial would put repeats of a
test condition into training and let a model look up its mean — CV would then reward
memorising replicates (the paper's setup does not say how its folds were drawn; this is
the honest choice). Grouping by configuration rather than by condition also keeps the
other joints and the other direction of a test pose out of training, so a column measures
the error on start poses the model has never seen. Per-joint and combined models use the
same folds, so their columns compare.

Fits run as independent joblib tasks (per delay, model, method and fold, plus the final
fits on all data), biggest first; under ``joblib.parallel_config(backend="dask")`` the same
tasks run on a Dask cluster (pass ``jobs=-1``; ``jobs=1`` runs in-process without joblib).
"""

from __future__ import annotations

import hashlib
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.delays import JOINT_RESPONSE_FLAGS, RESPONSE_FLAG_WHY, DelayTable
from timedexec.errors import ConfigError
from timedexec.learning._calibrate import (
    CALIBRATED_METHOD,
    bound_quantile,
    gaussian_coverage,
    std_scale_factor,
)
from timedexec.learning._features import encode_inputs
from timedexec.learning._method import ModelInputs
from timedexec.learning._registry import DEFAULT_METHODS, check_methods, get_method
from timedexec.learning._thermal import thermal_state
from timedexec.robots import ROBOT_NAMES, get_robot_entry

__all__ = [
    "DELAYS",
    "PAPER_TABLES",
    "CVResult",
    "TrainResult",
    "cross_validate",
    "noise_floor",
    "paper_family",
    "train_delay_models",
]


#: The two delays, each modelled separately (delay-table column names).
DELAYS: tuple[str, ...] = ("actuation_delay", "response_delay")

#: The paper's Tables I (actuation) and II (response): 10-fold CV error in ms, columns
#: J1, J2, J3, J5 (UR response: J4 instead of J5), combined, average.
PAPER_TABLES: dict[str, dict[str, dict[str, tuple[float, ...]]]] = {
    "kuka": {
        "actuation_delay": {
            "median": (2.27, 2.68, 4.61, 3.51, 3.67, 3.35),
            "nn": (1.79, 2.55, 4.74, 3.37, 3.21, 3.13),
            "rt": (1.99, 2.48, 3.74, 3.76, 3.33, 3.06),
            "gpr": (1.85, 2.27, 4.30, 3.39, 3.48, 3.06),
        },
        "response_delay": {
            "median": (2.13, 2.37, 4.30, 3.09, 3.33, 3.05),
            "nn": (1.70, 2.32, 4.68, 2.22, 2.36, 2.65),
            "rt": (1.86, 2.21, 3.62, 2.31, 2.37, 2.47),
            "gpr": (1.63, 2.17, 4.23, 3.11, 2.63, 2.75),
        },
    },
    "ur": {
        "actuation_delay": {
            "median": (6.18, 4.64, 6.08, 2.59, 5.33, 4.96),
            "nn": (4.08, 5.32, 3.86, 2.49, 3.12, 3.77),
            "rt": (4.63, 5.41, 4.28, 2.72, 3.42, 4.09),
            "gpr": (5.01, 4.89, 3.68, 2.47, 3.36, 3.88),
        },
        "response_delay": {
            "median": (4.82, 2.00, 4.08, 4.90, 5.09, 4.18),
            "nn": (4.11, 2.48, 4.24, 5.22, 4.84, 4.01),
            "rt": (4.66, 2.44, 4.47, 5.84, 5.33, 4.35),
            "gpr": (3.88, 2.44, 3.75, 5.20, 5.05, 3.82),
        },
    },
}
_PAPER_COLUMNS = ("1", "2", "3", "5", "combined", "average")
_PAPER_ROBOTS = {"kuka": "KUKA KR 5", "ur": "UR10"}


def paper_family(robot: str) -> str | None:
    """The key of :data:`PAPER_TABLES` a robot's figures sit beside (its catalog entry's
    ``paper_family``: ``"ur"`` or ``"kuka"``), or None for a robot outside the catalog."""
    return get_robot_entry(robot).paper_family if robot in ROBOT_NAMES else None


# ---------------------------------------------------------------------- data


@dataclass(frozen=True)
class _Data:
    """The arrays of a validated delay table that learning uses."""

    q: FloatArray
    joint: NDArray[np.int64]
    direction: NDArray[np.int64]
    y: dict[str, FloatArray]
    config: NDArray[np.intp]
    condition: NDArray[np.intp]
    joints: tuple[int, ...]
    robot: str
    sha256: str
    t_h: FloatArray  # sweep time per trial: its condition's mean t_start, hours
    time_input: bool
    #: Per delay, the rows it may be trained on (a ``response_flag`` rules out the
    #: response delay only: ``DelayTable.usable``).
    usable: dict[str, NDArray[np.bool_]]
    power_on_clock: bool = False  # t_h is the time since power-on (t_since_power_on)

    def rows(self, key: str, delay: str) -> NDArray[np.intp]:
        mask = self.usable[delay]
        if key != "combined":
            mask = mask & (self.joint == int(key))
        return np.flatnonzero(mask)

    def X(self, key: str, rows: NDArray[np.intp]) -> FloatArray:
        t = self.t_h[rows] if self.time_input else None
        if key == "combined":
            return encode_inputs(
                self.q[rows], self.direction[rows], self.joint[rows], self.joints, t_h=t
            )
        return encode_inputs(self.q[rows], self.direction[rows], t_h=t)


#: What a measured delay can be, s: a joint cannot move before its command arrives, and a
#: state cannot be older than... a second is ten times the slowest controller's delay; the
#: response fit's noise can put a near-zero age slightly below 0.
DELAY_RANGE_S = {"actuation_delay": (0.0, 1.0), "response_delay": (-0.005, 1.0)}
DELAY_RANGE_WHY = {
    "actuation_delay": "no arm moves before its command arrives, none waits a second",
    "response_delay": "a state's age: at least 0 (less 5 ms of fit noise), at most a second",
}


def _prepare(table: DelayTable, time_input: bool = False) -> _Data:
    if not isinstance(table, DelayTable):
        raise ConfigError(f"expected a DelayTable, got {type(table).__name__}")
    for name in DELAYS:
        keep = table.usable(name)
        values = table[name]
        bad = ~np.isfinite(values) & keep
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                f"{table.source}: column {name!r} row {row} is {values[row]}; delays must be "
                "finite seconds to train (mark unmeasurable trials in the 'flag' column)"
            )
        low, high = DELAY_RANGE_S[name]
        out = keep & ((values < low) | (values > high))
        if out.any():
            row = int(np.flatnonzero(out)[0])
            raise ConfigError(
                f"{table.source}: column {name!r} row {row} is {float(values[row])!r} s "
                f"({out.sum()} such row(s)); a measured {name.replace('_', ' ')} lies in "
                f"{low:g} .. {high:g} s ({DELAY_RANGE_WHY[name]}): fix the row, or mark the "
                "trial in the 'flag' column"
            )
    t = table.validated_for_training()
    if len(t) == 0:
        raise ConfigError(f"{table.source}: no trial left to train on (all flagged)")
    robots = t.robots
    if len(robots) != 1:
        raise ConfigError(
            f"{table.source}: the table mixes robots ({', '.join(robots)}); train one robot at a time"
        )
    _check_joint_limits(table, robots[0])
    q = t.q
    joint = t["joint"].astype(np.int64)
    direction = t["direction"].astype(np.int64)
    y = {d: t[d].astype(float) for d in DELAYS}
    usable = {d: t.usable(d) for d in DELAYS}
    flags = np.array(t.columns.get("response_flag", [""] * len(t)), dtype=object)
    for j in sorted({int(x) for x in joint}):
        on_j = joint == j
        if not usable["response_delay"][on_j].any():
            kinds = sorted({str(f) for f in flags[on_j]})
            if all(k in JOINT_RESPONSE_FLAGS for k in kinds):
                # The joint's only measurement: the age its trials share is uncertain by
                # the gear's play or biased by the noise (~0.1-0.15 ms on the compliant
                # benchmark), not unknown.
                usable["response_delay"] = usable["response_delay"] | on_j
                why = "; ".join(f"{k!r}: {RESPONSE_FLAG_WHY[k]}" for k in kinds)
                warnings.warn(
                    f"{table.source}: every response delay of joint {j} is flagged ({why}); "
                    "its response model is trained on them as the joint's only measurement, "
                    "and back-dating that joint carries that extra uncertainty",
                    stacklevel=3,
                )
                continue
            reasons = t.select(joint == j).reason_counts("response_flag")
            raise ConfigError(
                f"{table.source}: every response delay of joint {j} carries a response_flag "
                f"({', '.join(f'{r}: {c}' for r, c in reasons.items())}), so its response "
                "model has nothing to learn from; measure that joint again (more poses, "
                "less noise) or drop its rows"
            )
    config = np.unique(q, axis=0, return_inverse=True)[1].reshape(-1)
    key = np.column_stack([config, joint, direction])
    condition = np.unique(key, axis=0, return_inverse=True)[1].reshape(-1)
    # The condition's mean start time: its repeats run back to back (seconds apart, against
    # an hour-long warm-up), so one time per condition keeps replicates identical rows.
    # On the thermal clock (time since power-on) where the table has it.
    power_on_clock = "t_since_power_on" in t
    t_start = t["t_since_power_on" if power_on_clock else "t_start"].astype(float)
    t_h = (np.bincount(condition, weights=t_start) / np.bincount(condition))[condition] / 3600.0
    h = hashlib.sha256()
    for arr in (q, joint, direction, y["actuation_delay"], y["response_delay"]):
        h.update(np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<")).tobytes())
    if not usable["response_delay"].all():  # (a table without response flags: as before)
        h.update(usable["response_delay"].tobytes())
    return _Data(
        q=q,
        joint=joint,
        direction=direction,
        y=y,
        config=config,
        condition=condition,
        joints=tuple(sorted({int(j) for j in joint})),
        robot=robots[0],
        sha256=h.hexdigest(),
        t_h=t_h,
        time_input=time_input,
        usable=usable,
        power_on_clock=power_on_clock,
    )


def _response_flagged(data: _Data) -> dict[str, int]:
    """``{"response_flagged": n}`` for the manifest where n trials trained the actuation
    models but not the response models (nothing for a table without response flags)."""
    n = int(np.sum(~data.usable["response_delay"]))
    return {"response_flagged": n} if n else {}


def _check_joint_limits(table: DelayTable, robot: str) -> None:
    """Refuse start configurations outside the robot's joint limits (every row, flagged or
    not: such a row is corrupt, e.g. degrees in a rad column); the message names the row
    (0-based, as the table's other messages), the joint, the value and the limits."""
    from timedexec.robots import check_configuration, get_robot

    try:
        check_configuration(get_robot(robot), table.q)
    except ConfigError as exc:
        raise ConfigError(
            f"{table.source}: {exc} (q1..q6 of a delay table are the start configuration in "
            "rad: fix or drop that row)"
        ) from None


def _keys(data: _Data) -> list[str]:
    return [*(str(j) for j in data.joints), "combined"]


def fold_of_configuration(
    config: NDArray[np.intp], folds: int, random_state: int | None
) -> NDArray[np.intp]:
    """Fold index per trial; all trials of a start configuration share a fold.

    Configurations are shuffled (``random_state``) and dealt round-robin, so fold sizes
    differ by at most one configuration.
    """
    n_cfg = int(config.max()) + 1
    if n_cfg < folds:
        raise ConfigError(
            f"{folds}-fold cross-validation needs at least {folds} distinct start "
            f"configurations; the table has {n_cfg} (use --folds {max(n_cfg, 2)} or more data)"
        )
    perm = np.random.default_rng(random_state).permutation(n_cfg)
    fold_of_cfg = np.empty(n_cfg, dtype=np.intp)
    fold_of_cfg[perm] = np.arange(n_cfg) % folds
    return fold_of_cfg[config]


def noise_floor(y: FloatArray, condition: NDArray[np.intp]) -> float:
    """Replicate scatter, s: sqrt of the pooled within-condition variance.

    ``sqrt(Σ_i Σ_j (y_ij - ȳ_i)² / Σ_i (n_i - 1))``: the error a model that knew every
    condition's mean exactly would still make on a new trial. NaN without replicates.
    """
    _, inv = np.unique(condition, return_inverse=True)
    inv = inv.reshape(-1)
    cnt = np.bincount(inv)
    mean = np.bincount(inv, weights=y) / cnt
    dof = int(np.sum(cnt - 1))
    if dof == 0:
        return float("nan")
    return float(np.sqrt(np.sum((y - mean[inv]) ** 2) / dof))


# -------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class _Task:
    delay: str
    key: str
    method: str
    fold: int  # -1: final fit on all data
    cost: float


def _run_task(
    task: _Task,
    data: _Data,
    fold_idx: NDArray[np.intp] | None,
    seed: int,
) -> tuple[_Task, Any, float]:
    from timedexec.learning._threads import single_threaded_blas

    start = time.perf_counter()
    method = get_method(task.method)
    rows = data.rows(task.key, task.delay)
    y = data.y[task.delay][rows]
    X = data.X(task.key, rows)
    inputs = ModelInputs.of(data.robot, task.key, data.joints, data.time_input)
    est = method.estimator(inputs, seed)
    with single_threaded_blas():
        if task.fold < 0:
            est.fit(X, y)
            resid = est.predict(X) - y
            out: Any = {
                "arrays": est.to_arrays(),
                "train_rmse_s": float(np.sqrt(np.mean(resid**2))),
                "info": method.info(est),
            }
        else:
            assert fold_idx is not None
            f = fold_idx[rows]
            test = f == task.fold
            if not test.any() or test.all():
                out = None
            else:
                est.fit(X[~test], y[~test])
                if method.variance:
                    # the single-trial std (latent + noise), what DelayModel reports as
                    # *_std before calibration: the GP's held-out residuals calibrate it
                    mean, std = est.predict(X[test], return_std=True)
                    out = {"mean": mean, "std": std}
                else:
                    out = {"mean": est.predict(X[test]), "std": None}
    return task, out, time.perf_counter() - start


# ------------------------------------------------------------------- results


@dataclass(frozen=True)
class CVResult:
    """Cross-validation scores in the layout of the paper's Tables I and II.

    Attributes
    ----------
    scores_ms : dict
        ``scores_ms[delay][method][column]`` in ms; columns: each joint present ("1", "2",
        ...), "combined" and "average" (the mean of the other columns, as the paper's).
    noise_floor_ms : dict
        ``noise_floor_ms[delay][column]``: replicate scatter (what no model can beat), ms.
    folds : int
        Number of folds.
    robot : str
        Robot of the table.
    n_trials, n_conditions, n_configurations : int
        Size of the data.
    seconds : float
        Wall time of the run.
    fit_seconds : dict
        CPU-side seconds spent in fits, per method.
    time_input : bool
        Whether the sweep time was an input.
    std_scale : dict
        ``std_scale[delay][key]``: factor (>= 1) on the GP's single-trial std from its
        held-out standardised residuals (:func:`~timedexec.learning.std_scale_factor`);
        empty without "gpr".
    std_held_out : dict
        ``std_held_out[delay][key]``: the GP's held-out statistics behind the scale:
        ``trials``, ``rms_z`` (RMS of ``(y - mean) / std``, before the floor at 1) and
        ``coverage_95_gp`` / ``coverage_95_calibrated`` (share of held-out trials inside the
        Gaussian interval ``mean ± 1.96 std`` before and after the scale; delays quantised by
        the controller cycle have short tails, so a Gaussian interval covers more than 95 %
        at the right std).
    bound_z : dict
        ``bound_z[delay][key]``: half-width of the GP's 95 % prediction bound in calibrated
        stds (:func:`~timedexec.learning.bound_quantile` of the held-out ``|y - mean| /
        (c · std)``, split-conformal over the folds); keys without enough held-out trials
        are absent.
    """

    scores_ms: dict[str, dict[str, dict[str, float]]]
    noise_floor_ms: dict[str, dict[str, float]]
    folds: int
    robot: str
    n_trials: int
    n_conditions: int
    n_configurations: int
    seconds: float = 0.0
    fit_seconds: dict[str, float] = field(default_factory=dict)
    time_input: bool = False
    std_scale: dict[str, dict[str, float]] = field(default_factory=dict)
    std_held_out: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    bound_z: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, dict[str, dict[str, float]]]:
        """The CV.json content: ``{delay: {method: {column: ms}}}``."""
        return {d: {m: dict(cols) for m, cols in ms.items()} for d, ms in self.scores_ms.items()}

    def table_text(self) -> str:
        """Tables I/II: ours beside the paper's (same robot family), plus the noise floor."""
        family = paper_family(self.robot)
        paper = PAPER_TABLES.get(family or "", {})
        lines: list[str] = []
        for n_tab, delay in zip(("I", "II"), DELAYS, strict=True):
            if delay not in self.scores_ms:
                continue
            methods = self.scores_ms[delay]
            cols = list(next(iter(methods.values())).keys())
            heads = [f"J{c}" if c.isdigit() else c for c in cols]
            lines.append(
                f"Table {n_tab}: {delay.replace('_', ' ')}, {self.folds}-fold CV error (ms), "
                f"{self.robot}: ours / paper ({_PAPER_ROBOTS.get(family or '', 'none')})"
            )
            lines.append(f"{'':8}" + "".join(f"{h:>16}" for h in heads))
            for m, scores in methods.items():
                cells = []
                for c in cols:
                    ours = scores[c]
                    ref = _paper_value(paper.get(delay, {}).get(m), c)
                    ref_text = f"{ref:5.2f}" if ref is not None else "    -"
                    cells.append(f"{ours:8.2f} / {ref_text}")
                lines.append(f"{m:8}" + "".join(f"{c:>16}" for c in cells))
            floor = self.noise_floor_ms.get(delay, {})
            lines.append(
                f"{'floor':8}" + "".join(f"{floor.get(c, float('nan')):8.2f}        " for c in cols)
            )
            if family == "ur" and delay == "response_delay" and "5" in cols:
                lines.append("(paper's UR response table has joint 4 in the J5 column)")
            lines.append("")
        for delay, by_key in self.std_scale.items():
            if not by_key:
                continue
            text = ", ".join(f"{'J' + k if k.isdigit() else k} x{c:.2f}" for k, c in by_key.items())
            lines.append(f"GP std scale, {delay.replace('_', ' ')}: {text}")
        if any(self.std_scale.values()):
            lines.append(
                "(GP std scale: max(1, RMS of the held-out (y - mean) / std); it multiplies "
                "the bundle's GP standard deviations)"
            )
        inputs = "configuration, joint, direction" + (" and sweep time" if self.time_input else "")
        lines.append(
            "floor: replicate scatter, sqrt of the pooled within-condition variance (no model "
            f"can beat it). Folds split by start configuration. Inputs: {inputs}."
        )
        return "\n".join(lines)


def _paper_value(row: tuple[float, ...] | None, column: str) -> float | None:
    if row is None or column not in _PAPER_COLUMNS:
        return None
    return row[_PAPER_COLUMNS.index(column)]


@dataclass(frozen=True)
class TrainResult:
    """What :func:`train_delay_models` produced: the model bundle and (optionally) CV scores."""

    model: Any  # DelayModel
    cv: CVResult | None
    seconds: float


# ---------------------------------------------------------------------- API


def _check_jobs(jobs: int) -> int:
    if isinstance(jobs, bool) or not isinstance(jobs, int) or (jobs < 1 and jobs != -1):
        raise ConfigError(f"jobs={jobs!r} must be a positive integer, or -1 for every worker")
    return jobs


def _run(
    data: _Data,
    methods: tuple[str, ...],
    folds: int,
    final: bool,
    jobs: int,
    random_state: int,
    progress: bool,
) -> tuple[dict[_Task, Any], dict[str, float], NDArray[np.intp] | None]:
    from timedexec._progress import Progress

    keys = _keys(data)
    fold_idx = fold_of_configuration(data.config, folds, random_state) if folds else None
    tasks: list[_Task] = []
    for delay in DELAYS:
        for key in keys:
            n_rows = len(data.rows(key, delay))
            for method in methods:
                fold_list = list(range(folds)) + ([-1] if final else [])
                for f in fold_list:
                    share = 1.0 if f < 0 else (folds - 1) / folds
                    tasks.append(
                        _Task(delay, key, method, f, get_method(method).cost(int(n_rows * share)))
                    )
    tasks.sort(key=lambda t: -t.cost)
    bar = Progress(len(tasks), "training", enabled=progress)
    results: dict[_Task, Any] = {}
    fit_s: dict[str, float] = dict.fromkeys(methods, 0.0)
    seeds = {t: (random_state * 1_000_003 + i) % (2**31 - 1) for i, t in enumerate(tasks)}
    if jobs == 1:
        it: Any = (_run_task(t, data, fold_idx, seeds[t]) for t in tasks)
    else:
        from joblib import Parallel, delayed

        calls = [delayed(_run_task)(t, data, fold_idx, seeds[t]) for t in tasks]
        try:
            it = Parallel(n_jobs=jobs, return_as="generator_unordered")(calls)
        except ValueError:  # a backend without result generators (e.g. multiprocessing)
            it = Parallel(n_jobs=jobs)(calls)
    for task, out, dt in it:
        results[task] = out
        fit_s[task.method] += dt
        bar.update()
    bar.close()
    return results, fit_s, fold_idx


def _scores(
    data: _Data,
    methods: tuple[str, ...],
    folds: int,
    results: Mapping[_Task, Any],
    fold_idx: NDArray[np.intp],
) -> tuple[dict[str, dict[str, dict[str, float]]], dict[str, dict[str, float]]]:
    keys = _keys(data)
    by_id = {(t.delay, t.key, t.method, t.fold): out for t, out in results.items()}
    scores: dict[str, dict[str, dict[str, float]]] = {}
    floors: dict[str, dict[str, float]] = {}
    for delay in DELAYS:
        scores[delay] = {}
        for method in methods:
            row: dict[str, float] = {}
            for key in keys:
                rows = data.rows(key, delay)
                y = data.y[delay][rows]
                f = fold_idx[rows]
                mses = []
                for k in range(folds):
                    pred = by_id.get((delay, key, method, k))
                    if pred is None:
                        continue
                    mses.append(float(np.mean((pred["mean"] - y[f == k]) ** 2)))
                row[key] = 1e3 * math.sqrt(float(np.mean(mses))) if mses else float("nan")
            row["average"] = float(np.mean([row[k] for k in keys]))
            scores[delay][method] = row
        fl: dict[str, float] = {}
        for key in keys:
            rows = data.rows(key, delay)
            fl[key] = 1e3 * noise_floor(data.y[delay][rows], data.condition[rows])
        fl["average"] = float(np.mean([fl[k] for k in keys]))
        floors[delay] = fl
    return scores, floors


def _std_calibration(
    data: _Data,
    folds: int,
    results: Mapping[_Task, Any],
    fold_idx: NDArray[np.intp],
) -> tuple[
    dict[str, dict[str, float]], dict[str, dict[str, dict[str, float]]], dict[str, dict[str, float]]
]:
    """The GP's std scale and bound quantile per delay and model, and the statistics.

    Returns ``(scale, held_out, bound_z)``: ``scale[delay][key]`` (:func:`std_scale_factor`
    of the held-out residuals of every fold), ``held_out[delay][key]`` (see
    :attr:`CVResult.std_held_out`) and ``bound_z[delay][key]`` (:func:`bound_quantile` of
    the same residuals over the calibrated std, see :attr:`CVResult.bound_z`).
    """
    by_id = {
        (t.delay, t.key, t.fold): out for t, out in results.items() if t.method == CALIBRATED_METHOD
    }
    scale: dict[str, dict[str, float]] = {}
    held_out: dict[str, dict[str, dict[str, float]]] = {}
    bound_z: dict[str, dict[str, float]] = {}
    for delay in DELAYS:
        scale[delay], held_out[delay], bound_z[delay] = {}, {}, {}
        for key in _keys(data):
            rows = data.rows(key, delay)
            y = data.y[delay][rows]
            f = fold_idx[rows]
            resid, std = [], []
            for k in range(folds):
                pred = by_id.get((delay, key, k))
                if pred is None:
                    continue
                resid.append(y[f == k] - pred["mean"])
                std.append(pred["std"])
            if not resid:
                continue
            r, s = np.concatenate(resid), np.concatenate(std)
            c = std_scale_factor(r, s)
            scale[delay][key] = c
            held_out[delay][key] = {
                "trials": len(r),
                "rms_z": float(np.sqrt(np.mean((r / s) ** 2))),
                "coverage_95_gp": gaussian_coverage(r, s, 0.95),
                "coverage_95_calibrated": gaussian_coverage(r, s, 0.95, scale=c),
            }
            q = bound_quantile(r, c * s)
            if math.isfinite(q):
                bound_z[delay][key] = q
    return scale, held_out, bound_z


def cross_validate(
    table: DelayTable,
    *,
    methods: Sequence[str] | str = DEFAULT_METHODS,
    folds: int = 10,
    jobs: int = 1,
    random_state: int = 0,
    progress: bool = False,
    time_input: bool = False,
) -> CVResult:
    """K-fold cross-validation of every method, per joint and combined, both delays.

    Parameters
    ----------
    table : DelayTable
        One robot's delay table; flagged trials are dropped, NaN/inf delays refused; a
        trial with a ``response_flag`` trains the actuation models only.
    methods : sequence of str or comma list
        Registered methods (:data:`~timedexec.learning.METHODS`); default the paper's four
        (:data:`~timedexec.learning.DEFAULT_METHODS`).
    folds : int
        Number of folds (>= 2), split by start configuration.
    jobs : int
        joblib workers (-1: all); the scores do not depend on it.
    random_state : int
        Seeds the fold assignment and the estimators.
    progress : bool
        Progress on stderr.
    time_input : bool
        Add the sweep time as an input (see :func:`train_delay_models`).
    """
    return train_delay_models(
        table,
        methods=methods,
        folds=folds,
        jobs=jobs,
        random_state=random_state,
        progress=progress,
        final=False,
        time_input=time_input,
    ).cv  # type: ignore[return-value]


def train_delay_models(
    table: DelayTable,
    *,
    methods: Sequence[str] | str = DEFAULT_METHODS,
    folds: int = 10,
    jobs: int = 1,
    random_state: int = 0,
    progress: bool = False,
    period_s: float | None = None,
    source: str | None = None,
    source_sha256: str | None = None,
    final: bool = True,
    time_input: bool = False,
) -> TrainResult:
    """Cross-validate (``folds`` > 0) and train every method on all data into a bundle.

    Parameters
    ----------
    table : DelayTable
        One robot's delay table.
    methods, folds, jobs, random_state, progress
        As :func:`cross_validate`; ``folds=0`` skips cross-validation.
    period_s : float, optional
        Controller period the table was measured at, s; default the robot's default
        period (a KR 5 also runs at 4 ms: say so here).
    source, source_sha256 : str, optional
        Where the table came from and the sha256 of its file, for the manifest.
    final : bool
        Train the final models (False: CV only, ``model`` is None).
    time_input : bool
        Add the sweep time (``t_start`` averaged per condition, hours; the time since
        power-on, ``t_since_power_on``, where the table has it) as an input beside the
        published ones: separates the warm-up drift from the pose dependence. The bundle
        then predicts at the end of the sweep (warm) unless given a time. Either way the
        manifest's ``thermal_state`` says which thermal states the training saw.

    Returns
    -------
    TrainResult
        ``model`` (a :class:`~timedexec.learning.DelayModel`), ``cv`` (or None).
    """
    from timedexec.robots import get_robot

    methods = check_methods(methods)
    jobs = _check_jobs(jobs)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 0 or folds == 1:
        raise ConfigError(f"folds={folds!r} must be 0 (no cross-validation) or an integer >= 2")
    data = _prepare(table, time_input=bool(time_input))
    try:
        spec = get_robot(data.robot, period_s=period_s)
    except ConfigError as exc:
        raise ConfigError(f"{table.source}: {exc}") from None
    start = time.perf_counter()
    results, fit_s, fold_idx = _run(data, methods, folds, final, jobs, random_state, progress)
    cv: CVResult | None = None
    if folds:
        assert fold_idx is not None
        scores, floors = _scores(data, methods, folds, results, fold_idx)
        std_scale: dict[str, dict[str, float]] = {}
        std_held: dict[str, dict[str, dict[str, float]]] = {}
        bound_z: dict[str, dict[str, float]] = {}
        if CALIBRATED_METHOD in methods:
            std_scale, std_held, bound_z = _std_calibration(data, folds, results, fold_idx)
        cv = CVResult(
            scores_ms=scores,
            noise_floor_ms=floors,
            folds=folds,
            robot=data.robot,
            n_trials=len(data.joint),
            n_conditions=int(data.condition.max()) + 1,
            n_configurations=int(data.config.max()) + 1,
            seconds=time.perf_counter() - start,
            fit_seconds=fit_s,
            time_input=data.time_input,
            std_scale=std_scale,
            std_held_out=std_held,
            bound_z=bound_z,
        )
    model = None
    if final:
        from timedexec.learning._bundle import DelayModel

        finals = {(t.method, t.delay, t.key): out for t, out in results.items() if t.fold < 0}
        model = DelayModel.from_training(
            finals,
            robot=spec.name,
            period_s=spec.controller_period_s,
            joints=data.joints,
            keys=_keys(data),
            methods=methods,
            cv=cv,
            time_input=data.time_input,
            time_range_s=(float(data.t_h.min() * 3600.0), float(data.t_h.max() * 3600.0)),
            thermal=thermal_state(data.t_h * 3600.0, power_on_clock=data.power_on_clock),
            training={
                "arrays_sha256": data.sha256,
                "file_sha256": source_sha256,
                "source": source or table.source,
                "trials": len(data.joint),
                "conditions": int(data.condition.max()) + 1,
                "configurations": int(data.config.max()) + 1,
                **_response_flagged(data),
            },
        )
    return TrainResult(model=model, cv=cv, seconds=time.perf_counter() - start)
