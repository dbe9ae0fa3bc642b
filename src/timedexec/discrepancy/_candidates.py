"""Score every effect of the vocabulary as an explanation of the residuals.

Each candidate effect not yet in the model is turned into *signature* columns: how the
simulated condition means change when the effect is switched on at its vocabulary
magnitude, from the calibrated current model (one simulation per candidate; an effect with
``signature_per_joint`` gives one column per joint, per-joint levels one indicator per
joint, whole response periods one period of response). The residuals of the condition
means are regressed on the model's nuisance columns (its constants and the sensitivities of its own
parameters, which may move when the candidate enters) plus the signature, with the
amplitudes bounded to the physically possible sign.

Criterion:

* **Cross-validation** grouped by condition (K folds of conditions, each condition's
  replicates together since the unit is a condition mean): the held-out squared error with
  the candidate must fall below that of the nuisance columns alone. The share of the
  *excess* held-out error (above the pure error) it removes is the candidate's score.
* **Significance**: the extra-sum-of-squares F test of the candidate's columns, over the
  larger of the pure-error variance of a condition mean (from the replicates) and the
  residual variance left with the candidate (so structure that nothing explains counts as
  noise, never as evidence), Bonferroni-corrected over the candidates scored.

A candidate is *significant* when its p-value is below ``alpha / n_candidates``, its
cross-validated gain is positive and it removes at least ``min_share`` of the excess.

When no signature is significant although the model does not fit, the calibration may have
bent the present effects' parameters to mimic the missing one beyond what a linearised
signature can undo; :func:`refit_candidates` then recalibrates the whole model with each
simulated candidate and applies the same criteria to the recalibrated models.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.discrepancy._conditions import NoiseFloor
from timedexec.discrepancy._model import (
    FittedModel,
    SimModel,
    actuation_columns,
    calibrate,
    default_effect,
    joint_levels,
)
from timedexec.effects import EFFECTS, Effect, effect_type

__all__ = [
    "CandidateScore",
    "compare_models",
    "fit_bounded",
    "initial_effect",
    "n_new_params",
    "refit_candidates",
    "score_candidates",
]


@dataclass(eq=False)
class CandidateScore:
    """How well one effect of the vocabulary explains the residuals."""

    name: str
    acts_on: str
    n_columns: int
    coef: FloatArray
    cv_mse_null_ms2: float
    cv_mse_ms2: float
    excess_share: float
    f_stat: float
    df1: int
    df2: float
    p_value: float
    significant: bool = False
    labels: list[str] = field(default_factory=list)
    signature: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    method: str = "signature"
    refit: FittedModel | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe evidence."""
        return {
            "effect": self.name,
            "method": self.method,
            "acts_on": self.acts_on,
            "columns": self.n_columns,
            "cv_mse_without_ms2": self.cv_mse_null_ms2,
            "cv_mse_with_ms2": self.cv_mse_ms2,
            "cv_share_of_excess_explained": self.excess_share,
            "f_statistic": self.f_stat,
            "df": [self.df1, self.df2 if np.isfinite(self.df2) else None],
            "p_value": self.p_value,
            "significant": self.significant,
            "amplitudes": {lab: float(c) for lab, c in zip(self.labels, self.coef, strict=True)},
        }


