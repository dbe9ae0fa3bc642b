"""The library of candidate terms beyond the vocabulary and the sparse selection over it:
a held-out criterion, the shape refined, the uncertainty given.

What a cell brings that no effect of the vocabulary describes (cables and hoses, drive and
gear periodicity, local contacts, load paths through another joint) shows in the residuals
of the actuation condition means as a function of where the arm is. The library holds the
forms such effects can plausibly take, over every measured joint (its conditions only) and
the configuration quantities the table and the robot's own model give:

* **inputs**: the joint angles ``q1``..``q6`` (those that vary over the sweep) and the
  gravity torque ``tauK`` of every *other* joint K that holds one (from the robot's
  kinematic and inertial model, :func:`timedexec.robots.gravity_torque`). The actuated
  joint's own holding torque is left out: load-dependent friction of that joint is the
  vocabulary's (``gravity_load``, ``gravity_direction``), as are constants per joint
  (``joint_offset``) or per direction (``direction``) and sweep time (``thermal_drift``).
* **forms**, each for a physical reason:

  - ``linear`` (a slope about the sweep's mean): a drag that grows steadily with an angle
    or with the load another joint carries through a shared gear or cable;
  - ``hinge_up`` / ``hinge_down`` (zero up to a knot, then linear): a cable or hose that
    is slack over part of the range and tightens beyond an angle;
  - ``harmonic`` (sin and cos of n·angle, n = 1, 2, 3): periodic drive and gear effects
    (eccentricity, cogging folded down to the angles a sweep samples), a cable wound
    around an axis;
  - ``bump`` (a Gaussian in one angle) and ``bump2`` (in two): a local contact, a hose or
    an obstacle touched in one region of the workspace;
  - ``product`` (the product of two angles about their means): a drag that depends on two
    angles at once over the whole range (a hose routed across two joints, whose bending
    follows both) — the first cross term of any smooth dependence on two angles, where a
    bump is its local form;

* **gates**: both directions, the positive or the negative only (a cable that pulls
  against one direction of motion, a one-way clutch or brake).

Each candidate acts on one joint, or on every measured joint with one shape and one size
(selected by that shared column, which pools the joints' evidence; once chosen its size is
fitted per joint). A term some joints share is found on each and merged when one shape
serves them all. Knots, centres and widths start on a grid of the input's quantiles
(the grid counts in the multiplicity) and are refined by nonlinear least squares once a
candidate is chosen.

Selection (:func:`discover`), forward, one term per step: every candidate is scored by
the extra-sum-of-squares F test of its columns against the residuals left by the model's
nuisance columns (its constants, the sensitivities of its calibrated parameters, the
terms already chosen), over the larger of the pure-error variance and the residual
variance, Bonferroni over the whole library (a null table stays empty with probability
>= 1 - alpha per step); the best candidates by p are then scored held out, leaving out
one *configuration* at a time (all its conditions: a term is a function of the
configuration, so the other joints and directions at the same pose would leak it). A
candidate passes at p < alpha / N, held-out z >= 1 and a share >= ``min_share`` of the
excess held-out error; of those within one standard error of the best held-out error, the
simplest form is kept (fewest columns and shape parameters). The loop stops when nothing
passes. Then backward: a term a later one made redundant (dropping it does not raise the
held-out error, z < 1) is dropped, the weakest first.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.discrepancy._model import SimModel
from timedexec.effects import DataTerm, register_term, term_columns
from timedexec.robots import gravity_torque

__all__ = [
    "FIXED_SHAPE",
    "Candidate",
    "Found",
    "Library",
    "discover",
    "merge_terms",
    "nested_test",
    "refine",
    "register_found",
    "term_uncertainty",
]


#: Complexity of each form for the parsimony rule: its columns plus its fitted shape
#: parameters (a harmonic's order is chosen from three, like a grid point).
COMPLEXITY = {
    "linear": 1,
    "hinge_up": 2,
    "hinge_down": 2,
    "harmonic": 2,
    "product": 2,
    "bump": 3,
    "bump2": 5,
}
#: Forms whose shape is not fitted (a slope's and a product's references are the sweep's
#: means, a harmonic's order is a grid point).
FIXED_SHAPE = ("linear", "harmonic", "product")
#: Quantiles of an input (over the distinct configurations) where knots are placed.
KNOTS = tuple(np.round(np.linspace(0.15, 0.85, 8), 3))
#: Quantiles where bump centres are placed, and widths as fractions of the input's range.
BUMP_CENTRES = tuple(np.round(np.linspace(0.1, 0.9, 9), 3))
BUMP_WIDTHS = (0.06, 0.12, 0.2)
#: The same for two-input bumps (a coarser grid: 25 centres x 2 widths per pair).
BUMP2_CENTRES = (0.1, 0.3, 0.5, 0.7, 0.9)
BUMP2_WIDTHS = (0.15, 0.3)
HARMONICS = (1, 2, 3)
#: Smallest spread of an angle (rad) over a joint's conditions for it to be an input.
MIN_ANGLE_SPREAD = 0.2
#: A candidate must be "on" (|column| >= a quarter of its peak) at this many
#: configurations, and (except a slope or a harmonic) "off" at as many: a column that is
#: an indicator of one or two poses, or a constant over the joint, is not a shape.
MIN_SUPPORT = 3
#: Candidates scored held out at each step (the best by p).
HELD_OUT_TOP = 24
#: Most terms :func:`discover` selects.
MAX_TERMS = 4
#: Smallest size of a chosen term, in standard errors (its shape free), for it to count.
MIN_SIZE_Z = 3.0
_GATES = (0, 1, -1)


@dataclass(frozen=True)
class Candidate:
    """One candidate term: a form of one or two inputs on one joint's conditions (or, once
    merged, several joints'), on one direction or both."""

    joints: tuple[int, ...]
    inputs: tuple[str, ...]
    form: str
    shape: tuple[float, ...]
    direction: int

    @property
    def complexity(self) -> int:
        """Columns plus fitted shape parameters (the parsimony rule's count)."""
        return COMPLEXITY[self.form]

    @property
    def label(self) -> str:
        """Short text: ``joint 3: hinge_up(q5; 0.40), positive``."""
        shape = ", ".join(f"{v:.2f}" for v in self.shape)
        side = {0: "", 1: ", positive direction", -1: ", negative direction"}[self.direction]
        joints = ", ".join(map(str, self.joints))
        return f"joint{'s' if len(self.joints) > 1 else ''} {joints}: {self.form}({', '.join(self.inputs)}; {shape}){side}"

    def term(self) -> DataTerm:
        """The candidate as an (unregistered, zero-coefficient) data term."""
        return DataTerm(
            joints=self.joints,
            inputs=self.inputs,
            form=self.form,
            shape=self.shape,
            direction=self.direction,
        )


