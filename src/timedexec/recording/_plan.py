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
from numpy.typing import NDArray

from timedexec._validation import DictMixin, check_non_negative, check_positive
from timedexec.errors import ConfigError
from timedexec.recording._schema import GyroHeader
from timedexec.robots import RobotSpec, check_configuration, get_robot, get_robot_entry

__all__ = [
    "FULL_SWEEP_TRIALS",
    "SweepPlan",
    "SweepProtocol",
    "TrialProfile",
    "calibration_ranges",
]

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
    ) -> SweepPlan:
        """Draw a plan of ``n_trials`` trials.

        Configurations are a scrambled Sobol (quasi-random) sample of the calibration ranges
        (:func:`calibration_ranges`), so few configurations still cover the space; each is
        used for every joint in ``joints``, both directions, ``repeats`` times.
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
        sampler = qmc.Sobol(d=6, scramble=True, seed=np.random.default_rng(seed))
        m = max(0, math.ceil(math.log2(max(n_configs, 1))))
        unit = sampler.random_base2(m)[:n_configs]
        configs = lo + unit * (hi - lo)
        configs[:, 5] = 0.0  # the flange joint carries the gyro: keep it at zero
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


@dataclass(frozen=True, kw_only=True)
class TrialProfile(DictMixin):
    """The calibration motion of one trial and the recording window.

    One joint moves out and back: accelerate at ``acceleration_rad_s2`` to ``speed_rad_s``,
    hold for ``hold_s``, decelerate to rest, pause ``pause_s``, then the mirror image back to
    the start pose. Trial time 0 is the arrival of the state package that triggers the
    command; the recording covers ``[-pre_s, record_s)``.
    """

    speed_rad_s: float = 0.4
    acceleration_rad_s2: float = 8.0
    hold_s: float = 0.05
    pause_s: float = 0.15
    pre_s: float = 0.05
    record_s: float = 0.65

    def __post_init__(self) -> None:
        check_positive(
            "profile",
            speed_rad_s=self.speed_rad_s,
            acceleration_rad_s2=self.acceleration_rad_s2,
            record_s=self.record_s,
        )
        check_non_negative("profile", hold_s=self.hold_s, pause_s=self.pause_s, pre_s=self.pre_s)
        if self.pause_s + self.pulse_s < self.pulse_s + 0.14:
            raise ConfigError(
                f"profile: pause_s={self.pause_s} s must be >= 0.14 s so the out pulse can be "
                "aligned without the return pulse (delays up to 0.12 s)"
            )

    @property
    def pulse_s(self) -> float:
        """Duration of one pulse (out or back), s."""
        return 2.0 * self.speed_rad_s / self.acceleration_rad_s2 + self.hold_s

    @property
    def duration_s(self) -> float:
        """Commanded motion duration, out and back, s."""
        return 2.0 * self.pulse_s + self.pause_s

    @property
    def template(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~timedexec.sim.pulse_profile` for this motion."""
        return {
            "speed_rad_s": self.speed_rad_s,
            "acceleration_rad_s2": self.acceleration_rad_s2,
            "hold_s": self.hold_s,
            "pause_s": self.pause_s,
        }

    @property
    def displacement_rad(self) -> float:
        """Joint travel of the out pulse, rad."""
        return self.speed_rad_s * (self.speed_rad_s / self.acceleration_rad_s2 + self.hold_s)


@dataclass(frozen=True, kw_only=True)
class SweepProtocol(DictMixin):
    """How a calibration sweep runs on any robot, live or simulated.

    What the live runner needs and a recording states: the controller period, the trial
    motion, the gyro's constants and the pauses. The simulator derives one from its
    settings (``SimSettings.protocol``); a live run builds one from measured values.

    Parameters
    ----------
    robot : str
        Robot name (one of :data:`~timedexec.robots.ROBOT_NAMES`).
    controller_period_s : float
        Controller cycle, s.
    profile : TrialProfile
        The calibration motion and the recording window.
    gyro : GyroHeader
        The sensor's constants (filter group delay and transport latency included).
    still_s : float
        Stationary gyro recording before the sweep (filter design, zero-rate), s.
    config_move_s : float
        Time allowed to move to a new configuration, s.
    trial_gap_s : float
        Stillness required between trials, s.
    """

    robot: str
    controller_period_s: float
    profile: TrialProfile = field(default_factory=lambda: TrialProfile())
    gyro: GyroHeader = field(default_factory=lambda: GyroHeader())
    still_s: float = 10.0
    config_move_s: float = 3.0
    trial_gap_s: float = 0.3

    def __post_init__(self) -> None:
        check_positive("protocol", controller_period_s=self.controller_period_s)
        check_non_negative(
            "protocol",
            still_s=self.still_s,
            config_move_s=self.config_move_s,
            trial_gap_s=self.trial_gap_s,
        )

    @property
    def spec(self) -> RobotSpec:
        """The robot spec with this protocol's controller period."""
        return get_robot(self.robot, period_s=self.controller_period_s)
