"""Where the simulation and the measurement disagree: per joint, direction, region of the
configuration space and time, against the noise floor.

Tests use the pooled pure-error variance of each condition mean ``v_i = s_p² / n_i``: a
group of conditions whose residuals ``r_i`` are pure noise has ``sum r_i² / v_i`` about
chi-square with as many degrees of freedom as conditions.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.discrepancy._conditions import Conditions, NoiseFloor
from timedexec.effects import Variable

__all__ = [
    "condition_variables",
    "locate",
    "sequence_entries",
    "unexplained_entries",
    "variable_fit",
]


#: A group whose chi-square p-value exceeds this shows no sign of a disagreement.
CLEAN_P = 0.1


def condition_variables(
    cond: Conditions, gravity_torque_nm: FloatArray, inertia_kgm2: FloatArray
) -> dict[str, Variable]:
    """The variables of each condition: the six joint angles, the actuated joint's holding
    torque (magnitude and signed by direction), its reflected inertia, the sweep time and
    the direction."""
    out: dict[str, Variable] = {}
    for i in range(6):
        out[f"q{i + 1}"] = Variable(
            f"q{i + 1}", f"joint {i + 1} angle q{i + 1}", "rad", "angle", cond.q_rad[:, i]
        )
    d = cond.direction.astype(float)
    out["gravity_torque"] = Variable(
        "gravity_torque",
        "|gravity torque| of the actuated joint",
        "N·m",
        "linear",
        np.abs(gravity_torque_nm),
    )
    out["direction_x_gravity"] = Variable(
        "direction_x_gravity",
        "direction x gravity torque",
        "N·m",
        "linear",
        d * gravity_torque_nm,
    )
    out["inertia"] = Variable(
        "inertia", "reflected inertia of the actuated joint", "kg·m²", "linear", inertia_kgm2
    )
    out["time"] = Variable("time", "time since sweep start", "s", "linear", cond.t_start_s)
    out["direction"] = Variable("direction", "direction", "+1/-1", "binary", d)
    return out


def _basis(var: Variable, mask: NDArray[np.bool_]) -> FloatArray | None:
    x = var.values[mask]
    n = len(x)
    if var.kind == "binary":
        if len(np.unique(x)) < 2:
            return None
        return np.column_stack([np.ones(n), x])
    if np.ptp(x) <= 1e-12:
        return None
    if var.kind == "angle":
        # Two harmonics: any smooth periodic dependence, and a slope over a limited range.
        return np.column_stack([np.ones(n), np.sin(x), np.cos(x), np.sin(2 * x), np.cos(2 * x)])
    z = (x - x.mean()) / x.std()
    return np.column_stack([np.ones(n), z, z**2, z**3])


def variable_fit(
    resid: FloatArray, var: Variable, mask: NDArray[np.bool_]
) -> dict[str, Any] | None:
    """Fit the residuals of ``mask`` with a smooth function of ``var``.

    Returns the share of the residual variance about its mean it explains, the F test's
    p-value and the fitted curve's extremes, or None when the variable does not vary there.
    """
    from scipy import stats

    a = _basis(var, mask)
    if a is None:
        return None
    y = resid[mask]
    n, k = a.shape
    if n <= k + 2:
        return None
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    fit = a @ coef
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    ss_res = float(np.sum((y - fit) ** 2))
    if ss_tot <= 0:
        return None
    share = 1.0 - ss_res / ss_tot
    f_stat = ((ss_tot - ss_res) / (k - 1)) / (ss_res / (n - k)) if ss_res > 0 else np.inf
    p = float(stats.f.sf(f_stat, k - 1, n - k))
    x = var.values[mask]
    hi, lo = int(np.argmax(fit)), int(np.argmin(fit))
    return {
        "variable": var.key,
        "label": var.label,
        "unit": var.unit,
        "share": float(share),
        "p_value": p,
        "high_at": float(x[hi]),
        "high_ms": float(fit[hi] * 1e3),
        "low_at": float(x[lo]),
        "low_ms": float(fit[lo] * 1e3),
    }


def _group_test(resid: FloatArray, v: FloatArray, mask: NDArray[np.bool_]) -> dict[str, Any]:
    from scipy import stats

    r = resid[mask]
    n = int(mask.sum())
    chi = float(np.sum(r**2 / v[mask])) if n else 0.0
    rms = float(np.sqrt(np.mean(r**2))) if n else 0.0
    noise = float(np.sqrt(np.mean(v[mask]))) if n else 0.0
    return {
        "conditions": n,
        "mean_ms": float(r.mean() * 1e3) if n else 0.0,
        "rms_ms": rms * 1e3,
        "noise_ms": noise * 1e3,
        "excess_ms": float(np.sqrt(max(rms**2 - noise**2, 0.0)) * 1e3),
        "p_value": float(stats.chi2.sf(chi, n)) if n else 1.0,
    }


def locate(
    cond: Conditions,
    resid: FloatArray,
    noise: NoiseFloor,
    delay: str,
    variables: dict[str, Variable],
) -> dict[str, Any]:
    """Where ``resid`` (measured minus simulated condition means of ``delay``, s) exceeds
    the noise: per joint and direction, per quarter of the sweep's time, and the variable
    each joint's residuals follow best."""
    v = noise.pooled_var_s2[delay] / cond.n
    groups = []
    for j in cond.joints:
        for d in (1, -1):
            mask = (cond.joint == j) & (cond.direction == d)
            if mask.any():
                groups.append({"joint": j, "direction": d, **_group_test(resid, v, mask)})
    times = []
    edges = np.quantile(cond.t_start_s, [0.0, 0.25, 0.5, 0.75, 1.0])
    for k in range(4):
        mask = (cond.t_start_s >= edges[k]) & (
            (cond.t_start_s < edges[k + 1]) if k < 3 else np.ones(len(cond), dtype=bool)
        )
        if mask.any():
            times.append(
                {
                    "from_s": float(edges[k]),
                    "to_s": float(edges[k + 1]),
                    **_group_test(resid, v, mask),
                }
            )
    follows = []
    for j in cond.joints:
        mask = cond.joint == j
        fits = [f for f in (variable_fit(resid, var, mask) for var in variables.values()) if f]
        if fits:
            best = max(fits, key=lambda f: f["share"])
            follows.append({"joint": j, **best})
    return {
        "delay": delay,
        "overall": _group_test(resid, v, np.ones(len(cond), dtype=bool)),
        "by_joint_direction": groups,
        "by_time": times,
        "follows": follows,
    }