class Library:
    """Every candidate term over the measured conditions of ``model``, with its columns.

    Attributes
    ----------
    inputs : dict name -> ndarray (m,)
        The inputs' values per condition (``qK`` rad, ``tauK`` N·m).
    candidates : list of Candidate
    columns : list of ndarray (m, k)
        Each candidate's columns (k = 1, or 2 for a harmonic).
    groups : ndarray of int (m,)
        The configuration of each condition (the held-out unit).
    """

    def __init__(self, model: SimModel) -> None:
        cond = model.cond
        self.model = model
        self.pose = model.pose
        m = len(cond)
        self.groups = cond.config
        self.direction = cond.direction.astype(float)
        self.inputs: dict[str, FloatArray] = {}
        for k in range(6):
            q = cond.q_rad[:, k]
            if np.ptp(q) >= MIN_ANGLE_SPREAD:
                self.inputs[f"q{k + 1}"] = q
        tau = gravity_torque(model.spec, cond.q_rad)
        top = float(np.max(np.abs(tau))) if tau.size else 0.0
        for k in range(6):
            # Every torque that varies over the sweep (a wrist's is a hundredth of the
            # shoulder's but a cable or gear on it may still follow it); not one that is
            # zero up to rounding (a joint whose axis stays vertical).
            if top > 0 and np.ptp(tau[:, k]) >= max(1e-6 * top, 1e-3):
                self.inputs[f"tau{k + 1}"] = tau[:, k]
        self.candidates: list[Candidate] = []
        self.columns: list[FloatArray] = []
        for cand, cols in self._generate(cond.joint, cond.joints):
            self.candidates.append(cand)
            self.columns.append(cols)
        single = [i for i, c in enumerate(self.columns) if c.shape[1] == 1]
        double = [i for i, c in enumerate(self.columns) if c.shape[1] == 2]
        self.single = np.asarray(single, dtype=np.int64)
        self.double = np.asarray(double, dtype=np.int64)
        self.c1 = (
            np.column_stack([self.columns[i][:, 0] for i in single]) if single else np.zeros((m, 0))
        )
        self.c2 = (
            np.stack([self.columns[i] for i in double], axis=1) if double else np.zeros((m, 0, 2))
        )

    def __len__(self) -> int:
        return len(self.candidates)

    def gate(self, direction: int) -> FloatArray:
        """1 on the conditions of ``direction`` (0: all), else 0."""
        if direction == 0:
            return np.ones(len(self.direction))
        out: FloatArray = (np.sign(self.direction) == direction).astype(np.float64)
        return out

    def values(self, cand: Candidate) -> FloatArray:
        """The candidate's columns at the conditions, (m, k): exactly the data term's basis
        (the simulator applies the same formula)."""
        out: FloatArray = np.asarray(cand.term().basis(self.pose), dtype=np.float64)
        return out

    def _support_ok(self, col: FloatArray, mask: NDArray[np.bool_], both_sides: bool) -> bool:
        a = np.abs(col[mask])
        top = float(a.max()) if a.size else 0.0
        if top <= 1e-12:
            return False
        groups = self.groups[mask]
        on = len(np.unique(groups[a >= 0.25 * top]))
        off = len(np.unique(groups[a < 0.25 * top]))
        return on >= MIN_SUPPORT and (not both_sides or off >= MIN_SUPPORT)

    def _generate(
        self, joint: NDArray[np.int64], joints: tuple[int, ...]
    ) -> Iterator[tuple[Candidate, FloatArray]]:
        first = np.unique(self.groups, return_index=True)[1]
        angles = [n for n in self.inputs if n.startswith("q")]
        # Each joint on its own, and (with several joints) all of them sharing one shape
        # and one size: a cable, hose or drive-side effect that every drive feels alike
        # pools the evidence of every joint (selected with one shared column; once chosen,
        # each joint's coefficient is fitted on its own).
        sets = [(j,) for j in joints] + ([tuple(joints)] if len(joints) > 1 else [])
        for js in sets:
            rows = np.isin(joint, js)
            base: list[tuple[tuple[str, ...], str, tuple[float, ...]]] = []
            for name, x in self.inputs.items():
                if name in {f"tau{j}" for j in js} or np.ptp(x[rows]) <= 1e-9:
                    continue
                distinct = np.unique(x[first])
                lo, hi = float(distinct.min()), float(distinct.max())
                span = hi - lo
                base.append(((name,), "linear", (float(np.mean(x)),)))
                for qk in KNOTS:
                    k = float(np.quantile(distinct, qk))
                    base.append(((name,), "hinge_up", (k,)))
                    base.append(((name,), "hinge_down", (k,)))
                if name.startswith("q"):
                    base += [((name,), "harmonic", (float(n),)) for n in HARMONICS]
                for qc in BUMP_CENTRES:
                    c = float(np.quantile(distinct, qc))
                    base += [((name,), "bump", (c, w * span)) for w in BUMP_WIDTHS]
            for a_i, a in enumerate(angles):
                for b in angles[a_i + 1 :]:
                    da, db = np.unique(self.inputs[a][first]), np.unique(self.inputs[b][first])
                    for qa in BUMP2_CENTRES:
                        for qb in BUMP2_CENTRES:
                            ca, cb = float(np.quantile(da, qa)), float(np.quantile(db, qb))
                            for w in BUMP2_WIDTHS:
                                base.append(
                                    ((a, b), "bump2", (ca, w * np.ptp(da), cb, w * np.ptp(db)))
                                )
                    base.append(
                        (
                            (a, b),
                            "product",
                            (float(np.mean(self.inputs[a])), float(np.mean(self.inputs[b]))),
                        )
                    )
            for inputs, form, shape in base:
                x = np.column_stack([self.inputs[n] for n in inputs])
                raw = term_columns(form, x, shape)
                for d in _GATES:
                    mask = rows & (self.gate(d) > 0)
                    cols = raw * mask[:, None]
                    if not self._support_ok(cols[:, 0], mask, both_sides=form not in FIXED_SHAPE):
                        continue
                    yield Candidate(js, inputs, form, shape, d), cols


