"""The sweep plan: which configuration, joint, direction and repeat each trial runs.

Published protocol (DESIGN.md §1): joints 1, 2, 3 and 5, both directions, 10 repeats per
configuration; the UR10 and KR 5 sweeps held about 33,500 trials. Trials are ordered as a
robot runs them: per configuration, per joint, per direction, the repeats.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec, check_configuration, get_robot, get_robot_entry

__all__ = ["FULL_SWEEP_TRIALS", "SweepPlan", "calibration_ranges"]

#: The paper's full sweep size.
FULL_SWEEP_TRIALS = 33_500


def calibration_ranges(
    spec: RobotSpec, *, margin_rad: float = 0.1
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Joint ranges the plan samples from, rad, shapes (6,) and (6,).

    The joint limits shrunk by ``margin_rad`` (room for the trial motion), within the
    robot's sweep ranges (its catalog entry's ``sweep_q_min_rad`` / ``sweep_q_max_rad``:
    poses that keep the arm above its base plane; a calibration sweep must not drive into
    the table).
    """
    entry = get_robot_entry(spec.name)
    lo = np.array(spec.q_min_rad, dtype=float) + margin_rad
    hi = np.array(spec.q_max_rad, dtype=float) - margin_rad
    lo[:] = np.maximum(lo, entry.sweep_q_min_rad)
    hi[:] = np.minimum(hi, entry.sweep_q_max_rad)
    if np.any(hi <= lo):
        raise ConfigError(f"robot {spec.name}: empty calibration range after margins")
    return lo, hi


