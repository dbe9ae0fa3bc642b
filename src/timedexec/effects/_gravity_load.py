"""``gravity_load``: the gear's breakaway friction grows with the load the joint holds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._columns import normalised_per_joint, per_joint_columns, stack_columns
from timedexec._types import FloatArray
from timedexec.effects._base import Effect, FitParam, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["GravityLoad"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class GravityLoad(Effect):
    """Breakaway torque grows with the gravity torque the joint holds.

    Load-dependent friction of the gear: the breakaway (static friction) torque of a joint
    grows by ``friction_per_load`` N·m per N·m of gravity torque it holds at the start pose.
    A joint holding more load needs longer before its velocity loop breaks it free.

    Parameters
    ----------
    friction_per_load : float
        Extra breakaway torque per unit holding torque, N·m/N·m (dimensionless), >= 0.
    """

    name: ClassVar[str] = "gravity_load"
    order: ClassVar[float] = 1
    meaning: ClassVar[str] = (
        "actuation delay grows with the gravity torque the actuated joint holds at the start pose"
    )
    variable: ClassVar[str] = "|gravity torque| (N·m)"
    variable_key: ClassVar[str] = "gravity_torque"
    fit_params: ClassVar[tuple[FitParam, ...]] = (FitParam("friction_per_load", 0.0, 3.0, 0.03),)
    shape_family: ClassVar[str | None] = "load"
    explain_verb: ClassVar[str] = "grows"
    friction_per_load: float = 0.2

    def __post_init__(self) -> None:
        self._check_finite()
        if self.friction_per_load < 0:
            raise ConfigError(
                f"gravity_load: friction_per_load={self.friction_per_load} must be >= 0"
            )

    def breakaway_extra_nm(
        self, pose: Pose, holding_nm: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        extra = self.friction_per_load * np.abs(holding_nm)
        return extra, extra

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        return cls(friction_per_load=float(np.clip(0.2 * amplitude[0], 0.01, 3.0)))

    def scaled(self, f: float) -> Effect:
        return GravityLoad(friction_per_load=self.friction_per_load * f)

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        u = np.abs(normalised_per_joint(x.joint, x.joints, x.gravity_torque_nm))
        cols, joints = per_joint_columns(x.joint, x.joints, u, ["x", "x2", "sqrt"])
        return [
            TermSpec(
                "load",
                "|gravity torque|, per joint (vanishes at zero load)",
                stack_columns(cols, len(x)),
                variable="gravity_torque",
                joints=joints,
                signature=True,
            )
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "friction_per_load": self.friction_per_load,
            "unit": "N·m of extra breakaway torque per N·m of holding torque",
        }
