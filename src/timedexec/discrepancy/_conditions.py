"""Conditions of a measured delay table and the noise floor their replicates give.

A *condition* is one distinct (start configuration, actuated joint, direction). A sweep
repeats each condition (10 times in the published protocol); the scatter of the repeats is
*pure error*: what no model of the condition can explain. Everything the discrepancy
workflow compares works on condition means.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS, DelayTable
from timedexec.errors import ConfigError

__all__ = ["MIN_PURE_ERROR_DF", "Conditions", "NoiseFloor", "group_conditions", "replicate_noise"]


#: Fewest degrees of freedom of pure error (sum over conditions of repeats - 1) and fewest
#: replicated conditions for a noise floor from replicates. Below, the fallback is used.
MIN_PURE_ERROR_DF = 30
MIN_REPLICATED_CONDITIONS = 5


@dataclass(frozen=True, eq=False)
class Conditions:
    """Condition means of a delay table.

    Attributes
    ----------
    robot : str
        The robot the table was measured on.
    q_rad : ndarray (m, 6)
        Start configuration of each condition, rad.
    joint, direction : ndarray of int (m,)
        Actuated joint (1-based) and direction (+1/-1).
    config : ndarray of int (m,)
        Index of the distinct start configuration.
    t_start_s : ndarray (m,)
        Mean sweep time of the condition's trials, s.
    n : ndarray of int (m,)
        Trials (replicates) per condition.
    mean_s, var_s2 : dict of delay name -> ndarray (m,)
        Mean (s) and sample variance (s², NaN for a single trial) of each delay.
    row_condition : ndarray of int (N,)
        Condition of each measured trial (row of the table after dropping flagged rows).
    n_dropped : int
        Trials left out (flagged or without a delay).
    row_delay_s : dict of delay name -> ndarray (N,), optional
        Each kept trial's delays, s (for the search over the order of the repeats).
    row_t_s : ndarray (N,), optional
        Each kept trial's sweep time, s.
    """

    robot: str
    q_rad: FloatArray
    joint: NDArray[np.int64]
    direction: NDArray[np.int64]
    config: NDArray[np.int64]
    t_start_s: FloatArray
    n: NDArray[np.int64]
    mean_s: dict[str, FloatArray]
    var_s2: dict[str, FloatArray]
    row_condition: NDArray[np.int64]
    n_dropped: int = 0
    row_delay_s: dict[str, FloatArray] | None = None
    row_t_s: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.joint)

    @property
    def n_trials(self) -> int:
        """Trials used (after dropping flagged or unmeasured ones)."""
        return int(self.n.sum())

    @property
    def joints(self) -> tuple[int, ...]:
        """Actuated joints present, sorted."""
        return tuple(int(j) for j in np.unique(self.joint))


def group_conditions(table: DelayTable, *, robot: str | None = None) -> Conditions:
    """Group the trials of ``table`` into conditions (configuration, joint, direction).

    Rows with a non-empty ``flag`` or a non-finite delay are dropped. Configurations that
    agree to 1 µrad are the same configuration.

    Raises
    ------
    ConfigError
        The table holds several robots (and ``robot`` does not pick one), or nothing is
        left after dropping unmeasured trials.
    """
    robots = table.robots
    if robot is None:
        if len(robots) != 1:
            raise ConfigError(
                f"{table.source}: the table holds trials of {len(robots)} robots "
                f"({', '.join(robots)}); pick one with --robot"
            )
        robot = robots[0]
    keep = np.array([str(r) == robot for r in table["robot"]], dtype=bool)
    if not keep.any():
        raise ConfigError(
            f"{table.source}: no trials of robot {robot!r}; the table holds {', '.join(robots)}"
        )
    if "flag" in table:
        keep &= np.array([not f for f in table["flag"]], dtype=bool)
    for name in DELAY_COLUMNS:
        keep &= np.isfinite(table[name])
    n_dropped = int(len(table) - keep.sum())
    if not keep.any():
        raise ConfigError(
            f"{table.source}: every trial is flagged or has a missing delay; nothing to compare"
        )
    q = table.q[keep]
    joint = table["joint"][keep].astype(np.int64)
    direction = table["direction"][keep].astype(np.int64)
    t = table["t_start"][keep].astype(float)
    q_key = np.round(q * 1e6).astype(np.int64)
    _, config_rows = np.unique(q_key, axis=0, return_inverse=True)
    config_rows = config_rows.reshape(-1)
    key = np.column_stack([config_rows, joint, direction])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # Order conditions by their first trial, as the sweep ran them.
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    cond = rank[inverse]
    first = first[order]
    m = len(first)
    n = np.bincount(cond, minlength=m).astype(np.int64)
    mean: dict[str, FloatArray] = {}
    var: dict[str, FloatArray] = {}
    rows: dict[str, FloatArray] = {}
    for name in DELAY_COLUMNS:
        y = table[name][keep].astype(float)
        rows[name] = y
        mu = np.bincount(cond, weights=y, minlength=m) / n
        ss = np.bincount(cond, weights=(y - mu[cond]) ** 2, minlength=m)
        with np.errstate(invalid="ignore", divide="ignore"):
            var[name] = np.where(n > 1, ss / np.maximum(n - 1, 1), np.nan)
        mean[name] = mu
    _, config = np.unique(config_rows[first], return_inverse=True)
    return Conditions(
        robot=robot,
        q_rad=q[first],
        joint=joint[first],
        direction=direction[first],
        config=config.reshape(-1).astype(np.int64),
        t_start_s=np.bincount(cond, weights=t, minlength=m) / n,
        n=n,
        mean_s=mean,
        var_s2=var,
        row_condition=cond.astype(np.int64),
        n_dropped=n_dropped,
        row_delay_s=rows,
        row_t_s=t,
    )


@dataclass(frozen=True, eq=False)
class NoiseFloor:
    """What replicate scatter alone gives, per delay.

    Attributes
    ----------
    floor_s : dict delay -> float
        The gap (RMS over conditions of measured minus simulated mean) that pure error alone
        produces: ``sqrt(mean_i(s_i² / n_i))``, s.
    mean_var_s2 : dict delay -> ndarray (m,)
        Variance of each condition mean, s² (pooled variance / n_i where a condition has a
        single trial).
    pooled_var_s2 : dict delay -> float
        Pooled variance of a single trial, s².
    df : float
        Degrees of freedom of the pure-error estimate (``inf`` for the fallback).
    source : str
        ``"replicates"`` or a description of the fallback.
    warning : str or None
        Why the fallback was used.
    """

    floor_s: dict[str, float]
    mean_var_s2: dict[str, FloatArray]
    pooled_var_s2: dict[str, float]
    df: float
    source: str
    warning: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe summary (ms)."""
        return {
            "noise_floor_ms": {k: v * 1e3 for k, v in self.floor_s.items()},
            "trial_sd_ms": {k: float(np.sqrt(v) * 1e3) for k, v in self.pooled_var_s2.items()},
            "pure_error_df": self.df if np.isfinite(self.df) else None,
            "source": self.source,
            "warning": self.warning,
        }


