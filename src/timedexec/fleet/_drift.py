"""Has the robot drifted from the model it runs? The fleet's monitor state, from a new sweep.

The deployed model predicts every trial of the new sweep; per actuated joint and per delay
the mean of (measured - predicted) is the shift since the model was trained. A shift is
reported when it is both **large enough to matter** (``|shift| >= drift_ms``, default 1 ms:
2.5 mm of seam at 0.25 m/s) and **significant** (``|z| >= z_crit``, a two-sided test at
``alpha`` with a Bonferroni correction over every joint and delay tested, so the chance of a
false alarm for a robot is at most ``alpha``). The standard error is that of a mean of
independent trials (``std / sqrt(n)``): replicates of a condition share its pose effect, so
on few configurations it is optimistic; ``drift_ms`` guards against that.

This is the offline check of a fresh calibration sweep; watching a model in service from
the robot's own state stream (without a gyro) is ``DelayMonitor``'s job, not this one.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from timedexec.delays import DelayTable
from timedexec.errors import ConfigError

__all__ = ["DRIFT_STATES", "drift_check"]

#: Monitor states of a robot in the fleet report.
DRIFT_STATES = ("ok", "drift", "no reference", "error", "not run")
_DELAYS = ("actuation_delay", "response_delay")


def _z_crit(alpha: float, tests: int) -> float:
    from scipy.stats import norm

    return float(norm.isf(alpha / (2.0 * max(tests, 1))))


def drift_check(
    model: Any,
    table: DelayTable,
    *,
    drift_ms: float = 1.0,
    alpha: float = 1e-3,
) -> dict[str, Any]:
    """Compare a deployed delay model with a new sweep's delay table.

    Parameters
    ----------
    model : DelayModel
        The deployed model (``predict_many``; its GP if it has one, else its median).
    table : DelayTable
        The new sweep's measured delays; flagged trials and NaN delays are left out.
    drift_ms : float
        Smallest shift reported, ms (> 0).
    alpha : float
        False-alarm probability per robot (0 < alpha < 1).

    Returns
    -------
    dict
        ``state`` ("ok" or "drift"), ``method`` (the model's predictor used), ``z_crit``,
        ``drift_ms``, ``alpha``, ``checks`` (per joint and delay: ``joint``, ``delay``,
        ``n``, ``shift_ms``, ``se_ms``, ``z``, ``drifted``), ``drifted`` (the checks that
        fired, as "joint 2 actuation +3.1 ms" strings), ``not_covered`` (joints of the sweep
        the model has no model for).

    Raises
    ------
    ConfigError
        Bad ``drift_ms`` or ``alpha``, or a table with no measured trial.
    """
    if not (isinstance(drift_ms, int | float) and math.isfinite(drift_ms) and drift_ms > 0):
        raise ConfigError(f"drift_ms={drift_ms!r} must be a positive number of milliseconds")
    if not (isinstance(alpha, int | float) and 0 < alpha < 1):
        raise ConfigError(f"alpha={alpha!r} must lie in (0, 1), e.g. 0.001")
    ok = np.ones(len(table), dtype=bool)
    if "flag" in table:
        ok &= np.array([not f for f in table["flag"]], dtype=bool)
    for name in _DELAYS:
        ok &= np.isfinite(np.asarray(table[name], dtype=float))
    if not ok.any():
        raise ConfigError(f"{table.source}: no measured trial to check the deployed model against")
    method = "gpr" if "gpr" in model.methods else "median"
    joints_model = {int(j) for j in model.joints}
    joint = np.asarray(table["joint"], dtype=np.int64)
    covered = ok & np.isin(joint, sorted(joints_model))
    not_covered = sorted({int(j) for j in joint[ok & ~covered]})
    checks: list[dict[str, Any]] = []
    if covered.any():
        rows = np.flatnonzero(covered)
        t_s = np.asarray(table["t_start"], dtype=float)[rows] if model.time_input else None
        pred = model.predict_many(
            joint[rows],
            np.asarray(table["direction"], dtype=np.int64)[rows],
            table.q[rows],
            t_s=t_s,
            method=method,
        )
        predicted = {"actuation_delay": pred.actuation_mean, "response_delay": pred.response_mean}
        tested = sorted({int(j) for j in joint[rows]})
        z_crit = _z_crit(alpha, len(tested) * len(_DELAYS))
        for j in tested:
            sel = joint[rows] == j
            for name in _DELAYS:
                resid = (
                    np.asarray(table[name], dtype=float)[rows][sel] - predicted[name][sel]
                ) * 1e3
                n = int(resid.size)
                shift = float(np.mean(resid))
                se = float(np.std(resid, ddof=1) / math.sqrt(n)) if n > 1 else math.inf
                z = shift / se if se > 0 else math.copysign(math.inf, shift)
                checks.append(
                    {
                        "joint": j,
                        "delay": name,
                        "n": n,
                        "shift_ms": shift,
                        "se_ms": se,
                        "z": z,
                        "drifted": bool(abs(shift) >= drift_ms and abs(z) >= z_crit),
                    }
                )
    else:
        z_crit = _z_crit(alpha, 1)
    drifted = [
        f"joint {c['joint']} {c['delay'].split('_')[0]} {c['shift_ms']:+.1f} ms (z {c['z']:+.1f})"
        for c in checks
        if c["drifted"]
    ]
    return {
        "state": "drift" if drifted else "ok",
        "method": method,
        "drift_ms": float(drift_ms),
        "alpha": float(alpha),
        "z_crit": z_crit,
        "checks": checks,
        "drifted": drifted,
        "not_covered": not_covered,
    }
