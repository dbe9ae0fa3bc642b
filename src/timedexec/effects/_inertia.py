"""``inertia``: the true, pose-dependent reflected inertia acts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._columns import per_joint_columns, stack_columns
from timedexec._types import FloatArray
from timedexec.effects._base import Effect, FitParam, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["Inertia"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class Inertia(Effect):
    """The true, pose-dependent reflected inertia acts (instead of the nominal one).

    The joint's true reflected inertia at the start pose is used; without the effect every
    pose has the nominal inertia (the one the velocity loop is tuned for). More inertia
    means a slower rise after breakaway.

    Parameters
    ----------
    scale : float
        Multiplier on the link part of the inertia (1.0 = the robot spec's values), > 0.
    """

    name: ClassVar[str] = "inertia"
    order: ClassVar[float] = 4
    meaning: ClassVar[str] = (
        "actuation delay grows with the inertia the joint must accelerate (distal joint angles)"
    )
    variable: ClassVar[str] = "reflected inertia (kg·m²)"
    variable_key: ClassVar[str] = "inertia"
    fit_params: ClassVar[tuple[FitParam, ...]] = (FitParam("scale", 0.05, 20.0, 0.1, log=True),)
    shape_family: ClassVar[str | None] = "inertia"
    explain_verb: ClassVar[str] = "grows"
    scale: float = 1.0

    def __post_init__(self) -> None:
        self._check_finite()
        if self.scale <= 0:
            raise ConfigError(f"inertia: scale={self.scale} must be > 0")

    def acting_inertia_kgm2(self, pose: Pose) -> FloatArray:
        rotor = pose.rotor_kgm2
        out: FloatArray = rotor + self.scale * (pose.inertia_kgm2 - rotor)
        return out

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        return cls(scale=float(np.clip(amplitude[0], 0.05, 20.0)))

    def scaled(self, f: float) -> Effect:
        return Inertia(scale=float(self.scale**f))

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.log(
                np.maximum(x.inertia_kgm2, 1e-12) / np.maximum(x.nominal_inertia_kgm2, 1e-12)
            )
        cols, joints = per_joint_columns(x.joint, x.joints, w, ["x", "x2"], min_spread=0.02)
        return [
            TermSpec(
                "inertia",
                "log(reflected inertia / nominal), per joint",
                stack_columns(cols, len(x)),
                variable="inertia",
                joints=joints,
                signature=True,
            )
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {"scale": self.scale, "unit": "x the robot spec's link inertia"}
