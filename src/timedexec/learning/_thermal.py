"""The thermal state a delay model answers for, and whether a query is about another.

A robot's friction, and with it its actuation delay, drifts while it warms up after power-on
(the simulators' ``thermal_drift``: friction 60 % above warm at power-on, relaxing with an
hour's time constant). A model answers for the robot in the thermal states its training
sweep saw, measured on the **thermal clock**, the time since the robot was powered on
(the delay table's ``t_since_power_on``, where the recorder knew the power-on: the
simulators, ``calibrate`` through a driver that knows it). A table without it gives the
sweep's own clock, on which no thermal state can be read ("unknown").

**What "asked about another" means.** A query gives ``t_s``, the time since power-on of
the robot it is about. It is in the model's thermal state when it lies in the training
trials' span on the thermal clock (widened by :data:`THERMAL_MARGIN_S` or a tenth of the
span), or when both the query and the end of the training span are at least
:data:`WARM_AFTER_S` after power-on (warm robots are alike: at three time constants the
drift left is 3 %). Otherwise :class:`~timedexec.errors.ThermalStateWarning`: a model of a
warm robot asked about one 10 minutes after power-on, or a model calibrated in the first
45 minutes asked about a robot that has worked for hours.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["THERMAL_MARGIN_S", "WARM_AFTER_S", "thermal_mismatch", "thermal_state"]

#: From this long after power-on a robot counts as warm, s (three of the simulators'
#: hour-long warm-up time constants: friction within 3 % of warm).
WARM_AFTER_S = 3 * 3600.0
#: A query this close to the training span (or a tenth of the span, if larger) is inside it, s.
THERMAL_MARGIN_S = 600.0


def _label(lo_s: float, hi_s: float) -> str:
    if lo_s >= WARM_AFTER_S:
        return "warm"
    if hi_s <= WARM_AFTER_S:
        return "cold"
    return "cold to warm"


def thermal_state(times_s: ArrayLike, *, power_on_clock: bool) -> dict[str, Any]:
    """The manifest's ``thermal_state`` for training trials at ``times_s``.

    Parameters
    ----------
    times_s : array, shape (n,)
        The training trials' (or conditions') times, s: since power-on when
        ``power_on_clock``, else on the sweep's own clock.
    power_on_clock : bool
        Whether the times are on the thermal clock (time since power-on).

    Returns
    -------
    dict
        ``clock`` ("power-on" or "sweep": what ``t_s`` means for the model), ``range_s``
        (the span of ``times_s``), ``state`` ("cold", "warm", "cold to warm" or "unknown"
        without the power-on), ``warm_after_s``.
    """
    t = np.asarray(times_s, dtype=float)
    lo, hi = (float(t.min()), float(t.max())) if t.size else (math.nan, math.nan)
    return {
        "clock": "power-on" if power_on_clock else "sweep",
        "range_s": [lo, hi],
        "state": _label(lo, hi) if power_on_clock and t.size else "unknown",
        "warm_after_s": WARM_AFTER_S,
    }


def _describe(t_s: float) -> str:
    state = "warm" if t_s >= WARM_AFTER_S else "cold"
    return f"{t_s / 60:.0f} min after power-on ({state})"


def thermal_mismatch(state: dict[str, Any] | None, t_s: ArrayLike) -> str | None:
    """Why a query at ``t_s`` (s since power-on) is about another thermal state than the
    model's ``state`` (the manifest's ``thermal_state``), or None when it is not (or the
    model's thermal clock is unknown)."""
    if not state or state.get("clock") != "power-on":
        return None
    lo, hi = (float(v) for v in state["range_s"])
    warm_after = float(state.get("warm_after_s", WARM_AFTER_S))
    margin = max(THERMAL_MARGIN_S, 0.1 * (hi - lo))
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    inside = (t >= lo - margin) & (t <= hi + margin)
    both_warm = (t >= warm_after) & (hi >= warm_after)
    off = ~(inside | both_warm)
    if not off.any():
        return None
    first = float(t[off][0])
    how_many = "" if t.size == 1 else f" ({int(off.sum())} of {t.size} queries)"
    return (
        f"the delay model was trained on a robot {lo / 60:.0f}-{hi / 60:.0f} min after "
        f"power-on ({state.get('state', _label(lo, hi))}); asked about one "
        f"{_describe(first)}{how_many}: its delays are those of the robot it saw (a cold "
        "robot's friction, and actuation delay, are larger); calibrate in the thermal state "
        "the robot works in, or over its warm-up with the time input (docs/calibration.md)"
    )