# ------------------------------------------------------------------------ linear algebra
def _orth(a: FloatArray) -> FloatArray:
    """Orthonormal columns spanning ``a`` (directions below 1e-8 of the largest dropped)."""
    if a.shape[1] == 0:
        return np.zeros((a.shape[0], 0))
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    if sv[0] <= 0:
        return np.zeros((a.shape[0], 0))
    out: FloatArray = u[:, sv > sv[0] * 1e-8]
    return out


def _extend(u0: FloatArray, cols: FloatArray) -> FloatArray:
    rest = cols - u0 @ (u0.T @ cols)
    rest = rest - u0 @ (u0.T @ rest)
    scale = float(np.max(np.linalg.norm(cols, axis=0))) if cols.size else 0.0
    keep = _orth(rest)
    if keep.shape[1] and scale > 0:
        norms = np.linalg.norm(rest, axis=0)
        if float(norms.max()) < 1e-6 * scale:
            keep = np.zeros((len(cols), 0))
    return np.column_stack([u0, keep])


def _group_loo(u: FloatArray, b: FloatArray, groups: NDArray[np.int64]) -> FloatArray:
    """Leave-one-group-out residuals of the least-squares fit of ``b`` on the orthonormal
    ``u``: per group G, (I - H_GG)^-1 e_G (exact for least squares); NaN where a group is
    fitted by columns of its own."""
    e = b - u @ (u.T @ b)
    out = np.full(len(b), np.nan)
    for g in np.unique(groups):
        idx = np.nonzero(groups == g)[0]
        ug = u[idx]
        a = np.eye(len(idx)) - ug @ ug.T
        if np.linalg.cond(a) > 1e6:
            continue
        out[idx] = np.linalg.solve(a, e[idx])
    return out


