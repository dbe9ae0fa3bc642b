"""``gravity_direction``: lifting a load needs more breakaway torque than lowering it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._columns import normalised_per_joint, per_joint_columns, stack_columns
from timedexec._types import FloatArray
from timedexec.effects._base import Effect, FitParam, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["GravityDirection"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class GravityDirection(Effect):
    """Lifting needs more breakaway torque than lowering.

    Breakaway torque changes by ``friction_per_load`` · d · τ_g (d the direction, τ_g the
    holding torque; d · τ_g > 0 means the motion raises the potential energy).

    Parameters
    ----------
    friction_per_load : float
        Breakaway torque change per unit signed holding torque d · τ_g, dimensionless, >= 0.
    """

    name: ClassVar[str] = "gravity_direction"
    order: ClassVar[float] = 2
    meaning: ClassVar[str] = (
        "moving against gravity differs from moving with it (direction x gravity torque sign)"
    )
    variable: ClassVar[str] = "direction x gravity torque (N·m)"
    variable_key: ClassVar[str] = "direction_x_gravity"
    fit_params: ClassVar[tuple[FitParam, ...]] = (FitParam("friction_per_load", 0.0, 3.0, 0.03),)
    shape_family: ClassVar[str | None] = "direction_x_load"
    friction_per_load: float = 0.08

    def __post_init__(self) -> None:
        self._check_finite()
        if self.friction_per_load < 0:
            raise ConfigError(
                f"gravity_direction: friction_per_load={self.friction_per_load} must be >= 0"
            )

    def breakaway_extra_nm(
        self, pose: Pose, holding_nm: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        # Moving in + against a positive holding torque lifts the load.
        lift = self.friction_per_load * holding_nm
        return lift, -lift

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        return cls(friction_per_load=float(np.clip(0.08 * amplitude[0], 0.005, 3.0)))

    def scaled(self, f: float) -> Effect:
        return GravityDirection(friction_per_load=self.friction_per_load * f)

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        v = x.direction * normalised_per_joint(x.joint, x.joints, x.gravity_torque_nm)
        cols, joints = per_joint_columns(x.joint, x.joints, v, ["x", "x|x|", "sign_sqrt"])
        return [
            TermSpec(
                "direction_x_load",
                "direction x gravity torque, per joint",
                stack_columns(cols, len(x)),
                parents=("load", "direction_x_joint"),
                variable="direction_x_gravity",
                joints=joints,
                signature=True,
            )
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "friction_per_load": self.friction_per_load,
            "unit": "N·m of breakaway torque change per N·m of direction x holding torque",
        }