def _direction_text(direction: str) -> str:
    return {"both": "both directions", "+1": "positive direction", "-1": "negative direction"}[
        direction
    ]


def unexplained_entries(
    cond: Conditions,
    resid: FloatArray,
    noise: NoiseFloor,
    delay: str,
    variables: dict[str, Variable],
    *,
    alpha: float,
) -> list[dict[str, Any]]:
    """Describe what remains: which joints and directions disagree beyond the noise and
    which variable the disagreement follows. One entry per group of joints that share the
    same direction pattern and variable."""
    v = noise.pooled_var_s2[delay] / cond.n
    joints = cond.joints
    located: list[dict[str, Any]] = []
    for j in joints:
        mask = cond.joint == j
        test = _group_test(resid, v, mask)
        if test["p_value"] >= alpha / len(joints):
            continue
        sub = {d: _group_test(resid, v, mask & (cond.direction == d)) for d in (1, -1)}
        # One direction only when it disagrees and the other shows no sign of it at all.
        strict = alpha / (2 * len(joints))
        only = [d for d in (1, -1) if sub[d]["p_value"] < strict and sub[-d]["p_value"] > CLEAN_P]
        direction = f"{only[0]:+d}" if len(only) == 1 else "both"
        dmask = mask if direction == "both" else mask & (cond.direction == int(direction))
        fits = [f for f in (variable_fit(resid, var, dmask) for var in variables.values()) if f]
        fits = [f for f in fits if f["p_value"] < alpha]
        best = max(fits, key=lambda f: f["share"]) if fits else None
        located.append(
            {"joint": j, "direction": direction, "test": test, "fit": best, "mask": dmask}
        )
    entries: list[dict[str, Any]] = []
    keys: dict[tuple[str, str], dict[str, Any]] = {}
    for item in located:
        var = item["fit"]["variable"] if item["fit"] else "none"
        key = (item["direction"], var)
        if key in keys:
            keys[key]["joints"].append(item["joint"])
            keys[key]["mask"] = keys[key]["mask"] | item["mask"]
            continue
        keys[key] = {
            "joints": [item["joint"]],
            "direction": item["direction"],
            "fit": item["fit"],
            "mask": item["mask"],
        }
    for (direction, var), grp in keys.items():
        mask = grp["mask"]
        test = _group_test(resid, v, mask)
        fit = variable_fit(resid, variables[var], mask) if var != "none" else None
        joints_txt = ", ".join(str(j) for j in grp["joints"])
        plural = "s" if len(grp["joints"]) > 1 else ""
        what = delay.replace("_", " ")
        text = (
            f"{what} on joint{plural} {joints_txt} ({_direction_text(direction)}) disagrees "
            f"with the simulation by {test['excess_ms']:.2f} ms RMS beyond the noise "
            f"({test['rms_ms']:.2f} ms RMS, noise {test['noise_ms']:.2f} ms)"
        )
        if fit is not None and fit["share"] > 0:
            text += (
                f"; it follows the {fit['label']} ({fit['unit']}), which explains "
                f"{100 * fit['share']:.0f} % of it: highest ({fit['high_ms']:+.2f} ms) near "
                f"{fit['variable']} = {fit['high_at']:.2f} {fit['unit']}, lowest "
                f"({fit['low_ms']:+.2f} ms) near {fit['variable']} = {fit['low_at']:.2f} {fit['unit']}"
            )
        else:
            text += f"; on average {test['mean_ms']:+.2f} ms, following none of the variables tried"
        text += ". No effect of the vocabulary explains it."
        entries.append(
            {
                "delay": delay,
                "joints": grp["joints"],
                "direction": direction,
                "variable": fit["variable"] if fit else None,
                "variable_label": f"{fit['label']} ({fit['unit']})" if fit else None,
                "share_explained_by_variable": fit["share"] if fit else None,
                "conditions": test["conditions"],
                "mean_ms": test["mean_ms"],
                "rms_ms": test["rms_ms"],
                "excess_rms_ms": test["excess_ms"],
                "noise_ms": test["noise_ms"],
                "p_value": test["p_value"],
                "description": text,
            }
        )
    entries.sort(key=lambda e: -e["excess_rms_ms"])
    return entries


