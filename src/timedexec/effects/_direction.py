"""``direction``: a pose-independent asymmetry between positive and negative motion."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._columns import stack_columns
from timedexec._types import FloatArray
from timedexec._validation import check_joint_tuple
from timedexec.effects._base import Effect, FitParam, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["Direction"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class Direction(Effect):
    """Pose-independent direction asymmetry of each joint's breakaway torque.

    Breakaway torque scales by ``1 + asymmetry_j · d`` (d the direction).

    Parameters
    ----------
    asymmetry : tuple of 6 float
        Breakaway torque is scaled by ``1 + asymmetry[j] * direction``; each in (-0.9, 0.9).
    """

    name: ClassVar[str] = "direction"
    order: ClassVar[float] = 3
    meaning: ClassVar[str] = "a pose-independent asymmetry between positive and negative motion"
    variable: ClassVar[str] = "direction (+1/-1)"
    variable_key: ClassVar[str] = "direction"
    signature_bounds: ClassVar[tuple[float, float]] = (-np.inf, np.inf)
    signature_per_joint: ClassVar[bool] = True
    fit_params: ClassVar[tuple[FitParam, ...]] = (
        FitParam("asymmetry", -0.85, 0.85, 0.04, per_joint=True),
    )
    shape_family: ClassVar[str | None] = "direction_x_joint"
    asymmetry: tuple[float, ...] = (0.2, 0.15, 0.2, 0.2, 0.2, 0.2)

    def __post_init__(self) -> None:
        object.__setattr__(
            self,
            "asymmetry",
            check_joint_tuple(f"effect {self.name!r}", "asymmetry", self.asymmetry),
        )
        self._check_finite()
        if any(abs(a) >= 0.9 for a in self.asymmetry):
            raise ConfigError(f"direction: asymmetry {self.asymmetry} must lie in (-0.9, 0.9)")

    def breakaway_factors(self, pose: Pose) -> tuple[FloatArray, FloatArray]:
        asym = np.asarray(self.asymmetry)[pose.joint - 1]
        return 1.0 + asym, 1.0 - asym

    @classmethod
    def signature_effect(cls, sweep_span_s: float) -> Effect:
        """One asymmetry (0.2) on every joint."""
        return cls(asymmetry=(0.2,) * 6)

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        asym = [0.0] * 6
        for j, amp in zip(joints, amplitude, strict=True):
            asym[j - 1] = float(np.clip(0.2 * amp, -0.8, 0.8))
        return cls(asymmetry=tuple(asym))

    def scaled(self, f: float) -> Effect:
        return Direction(asymmetry=tuple(a * f for a in self.asymmetry))

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        m = len(x)
        d = x.direction
        return [
            TermSpec(
                "direction",
                "direction (all joints alike)",
                stack_columns([d], m),
                variable="direction",
            ),
            TermSpec(
                "direction_x_joint",
                "direction, per joint",
                stack_columns([d * mk for mk in x.masks], m),
                parents=("direction", "joint"),
                variable="direction",
                signature=True,
            ),
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "asymmetry": {f"joint {j}": self.asymmetry[j - 1] for j in joints},
            "unit": "breakaway torque scale 1 + asymmetry x direction (fraction)",
        }

    def explain(
        self, x: TermInputs, contrib_ms: FloatArray, *, shaped: bool
    ) -> tuple[dict[str, Any], str]:
        per: dict[str, float] = {}
        ranked: list[tuple[float, str]] = []
        for j in x.joints:
            mk = x.joint == j
            pos = contrib_ms[mk & (x.direction == 1)]
            neg = contrib_ms[mk & (x.direction == -1)]
            if len(pos) and len(neg):
                diff = float(pos.mean() - neg.mean())
                per[f"joint {j}"] = diff
                side = "positive" if diff > 0 else "negative"
                ranked.append(
                    (abs(diff), f"joint {j} moves {abs(diff):.2f} ms later in the {side} direction")
                )
        ranked.sort(reverse=True)
        return {"positive_minus_negative_ms": per}, "; ".join(text for _, text in ranked)
