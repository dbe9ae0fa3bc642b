"""What an added effect does, in words and observable units: its fitted parameters in
physical units and its contribution to the delays. An effect with a sentence of its own
says it (``Effect.explain``); the others get slopes per unit of their variable, per joint."""

from __future__ import annotations

from typing import Any

import numpy as np

from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._model import FittedModel, SimModel, closed_form_shift_s
from timedexec.effects import Effect, TermInputs, Variable, effect_type

__all__ = ["describe_parameters", "gaps_ms", "observed_effect"]


def gaps_ms(fitted: FittedModel) -> dict[str, float]:
    """The gap of each delay, ms."""
    return {d: fitted.gap_s(d) * 1e3 for d in DELAY_COLUMNS}


def describe_parameters(effect: Effect, model: SimModel) -> dict[str, Any]:
    """Fitted parameters in physical units."""
    return effect.describe(model.cond.joints, model.period_s)


def observed_effect(
    name: str,
    model: SimModel,
    after: FittedModel,
    variables: dict[str, Variable],
    inputs: TermInputs,
    extra_ms: FloatArray | None = None,
) -> tuple[dict[str, Any], str, FloatArray]:
    """What the added effect does to the delays, in observable units, a sentence, and its
    contribution to every condition mean (ms; the simulator's form, or a closed-form
    effect's shift, plus ``extra_ms``, its measured shape beyond that form)."""
    cond = model.cond
    cls = effect_type(name)
    # None when the effect entered by its measured shape alone (its simulated form does
    # not fit): its contribution is the shape.
    eff = after.effects.get(name)
    if eff is not None and eff.closed_form is not None:
        contrib = closed_form_shift_s(eff, model) * 1e3
    else:
        without = after.effects.without(name)
        contrib = (after.sim[cls.acts_on] - model.simulate(without)[cls.acts_on]) * 1e3
    if extra_ms is not None:
        contrib = contrib + extra_ms
    told = None if eff is None else eff.explain(inputs, contrib, shaped=extra_ms is not None)
    if told is not None:
        return (*told, contrib)
    var = variables[cls.variable_key]
    slopes: dict[str, float] = {}
    rows: list[tuple[float, str]] = []
    for j in cond.joints:
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
    head = f"{cls.acts_on.replace('_', ' ')} {cls.explain_verb} with the {var.label}"
    texts = [t for _, t in rows]
    return (
        {f"slope_ms_per_{var.unit}": slopes},
        head + (": " + "; ".join(texts) if texts else ""),
        contrib,
    )