def fit_bounded(a: FloatArray, b: FloatArray, lower: FloatArray, upper: FloatArray) -> FloatArray:
    """Least squares ``min |a x - b|`` with ``lower <= x <= upper`` (columns rescaled)."""
    if a.shape[1] == 0:
        return np.zeros(0)
    scale = np.sqrt(np.mean(a**2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    a_s = a / scale
    lo, hi = lower * scale, upper * scale
    if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
        x, *_ = np.linalg.lstsq(a_s, b, rcond=None)
    else:
        from scipy.optimize import lsq_linear

        x = lsq_linear(a_s, b, bounds=(lo, hi), method="bvls").x
    out: FloatArray = x / scale
    return out


def _nuisance(
    model: SimModel, fitted: FittedModel, delay: str
) -> tuple[FloatArray, FloatArray, FloatArray, list[str]]:
    """Columns (in ms) the model can still move: its constants and its own parameters'
    sensitivities. Returns (columns, lower, upper, labels)."""
    m = len(model.cond)
    if delay == "actuation_delay":
        linear = actuation_columns(model, fitted.effects)
        cols = list(linear.T)
        if joint_levels(fitted.effects):
            labels = [f"offset joint {j}" for j in model.joint_rows]
        else:
            labels = ["constant"]
        labels += [f"data term column {k}" for k in range(len(labels), linear.shape[1])]
        cols += [fitted.jac[:, k] * 1e3 for k in range(fitted.jac.shape[1])]
        labels += [p.label for p in fitted.params]
        a = np.column_stack(cols)
        inf = np.full(a.shape[1], np.inf)
        return a, -inf, inf, labels
    lo, hi = model.response_offset_bounds_s
    # The residual already has the fitted offset removed: it may move within its bounds.
    lower = np.array([(lo - fitted.resp_offset_s) * 1e3 - 1e-9])
    upper = np.array([(hi - fitted.resp_offset_s) * 1e3 + 1e-9])
    return np.ones((m, 1)), lower, upper, ["response constant"]


def signature(model: SimModel, fitted: FittedModel, name: str) -> tuple[FloatArray, list[str]]:
    """The candidate's columns (ms per unit amplitude) and their labels."""
    cond = model.cond
    m = len(cond)
    cls = effect_type(name)
    if cls.closed_form == "joint_levels":
        joints = list(model.joint_rows)
        # The constant stays in the nuisance: one joint is the reference.
        cols = [model.joint_rows[j].astype(float) for j in joints[1:]]
        return (
            np.column_stack(cols) if cols else np.zeros((m, 0)),
            [f"joint {j} - joint {joints[0]} (ms)" for j in joints[1:]],
        )
    if cls.closed_form == "response_periods":
        return np.full((m, 1), model.period_s * 1e3), ["periods"]
    with_e = fitted.effects.with_effect(default_effect(name, model))
    diff = (model.simulate(with_e)[cls.acts_on] - fitted.sim[cls.acts_on]) * 1e3
    if cls.signature_per_joint:
        cols = [np.where(model.joint_rows[j], diff, 0.0) for j in model.joint_rows]
        return np.column_stack(cols), [f"joint {j}" for j in model.joint_rows]
    return diff[:, None], ["x vocabulary magnitude"]


def _folds(m: int, k: int, seed: int) -> NDArray[np.int64]:
    rng = np.random.default_rng([seed, 0xCF])
    fold = np.arange(m) % k
    rng.shuffle(fold)
    return fold


def _cv_mse(
    a: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray, fold: NDArray[np.int64]
) -> float:
    err = np.empty_like(b)
    for f in np.unique(fold):
        test = fold == f
        x = fit_bounded(a[~test], b[~test], lo, hi)
        err[test] = b[test] - a[test] @ x
    return float(np.mean(err**2))


def score_candidates(
    model: SimModel,
    fitted: FittedModel,
    noise: NoiseFloor,
    *,
    alpha: float = 0.01,
    min_share: float = 0.05,
    folds: int = 5,
    seed: int = 0,
    exclude: tuple[str, ...] = (),
) -> list[CandidateScore]:
    """Score every effect of the vocabulary that the model lacks; best first.

    Parameters
    ----------
    model, fitted : the simulator and the calibrated current model.
    noise : NoiseFloor
    alpha : float
        Family-wise significance level (Bonferroni over the candidates scored).
    min_share : float
        Smallest share of the excess cross-validated error a candidate must remove.
    folds : int
        Cross-validation folds (of conditions).
    seed : int
        Seeds the fold assignment.
    exclude : tuple of str
        Effects not to score (e.g. rejected earlier).
    """
    from scipy import stats

    names = [n for n in EFFECTS.vocabulary if n not in fitted.effects and n not in exclude]
    m = len(model.cond)
    fold = _folds(m, min(folds, m), seed)
    scores: list[CandidateScore] = []
    null_cache: dict[str, tuple[float, float]] = {}
    for name in names:
        delay = effect_type(name).acts_on
        b = fitted.resid_s[delay] * 1e3
        a0, lo0, hi0, _ = _nuisance(model, fitted, delay)
        cols, labels = signature(model, fitted, name)
        if cols.shape[1] == 0 or not np.any(np.abs(cols) > 1e-9):
            continue
        lo_c, hi_c = effect_type(name).signature_bounds
        a = np.column_stack([a0, cols])
        lo = np.r_[lo0, np.full(cols.shape[1], lo_c)]
        hi = np.r_[hi0, np.full(cols.shape[1], hi_c)]
        if delay not in null_cache:
            x0 = fit_bounded(a0, b, lo0, hi0)
            ss0 = float(np.sum((b - a0 @ x0) ** 2))
            null_cache[delay] = (ss0, _cv_mse(a0, b, lo0, hi0, fold))
        ss0, cv0 = null_cache[delay]
        x = fit_bounded(a, b, lo, hi)
        ss1 = float(np.sum((b - a @ x) ** 2))
        cv1 = _cv_mse(a, b, lo, hi, fold)
        k = cols.shape[1]
        p_total = a.shape[1] + (
            fitted.n_fitted[delay] - a0.shape[1] if delay == "actuation_delay" else 0
        )
        df_resid = max(m - p_total, 1)
        pure = float(np.mean(noise.mean_var_s2[delay])) * 1e6
        resid_ms = ss1 / df_resid
        if resid_ms > pure:
            denom, df2 = resid_ms, float(df_resid)
        else:
            denom, df2 = pure, noise.df
        f_stat = max(ss0 - ss1, 0.0) / k / denom if denom > 0 else 0.0
        if np.isfinite(df2):
            p_value = float(stats.f.sf(f_stat, k, df2))
        else:
            p_value = float(stats.chi2.sf(f_stat * k, k))
        excess = max(cv0 - pure, 0.05 * cv0, 1e-12)
        share = float(np.clip((cv0 - cv1) / excess, -np.inf, 1.0))
        scores.append(
            CandidateScore(
                name=name,
                acts_on=delay,
                n_columns=k,
                coef=x[a0.shape[1] :],
                cv_mse_null_ms2=cv0,
                cv_mse_ms2=cv1,
                excess_share=share,
                f_stat=float(f_stat),
                df1=k,
                df2=df2,
                p_value=p_value,
                labels=labels,
                signature=cols,
            )
        )
    n = max(len(scores), 1)
    for s in scores:
        s.significant = bool(
            s.p_value < alpha / n
            and s.cv_mse_ms2 < s.cv_mse_null_ms2
            and s.excess_share >= min_share
        )
    scores.sort(key=lambda s: (not s.significant, -(s.cv_mse_null_ms2 - s.cv_mse_ms2)))
    return scores


def initial_effect(score: CandidateScore, model: SimModel) -> Effect:
    """The candidate at the magnitude its fitted amplitude suggests (start of the
    nonlinear calibration)."""
    return effect_type(score.name).from_amplitude(
        score.coef, tuple(model.joint_rows), model.sweep_span_s
    )


def compare_models(
    before: FittedModel,
    after: FittedModel,
    noise: NoiseFloor,
    delay: str,
    n_new: int,
    threshold: float,
) -> dict[str, Any]:
    """Extra-sum-of-squares F test of ``after`` (``n_new`` more parameters) against
    ``before`` on ``delay``; the denominator is the larger of the pure-error variance and
    the residual variance left by ``after``."""
    from scipy import stats

    ss0 = float(np.sum(before.resid_s[delay] ** 2)) * 1e6
    ss1 = float(np.sum(after.resid_s[delay] ** 2)) * 1e6
    m = len(after.resid_s[delay])
    df_resid = max(m - after.n_fitted[delay], 1)
    pure = float(np.mean(noise.mean_var_s2[delay])) * 1e6
    resid = ss1 / df_resid
    denom, df2 = (resid, float(df_resid)) if resid > pure else (pure, noise.df)
    k = max(n_new, 1)
    f_stat = max(ss0 - ss1, 0.0) / k / denom if denom > 0 else 0.0
    p = (
        float(stats.f.sf(f_stat, k, df2))
        if np.isfinite(df2)
        else float(stats.chi2.sf(f_stat * k, k))
    )
    return {
        "f_statistic": float(f_stat),
        "df": [k, df2 if np.isfinite(df2) else None],
        "p_value": p,
        "confirmed": bool(p < threshold and ss1 < ss0),
    }


def n_new_params(effect: str, model: SimModel) -> int:
    """Parameters the effect ``effect`` adds to the model of the measured conditions."""
    return effect_type(effect).n_parameters(len(model.cond.joints))


def _loo_cv_mse(cols: FloatArray, resid_ms: FloatArray, fold: NDArray[np.int64]) -> float:
    """Cross-validated error of a model fitted by least squares, from its full-data fit:
    per fold, one Gauss-Newton step from the full-data optimum with the fold left out
    (exact for a model linear in its parameters; ``cols`` are its sensitivities)."""
    err = np.empty_like(resid_ms)
    scale = np.sqrt(np.mean(cols**2, axis=0))
    a = cols / np.where(scale > 0, scale, 1.0)
    for f in np.unique(fold):
        test = fold == f
        step, *_ = np.linalg.lstsq(a[~test], resid_ms[~test], rcond=None)
        err[test] = resid_ms[test] - a[test] @ step
    return float(np.mean(err**2))


def _act_columns(model: SimModel, fitted: FittedModel) -> FloatArray:
    """All sensitivities of a calibrated model's actuation means (ms per unit)."""
    const = actuation_columns(model, fitted.effects)
    return np.column_stack([const, *(fitted.jac[:, k] * 1e3 for k in range(fitted.jac.shape[1]))])


def refit_candidates(
    model: SimModel,
    fitted: FittedModel,
    noise: NoiseFloor,
    screened: list[CandidateScore],
    *,
    alpha: float = 0.01,
    min_share: float = 0.05,
    folds: int = 5,
    seed: int = 0,
    exclude: tuple[str, ...] = (),
) -> list[CandidateScore]:
    """Score the simulated candidates by recalibrating the whole model with each.

    Used when the signature screen (:func:`score_candidates`) finds nothing although the
    model does not fit: the calibration may have bent the present effects' parameters to
    mimic a missing one, far beyond where the linearised signature can undo it. Each
    candidate is added and *everything* recalibrated; the recalibrated model is compared
    with the current one by the extra-sum-of-squares F test and by cross-validation over
    folds of conditions (each model's leave-fold-out fit approximated by one Gauss-Newton
    step from its full-data optimum). Bonferroni over the candidates refitted.
    """
    names = [
        n
        for n in EFFECTS.vocabulary
        if EFFECTS[n].closed_form is None and n not in fitted.effects and n not in exclude
    ]
    by_name = {s.name: s for s in screened}
    delay = "actuation_delay"
    m = len(model.cond)
    fold = _folds(m, min(folds, m), seed)
    r0 = fitted.resid_s[delay] * 1e3
    cv0 = _loo_cv_mse(_act_columns(model, fitted), r0, fold)
    pure = float(np.mean(noise.mean_var_s2[delay])) * 1e6
    out: list[CandidateScore] = []
    for name in names:
        screen = by_name.get(name)
        start = (
            initial_effect(screen, model)
            if screen is not None and np.any(np.abs(screen.coef) > 1e-9)
            else default_effect(name, model)
        )
        refit = calibrate(model, fitted.effects.with_effect(start))
        r1 = refit.resid_s[delay] * 1e3
        cv1 = _loo_cv_mse(_act_columns(model, refit), r1, fold)
        k = n_new_params(name, model)
        test = compare_models(fitted, refit, noise, delay, k, 1.0)
        excess = max(cv0 - pure, 0.05 * cv0, 1e-12)
        out.append(
            CandidateScore(
                name=name,
                acts_on=delay,
                n_columns=k,
                coef=np.zeros(0),
                cv_mse_null_ms2=cv0,
                cv_mse_ms2=cv1,
                excess_share=float(min((cv0 - cv1) / excess, 1.0)),
                f_stat=test["f_statistic"],
                df1=k,
                df2=float(test["df"][1]) if test["df"][1] is not None else float("inf"),
                p_value=test["p_value"],
                method="refit",
                refit=refit,
            )
        )
    n = max(len(out), 1)
    for s in out:
        s.significant = bool(
            s.p_value < alpha / n
            and s.cv_mse_ms2 < s.cv_mse_null_ms2
            and s.excess_share >= min_share
        )
    out.sort(key=lambda s: (not s.significant, -(s.cv_mse_null_ms2 - s.cv_mse_ms2)))
    return out