@dataclass(frozen=True, kw_only=True)
class SweepPlan:
    """A calibration sweep plan.

    Attributes
    ----------
    robot : str
        Robot spec name.
    q_start_rad : ndarray, shape (n, 6)
        Start configuration per trial, rad.
    joint : ndarray of int, shape (n,)
        Actuated joint, 1-based.
    direction : ndarray of int, shape (n,)
        +1 or -1.
    config_index : ndarray of int, shape (n,)
        Index of the distinct start configuration.
    repeat : ndarray of int, shape (n,)
        Repeat number within the condition (configuration, joint, direction).
    seed : int or None
        Seed the plan was drawn with (None for a plan given explicitly).
    """

    robot: str
    q_start_rad: NDArray[np.float64]
    joint: NDArray[np.int64]
    direction: NDArray[np.int64]
    config_index: NDArray[np.int64]
    repeat: NDArray[np.int64]
    seed: int | None = None
    joints: tuple[int, ...] = field(default=(1, 2, 3, 5))
    repeats: int = 10

    def __post_init__(self) -> None:
        n = len(self.joint)
        if n == 0:
            raise ConfigError(
                "the sweep plan is empty; give at least one trial (--trials N, N >= 1)"
            )
        spec = get_robot(self.robot)
        q = check_configuration(spec, np.asarray(self.q_start_rad, dtype=float).reshape(n, 6))
        object.__setattr__(self, "q_start_rad", q)
        for name in ("joint", "direction", "config_index", "repeat"):
            arr = np.asarray(getattr(self, name), dtype=np.int64)
            if arr.shape != (n,):
                raise ConfigError(f"sweep plan: {name} has shape {arr.shape}, expected ({n},)")
            object.__setattr__(self, name, arr)
        bad = ~np.isin(self.joint, np.arange(1, 7))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ConfigError(f"sweep plan row {i}: joint {self.joint[i]} outside 1..6")
        bad = ~np.isin(self.direction, (-1, 1))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ConfigError(f"sweep plan row {i}: direction {self.direction[i]} must be +1 or -1")

    def __len__(self) -> int:
        return len(self.joint)

    @classmethod
    def generate(
        cls,
        robot: str | RobotSpec,
        n_trials: int,
        *,
        seed: int = 0,
        joints: Sequence[int] = (1, 2, 3, 5),
        repeats: int = 10,
        q_range_rad: tuple[ArrayLike, ArrayLike] | None = None,
    ) -> SweepPlan:
        """Draw a plan of ``n_trials`` trials.

        Configurations are a scrambled Sobol (quasi-random) sample of the calibration ranges
        (:func:`calibration_ranges`), so few configurations still cover the space; each is
        used for every joint in ``joints``, both directions, ``repeats`` times.
        ``q_range_rad`` = ``(lo, hi)`` (6,) each, rad, narrows the ranges further (a cell
        that reaches less: RSI's correction limits around the pose where RSI started); a
        joint whose narrowed range is empty keeps the middle of what it reaches.
        """
        spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
        if isinstance(n_trials, bool) or not isinstance(n_trials, int | np.integer) or n_trials < 1:
            raise ConfigError(
                f"number of trials {n_trials!r} must be a positive integer (1 .. 10,000,000)"
            )
        if n_trials > 10_000_000:
            raise ConfigError(f"number of trials {n_trials} exceeds 10,000,000; split the sweep")
        if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
            raise ConfigError(f"repeats={repeats!r} must be a positive integer")
        joints = tuple(int(j) for j in joints)
        if not joints or any(j not in range(1, 7) for j in joints):
            raise ConfigError(f"joints {joints} must be a non-empty subset of 1..6")
        per_config = len(joints) * 2 * repeats
        n_configs = math.ceil(n_trials / per_config)
        from scipy.stats import qmc

        lo, hi = calibration_ranges(spec)
        if q_range_rad is not None:
            lo, hi = _narrowed(spec, lo, hi, q_range_rad)
        sampler = qmc.Sobol(d=6, scramble=True, seed=np.random.default_rng(seed))
        m = max(0, math.ceil(math.log2(max(n_configs, 1))))
        unit = sampler.random_base2(m)[:n_configs]
        configs = lo + unit * (hi - lo)
        # the flange joint carries the gyro: keep it at zero (where a narrowed range allows)
        configs[:, 5] = 0.0 if q_range_rad is None else np.clip(0.0, lo[5], hi[5])
        cfg = np.repeat(np.arange(n_configs), per_config)
        within = np.tile(np.arange(per_config), n_configs)
        joint = np.asarray(joints)[within // (2 * repeats)]
        direction = np.where((within // repeats) % 2 == 0, 1, -1)
        repeat = within % repeats
        sl = slice(0, n_trials)
        return cls(
            robot=spec.name,
            q_start_rad=configs[cfg[sl]],
            joint=joint[sl],
            direction=direction[sl],
            config_index=cfg[sl],
            repeat=repeat[sl],
            seed=seed,
            joints=joints,
            repeats=repeats,
        )

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The plan as named arrays (for the recording's static part)."""
        return {
            "plan_q_start_rad": self.q_start_rad,
            "plan_joint": self.joint,
            "plan_direction": self.direction,
            "plan_config_index": self.config_index,
            "plan_repeat": self.repeat,
        }

    @classmethod
    def from_arrays(cls, robot: str, arrays: Mapping[str, NDArray[Any]], **kw: Any) -> SweepPlan:
        """Inverse of :meth:`to_arrays`."""
        return cls(
            robot=robot,
            q_start_rad=np.asarray(arrays["plan_q_start_rad"]),
            joint=np.asarray(arrays["plan_joint"]),
            direction=np.asarray(arrays["plan_direction"]),
            config_index=np.asarray(arrays["plan_config_index"]),
            repeat=np.asarray(arrays["plan_repeat"]),
            **kw,
        )

    def meta(self) -> dict[str, Any]:
        """JSON-safe description (without the arrays)."""
        return {
            "robot": self.robot,
            "n_trials": len(self),
            "seed": self.seed,
            "joints": list(self.joints),
            "repeats": self.repeats,
            "n_configurations": int(self.config_index.max()) + 1,
        }


def _narrowed(
    spec: RobotSpec, lo: NDArray[np.float64], hi: NDArray[np.float64],
    q_range_rad: tuple[ArrayLike, ArrayLike],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # fmt: skip
    """The calibration ranges inside ``q_range_rad``; an empty intersection collapses to
    the middle of ``q_range_rad`` (clipped to the joint limits)."""
    r_lo, r_hi = (np.broadcast_to(np.asarray(r, dtype=float), (6,)) for r in q_range_rad)
    if not (np.all(np.isfinite(r_lo)) and np.all(np.isfinite(r_hi)) and np.all(r_lo <= r_hi)):
        raise ConfigError(
            f"q_range_rad={q_range_rad!r}: give (lo, hi), 6 finite angles each, lo <= hi"
        )
    n_lo, n_hi = np.maximum(lo, r_lo), np.minimum(hi, r_hi)
    empty = n_lo > n_hi
    mid = np.clip(0.5 * (r_lo + r_hi), spec.q_min_rad, spec.q_max_rad)
    return np.where(empty, mid, n_lo), np.where(empty, mid, n_hi)