def replicate_noise(
    cond: Conditions, *, fallback_var_s2: dict[str, float] | None = None
) -> NoiseFloor:
    """The noise floor from the replicates of ``cond``.

    Parameters
    ----------
    cond : Conditions
    fallback_var_s2 : dict delay -> float, optional
        Per-trial variance to use when the replicates cannot give one (too few repeats);
        without it such a table raises.

    Raises
    ------
    ConfigError
        Too few repeats and no fallback given.
    """
    replicated = cond.n > 1
    df = float(np.sum(cond.n[replicated] - 1))
    enough = df >= MIN_PURE_ERROR_DF and int(replicated.sum()) >= MIN_REPLICATED_CONDITIONS
    warning = None
    pooled: dict[str, float] = {}
    if enough:
        for name in DELAY_COLUMNS:
            v = cond.var_s2[name]
            pooled[name] = float(np.sum((cond.n[replicated] - 1) * v[replicated]) / df)
        source = "replicates"
    else:
        warning = (
            f"too few repeats to estimate the noise floor: {int(replicated.sum())} of "
            f"{len(cond)} conditions are repeated ({df:.0f} degrees of freedom of pure error; "
            f"at least {MIN_PURE_ERROR_DF} over {MIN_REPLICATED_CONDITIONS} conditions are "
            "needed). Repeat each condition (same configuration, joint and direction) about 10 "
            "times."
        )
        if fallback_var_s2 is None:
            raise ConfigError(warning)
        pooled = {k: float(v) for k, v in fallback_var_s2.items()}
        df = float("inf")
        source = "fallback: the simulator's trial-to-trial timing scatter at these conditions"
        warning += (
            " Fallback: the noise floor is the simulator's own trial-to-trial scatter "
            "(controller cycle phase, packing phase, jitter) at the measured conditions; a "
            "real robot or an extraction may scatter more, so small disagreements may be "
            "over-reported."
        )
    mean_var: dict[str, FloatArray] = {}
    floor: dict[str, float] = {}
    for name in DELAY_COLUMNS:
        if enough:
            v = np.where(replicated, cond.var_s2[name], pooled[name])
        else:
            v = np.full(len(cond), pooled[name])
        # A single condition's s_i^2 is noisy; its mean over conditions is what the gap sees.
        mean_var[name] = v / cond.n
        floor[name] = float(np.sqrt(np.mean(mean_var[name])))
    return NoiseFloor(floor, mean_var, pooled, df, source, warning)
