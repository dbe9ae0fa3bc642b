"""Forward selection of structural terms on the residuals, with a held-out criterion, a
hierarchy rule and a parsimony test.

The residuals ``b`` of the condition means (ms) are explained by the model's nuisance
columns (its constants, the sensitivities of its own parameters, the shapes of effects
already named) plus term families (:mod:`timedexec.discrepancy._terms`). Each step scores
every *unit* — a family together with those of its parents (main effects) not yet
selected — by

* **held-out error**: leave-one-condition-out residuals of the least-squares fit (exact,
  from the hat matrix: ``e_i / (1 - h_ii)``; a condition's replicates are one mean, so
  leaving out a condition leaves out all its trials). The paired gain
  ``g_i = e0_i² - e1_i²`` of every condition gives the mean held-out gain and its
  standard error; ``z = mean(g) / se(g)``;
* **significance**: the extra-sum-of-squares F test over the larger of the pure-error
  variance of a condition mean and the residual variance left with the unit (structure
  nothing explains counts as noise, never as evidence); a column chosen on the same
  residuals (a change point) is charged extra degrees of freedom;
* **share of the excess** held-out error it removes (above the pure error).

A unit *passes* when its p-value is below ``alpha / units`` — Bonferroni over the units of
its class in the step, the vocabulary's and those outside it counted apart so that many
shapes outside the vocabulary do not take the power to name an effect of it — its
held-out gain is at least ``z_min`` standard errors (1: the one-standard-error rule) and
it removes at least ``min_share`` of the excess.

**Parsimony.** Of the passing units, those whose held-out error is within one standard
error of the best one (paired) explain the same; the one with the fewest columns is
taken. An interaction that explains what two main effects explain therefore wins as one
effect when it needs fewer columns, and a main effect wins over an interaction that
adds nothing to it.

**Hierarchy.** When the chosen unit is an interaction scored with its missing parents,
each part is kept only if it explains significantly more than the other parts (F test at
``alpha`` over the number of parts, held-out gain of at least ``z_min`` standard errors):
an interaction is never credited with what its main effects explain, and a main effect is
never named for what the interaction explains.

The selection stops when no unit passes — a held-out criterion, not a count.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from timedexec._types import FloatArray
from timedexec.discrepancy._terms import TermFamily

__all__ = ["Selection", "UnitScore", "forward_select", "loo_fit", "score_unit"]


#: Relative singular-value cut-off of the least-squares fits (collinear columns).
_RCOND = 1e-8
#: A condition with leverage above 1 - this is fitted by a column of its own: its
#: held-out residual is left out of the comparisons (one such condition would otherwise
#: decide the mean and the spread of the held-out gain alone).
_MAX_LEVERAGE_GAP = 0.05


def _basis(a: FloatArray, scale: float | None = None) -> FloatArray:
    """Orthonormal columns spanning ``a`` (directions with singular values below
    ``_RCOND`` x ``scale``, default the largest, are dropped)."""
    if a.shape[1] == 0:
        return np.zeros((a.shape[0], 0))
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    top = float(sv[0]) if scale is None else scale
    if top <= 0:
        return np.zeros((a.shape[0], 0))
    out: FloatArray = u[:, sv > top * _RCOND]
    return out


def _loo_from_basis(u: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, int]:
    res = b - u @ (u.T @ b)
    h = np.sum(u**2, axis=1)
    # A condition fitted exactly by a column of its own (h = 1) has no held-out prediction;
    # NaN marks it (the comparisons leave it out).
    with np.errstate(divide="ignore", invalid="ignore"):
        loo = np.where(h < 1.0 - _MAX_LEVERAGE_GAP, res / (1.0 - h), np.nan)
    return res, loo, int(u.shape[1])


def loo_fit(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, int]:
    """Least squares of ``b`` on the columns of ``a``.

    Returns the in-sample residuals, the leave-one-out residuals (``e_i / (1 - h_ii)``,
    exact for least squares; NaN where a condition's leverage is 1) and the rank of ``a``.
    """
    return _loo_from_basis(_basis(a), b)


def _extend(u0: FloatArray, cols: FloatArray) -> FloatArray:
    """Orthonormal basis of span(u0, cols), from ``u0`` (orthonormal) by adding what
    ``cols`` hold beyond it (cheaper than a decomposition of the whole design)."""
    if cols.shape[1] == 0:
        return u0
    scale = float(np.max(np.linalg.norm(cols, axis=0)))
    rest = cols - u0 @ (u0.T @ cols) if u0.shape[1] else cols
    # Twice: one Gram-Schmidt pass loses orthogonality for nearly dependent columns.
    rest = rest - u0 @ (u0.T @ rest) if u0.shape[1] else rest
    u1 = _basis(rest, scale * 1e2)
    return np.column_stack([u0, u1]) if u0.shape[1] else u1


@dataclass(eq=False)
class UnitScore:
    """The evidence for one unit (a family and the parents scored with it)."""

    key: str
    parts: tuple[str, ...]
    effect: str | None
    label: str
    delay: str
    columns: int
    cv_mse_null_ms2: float
    cv_mse_ms2: float
    excess_share: float
    z: float
    f_stat: float
    df1: int
    df2: float
    p_value: float
    passed: bool = False
    #: The p-value it had to beat (``alpha`` over the units of its class in its step).
    threshold: float = 0.0
    #: The joints and the variable of its family (for reports).
    joints: tuple[int, ...] = ()
    variable: str | None = None
    kept: tuple[str, ...] = ()
    part_tests: dict[str, dict[str, float]] = field(default_factory=dict)
    loo_sq: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe evidence (the keys of the signature screen's evidence, plus the
        family, its parts, the held-out z and the parts kept by the hierarchy rule)."""

        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "effect": self.effect,
            "method": "structure",
            "family": self.key,
            "family_label": self.label,
            "acts_on": self.delay,
            "scored_with": list(self.parts[1:]),
            "kept": list(self.kept),
            "columns": self.columns,
            "cv": "leave one condition out",
            "cv_mse_without_ms2": num(self.cv_mse_null_ms2),
            "cv_mse_with_ms2": num(self.cv_mse_ms2),
            "cv_share_of_excess_explained": num(self.excess_share),
            "held_out_z": num(self.z),
            "f_statistic": num(self.f_stat),
            "df": [self.df1, num(self.df2)],
            "p_value": num(self.p_value),
            "significant": self.passed,
            "parts": {
                k: {name: num(v) for name, v in t.items()} for k, t in self.part_tests.items()
            },
        }


