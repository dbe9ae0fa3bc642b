"""What an added effect does, in words and observable units: its fitted parameters in
physical units and its contribution to the delays (slopes per joint, per direction, early
and late in the sweep)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._locate import EFFECT_VARIABLE, Variable
from timedexec.discrepancy._model import FittedModel, SimModel
from timedexec.effects import (
    Direction,
    Effect,
    GravityDirection,
    GravityLoad,
    Inertia,
    JointOffset,
    ResponseExtraCycle,
    ThermalDrift,
)

__all__ = ["describe_parameters", "gaps_ms", "observed_effect"]

FloatArray = NDArray[np.float64]


def gaps_ms(fitted: FittedModel) -> dict[str, float]:
    return {d: fitted.gap_s(d) * 1e3 for d in DELAY_COLUMNS}


def describe_parameters(effect: Effect, model: SimModel) -> dict[str, Any]:
    """Fitted parameters in physical units."""
    joints = model.cond.joints
    if isinstance(effect, GravityLoad):
        return {
            "friction_per_load": effect.friction_per_load,
            "unit": "N·m of extra breakaway torque per N·m of holding torque",
        }
    if isinstance(effect, GravityDirection):
        return {
            "friction_per_load": effect.friction_per_load,
            "unit": "N·m of breakaway torque change per N·m of direction x holding torque",
        }
    if isinstance(effect, Direction):
        return {
            "asymmetry": {f"joint {j}": effect.asymmetry[j - 1] for j in joints},
            "unit": "breakaway torque scale 1 + asymmetry x direction (fraction)",
        }
    if isinstance(effect, Inertia):
        return {"scale": effect.scale, "unit": "x the robot spec's link inertia"}
    if isinstance(effect, ThermalDrift):
        return {
            "cold_excess": effect.cold_excess,
            "time_constant_s": effect.time_constant_s,
            "unit": "friction excess at sweep start (fraction); warm-up time constant (s)",
        }
    if isinstance(effect, JointOffset):
        return {
            "offsets_ms": {f"joint {j}": effect.offsets_s[j - 1] * 1e3 for j in joints},
            "unit": "ms of extra dead time per joint (the smallest is 0; the robot constant holds the rest)",
        }
    if isinstance(effect, ResponseExtraCycle):
        return {
            "cycles": effect.cycles,
            "period_ms": model.period_s * 1e3,
            "unit": "whole controller periods between sampling and sending",
        }
    return effect.to_dict()


def observed_effect(
    name: str,
    model: SimModel,
    after: FittedModel,
    variables: dict[str, Variable],
    extra_ms: FloatArray | None = None,
) -> tuple[dict[str, Any], str, FloatArray]:
    """What the added effect does to the delays, in observable units, a sentence, and its
    contribution to every condition mean (ms; the simulator's form plus ``extra_ms``, its
    measured shape beyond that form)."""
    cond = model.cond
    joints = cond.joints
    eff = after.effects.get(name)
    if isinstance(eff, JointOffset):
        offsets = eff.offsets_s
        ref = min(joints, key=lambda j: offsets[j - 1])
        parts = [f"joint {j} {offsets[j - 1] * 1e3:+.2f} ms" for j in joints if j != ref]
        return (
            {"offset_ms": {f"joint {j}": offsets[j - 1] * 1e3 for j in joints}},
            f"actuation delay per joint, relative to joint {ref}: " + ", ".join(parts),
            np.asarray(offsets)[cond.joint - 1] * 1e3,
        )
    if isinstance(eff, ResponseExtraCycle):
        extra = eff.cycles * model.period_s * 1e3
        mean = float(np.mean(cond.mean_s["response_delay"]) * 1e3)
        return (
            {"extra_ms": extra, "measured_mean_response_ms": mean},
            f"the measured response delay (mean {mean:.2f} ms) exceeds what sampling and "
            f"sending within one {model.period_s * 1e3:.1f} ms cycle can give; the state "
            f"leaves {eff.cycles} more period{'s' if eff.cycles > 1 else ''} later "
            f"(+{extra:.1f} ms)",
            np.full(len(cond), extra),
        )
    without = after.effects.without(name)
    contrib = (after.sim["actuation_delay"] - model.simulate(without)["actuation_delay"]) * 1e3
    if extra_ms is not None:
        contrib = contrib + extra_ms
    if isinstance(eff, Direction):
        per: dict[str, float] = {}
        ranked: list[tuple[float, str]] = []
        for j in joints:
            mk = cond.joint == j
            pos = contrib[mk & (cond.direction == 1)]
            neg = contrib[mk & (cond.direction == -1)]
            if len(pos) and len(neg):
                diff = float(pos.mean() - neg.mean())
                per[f"joint {j}"] = diff
                side = "positive" if diff > 0 else "negative"
                ranked.append(
                    (abs(diff), f"joint {j} moves {abs(diff):.2f} ms later in the {side} direction")
                )
        ranked.sort(reverse=True)
        return (
            {"positive_minus_negative_ms": per},
            "; ".join(text for _, text in ranked),
            contrib,
        )
    if isinstance(eff, ThermalDrift):
        t = cond.t_start_s
        early, late = t <= np.quantile(t, 0.1), t >= np.quantile(t, 0.9)
        first, last = float(contrib[early].mean()), float(contrib[late].mean())
        minutes = eff.time_constant_s / 60
        text = (
            f"actuation delay is {first:.2f} ms longer in the first tenth of the sweep and "
            f"{last:.2f} ms longer in the last"
        )
        if extra_ms is None:
            text += f" (friction relaxes with a time constant of {minutes:.0f} min)"
        return (
            {"first_tenth_ms": first, "last_tenth_ms": last, "time_constant_min": minutes},
            text,
            contrib,
        )
    var = variables[EFFECT_VARIABLE[name]]
    slopes: dict[str, float] = {}
    rows: list[tuple[float, str]] = []
    for j in joints:
        mk = cond.joint == j
        if np.sqrt(np.mean(contrib[mk] ** 2)) < 0.02:
            continue  # the effect does (next to) nothing on this joint
        x, y = var.values[mk], contrib[mk]
        if np.ptp(x) > 1e-9 * max(float(np.max(np.abs(x))), 1e-300):
            xc = float(x.mean())
            slope = float(np.dot(x - xc, y - y.mean()) / np.dot(x - xc, x - xc))
            intercept = float(y.mean()) - slope * xc
        else:
            slope, intercept = 0.0, float(y.mean())
        slopes[f"joint {j}"] = float(slope)
        lo, hi = float(x.min()), float(x.max())
        text = (
            f"joint {j} by {slope:+.3f} ms per {var.unit} ({intercept + slope * lo:+.2f} ms at "
            f"{lo:.3g} to {intercept + slope * hi:+.2f} ms at {hi:.3g} {var.unit})"
        )
        rows.append((float(np.ptp(y)), text))
    rows.sort(reverse=True)
    verb = "grows" if name in ("gravity_load", "inertia") else "changes"
    head = f"actuation delay {verb} with the {var.label}"
    texts = [t for _, t in rows]
    return (
        {f"slope_ms_per_{var.unit}": slopes},
        head + (": " + "; ".join(texts) if texts else ""),
        contrib,
    )
