"""Sequential design of an adaptive calibration sweep: where the next trials go.

No robot and no recording here: the candidate pool (:func:`design_pool`), the models of
the measured delays (:class:`DesignModel`, one Gaussian process per joint from
:mod:`timedexec.learning`) and the choice of a batch (:func:`choose_batch`).

**Units.** The sweep runs *units*: one joint at one start configuration, both directions,
``repeats`` trials each (2 by default, so every unit also measures the trial scatter). A
unit costs ``2 · repeats`` trials of robot time, plus a move when its configuration is new
to the batch.

**Design rule** (integrated mean squared error, IMSE; Sacks et al. 1989, Gramacy 2020
§6.2). The error a model makes on a new trial in the workspace is, per joint ``j``, its
latent variance plus the trial noise averaged over the *reference* configurations (a fixed
sample of the workspace, both directions). A unit at configuration ``c`` removes from the
joint's latent variance at every reference input ``r``
``Σ_rc (Σ_cc + σ²/repeats · I)⁻¹ Σ_cr`` (``Σ`` the GP's posterior covariance, ``c`` the
unit's two directions) — a quantity that does not depend on the delays the unit will
measure. Greedy, unit by unit: take the unit with the largest reduction of the mean
(over joints and reference inputs) variance per second of robot time, condition the GP's
covariance on it (a rank-2 update) and repeat until the batch's robot time is spent. The
units already chosen but not yet measured (the batch the robot is running) enter the same
way first, so a batch never repeats its predecessor's work. The variances are those of the
GP calibrated on held-out trials: each joint's latent variance is multiplied by
``c_j² = max(1, mean z²)`` of its standardised errors on the newest batches, predicted by
the model before it saw them (a GP that is sure of itself where it is wrong gets more
trials; :func:`~timedexec.learning.std_scale_factor` is the same rule).

**Estimated error** (what progress shows and the stopping rule reads):
``E = sqrt(mean_j c_j² mean_r (var_j(r) + σ²_j))``, the RMS error of a new trial the model
expects over the workspace, calibrated as a bundle's trial std is (its held-out mean
squared error where the newest batches were); its floor ``sqrt(mean_j σ²_j)`` (the trial
noise, pinned by the repeats) is what no model can beat.

**Stopping rule.** Before a batch is chosen, the greedy continues (as a plan, nothing is
run) for ``stop_horizon_s`` of robot time; the sweep stops when both

* that would lower ``E`` by less than ``stop_fraction`` of the floor: another 10 minutes
  (default) would improve the model by less than a tenth of the trial noise (default), and
* the estimate is borne out: the RMS error on the newest ``calibration_batches`` measured
  batches, each predicted before the model saw it, is at most ``E`` plus that tenth.

A GP fitted on a few configurations is sure of itself where it is wrong (it then predicts
small gains everywhere), so the rule waits until ``calibration_batches`` held-out batches
have calibrated the variances, and the held-out check keeps it from stopping on a model
whose own estimate is not confirmed. The budget (``budget_s``) ends the sweep otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec._validation import DictMixin, check_positive
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError
from timedexec.learning import (
    DelayGP,
    encode_inputs,
    single_threaded_blas,
    std_scale_factor,
)
from timedexec.recording import SweepPlan, calibration_ranges
from timedexec.robots import RobotSpec, check_configuration, get_robot

__all__ = [
    "AdaptiveSettings",
    "DesignModel",
    "Unit",
    "Workspace",
    "choose_batch",
    "design_pool",
    "first_batches",
    "unit_rows",
]


#: A unit: (configuration index in the pool, joint).
Unit = tuple[int, int]


@dataclass(frozen=True, kw_only=True)
class Workspace(DictMixin):
    """Where the robot will work, so the sweep spends its time there.

    Either a joint-range box (``q_min_rad``/``q_max_rad``, intersected with the robot's
    calibration ranges; the default is those ranges) or a list of configurations
    (``configurations_rad``, each inside the joint limits). Joint 6 carries the gyro and
    stays at 0 in every configuration.
    """

    q_min_rad: tuple[float, ...] | None = None
    q_max_rad: tuple[float, ...] | None = None
    configurations_rad: tuple[tuple[float, ...], ...] | None = None

    def __post_init__(self) -> None:
        box = self.q_min_rad is not None or self.q_max_rad is not None
        if box and self.configurations_rad is not None:
            raise ConfigError("workspace: give a joint-range box or configurations, not both")
        if box:
            if self.q_min_rad is None or self.q_max_rad is None:
                raise ConfigError("workspace: a box needs both q_min_rad and q_max_rad")
            lo = tuple(float(v) for v in self.q_min_rad)
            hi = tuple(float(v) for v in self.q_max_rad)
            if len(lo) != 6 or len(hi) != 6:
                raise ConfigError(
                    f"workspace: the box needs 6 lower and 6 upper bounds (rad), got "
                    f"{len(lo)} and {len(hi)}"
                )
            if not all(
                math.isfinite(a) and math.isfinite(b) and a <= b
                for a, b in zip(lo, hi, strict=True)
            ):
                raise ConfigError(
                    f"workspace: box bounds {lo} .. {hi} must be finite with low <= high per joint"
                )
            object.__setattr__(self, "q_min_rad", lo)
            object.__setattr__(self, "q_max_rad", hi)
        if self.configurations_rad is not None:
            rows = tuple(tuple(float(v) for v in row) for row in self.configurations_rad)
            if not rows or any(len(r) != 6 for r in rows):
                raise ConfigError(
                    "workspace: configurations must be a non-empty list of 6 joint angles (rad)"
                )
            object.__setattr__(self, "configurations_rad", rows)

    @property
    def is_list(self) -> bool:
        """Whether the workspace is a list of configurations."""
        return self.configurations_rad is not None

    def cut_to(self, lo_rad: Any, hi_rad: Any, *, reach: str, fix: str) -> Workspace:
        """This box (the calibration ranges when none is given) cut to ``lo_rad`` ..
        ``hi_rad`` (6,) each, rad: what the robot can reach here (RSI: the correction's
        limit around the pose where RSI started, less a trial's excursion).

        Raises
        ------
        ConfigError
            A listed workspace, or no room on some joint (naming it, both ranges,
            ``reach`` (what the bounds are) and ``fix``).
        """
        if self.configurations_rad is not None:
            raise ConfigError("workspace: a list of configurations is checked, not cut")
        lo, hi = np.array(lo_rad, dtype=float), np.array(hi_rad, dtype=float)
        if self.q_min_rad is not None and self.q_max_rad is not None:
            lo = np.maximum(lo, self.q_min_rad)
            hi = np.minimum(hi, self.q_max_rad)
        for j in np.flatnonzero(lo > hi):
            box = "" if self.q_min_rad is None or self.q_max_rad is None else (
                f" (--workspace {math.degrees(self.q_min_rad[j]):.1f}.."
                f"{math.degrees(self.q_max_rad[j]):.1f} deg)"
            )  # fmt: skip
            raise ConfigError(
                f"joint {j + 1}: the sweep has no room within {reach} "
                f"({math.degrees(lo_rad[j]):.1f}..{math.degrees(hi_rad[j]):.1f} deg){box}; {fix}"
            )
        return Workspace(q_min_rad=tuple(lo.tolist()), q_max_rad=tuple(hi.tolist()))

    def describe(self) -> str:
        """One line for messages and progress."""
        if self.configurations_rad is not None:
            return f"{len(self.configurations_rad)} listed configurations"
        if self.q_min_rad is None:
            return "the calibration ranges"
        assert self.q_max_rad is not None
        return "box " + ", ".join(
            f"q{i + 1} {a:.2f}..{b:.2f}"
            for i, (a, b) in enumerate(zip(self.q_min_rad, self.q_max_rad, strict=True))
        )

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Workspace:
        """Inverse of :meth:`to_dict`."""
        conf = d.get("configurations_rad")
        return cls(
            q_min_rad=None if d.get("q_min_rad") is None else tuple(d["q_min_rad"]),
            q_max_rad=None if d.get("q_max_rad") is None else tuple(d["q_max_rad"]),
            configurations_rad=None if conf is None else tuple(tuple(r) for r in conf),
        )


@dataclass(frozen=True, kw_only=True)
class AdaptiveSettings(DictMixin):
    """How an adaptive sweep chooses, batches and stops (see the module docstring).

    Parameters
    ----------
    budget_s : float
        Robot time after which the sweep stops, s (the sweep's own clock).
    batch_s : float
        Robot time of one batch, s: the next batch is chosen while this one runs.
    repeats : int
        Trials per direction of a unit (>= 1; 2 measures the trial scatter too).
    joints : tuple of int
        Joints calibrated (the published protocol: 1, 2, 3, 5).
    pool_size : int
        Candidate configurations drawn in a box workspace (scrambled Sobol).
    reference_size : int
        Workspace configurations the estimated error is averaged over.
    candidates : int
        Candidate configurations scored per batch (a seeded sample of the pool).
    stop_horizon_s, stop_fraction : float
        Stop when another ``stop_horizon_s`` of robot time would lower the estimated error
        by less than ``stop_fraction`` of the noise floor.
    calibration_batches : int
        Newest held-out batches whose standardised errors calibrate each joint's variance.
    seed : int
        Pool, reference, candidates and GP fits.
    """

    budget_s: float = 45 * 60.0
    batch_s: float = 180.0
    repeats: int = 2
    joints: tuple[int, ...] = (1, 2, 3, 5)
    pool_size: int = 2048
    reference_size: int = 256
    candidates: int = 1024
    stop_horizon_s: float = 600.0
    stop_fraction: float = 0.1
    calibration_batches: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        check_positive(
            "adaptive",
            budget_s=self.budget_s,
            batch_s=self.batch_s,
            stop_horizon_s=self.stop_horizon_s,
        )
        if not 0.0 <= self.stop_fraction < 1.0:
            raise ConfigError(
                f"adaptive: stop_fraction={self.stop_fraction} must lie in [0, 1) (a share "
                "of the noise floor; 0 never stops early)"
            )
        for name, low in (
            ("repeats", 1),
            ("pool_size", 2),
            ("reference_size", 2),
            ("candidates", 2),
            ("calibration_batches", 1),
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"adaptive: {name}={v!r} must be an integer >= {low}")
        joints = tuple(int(j) for j in self.joints)
        if (
            not joints
            or len(set(joints)) != len(joints)
            or any(j not in range(1, 6) for j in joints)
        ):
            raise ConfigError(
                f"adaptive: joints {self.joints} must be distinct joints of 1..5 (joint 6 "
                "carries the gyro)"
            )
        object.__setattr__(self, "joints", joints)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> AdaptiveSettings:
        """Inverse of :meth:`to_dict`."""
        kw = dict(d)
        if "joints" in kw:
            kw["joints"] = tuple(kw["joints"])
        return cls(**kw)


# ---------------------------------------------------------------------------- the pool


def design_pool(
    robot: str | RobotSpec, workspace: Workspace, settings: AdaptiveSettings
) -> SweepPlan:
    """The candidate plan: every unit of every pool configuration, in the sweep plan's
    order (configuration, joint, direction, repeat); a sweep runs a subset of its rows.

    The pool is a scrambled Sobol sample (``seed``) of the workspace box within the
    robot's calibration ranges, or the listed configurations.
    """
    spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
    if workspace.configurations_rad is not None:
        configs = check_configuration(spec, np.asarray(workspace.configurations_rad, dtype=float))
        configs = np.unique(configs, axis=0)
        configs[:, 5] = 0.0
    else:
        from scipy.stats import qmc

        lo, hi = calibration_ranges(spec)
        if workspace.q_min_rad is not None and workspace.q_max_rad is not None:
            wlo, whi = np.asarray(workspace.q_min_rad), np.asarray(workspace.q_max_rad)
            lo, hi = np.maximum(lo, wlo), np.minimum(hi, whi)
            empty = [i + 1 for i in range(5) if hi[i] < lo[i]]
            if empty:
                raise ConfigError(
                    f"workspace: {workspace.describe()} leaves no room for joint(s) "
                    f"{', '.join(map(str, empty))} within {spec.name}'s calibration ranges "
                    f"{np.round(calibration_ranges(spec)[0], 2).tolist()} .. "
                    f"{np.round(calibration_ranges(spec)[1], 2).tolist()} rad"
                )
        sampler = qmc.Sobol(d=6, scramble=True, seed=np.random.default_rng([settings.seed, 0x5B]))
        unit = sampler.random_base2(max(1, math.ceil(math.log2(settings.pool_size))))
        configs = lo + unit[: settings.pool_size] * (hi - lo)
        configs[:, 5] = 0.0
    per_config = len(settings.joints) * 2 * settings.repeats
    n = len(configs)
    cfg = np.repeat(np.arange(n), per_config)
    within = np.tile(np.arange(per_config), n)
    r = settings.repeats
    return SweepPlan(
        robot=spec.name,
        q_start_rad=configs[cfg],
        joint=np.asarray(settings.joints)[within // (2 * r)],
        direction=np.where((within // r) % 2 == 0, 1, -1),
        config_index=cfg,
        repeat=within % r,
        seed=settings.seed,
        joints=settings.joints,
        repeats=r,
    )


def pool_configurations(plan: SweepPlan) -> FloatArray:
    """The pool's configurations (one row per configuration index), rad."""
    first = np.unique(plan.config_index, return_index=True)[1]
    return np.asarray(plan.q_start_rad[first], dtype=float)


def unit_rows(plan: SweepPlan, unit: Unit) -> NDArray[np.int64]:
    """The plan rows of a unit, in run order (direction +1 repeats, then -1)."""
    c, j = unit
    per_joint = 2 * plan.repeats
    per_config = len(plan.joints) * per_joint
    start = c * per_config + plan.joints.index(j) * per_joint
    return np.arange(start, start + per_joint, dtype=np.int64)


def rows_units(plan: SweepPlan, rows: NDArray[np.int64]) -> list[Unit]:
    """The units of plan rows, in order of first appearance."""
    seen: dict[Unit, None] = {}
    for i in np.asarray(rows, dtype=np.int64).tolist():
        seen.setdefault((int(plan.config_index[i]), int(plan.joint[i])), None)
    return list(seen)


def config_cost_s(settings: AdaptiveSettings, trial_s: float, move_s: float) -> float:
    """Robot time of one configuration with every joint, s."""
    return len(settings.joints) * 2 * settings.repeats * trial_s + move_s


def first_batches(
    plan: SweepPlan, settings: AdaptiveSettings, trial_s: float, move_s: float
) -> list[list[Unit]]:
    """The two batches chosen before any model exists: the pool's first configurations
    (a Sobol sequence is space-filling in its prefixes; a listed workspace in its order),
    every joint."""
    n_pool = int(plan.config_index.max()) + 1
    per = max(2, int(settings.batch_s // config_cost_s(settings, trial_s, move_s)))
    out: list[list[Unit]] = []
    for b in range(2):
        configs = range(b * per, min((b + 1) * per, n_pool))
        out.append([(c, j) for c in configs for j in settings.joints])
    return [b for b in out if b]


# --------------------------------------------------------------------------- the model


@dataclass
class DesignModel:
    """Per-joint Gaussian processes of the measured actuation delay and what the design
    needs of them.

    Attributes
    ----------
    gps : dict of int to DelayGP
        Fitted per joint (exact posterior variance).
    scale2 : dict of int to float
        ``c_j²``: the held-out calibration of each joint's latent variance (>= 1).
    noise_s2 : dict of int to float
        Trial noise variance per joint, s².
    trials : int
        Trials the model was fitted on.
    calibrated_by : int
        Held-out batches behind ``scale2`` (the stopping rule waits for
        ``AdaptiveSettings.calibration_batches`` of them).
    """

    gps: dict[int, DelayGP]
    scale2: dict[int, float] = field(default_factory=dict)
    noise_s2: dict[int, float] = field(default_factory=dict)
    trials: int = 0
    calibrated_by: int = 0  # held-out batches behind scale2

    @classmethod
    def fit(
        cls,
        table: DelayTable,
        joints: Sequence[int],
        *,
        seed: int,
        scale2: Mapping[int, float] | None = None,
        calibrated_by: int = 0,
    ) -> DesignModel:
        """Fit one GP per joint on the table's unflagged measured actuation delays."""
        t = table.validated_for_training()
        q = t.q
        joint = np.asarray(t["joint"], dtype=np.int64)
        d = np.asarray(t["direction"], dtype=np.int64)
        y = np.asarray(t["actuation_delay"], dtype=float)
        gps: dict[int, DelayGP] = {}
        noise: dict[int, float] = {}
        with single_threaded_blas():
            for k, j in enumerate(joints):
                m = joint == j
                if m.sum() < 4:
                    raise ConfigError(
                        f"adaptive design: joint {j} has {int(m.sum())} measured trials; the "
                        "first batches must measure every joint (are its trials all flagged?)"
                    )
                gp = DelayGP(
                    random_state=np.random.default_rng([seed, k]),
                    max_variance_conditions=None,
                    # exact (the design needs covariances): 24 h of units is ~6,000 conditions
                    max_exact_conditions=20_000,
                ).fit(encode_inputs(q[m], d[m]), y[m])
                gps[j] = gp
                noise[j] = float(gp.noise_std_**2)
        scale = {j: float((scale2 or {}).get(j, 1.0)) for j in joints}
        return cls(
            gps=gps, scale2=scale, noise_s2=noise, trials=len(y), calibrated_by=calibrated_by
        )

    @property
    def floor_s(self) -> float:
        """The noise floor: RMS trial noise over the joints, s."""
        return math.sqrt(float(np.mean(list(self.noise_s2.values()))))

    def held_out(self, table: DelayTable) -> dict[int, tuple[FloatArray, FloatArray]]:
        """Per joint, residuals ``y - mean`` (s) and standardised residuals of trials the
        model has not seen (the next measured batch)."""
        t = table.validated_for_training()
        joint = np.asarray(t["joint"], dtype=np.int64)
        out: dict[int, tuple[FloatArray, FloatArray]] = {}
        for j, gp in self.gps.items():
            m = joint == j
            if not m.any():
                continue
            X = encode_inputs(t.q[m], np.asarray(t["direction"], dtype=np.int64)[m])
            mean, std = gp.predict(X, return_std=True)
            r = np.asarray(t["actuation_delay"], dtype=float)[m] - mean
            out[j] = (r, r / std)
        return out


def held_out_scale2(
    residuals: Sequence[Mapping[int, tuple[FloatArray, FloatArray]]], joints: Sequence[int]
) -> dict[int, float]:
    """``c_j²`` from the standardised held-out residuals of the newest batches."""
    out: dict[int, float] = {}
    for j in joints:
        z = [r[j][1] for r in residuals if j in r]
        if z:
            zz = np.concatenate(z)
            out[j] = std_scale_factor(zz, np.ones_like(zz)) ** 2
        else:
            out[j] = 1.0
    return out


# ------------------------------------------------------------------------ the choice


def _encode2(q: FloatArray) -> FloatArray:
    """Both directions of each configuration: rows 2i (+1) and 2i+1 (-1)."""
    return encode_inputs(np.repeat(q, 2, axis=0), np.tile([1, -1], len(q)))


class _JointState:
    """One joint's posterior covariances over the candidates and the reference inputs,
    conditioned on the units taken so far (rank-2 updates)."""

    def __init__(self, model: DesignModel, j: int, Xc: FloatArray, Xr: FloatArray, reps: int):
        pred = model.gps[j].predictor_
        self.pred = pred
        self.Xc = Xc
        self.scale2 = model.scale2.get(j, 1.0)
        self.noise = model.noise_s2[j] / reps
        self.Scr = pred.latent_cov(Xc, Xr)  # (2nc, 2nr)
        n = len(Xc) // 2
        var = np.empty((n, 2, 2))
        for i in range(0, n, 256):  # each candidate's own 2x2 block
            sl = slice(i, min(i + 256, n))
            block = pred.latent_cov(Xc[2 * sl.start : 2 * sl.stop], Xc[2 * sl.start : 2 * sl.stop])
            k = np.arange(sl.stop - sl.start)
            var[sl, 0, 0] = block[2 * k, 2 * k]
            var[sl, 1, 1] = block[2 * k + 1, 2 * k + 1]
            var[sl, 0, 1] = var[sl, 1, 0] = block[2 * k, 2 * k + 1]
        self.Vcc = var
        self.taken: list[tuple[FloatArray, FloatArray]] = []  # (Σ(cand, unit), M⁻¹)

    def gain(self) -> FloatArray:
        """Per candidate: the drop of the mean (over reference inputs) latent variance,
        calibrated, that its unit would bring, s²."""
        A, B = self.Scr[0::2], self.Scr[1::2]
        saa, sab, sbb = (A * A).sum(1), (A * B).sum(1), (B * B).sum(1)
        M = self.Vcc.copy()
        M[:, 0, 0] += self.noise
        M[:, 1, 1] += self.noise
        det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] ** 2
        quad = (M[:, 1, 1] * saa - 2.0 * M[:, 0, 1] * sab + M[:, 0, 0] * sbb) / det
        return np.asarray(self.scale2 * quad / self.Scr.shape[1], dtype=float)

    def gain_at(self, i: int) -> float:
        """:meth:`gain` of candidate ``i`` alone, s²."""
        rows = [2 * i, 2 * i + 1]
        A = self.Scr[rows]
        M = self.Vcc[i] + self.noise * np.eye(2)
        return float(self.scale2 * np.sum(A * np.linalg.solve(M, A)) / self.Scr.shape[1])

    def take(self, i: int) -> None:
        """Condition on the unit of candidate ``i``."""
        rows = [2 * i, 2 * i + 1]
        S = self.pred.latent_cov(self.Xc, self.Xc[rows])  # (2nc, 2) prior-to-batch
        for U, Minv in self.taken:
            S -= U @ (Minv @ U[rows].T)
        M = S[rows] + self.noise * np.eye(2)
        M_inv: FloatArray = np.asarray(np.linalg.inv(M), dtype=np.float64)
        self.Scr -= S @ (M_inv @ self.Scr[rows])
        U3 = S.reshape(-1, 2, 2)
        self.Vcc -= np.einsum("cij,jk,clk->cil", U3, M_inv, U3)
        self.taken.append((S, M_inv))


def _mean_ref_var(model: DesignModel, j: int, Xr: FloatArray) -> float:
    _, var = model.gps[j].predictor_.predict(Xr)
    return float(np.mean(var))


@dataclass(frozen=True)
class BatchChoice:
    """What :func:`choose_batch` decided.

    Attributes
    ----------
    units : list of Unit
        The batch, in run order (configurations on a short tour, joints in order).
    error_s : float
        Estimated RMS error of a new trial in the workspace now (with the units already
        chosen), s.
    error_after_s : float
        The same after this batch.
    error_horizon_s : float
        The same after ``stop_horizon_s`` more robot time of greedy units.
    floor_s : float
        The noise floor, s.
    stop : bool
        The stopping rule fired: the batch is empty.
    """

    units: list[Unit]
    error_s: float
    error_after_s: float
    error_horizon_s: float
    floor_s: float
    stop: bool


def choose_batch(
    model: DesignModel,
    pool_q: FloatArray,
    *,
    done: set[Unit],
    pending: Sequence[Unit],
    settings: AdaptiveSettings,
    trial_s: float,
    move_s: float,
    rng: np.random.Generator,
    reference: NDArray[np.intp],
    start_q: FloatArray | None = None,
    held_out_rmse_s: float = math.nan,
) -> BatchChoice:
    """The next batch by greedy IMSE (module docstring), and the stopping rule.

    Parameters
    ----------
    model : DesignModel
        Fitted on every measured unit.
    pool_q : array (n_pool, 6)
        The pool's configurations, rad.
    done : set of Unit
        Units measured (or chosen) before ``pending``; never chosen again.
    pending : sequence of Unit
        Units chosen but not yet measured (the running batch): conditioned on first.
    settings : AdaptiveSettings
    trial_s, move_s : float
        Robot time of one trial and of a move to a new configuration, s.
    rng : Generator
        Draws the candidates.
    reference : array of int
        Pool indices of the reference configurations.
    start_q : array (6,), optional
        Where the robot will be when the batch starts (the tour starts there).
    held_out_rmse_s : float
        RMS error of the model's predictions on the newest measured batches, each predicted
        before the model saw it, s (pooled over the ``calibration_batches`` newest); NaN
        when none (the stopping rule then waits).
    """
    joints = list(model.gps)
    taken = set(done) | set(pending)
    open_cfg = np.array(
        [c for c in range(len(pool_q)) if any((c, j) not in taken for j in joints)], dtype=np.intp
    )
    pend_cfg = sorted({c for c, _ in pending})
    sample = open_cfg
    if len(open_cfg) > settings.candidates:
        sample = np.sort(rng.choice(open_cfg, settings.candidates, replace=False))
    cand = np.union1d(sample, np.asarray(pend_cfg, dtype=np.intp)).astype(np.intp)
    pos = {int(c): i for i, c in enumerate(cand)}
    Xc = _encode2(pool_q[cand])
    Xr = _encode2(pool_q[reference])
    reps = settings.repeats
    with single_threaded_blas():
        states = {j: _JointState(model, j, Xc, Xr, reps) for j in joints}
        ref_var = {j: states[j].scale2 * _mean_ref_var(model, j, Xr) for j in joints}
        noise = float(np.mean([model.noise_s2[j] for j in joints]))
        scaled_noise = float(
            np.mean([model.scale2.get(j, 1.0) * model.noise_s2[j] for j in joints])
        )

        def error() -> float:
            return math.sqrt(max(float(np.mean(list(ref_var.values()))), 0.0) + scaled_noise)

        def take(c: int, j: int) -> None:
            i = pos[c]
            ref_var[j] -= states[j].gain_at(i)
            states[j].take(i)

        for c, j in pending:
            take(c, j)
        error_now = error()
        unit_s = 2 * reps * trial_s
        blocked = {j: np.array([(int(c), j) in taken for c in cand]) for j in joints}
        chosen: list[Unit] = []
        spent = 0.0
        in_batch: set[int] = set()
        batch_open = True
        error_after: float | None = None
        error_horizon: float | None = None
        limit = max(settings.batch_s, settings.stop_horizon_s)
        while True:
            best: tuple[float, int, int, float] | None = None
            for j in joints:
                g = states[j].gain()
                cost = np.full(len(cand), unit_s + move_s)
                if in_batch:
                    cost[[pos[c] for c in in_batch]] = unit_s
                ratio = np.where(blocked[j], -np.inf, g / cost)
                i = int(np.argmax(ratio))
                if np.isfinite(ratio[i]) and (best is None or ratio[i] > best[0]):
                    best = (float(ratio[i]), i, j, float(cost[i]))
            if best is None or spent + best[3] > limit:
                break
            _, i, j, cost_s = best
            if batch_open and spent + cost_s > settings.batch_s:
                batch_open = False  # the batch ends here; what follows is only planned
                error_after = error()
            if error_horizon is None and spent + cost_s > settings.stop_horizon_s:
                error_horizon = error()
            spent += cost_s
            c = int(cand[i])
            take(c, j)
            blocked[j][i] = True
            in_batch.add(c)
            if batch_open:
                chosen.append((c, j))
        error_after = error() if error_after is None else error_after
        error_horizon = error() if error_horizon is None else error_horizon
    floor = math.sqrt(noise)
    # The horizon starts where the running batch ends: the next stop_horizon_s of robot time.
    # Held-out check: the model's estimate must have been borne out on trials it had not
    # seen (the newest batches, each predicted before it was measured); a GP that is sure of
    # itself where it is wrong predicts small gains everywhere.
    confirmed = math.isfinite(held_out_rmse_s) and held_out_rmse_s <= error_now + (
        settings.stop_fraction * floor
    )
    converged = (
        model.calibrated_by >= settings.calibration_batches
        and confirmed
        and (error_now - error_horizon) < settings.stop_fraction * floor
    )
    stop = converged or not chosen
    units = [] if stop else _tour(chosen, pool_q, start_q)
    return BatchChoice(units, error_now, error_after, error_horizon, floor, stop)


def _tour(units: list[Unit], pool_q: FloatArray, start_q: FloatArray | None) -> list[Unit]:
    """The units grouped by configuration, configurations on a nearest-neighbour tour
    (largest joint move as the distance) from ``start_q``; joints in order."""
    by_cfg: dict[int, list[int]] = {}
    for c, j in units:
        by_cfg.setdefault(c, []).append(j)
    left = list(by_cfg)
    here = np.asarray(start_q, dtype=float) if start_q is not None else pool_q[left[0]]
    out: list[Unit] = []
    while left:
        d = [float(np.max(np.abs(pool_q[c] - here))) for c in left]
        c = left.pop(int(np.argmin(d)))
        out += [(c, j) for j in sorted(by_cfg[c])]
        here = pool_q[c]
    return out