@dataclass(eq=False)
class Selection:
    """What the forward selection accepted on one delay.

    Attributes
    ----------
    delay : str
    accepted : list of UnitScore
        The chosen unit of each step, in order.
    selected : list of str
        Family keys kept, in order.
    first_ranking : list of UnitScore
        Every unit scored at the first step, best first (the ranking of the candidates).
    contributions_ms : dict key -> ndarray (m,)
        Each selected family's fitted part of the residuals (jointly with the nuisance).
    resid_ms : ndarray (m,)
        Residuals left by the nuisance and every selected family.
    """

    delay: str
    accepted: list[UnitScore]
    selected: list[str]
    first_ranking: list[UnitScore]
    contributions_ms: dict[str, FloatArray]
    resid_ms: FloatArray


def _f_test(
    ss0: float,
    ss1: float,
    df1: int,
    rank1: int,
    m: int,
    pure_ms2: float,
    pure_df: float,
) -> tuple[float, float, float]:
    """Extra-sum-of-squares F test; denominator the larger of pure error and residual."""
    from scipy import stats

    df_resid = max(m - rank1, 1)
    resid = ss1 / df_resid
    denom, df2 = (resid, float(df_resid)) if resid > pure_ms2 else (pure_ms2, pure_df)
    k = max(df1, 1)
    f_stat = max(ss0 - ss1, 0.0) / k / denom if denom > 0 else 0.0
    if np.isfinite(df2):
        p = float(stats.f.sf(f_stat, k, df2))
    else:
        p = float(stats.chi2.sf(f_stat * k, k))
    return float(f_stat), float(df2), p