def _positions(cond: Conditions) -> NDArray[np.int64]:
    """Position of each kept trial among its condition's repeats, in sweep order (0 first)."""
    assert cond.row_t_s is not None
    c = cond.row_condition
    order = np.lexsort((cond.row_t_s, c))
    pos = np.empty(len(c), dtype=np.int64)
    sorted_c = c[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_c)) + 1]
    first = np.repeat(starts, np.diff(np.r_[starts, len(c)]))
    pos[order] = np.arange(len(c)) - first
    return pos


def _position_test(
    dev: FloatArray, pos: NDArray[np.int64], rows: NDArray[np.bool_], n_cond: int
) -> dict[str, Any] | None:
    """One-way test of within-condition deviations by repeat position (conditions as
    blocks: the deviations already have each condition's mean removed)."""
    from scipy import stats

    d, p = dev[rows], pos[rows]
    counts = np.bincount(p)
    # Positions that too few conditions reach say nothing; pool them into the last one.
    top = int(np.max(np.flatnonzero(counts >= 5))) if np.any(counts >= 5) else 0
    if top < 1:
        return None
    p = np.minimum(p, top)
    k = top + 1
    n_p = np.bincount(p, minlength=k).astype(float)
    eff = np.bincount(p, weights=d, minlength=k) / np.maximum(n_p, 1)
    ss_pos = float(np.sum(n_p * eff**2))
    ss_res = float(np.sum(d**2)) - ss_pos
    df_pos = k - 1
    df_res = len(d) - n_cond - df_pos
    if df_res <= 0 or ss_res <= 0:
        return None
    f_stat = (ss_pos / df_pos) / (ss_res / df_res)
    return {
        "effects_s": eff,
        "f_statistic": float(f_stat),
        "df": [df_pos, df_res],
        "p_value": float(stats.f.sf(f_stat, df_pos, df_res)),
    }


