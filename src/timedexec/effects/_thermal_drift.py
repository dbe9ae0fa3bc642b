"""``thermal_drift``: cold grease; friction relaxes as the joints warm up over the sweep."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._columns import (
    CHANGE_POINT_DF,
    change_point,
    per_joint_columns,
    stack_columns,
    sweep_fraction,
    time_basis,
)
from timedexec._types import FloatArray
from timedexec.effects._base import Effect, FitParam, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["ThermalDrift"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class ThermalDrift(Effect):
    """Friction starts high (cold grease) and relaxes over the sweep.

    Breakaway and kinetic friction start ``cold_excess`` above their warm values and relax
    with ``time_constant_s`` over the sweep.

    Parameters
    ----------
    cold_excess : float
        Relative friction excess at t = 0 (0.3 = 30 % above warm), >= 0.
    time_constant_s : float
        Warm-up time constant, s, > 0.
    """

    name: ClassVar[str] = "thermal_drift"
    order: ClassVar[float] = 5
    meaning: ClassVar[str] = "delays drift with time since the sweep started (warm-up)"
    variable: ClassVar[str] = "time since sweep start (s)"
    variable_key: ClassVar[str] = "time"
    fit_params: ClassVar[tuple[FitParam, ...]] = (
        FitParam("cold_excess", 0.0, 5.0, 0.04, group=".c"),
        FitParam("time_constant_s", 60.0, 1e6, 0.1, log=True, group=".t"),
    )
    shape_family: ClassVar[str | None] = "time"
    cold_excess: float = 0.6
    time_constant_s: float = 3600.0

    def __post_init__(self) -> None:
        self._check_finite()
        if self.cold_excess < 0 or self.time_constant_s <= 0:
            raise ConfigError(
                f"thermal_drift: cold_excess={self.cold_excess} must be >= 0 and "
                f"time_constant_s={self.time_constant_s} > 0"
            )

    def friction_factor(self, t_s: Any) -> Any:
        """Friction multiplier at sweep time ``t_s`` (s); array in, array out."""
        return 1.0 + self.cold_excess * np.exp(-np.asarray(t_s, dtype=float) / self.time_constant_s)

    def breakaway_factors(self, pose: Pose) -> tuple[FloatArray, FloatArray]:
        factor = self.friction_factor(pose.t_start_s)
        return factor, factor

    def viscous_factor(self, pose: Pose) -> FloatArray:
        out: FloatArray = self.friction_factor(pose.t_start_s)
        return out

    @classmethod
    def signature_effect(cls, sweep_span_s: float) -> Effect:
        """A time constant of the sweep's length (at least 10 min): the signature has the
        shape of a warm-up seen within the sweep."""
        return cls(cold_excess=0.6, time_constant_s=max(600.0, sweep_span_s))

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        base = cls.signature_effect(sweep_span_s)
        assert isinstance(base, ThermalDrift)
        return cls(
            cold_excess=float(np.clip(0.6 * amplitude[0], 0.01, 5.0)),
            time_constant_s=base.time_constant_s,
        )

    def scaled(self, f: float) -> Effect:
        return ThermalDrift(cold_excess=self.cold_excess * f, time_constant_s=self.time_constant_s)

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        m = len(x)
        s = sweep_fraction(x.t_start_s)
        basis = time_basis(s)
        cols, joints = per_joint_columns(x.joint, x.joints, s, ["1-s", "hinge_half", "fast"])
        # One change point for the robot (a warm-up that ends, a mode that switches, ends
        # for every joint at once), chosen on the residuals of all joints; its search costs
        # degrees of freedom the F test counts (CHANGE_POINT_DF).
        c = change_point(s, x.resid_ms) if x.resid_ms is not None else None
        extra = 0
        if c is not None:
            basis.append((s < c).astype(float))
            cols += [((s < c) & (x.joint == j)).astype(float) for j in joints]
            extra = CHANGE_POINT_DF
        return [
            TermSpec(
                "time",
                "time since the sweep started (vanishes at its end)",
                stack_columns(basis, m),
                variable="time",
                extra_df=extra,
                signature=True,
            ),
            TermSpec(
                "time_x_joint",
                "time since the sweep started, per joint",
                stack_columns(cols, m),
                parents=("time", "joint"),
                variable="time",
                joints=joints,
                extra_df=extra,
                signature=True,
            ),
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "cold_excess": self.cold_excess,
            "time_constant_s": self.time_constant_s,
            "unit": "friction excess at sweep start (fraction); warm-up time constant (s)",
        }

    def explain(
        self, x: TermInputs, contrib_ms: FloatArray, *, shaped: bool
    ) -> tuple[dict[str, Any], str]:
        t = x.t_start_s
        early, late = t <= np.quantile(t, 0.1), t >= np.quantile(t, 0.9)
        first, last = float(contrib_ms[early].mean()), float(contrib_ms[late].mean())
        minutes = self.time_constant_s / 60
        text = (
            f"actuation delay is {first:.2f} ms longer in the first tenth of the sweep and "
            f"{last:.2f} ms longer in the last"
        )
        if not shaped:
            text += f" (friction relaxes with a time constant of {minutes:.0f} min)"
        return {"first_tenth_ms": first, "last_tenth_ms": last, "time_constant_min": minutes}, text