def _score(
    key: str,
    parts: tuple[str, ...],
    fam: TermFamily,
    u0: FloatArray,
    b: FloatArray,
    cols: FloatArray,
    base: tuple[FloatArray, FloatArray, int],
    pure_ms2: float,
    pure_df: float,
    extra_df: int = 0,
) -> UnitScore:
    res0, loo0, r0 = base
    m = len(b)
    res1, loo1, r1 = _loo_from_basis(_extend(u0, cols), b)
    ss0, ss1 = float(res0 @ res0), float(res1 @ res1)
    # Columns chosen by a search on these residuals (a change point) count extra.
    extra = extra_df if r1 > r0 else 0
    f_stat, df2, p = _f_test(ss0, ss1, r1 - r0 + extra, r1 + extra, m, pure_ms2, pure_df)
    ok = np.isfinite(loo0) & np.isfinite(loo1)
    e0, e1 = loo0[ok] ** 2, loo1[ok] ** 2
    gain = e0 - e1
    n_ok = int(ok.sum())
    se = float(np.std(gain, ddof=1) / np.sqrt(n_ok)) if n_ok > 1 else np.inf
    z = float(gain.mean() / se) if se > 0 and n_ok else 0.0
    cv0 = float(e0.mean()) if n_ok else np.inf
    cv1 = float(e1.mean()) if n_ok else np.inf
    excess = max(cv0 - pure_ms2, 0.05 * cv0, 1e-12)
    share = float(min((cv0 - cv1) / excess, 1.0))
    return UnitScore(
        key=key,
        parts=parts,
        effect=fam.effect,
        label=fam.label,
        delay=fam.delay,
        columns=r1 - r0,
        cv_mse_null_ms2=cv0,
        cv_mse_ms2=cv1,
        excess_share=share,
        z=z,
        f_stat=f_stat,
        df1=r1 - r0,
        df2=df2,
        p_value=p,
        joints=fam.joints,
        variable=fam.variable,
        loo_sq=np.where(ok, loo1**2, np.nan),
    )