def sequence_entries(cond: Conditions, delay: str, *, alpha: float) -> list[dict[str, Any]]:
    """The order of the repeats: does the k-th repeat of a condition differ from the
    condition's mean (settling after a move, a first-trial effect, a trend within the
    repeats)? No model of condition means can see this, and no effect of the vocabulary
    has it; the deviations from each condition's mean are tested against their position
    among the repeats (F test, conditions as blocks). Returns an unexplained entry when
    significant at ``alpha``, naming the joints where it is significant on its own
    (Bonferroni), else all."""
    if cond.row_delay_s is None or cond.row_t_s is None:
        return []
    y = cond.row_delay_s[delay]
    c = cond.row_condition
    mean = cond.mean_s[delay]
    replicated = cond.n[c] >= 2
    dev = y - mean[c]
    pos = _positions(cond)
    test = _position_test(dev, pos, replicated, int(np.sum(cond.n >= 2)))
    if test is None or test["p_value"] >= alpha:
        return []
    joints = []
    for j in cond.joints:
        rows = replicated & (cond.joint[c] == j)
        tj = _position_test(dev, pos, rows, int(np.sum((cond.n >= 2) & (cond.joint == j))))
        if tj is not None and tj["p_value"] < alpha / len(cond.joints):
            joints.append(j)
    joints = joints or list(cond.joints)
    eff = test["effects_s"] * 1e3
    k = int(np.argmax(np.abs(eff)))
    rms = float(np.sqrt(np.mean(eff**2)))
    what = delay.replace("_", " ")
    ordinal = {0: "first", 1: "second", 2: "third"}.get(k, f"{k + 1}th")
    last = " (and later ones)" if k == len(eff) - 1 and k > 0 else ""
    text = (
        f"{what} depends on the order of the repeats: the {ordinal} repeat{last} of a "
        f"condition is {eff[k]:+.2f} ms off the condition's mean (repeat positions explain "
        f"{rms:.2f} ms RMS within conditions, F = {test['f_statistic']:.1f}, p = "
        f"{test['p_value']:.1e}; joint{'s' if len(joints) > 1 else ''} "
        f"{', '.join(str(j) for j in joints)}). Condition means cannot show it, and no "
        "effect of the vocabulary explains it."
    )
    return [
        {
            "delay": delay,
            "joints": joints,
            "direction": "both",
            "variable": None,
            "variable_label": "position among the repeats of a condition (sweep order)",
            "share_explained_by_variable": None,
            "conditions": int(np.sum(cond.n >= 2)),
            "mean_ms": 0.0,
            "rms_ms": rms,
            "excess_rms_ms": rms,
            "noise_ms": 0.0,
            "p_value": test["p_value"],
            "sequence": {
                "position_effects_ms": [float(e) for e in eff],
                "f_statistic": test["f_statistic"],
                "df": test["df"],
            },
            "description": text,
        }
    ]