def _f_p(
    gain: FloatArray, k: int, rss0: float, m: int, rank0: int, pure_ms2: float, pure_df: float
) -> tuple[FloatArray, FloatArray]:
    """F statistics and p-values of ``gain`` (sums of squares explained by k columns)."""
    from scipy import stats

    df_resid = max(m - rank0 - k, 1)
    resid = (rss0 - gain) / df_resid
    use_pure = resid <= pure_ms2
    denom = np.where(use_pure, pure_ms2, resid)
    f = np.where(denom > 0, np.maximum(gain, 0.0) / k / denom, 0.0)
    if np.isfinite(pure_df):
        p = np.where(use_pure, stats.f.sf(f, k, pure_df), stats.f.sf(f, k, df_resid))
    else:
        p = np.where(use_pure, stats.chi2.sf(f * k, k), stats.f.sf(f, k, df_resid))
    return f, p


# ------------------------------------------------------------------------------ scoring
@dataclass(eq=False)
class Found:
    """A candidate chosen by :func:`discover`, with its evidence.

    Attributes
    ----------
    candidate : Candidate
        With its shape refined.
    grid : Candidate
        The grid point it was chosen at.
    p_value, f_statistic : float
        Its F test at the grid point (the Bonferroni decision: p < alpha / library size).
    threshold : float
        alpha / library size.
    cv_mse_without_ms2, cv_mse_with_ms2 : float
        Held-out error (leave one configuration out) without and with it.
    held_out_z : float
    share : float
        Share of the excess held-out error it removes.
    alternatives : list of dict
        The runners-up (label, p, held-out error), best first.
    columns : ndarray (m, k)
        Its columns at the refined shape.
    """

    candidate: Candidate
    grid: Candidate
    p_value: float
    f_statistic: float
    threshold: float
    cv_mse_without_ms2: float
    cv_mse_with_ms2: float
    held_out_z: float
    share: float
    columns: FloatArray = field(repr=False)
    alternatives: list[dict[str, Any]] = field(default_factory=list)

    def evidence(self) -> dict[str, Any]:
        """JSON-safe evidence."""

        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "method": "discovery",
            "candidate_at_grid": self.grid.label,
            "library_size_threshold_p": num(self.threshold),
            "f_statistic": num(self.f_statistic),
            "p_value": num(self.p_value),
            "cv": "leave one configuration out",
            "cv_mse_without_ms2": num(self.cv_mse_without_ms2),
            "cv_mse_with_ms2": num(self.cv_mse_with_ms2),
            "held_out_z": num(self.held_out_z),
            "cv_share_of_excess_explained": num(self.share),
            "alternatives": self.alternatives,
        }


