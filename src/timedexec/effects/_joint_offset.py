"""``joint_offset``: each joint's drive applies the setpoint a constant time later."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._columns import stack_columns
from timedexec._types import FloatArray
from timedexec._validation import check_joint_tuple
from timedexec.effects._base import ClosedForm, Effect, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["JointOffset"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class JointOffset(Effect):
    """Each joint's drive applies the setpoint a constant time later.

    Each joint's drive applies the setpoint ``offsets_s[j]`` later (drive bus slot,
    filters). The onset moves by exactly the offset, so the discrepancy workflow fits it in
    closed form: a constant per joint (the smallest is 0; the robot's constant holds it).

    Parameters
    ----------
    offsets_s : tuple of 6 float
        Extra dead time per joint, s, each in [0, 0.05].
    """

    name: ClassVar[str] = "joint_offset"
    order: ClassVar[float] = 6
    meaning: ClassVar[str] = "each joint has its own constant offset"
    variable: ClassVar[str] = "joint"
    variable_key: ClassVar[str] = "joint"
    closed_form: ClassVar[ClosedForm | None] = "joint_levels"
    signature_bounds: ClassVar[tuple[float, float]] = (-np.inf, np.inf)
    offsets_s: tuple[float, ...] = (0.0, 0.0015, 0.0008, 0.0004, 0.0012, 0.0002)

    #: Largest offset the closed-form fit gives a joint, s (the parameter's bound).
    MAX_OFFSET_S: ClassVar[float] = 0.05

    def __post_init__(self) -> None:
        object.__setattr__(
            self,
            "offsets_s",
            check_joint_tuple(f"effect {self.name!r}", "offsets_s", self.offsets_s),
        )
        self._check_finite()
        if any(not 0.0 <= o <= self.MAX_OFFSET_S for o in self.offsets_s):
            raise ConfigError(f"joint_offset: offsets_s {self.offsets_s} must lie in [0, 0.05] s")

    def drive_delay_s(self, pose: Pose) -> FloatArray:
        out: FloatArray = np.asarray(self.offsets_s)[pose.joint - 1]
        return out

    @classmethod
    def signature_effect(cls, sweep_span_s: float) -> Effect:
        """No offset: the closed-form fit starts from the measured per-joint levels."""
        return cls(offsets_s=(0.0,) * 6)

    @classmethod
    def n_parameters(cls, n_joints: int) -> int:
        return max(n_joints - 1, 1)

    @classmethod
    def fit_closed_form(
        cls, y_s: FloatArray, pose: Pose, period_s: float, bounds_s: tuple[float, float]
    ) -> tuple[Effect, float]:
        """The per-joint means of ``y_s``: the smallest is the robot's constant, the
        others the joints' offsets above it."""
        joints = tuple(int(j) for j in np.unique(pose.joint))
        means = {j: float(y_s[pose.joint == j].mean()) for j in joints}
        base = min(means.values())
        offsets = [0.0] * 6
        for j, mu in means.items():
            offsets[j - 1] = min(mu - base, cls.MAX_OFFSET_S)
        return cls(offsets_s=tuple(offsets)), base

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        masks = x.masks
        if len(masks) < 2:
            return []
        return [
            TermSpec(
                "joint", "a constant per joint", stack_columns(masks[1:], len(x)), variable="joint"
            )
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "offsets_ms": {f"joint {j}": self.offsets_s[j - 1] * 1e3 for j in joints},
            "unit": "ms of extra dead time per joint (the smallest is 0; the robot constant holds the rest)",
        }

    def explain(
        self, x: TermInputs, contrib_ms: FloatArray, *, shaped: bool
    ) -> tuple[dict[str, Any], str]:
        offsets = self.offsets_s
        ref = min(x.joints, key=lambda j: offsets[j - 1])
        parts = [f"joint {j} {offsets[j - 1] * 1e3:+.2f} ms" for j in x.joints if j != ref]
        return (
            {"offset_ms": {f"joint {j}": offsets[j - 1] * 1e3 for j in x.joints}},
            f"actuation delay per joint, relative to joint {ref}: " + ", ".join(parts),
        )