def forward_select(
    b_ms: FloatArray,
    nuisance: FloatArray,
    families: dict[str, TermFamily],
    *,
    pure_ms2: float,
    pure_df: float,
    alpha: float = 0.01,
    min_share: float = 0.05,
    z_min: float = 1.0,
    max_terms: int = 12,
) -> Selection:
    """Select term families for the residuals ``b_ms`` (ms) step by step.

    Parameters
    ----------
    b_ms : ndarray (m,)
        Residuals of the condition means, ms.
    nuisance : ndarray (m, p)
        Columns the model can still move (always in the fit).
    families : dict key -> TermFamily
        The candidates (all of one delay).
    pure_ms2 : float
        Pure-error variance of a condition mean, ms² (mean over conditions).
    pure_df : float
        Its degrees of freedom (``inf`` for a fallback floor).
    alpha : float
        Family-wise level of a step, for the vocabulary's units and for those outside it
        each (Bonferroni over the units of the class).
    min_share : float
        Smallest share of the excess held-out error a unit must remove.
    z_min : float
        Smallest held-out gain, in standard errors of the paired gain (1: the
        one-standard-error rule of cross-validation).
    max_terms : int
        Most families selected (a guard; the held-out criterion stops first).

    Returns
    -------
    Selection
        The unit chosen at each step (with the parts the hierarchy rule kept), the
        families selected, the ranking of the first step and each family's fitted part.
    """
    b = np.asarray(b_ms, dtype=float)
    selected: list[str] = []
    accepted: list[UnitScore] = []
    first: list[UnitScore] = []

    def design(keys: list[str]) -> FloatArray:
        cols = [nuisance] + [families[k].columns for k in keys]
        cols = [c for c in cols if c.shape[1]]
        return np.column_stack(cols) if cols else np.zeros((len(b), 0))

    while len(selected) < max_terms:
        u0 = _basis(design(selected))
        base = _loo_from_basis(u0, b)
        units: list[UnitScore] = []
        for key, fam in families.items():
            if key in selected:
                continue
            missing = tuple(p for p in fam.parents if p in families and p not in selected)
            parts = (key, *missing)
            cols = np.column_stack([families[k].columns for k in parts])
            extra = sum(families[k].extra_df for k in parts)
            u = _score(key, parts, fam, u0, b, cols, base, pure_ms2, pure_df, extra)
            if u.columns <= 0:
                continue
            units.append(u)
        if not units:
            break
        # Separate multiplicity budgets for the vocabulary's families and for those outside
        # it: the many shapes outside the vocabulary must not take the power to name an
        # effect of it (family-wise error at most 2 alpha per step).
        n_in = max(sum(1 for u in units if u.effect is not None), 1)
        n_out = max(sum(1 for u in units if u.effect is None), 1)
        for u in units:
            n = n_in if u.effect is not None else n_out
            u.threshold = alpha / n
            sign_ok = True
            fam = families[u.key]
            if fam.positive:
                # An effect that only lengthens the delay (whole extra periods of response).
                res_mean = float(np.mean(base[0]))
                sign_ok = res_mean > 0
            u.passed = bool(
                sign_ok
                and u.p_value < alpha / n
                and u.z >= z_min
                and u.excess_share >= min_share
                and u.cv_mse_ms2 < u.cv_mse_null_ms2
            )
        units.sort(key=lambda s: (not s.passed, s.cv_mse_ms2))
        if not first:
            first = list(units)
        passing = [u for u in units if u.passed]
        if not passing:
            break
        best = passing[0]
        # Parsimony: units whose held-out error is within one standard error of the best
        # explain the same; take the one with the fewest columns.
        same = []
        for u in passing:
            d = u.loo_sq - best.loo_sq
            d = d[np.isfinite(d)]
            se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0
            if len(d) and float(d.mean()) <= se:
                same.append(u)
        chosen = min(same, key=lambda s: (s.columns, s.cv_mse_ms2))
        # Hierarchy: keep each part only if it explains what the other parts do not.
        kept: list[tuple[float, str]] = []
        if len(chosen.parts) == 1:
            kept = [(chosen.cv_mse_null_ms2 - chosen.cv_mse_ms2, chosen.key)]
        else:
            full = design([*selected, *chosen.parts])
            res_f, loo_f, r_f = loo_fit(full, b)
            for part in chosen.parts:
                others = [p for p in chosen.parts if p != part]
                a_o = design([*selected, *others])
                res_o, loo_o, r_o = loo_fit(a_o, b)
                extra = families[part].extra_df if r_f > r_o else 0
                f_stat, _, p = _f_test(
                    float(res_o @ res_o),
                    float(res_f @ res_f),
                    r_f - r_o + extra,
                    r_f + extra,
                    len(b),
                    pure_ms2,
                    pure_df,
                )
                both = np.isfinite(loo_o) & np.isfinite(loo_f)
                g = loo_o[both] ** 2 - loo_f[both] ** 2
                gain = float(g.mean()) if g.size else 0.0
                se = float(np.std(g, ddof=1) / np.sqrt(g.size)) if g.size > 1 else np.inf
                z = gain / se if se > 0 else 0.0
                chosen.part_tests[part] = {
                    "f_statistic": f_stat,
                    "p_value": p,
                    "cv_gain_ms2": gain,
                    "held_out_z": z,
                }
                # Bonferroni over the parts of the unit; held out as for a unit.
                if r_f > r_o and p < alpha / len(chosen.parts) and z >= z_min:
                    kept.append((gain, part))
            if not kept:
                kept = [(0.0, chosen.key)]
        kept.sort(reverse=True)
        chosen.kept = tuple(k for _, k in kept)
        accepted.append(chosen)
        selected.extend(chosen.kept)
    a = design(selected)
    contributions: dict[str, FloatArray] = {}
    if a.shape[1]:
        coef, *_ = np.linalg.lstsq(a, b, rcond=_RCOND)
        resid = b - a @ coef
        col = nuisance.shape[1]
        for k in selected:
            w = families[k].width
            contributions[k] = families[k].columns @ coef[col : col + w]
            col += w
    else:
        resid = b.copy()
    return Selection(
        delay=next(iter(families.values())).delay if families else "",
        accepted=accepted,
        selected=selected,
        first_ranking=first,
        contributions_ms=contributions,
        resid_ms=resid,
    )


def score_unit(
    b_ms: FloatArray,
    nuisance: FloatArray,
    family: TermFamily,
    *,
    pure_ms2: float,
    pure_df: float,
) -> UnitScore:
    """Score one family on the residuals ``b_ms`` (ms) over the ``nuisance`` columns:
    held-out gain, its z, the F test (no multiplicity correction; ``passed`` is not set)."""
    b = np.asarray(b_ms, dtype=float)
    u0 = _basis(nuisance)
    base = _loo_from_basis(u0, b)
    return _score(
        family.key,
        (family.key,),
        family,
        u0,
        b,
        family.columns,
        base,
        pure_ms2,
        pure_df,
        family.extra_df,
    )
