"""``response_extra_cycle``: state sampling and sending fall in separate controller cycles."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._types import FloatArray
from timedexec.effects._base import ClosedForm, Effect, Pose, TermInputs, TermSpec
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError

__all__ = ["ResponseExtraCycle"]


@register_effect
@dataclass(frozen=True, kw_only=True)
class ResponseExtraCycle(Effect):
    """State sampling and transmission fall in separate cycles.

    Every state package leaves ``cycles`` periods later. An exact shift of the response
    delay, fitted in closed form: the whole number of periods (up to
    :attr:`MAX_CYCLES_FITTED`) that leaves the least.

    Parameters
    ----------
    cycles : int
        Extra controller periods between sampling and sending, 1 or more.
    """

    name: ClassVar[str] = "response_extra_cycle"
    order: ClassVar[float] = 7
    meaning: ClassVar[str] = (
        "state sampling and transmission fall in separate cycles: one more period of response"
    )
    variable: ClassVar[str] = "controller period"
    acts_on: ClassVar[str] = "response_delay"
    variable_key: ClassVar[str] = "time"
    closed_form: ClassVar[ClosedForm | None] = "response_periods"
    cycles: int = 1

    #: Largest number of extra cycles the closed-form fit tries.
    MAX_CYCLES_FITTED: ClassVar[int] = 4

    def __post_init__(self) -> None:
        if not isinstance(self.cycles, int) or isinstance(self.cycles, bool) or self.cycles < 1:
            raise ConfigError(f"response_extra_cycle: cycles={self.cycles!r} must be an int >= 1")

    def response_delay_s(self, period_s: float) -> float:
        return period_s * self.cycles

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        return cls(cycles=max(1, round(float(amplitude[0]))))

    @classmethod
    def n_parameters(cls, n_joints: int) -> int:
        return 1

    @classmethod
    def fit_closed_form(
        cls, y_s: FloatArray, pose: Pose, period_s: float, bounds_s: tuple[float, float]
    ) -> tuple[Effect, float]:
        """The whole number of periods and the response constant (within ``bounds_s``)
        that leave the least sum of squares of ``y_s``."""
        lo, hi = bounds_s
        best: tuple[float, int, float] | None = None
        for k in range(1, cls.MAX_CYCLES_FITTED + 1):
            off = float(np.clip(y_s.mean() - k * period_s, lo, hi))
            ss = float(np.sum((y_s - k * period_s - off) ** 2))
            if best is None or ss < best[0] - 1e-15:
                best = (ss, k, off)
        assert best is not None
        _, cycles, offset = best
        return cls(cycles=cycles), offset

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        return [
            TermSpec(
                "response_cycle",
                f"a constant on the response delay (whole {x.period_s * 1e3:.0f} ms periods)",
                np.ones((len(x), 1)),
                positive=True,
            )
        ]

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {
            "cycles": self.cycles,
            "period_ms": period_s * 1e3,
            "unit": "whole controller periods between sampling and sending",
        }

    def explain(
        self, x: TermInputs, contrib_ms: FloatArray, *, shaped: bool
    ) -> tuple[dict[str, Any], str]:
        extra = self.cycles * x.period_s * 1e3
        mean = float(np.mean(x.mean_s["response_delay"]) * 1e3)
        return (
            {"extra_ms": extra, "measured_mean_response_ms": mean},
            f"the measured response delay (mean {mean:.2f} ms) exceeds what sampling and "
            f"sending within one {x.period_s * 1e3:.1f} ms cycle can give; the state "
            f"leaves {self.cycles} more period{'s' if self.cycles > 1 else ''} later "
            f"(+{extra:.1f} ms)",
        )