def _screen(
    lib: Library, u0: FloatArray, b: FloatArray, pure_ms2: float, pure_df: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Sum of squares each candidate explains beyond ``u0``, its F and p (arrays over the
    library)."""
    r = b - u0 @ (u0.T @ b)
    rss0 = float(r @ r)
    m = len(b)
    rank0 = u0.shape[1]
    n = len(lib)
    gain = np.zeros(n)
    f = np.zeros(n)
    p = np.ones(n)
    if lib.c1.shape[1]:
        num = lib.c1.T @ r
        uc = u0.T @ lib.c1
        den = np.sum(lib.c1**2, axis=0) - np.sum(uc**2, axis=0)
        ok = den > 1e-9 * np.sum(lib.c1**2, axis=0)
        g = np.where(ok, num**2 / np.where(ok, den, 1.0), 0.0)
        gain[lib.single] = g
        f1, p1 = _f_p(g, 1, rss0, m, rank0, pure_ms2, pure_df)
        f[lib.single], p[lib.single] = f1, np.where(ok, p1, 1.0)
    if lib.c2.shape[1]:
        a, c = lib.c2[:, :, 0], lib.c2[:, :, 1]
        ua, uc2 = u0.T @ a, u0.T @ c
        aa = np.sum(a * a, 0) - np.sum(ua * ua, 0)
        cc = np.sum(c * c, 0) - np.sum(uc2 * uc2, 0)
        ac = np.sum(a * c, 0) - np.sum(ua * uc2, 0)
        va, vc = a.T @ r, c.T @ r
        det = aa * cc - ac**2
        ok = det > 1e-9 * np.maximum(aa * cc, 1e-300)
        g = np.where(ok, (cc * va**2 - 2 * ac * va * vc + aa * vc**2) / np.where(ok, det, 1.0), 0.0)
        gain[lib.double] = g
        f2, p2 = _f_p(g, 2, rss0, m, rank0, pure_ms2, pure_df)
        f[lib.double], p[lib.double] = f2, np.where(ok, p2, 1.0)
    return gain, f, p


def _held_out(
    u0: FloatArray, b: FloatArray, cols: FloatArray, groups: NDArray[np.int64], loo0: FloatArray
) -> tuple[float, float, float, FloatArray]:
    """Held-out errors without and with ``cols``, the paired z, and the squared held-out
    residuals with it (per condition)."""
    loo1 = _group_loo(_extend(u0, cols), b, groups)
    ok = np.isfinite(loo0) & np.isfinite(loo1)
    e0, e1 = loo0[ok] ** 2, loo1[ok] ** 2
    gain = e0 - e1
    n = int(ok.sum())
    se = float(np.std(gain, ddof=1) / math.sqrt(n)) if n > 1 else math.inf
    z = float(gain.mean() / se) if se > 0 and n else 0.0
    sq = np.where(ok, loo1**2, np.nan)
    return (float(e0.mean()) if n else math.inf), (float(e1.mean()) if n else math.inf), z, sq


def _shape_bounds(lib: Library, cand: Candidate) -> tuple[list[float], list[float]]:
    """Bounds of the refinable shape parameters: knots within the 5-95 % quantiles of the
    input, centres within its range (+-10 %), widths 3-60 % of the range."""
    lo: list[float] = []
    hi: list[float] = []
    for name in cand.inputs:
        x = lib.inputs[name]
        a, b_ = float(x.min()), float(x.max())
        span = b_ - a
        if cand.form in ("hinge_up", "hinge_down"):
            lo.append(float(np.quantile(x, 0.05)))
            hi.append(float(np.quantile(x, 0.95)))
        elif cand.form in ("bump", "bump2"):
            lo += [a - 0.1 * span, 0.03 * span]
            hi += [b_ + 0.1 * span, 0.6 * span]
    return lo, hi


def refine(lib: Library, cand: Candidate, u0: FloatArray, b: FloatArray) -> Candidate:
    """The candidate with its knot, centres and widths fitted by nonlinear least squares
    (the coefficients and the nuisance projected out); forms without refinable shape
    (slope, harmonic) unchanged."""
    if cand.form in FIXED_SHAPE:
        return cand
    from scipy.optimize import least_squares

    r = b - u0 @ (u0.T @ b)
    lo, hi = _shape_bounds(lib, cand)
    x0 = np.clip(np.asarray(cand.shape, dtype=float), lo, hi)

    def resid(theta: FloatArray) -> FloatArray:
        c = lib.values(dataclasses.replace(cand, shape=tuple(float(v) for v in theta)))
        pc = c - u0 @ (u0.T @ c)
        if float(np.sum(pc**2)) <= 1e-12:
            return r
        coef, *_ = np.linalg.lstsq(pc, r, rcond=None)
        out: FloatArray = r - pc @ coef
        return out

    span = np.asarray(hi) - np.asarray(lo)
    try:
        res = least_squares(resid, x0, bounds=(lo, hi), x_scale=span * 0.1, max_nfev=200)
    except ValueError:
        return cand
    if float(np.sum(res.fun**2)) >= float(np.sum(resid(x0) ** 2)):
        return cand
    return dataclasses.replace(cand, shape=tuple(float(v) for v in res.x))


def discover(
    lib: Library,
    b_ms: FloatArray,
    nuisance: FloatArray,
    *,
    pure_ms2: float,
    pure_df: float,
    alpha: float,
    min_share: float,
    max_terms: int = MAX_TERMS,
) -> list[Found]:
    """Forward selection of terms from ``lib`` for the residuals ``b_ms`` (ms) beyond the
    ``nuisance`` columns (module docstring). Returns the terms chosen, in order, with their
    shapes refined."""
    b = np.asarray(b_ms, dtype=float)
    u0 = _orth(nuisance)
    n = max(len(lib), 1)
    threshold = alpha / n
    found: list[Found] = []
    while len(found) < max_terms:
        _, f, p = _screen(lib, u0, b, pure_ms2, pure_df)
        order = [int(i) for i in np.argsort(p, kind="stable")[:HELD_OUT_TOP] if p[i] < threshold]
        if not order:
            break
        loo0 = _group_loo(u0, b, lib.groups)
        scored = []
        for i in order:
            cv0, cv1, z, sq = _held_out(u0, b, lib.columns[i], lib.groups, loo0)
            excess = max(cv0 - pure_ms2, 0.05 * cv0, 1e-12)
            share = float(min((cv0 - cv1) / excess, 1.0))
            ok = z >= 1.0 and share >= min_share and cv1 < cv0
            scored.append((i, cv0, cv1, z, share, sq, ok))
        passing = [s for s in scored if s[6]]
        if not passing:
            break
        best = min(passing, key=lambda s: s[2])
        same = []
        for s in passing:
            d = s[5] - best[5]
            d = d[np.isfinite(d)]
            se = float(np.std(d, ddof=1) / math.sqrt(len(d))) if len(d) > 1 else 0.0
            if len(d) and float(d.mean()) <= se:
                same.append(s)
        chosen = min(same, key=lambda s: (lib.candidates[s[0]].complexity, s[2]))
        i, cv0, cv1, z, share, _, _ = chosen
        grid = lib.candidates[i]
        cand = refine(lib, grid, u0, b)
        unc = term_uncertainty(lib, cand, b, u0, pure_ms2=pure_ms2)
        if len(cand.joints) > 1:
            # A shape shared by every joint: kept on the joints whose own size is
            # determined (the others carry none of it).
            keep = tuple(
                j
                for j, z in zip(cand.joints, unc["size_z_per_joint"], strict=True)
                if z >= MIN_SIZE_Z
            )
            if keep and keep != cand.joints:
                cand = dataclasses.replace(cand, joints=keep)
                unc = term_uncertainty(lib, cand, b, u0, pure_ms2=pure_ms2)
        cols = lib.values(cand)
        size_z = unc["size_z"]
        if size_z < MIN_SIZE_Z:
            # Significant at its grid point, but its size is not determined once its shape
            # is free (a bump at the edge of the sampled range, say): not a finding.
            break
        alternatives = [
            {
                "candidate": lib.candidates[s[0]].label,
                "p_value": float(p[s[0]]),
                "cv_mse_with_ms2": float(s[2]),
                "passed": bool(s[6]),
            }
            for s in sorted(scored, key=lambda s: s[2])[:6]
            if s[0] != i
        ]
        found.append(
            Found(
                candidate=cand,
                grid=grid,
                p_value=float(p[i]),
                f_statistic=float(f[i]),
                threshold=threshold,
                cv_mse_without_ms2=cv0,
                cv_mse_with_ms2=cv1,
                held_out_z=z,
                share=share,
                columns=cols,
                alternatives=alternatives,
            )
        )
        u0 = _extend(u0, cols)
    return _prune(lib, found, b, _orth(nuisance))


def _prune(lib: Library, found: list[Found], b: FloatArray, u_base: FloatArray) -> list[Found]:
    """Backward elimination after the forward steps: a term chosen early (a simple form
    within one standard error of the best) that a later, better term made redundant is
    dropped, the weakest first, while dropping it does not raise the held-out error
    (paired z of the per-condition held-out errors < 1, the entry criterion's bar)."""
    kept = list(found)
    while len(kept) > 1:
        full = _group_loo(
            _extend(u_base, np.column_stack([f.columns for f in kept])), b, lib.groups
        )
        zs = []
        for f in kept:
            rest = np.column_stack([g.columns for g in kept if g is not f])
            without = _group_loo(_extend(u_base, rest), b, lib.groups)
            d = without**2 - full**2
            d = d[np.isfinite(d)]
            se = float(np.std(d, ddof=1) / math.sqrt(len(d))) if len(d) > 1 else 0.0
            zs.append(float(d.mean()) / se if se > 0 else math.inf)
        weakest = int(np.argmin(zs))
        if zs[weakest] >= 1.0:
            break
        kept.pop(weakest)
    return kept


def merge_terms(
    lib: Library,
    found: list[Found],
    b_ms: FloatArray,
    nuisance: FloatArray,
) -> list[tuple[Candidate, list[Found]]]:
    """Terms of one form, inputs and direction found on different joints, merged into one
    term of those joints when one shape serves them all: a slope, a harmonic or a product
    always (no shape is fitted), a hinge or a bump when the shape refitted to all of them is within
    one standard error of the separate shapes, held out. Returns (candidate, the terms it
    merges) in the order found."""
    out: list[tuple[Candidate, list[Found]]] = []
    done: set[int] = set()
    b = np.asarray(b_ms, dtype=float)
    for f in found:
        if id(f) in done:
            continue
        c = f.candidate
        members = [f]
        for g in found:
            gc = g.candidate
            if (
                id(g) not in done
                and g is not f
                and (gc.form, gc.inputs, gc.direction) == (c.form, c.inputs, c.direction)
                and not set(gc.joints) & {j for m in members for j in m.candidate.joints}
            ):
                members.append(g)
        done.update(id(g) for g in members)
        if len(members) == 1:
            out.append((c, members))
            continue
        joints = tuple(sorted(j for g in members for j in g.candidate.joints))
        shared = dataclasses.replace(c, joints=joints)
        if c.form in FIXED_SHAPE:
            out.append((shared, members))
            continue
        others = [g.columns for g in found if g not in members]
        u_other = _orth(np.column_stack([nuisance, *others]) if others else nuisance)
        shared = refine(lib, shared, u_other, b)
        # One shape for all: kept when its held-out error is within one standard error
        # of the separate shapes' held-out error (the one-standard-error rule, Hastie,
        # Tibshirani & Friedman, Elements of Statistical Learning, 2nd ed., sec. 7.10: the
        # simplest model whose error is within one SE of the best's). The SE is that of
        # the best's error, not of the paired difference: at 3 ms against a 0.3 ms floor
        # the paired test told apart shapes of two joints 1.7 SE apart (d007 of seed
        # 2026) and kept two terms for one contact.
        loo_sep = _group_loo(
            _extend(u_other, np.column_stack([g.columns for g in members])), b, lib.groups
        )
        loo_one = _group_loo(_extend(u_other, lib.values(shared)), b, lib.groups)
        ok = np.isfinite(loo_one) & np.isfinite(loo_sep)
        e_sep, e_one = loo_sep[ok] ** 2, loo_one[ok] ** 2
        se = float(np.std(e_sep, ddof=1) / math.sqrt(len(e_sep))) if len(e_sep) > 1 else 0.0
        if len(e_sep) and float(e_one.mean()) <= float(e_sep.mean()) + se:
            out.append((shared, members))
        else:
            out += [(g.candidate, [g]) for g in members]
    return out


def nested_test(
    b_ms: FloatArray,
    base: FloatArray,
    extra: FloatArray,
    *,
    pure_ms2: float,
    pure_df: float,
) -> dict[str, float]:
    """Extra-sum-of-squares F test of the columns ``extra`` beyond ``base`` on ``b_ms``
    (over the larger of the pure error and the residual variance): F, df, p."""
    b = np.asarray(b_ms, dtype=float)
    u0 = _orth(base)
    u1 = _extend(u0, extra)
    r0 = b - u0 @ (u0.T @ b)
    r1 = b - u1 @ (u1.T @ b)
    k = max(u1.shape[1] - u0.shape[1], 1)
    f, p = _f_p(
        np.array([float(r0 @ r0 - r1 @ r1)]),
        k,
        float(r0 @ r0),
        len(b),
        u0.shape[1],
        pure_ms2,
        pure_df,
    )
    return {"f_statistic": float(f[0]), "df": float(k), "p_value": float(p[0])}


def term_uncertainty(
    lib: Library,
    cand: Candidate,
    b_ms: FloatArray,
    nuisance: FloatArray,
    *,
    pure_ms2: float,
) -> dict[str, Any]:
    """A term's coefficients (ms per unit of its basis), their standard errors and those of
    its refinable shape parameters, from the Gauss-Newton covariance at the fit of ``b_ms``
    on the ``nuisance`` columns and the term: the residual variance (at least the pure
    error) times (JᵀJ)⁻¹, J the sensitivities of the fitted means to the coefficients, the
    shape and the nuisance. ``size_z_per_joint``: each joint's size in standard errors
    (slope or peak; a harmonic's amplitude); ``size_z``: the largest."""
    b = np.asarray(b_ms, dtype=float)
    cols = lib.values(cand)
    a = np.column_stack([nuisance, cols])
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    p0 = nuisance.shape[1]
    beta = coef[p0:]
    refinable = cand.form not in FIXED_SHAPE
    jac_shape = []
    if refinable:
        lo, hi = _shape_bounds(lib, cand)
        for k in range(len(cand.shape)):
            h = 1e-4 * (hi[k] - lo[k])
            s = list(cand.shape)
            s[k] += h
            c1 = lib.values(dataclasses.replace(cand, shape=tuple(s)))
            jac_shape.append(((c1 - cols) @ beta) / h)
    j = np.column_stack([nuisance, cols, *jac_shape])
    res = b - a @ coef
    dof = max(len(b) - int(np.linalg.matrix_rank(j)), 1)
    sigma2 = max(float(res @ res) / dof, pure_ms2)
    cov = sigma2 * np.linalg.pinv(j.T @ j)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    k = cols.shape[1]
    cov_c = cov[p0 : p0 + k, p0 : p0 + k]
    per = k // len(cand.joints)
    z = []
    for i in range(len(cand.joints)):
        c = beta[i * per : (i + 1) * per]
        block = cov_c[i * per : (i + 1) * per, i * per : (i + 1) * per]
        size = float(np.hypot(*c)) if per == 2 else abs(float(c[0]))
        var = float(c @ block @ c) / size**2 if per == 2 and size > 0 else float(block[0, 0])
        z.append(size / math.sqrt(var) if var > 0 else 0.0)
    return {
        "coefficients_ms": [float(v) for v in beta],
        "coefficient_se_ms": [float(v) for v in se[p0 : p0 + k]],
        "shape_se": [float(v) for v in se[p0 + k :]] if refinable else [],
        "coefficient_cov_ms2": cov_c.tolist(),
        "size_z": max(z) if z else 0.0,
        "size_z_per_joint": z,
    }


def register_found(cand: Candidate) -> DataTerm:
    """The candidate as a data term registered at run time (zero coefficients; the
    calibration fits them)."""
    return register_term(
        joints=cand.joints,
        inputs=cand.inputs,
        form=cand.form,
        shape=cand.shape,
        direction=cand.direction,
    )
