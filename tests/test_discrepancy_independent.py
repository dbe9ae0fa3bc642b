"""The discrepancy workflow on cases it was not built on (``discrepancy_cases.py``).

Three layers:

* the generator itself: every hidden form has the size it was drawn with, acts where it
  says, and is made without the simulator's physics;
* the structure search on synthetic residuals (no simulator, milliseconds): interactions
  named as one effect, main effects kept only where they add, a step in time on one
  joint named as time x joint, noise named as nothing;
* the workflow end to end on a fixed subset of the randomised family (fast suite, about
  30 s), and on the rest of the family of 60 cases (``slow``, two worker processes, about
  1 min on two cores; every case with ``TIMEDEXEC_FULL_TESTS=1``): fully right >= 90 %
  overall, interaction and time-beside-load cases >= 85 % each (issue 17).

Every analysis runs with BLAS on one thread (:func:`_run`), as the model fits do
(``timedexec.learning._threads``): OpenBLAS's two threads spinning for a core that another
process holds made one case 4-5x slower in wall time on a shared two-core VM (c003: 67 s
against 15 s; 1.5x the CPU), for the same result.
"""

from __future__ import annotations

import ast
import inspect
import math
from collections import defaultdict

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

import discrepancy_cases as dc
from conftest import full_or_bounded
from discrepancy_cases import (
    FORMS,
    KINDS,
    OUTSIDE_FORMS,
    Case,
    case_family,
    fast_subset,
    judge,
    make_context,
    make_hidden,
)
from timedexec.delays import REQUIRED_COLUMNS, DelayTable
from timedexec.discrepancy import (
    actuation_families,
    analyse_discrepancy,
    forward_select,
    group_conditions,
)
from timedexec.effects import EffectSet
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot, gravity_torque, joint_inertia

FAMILY_SEED = 2024
FAMILY_SIZE = 60


@pytest.fixture(scope="module")
def family() -> list[Case]:
    return case_family(FAMILY_SIZE, seed=FAMILY_SEED)


# ------------------------------------------------------------------ the generator
def _context(robot: str = "ur10", n: int = 1600, seed: int = 3) -> dc.Context:
    plan = SweepPlan.generate(robot, n, seed=seed)
    t = 10.0 + np.arange(n, dtype=float) * 1.2
    return make_context(plan, t, get_robot(robot).controller_period_s)


@pytest.mark.parametrize(
    "form", [f for forms in FORMS.values() for f in forms] + list(OUTSIDE_FORMS)
)
def test_every_hidden_form_has_its_size_and_place(form):
    """Each form's term has the RMS about its mean it was drawn with (to rounding), acts
    only on its joints and its delay, and carries its vocabulary name (None outside)."""
    ctx = _context()
    h = make_hidden(form, np.random.default_rng(5), joints=ctx.joints, size_ms=1.7, period_s=0.008)
    term = h.term_s(ctx) * 1e3
    assert term.shape == ctx.joint.shape
    assert np.all(np.isfinite(term))
    if form == "response_cycles":
        assert np.allclose(term, h.size_ms)  # whole periods
        assert h.size_ms in (8.0, 16.0)
    elif form == "sequence_first_repeat":
        assert np.allclose(term[ctx.repeat == 0], 1.7)
        assert np.all(term[ctx.repeat > 0] == 0)
    else:
        assert math.sqrt(np.mean((term - term.mean()) ** 2)) == pytest.approx(1.7, rel=1e-9)
    off = ~np.isin(ctx.joint, h.joints)
    if off.any() and form != "sequence_first_repeat":
        assert np.allclose(term[off], term[off][0])  # nothing varies where it does not act
    expected = next((n for n, forms in FORMS.items() if form in forms), None)
    assert h.name == expected
    assert (h.delay == "response_delay") == (form.startswith("response"))


def test_hidden_effects_are_made_without_the_simulator():
    """The hidden terms come from the robot's kinematics (``timedexec.robots``) and the
    generator's own formulas: nothing in ``make_hidden`` or the context refers to the
    simulator (only the base of a table, the start model, is simulated)."""
    for fn in (make_hidden, make_context, dc._scaled, dc._gains):
        tree = ast.parse(inspect.getsource(fn).lstrip())
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        names |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        assert not any("sim" in x.lower() and x != "size_ms" for x in names), (fn, names)


def test_case_table_is_the_base_plus_the_hidden_terms(family):
    """A case's table is a delay table with the contract's columns and 10 repeats per
    condition; without its hidden effects (and scatter) it is the start model's
    simulation, and the difference is exactly the hidden terms."""
    case = next(c for c in family if c.kind == "pair")
    table = case.table()
    assert isinstance(table, DelayTable)
    assert all(c in table for c in REQUIRED_COLUMNS)
    cond = group_conditions(table)
    assert np.all(cond.n == 10)
    plain = Case(**{**case.__dict__, "hidden": (), "extra_noise_ms": 0.0}).table()
    noiseless = Case(**{**case.__dict__, "extra_noise_ms": 0.0}).table()
    plan = SweepPlan.generate(case.robot, case.n_trials, seed=case.seed)
    ctx = make_context(plan, table["t_start"], get_robot(case.robot).controller_period_s)
    for d in ("actuation_delay", "response_delay"):
        want = sum((h.term_s(ctx) for h in case.hidden if h.delay == d), np.zeros(len(table)))
        np.testing.assert_allclose(noiseless[d] - plain[d], want, atol=1e-12)


def test_family_is_reproducible_balanced_and_varied(family):
    """The same seed gives the same family; every kind has a sixth of the cases; robots,
    start models and forms vary."""
    again = case_family(FAMILY_SIZE, seed=FAMILY_SEED)
    assert [c.describe() for c in again] == [c.describe() for c in family]
    other = case_family(FAMILY_SIZE, seed=FAMILY_SEED + 1)
    assert [c.describe() for c in other] != [c.describe() for c in family]
    counts = defaultdict(int)
    for c in family:
        counts[c.kind] += 1
    assert set(counts) == set(KINDS)
    assert all(v == FAMILY_SIZE // len(KINDS) for v in counts.values())
    assert {c.robot for c in family} == {"ur10", "ur10e", "kr5"}
    assert {c.start_label for c in family} == {"base", "default"}
    forms = {h.form for c in family for h in c.hidden}
    assert len(forms) >= 15


# ------------------------------------------------------------------ the structure search
@pytest.fixture(scope="module")
def synthetic() -> dict[str, object]:
    """Conditions of a 2,400-trial UR10 sweep and their variables (no simulation)."""
    spec = get_robot("ur10")
    plan = SweepPlan.generate(spec, 2400, seed=4)
    t = 10.0 + np.arange(len(plan), dtype=float) * 1.2
    table = DelayTable(
        {
            "trial": np.arange(len(plan)),
            "robot": "ur10",
            "joint": plan.joint,
            "direction": plan.direction,
            **{f"q{i + 1}": plan.q_start_rad[:, i] for i in range(6)},
            "t_start": t,
            "actuation_delay": np.zeros(len(plan)),
            "response_delay": np.zeros(len(plan)),
        }
    )
    cond = group_conditions(table)
    rows = np.arange(len(cond))
    tau = gravity_torque(spec, cond.q_rad)[rows, cond.joint - 1]
    inertia = joint_inertia(spec, cond.q_rad)[rows, cond.joint - 1]
    home = np.asarray(spec.home_q_rad, dtype=float)[None, :]
    nominal = joint_inertia(spec, home)[0][cond.joint - 1]
    return {"cond": cond, "tau": tau, "inertia": inertia, "nominal": nominal}


def _select(synthetic: dict[str, object], signal_ms: np.ndarray, seed: int = 0) -> list[str]:
    """Forward selection on ``signal_ms`` plus noise of 0.7 ms (a UR10 noise floor)."""
    cond = synthetic["cond"]
    sigma = 0.7
    b = signal_ms + np.random.default_rng(seed).normal(0.0, sigma, len(signal_ms))
    fams = actuation_families(
        cond,  # type: ignore[arg-type]
        gravity_torque_nm=synthetic["tau"],  # type: ignore[arg-type]
        inertia_kgm2=synthetic["inertia"],  # type: ignore[arg-type]
        nominal_inertia_kgm2=synthetic["nominal"],  # type: ignore[arg-type]
        present=(),
        resid_ms=b,  # as the workflow does: the time families' change points
    )
    sel = forward_select(b, np.ones((len(b), 1)), fams, pure_ms2=sigma**2, pure_df=len(b) * 9.0)
    return sel.selected


def _per_joint_max(cond, x):
    out = np.ones(len(x))
    for j in cond.joints:
        mk = cond.joint == j
        out[mk] = max(float(np.max(np.abs(x[mk]))), 1e-12)
    return out


def test_direction_x_load_is_named_as_one_effect(synthetic):
    """Lifting later than lowering, in proportion to the load (d·τ_g): one interaction
    (direction_x_load), not direction + load + per-joint offsets."""
    cond, tau = synthetic["cond"], synthetic["tau"]
    v = cond.direction * tau / _per_joint_max(cond, tau)
    assert _select(synthetic, 2.5 * v) == ["direction_x_load"]


def test_lifting_only_keeps_the_main_effect_beside_the_interaction(synthetic):
    """Only lifting is slower: max(d·τ_g, 0) = (|τ_g| + d·τ_g) / 2 is an interaction *and*
    half a load main effect; the hierarchy rule keeps both, nothing else."""
    cond, tau = synthetic["cond"], synthetic["tau"]
    v = cond.direction * tau / _per_joint_max(cond, tau)
    assert set(_select(synthetic, 4.0 * np.maximum(v, 0.0))) == {"direction_x_load", "load"}


def test_time_on_one_joint_is_time_x_joint_not_time_plus_offset(synthetic):
    """Joint 2 alone warms up (a step down at 40 % of the sweep): the interaction time x
    joint, not a time effect on every joint plus a joint offset."""
    cond = synthetic["cond"]
    s = (cond.t_start_s - cond.t_start_s.min()) / np.ptp(cond.t_start_s)
    signal = 3.0 * ((s < 0.4) & (cond.joint == 2))
    assert _select(synthetic, signal) == ["time_x_joint"]


def test_offset_and_direction_are_two_main_effects(synthetic):
    """A joint offset on joint 3 and one direction asymmetry on every joint: the two main
    effects, not their interaction."""
    cond = synthetic["cond"]
    signal = 2.0 * (cond.joint == 3) + 1.5 * cond.direction
    assert set(_select(synthetic, signal)) == {"joint", "direction"}


def test_an_angle_on_one_joint_is_outside_the_vocabulary(synthetic):
    """Joint 2 later by 1 ms per rad of q5: first the family outside the vocabulary on
    that joint, and nothing of the vocabulary. (A slope over q5 in ±3 rad is a sawtooth
    to two harmonics: what they leave may be taken by other angles on joint 2.)"""
    cond = synthetic["cond"]
    selected = _select(synthetic, 1.0 * cond.q_rad[:, 4] * (cond.joint == 2))
    assert selected[0] == "q5@joint2"
    assert all(k.startswith("q") and k.endswith("@joint2") for k in selected)


@pytest.mark.parametrize("seed", range(5))
def test_noise_selects_nothing(synthetic, seed):
    """Pure noise at the floor: no family passes (each step is tested at 1 % family-wise
    for the vocabulary and 1 % for the rest; five seeds)."""
    assert _select(synthetic, np.zeros(len(synthetic["cond"])), seed=seed) == []


# ------------------------------------------------------------------ the workflow
def _run(case: Case):
    with threadpool_limits(limits=1, user_api="blas"):
        result = analyse_discrepancy(case.table(), start=case.start_effects)
    return result, judge(case, result)


def _outcome(case_id: str) -> tuple[str, str, bool, str]:
    """Run one case of the family in a worker process: (kind, description, fully right,
    what a miss named and why). Takes the case's id (a case holds closures, which do not
    pickle); the worker draws the same seeded family."""
    case = next(c for c in case_family(FAMILY_SIZE, seed=FAMILY_SEED) if c.case_id == case_id)
    result, verdict = _run(case)
    why = f"{result.added_effects}: {verdict.reasons}"
    return case.kind, case.describe(), verdict.fully_right, why


FAST = [c.case_id for c in fast_subset(case_family(FAMILY_SIZE, seed=FAMILY_SEED), per_kind=2)]


@pytest.mark.parametrize("case_id", FAST)
def test_fixed_subset_is_fully_right(family, case_id):
    """Two cases of each kind, the first of the family (not chosen by outcome): each one
    fully right — every hidden effect named with at most one extra, gap at most 1.25 x
    the floor or halved, a null names nothing, an effect outside the vocabulary is
    reported unexplained where it sits."""
    case = next(c for c in family if c.case_id == case_id)
    result, verdict = _run(case)
    assert verdict.fully_right, (case.describe(), result.added_effects, verdict.reasons)


def test_first_repeat_effect_is_found_in_the_order_of_the_repeats():
    """The first repeat of every condition 3 ms later: condition means cannot show it (a
    constant); the search over the order of the repeats reports it as unexplained, names
    no effect, and says which repeat."""
    robot = "ur10"
    h = make_hidden(
        "sequence_first_repeat",
        np.random.default_rng(1),
        joints=(1, 2, 3, 5),
        size_ms=3.0,
        period_s=0.008,
    )
    case = Case("seq", "outside", robot, 1600, 77, EffectSet(), "base", (h,))
    result, verdict = _run(case)
    assert result.added_effects == []
    seq = [u for u in result.unexplained if "sequence" in u]
    assert len(seq) == 1
    effects = seq[0]["sequence"]["position_effects_ms"]
    # 3 ms on the first of 10 repeats: +2.7 ms against the mean, -0.3 ms for the others
    # (each estimated from 160 conditions to ~0.2 ms).
    assert effects[0] == pytest.approx(2.7, abs=0.6)
    assert "first repeat" in seq[0]["description"]
    assert verdict.fully_right


def test_report_of_an_interaction_case_has_evidence_size_and_gap(family):
    """Per named effect: its evidence (the structural family, held-out errors and z, F
    test, the parts the hierarchy rule kept), its size (ms RMS) and the gap it closes;
    the JSON stays finite and keeps the earlier keys."""
    import json

    case = next(
        c
        for c in family
        if c.kind == "interaction" and any(h.form.startswith("lift") for h in c.hidden)
    )
    result, _ = _run(case)
    doc = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert "gravity_direction" in doc["added_effects"]
    step = next(s for s in doc["steps"] if s["effect"] == "gravity_direction")
    ev = step["evidence"]
    for key in ("family", "held_out_z", "cv_mse_without_ms2", "cv_mse_with_ms2", "p_value", "kept"):
        assert key in ev
    assert ev["cv_mse_with_ms2"] < ev["cv_mse_without_ms2"]
    assert step["size_ms"] > 0.5
    assert step["gap_after_ms"]["actuation_delay"] < step["gap_before_ms"]["actuation_delay"]
    assert 0 < step["share_of_excess_gap_explained"] <= 1
    for key in (
        "added_effects",
        "gap_before_ms",
        "gap_after_ms",
        "unexplained",
        "final_candidates",
    ):
        assert key in doc
    assert "final_structure" in doc


# ------------------------------------------------------------------ the whole family
@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_family_rates(family):
    """The randomised family of 60 independent cases (issue 17): fully right >= 90 %
    overall, >= 85 % of the interaction and of the time-beside-load cases; the misses are
    listed in the failure message.

    Bounded form (CI): the 48 cases outside the fast subset, at the same thresholds. The 12
    of the fast subset are each asserted fully right by test_fixed_subset_is_fully_right in
    the fast tier, which .ci/run runs first and which stops it on a failure; running them
    again here repeated a quarter of the work (43 of 170 CPU-s on a shared VM). The bound
    carries over to the family: at most 4 misses in the 48 (>= 90 %) and 0 in the 12 is
    >= 56/60 = 93 % overall; at most 1 miss in a kind's 8 (>= 85 %: 7/8) and 0 in its 2 is
    >= 9/10 per kind, and a null case must be right in both. With TIMEDEXEC_FULL_TESTS=1
    all 60 run here. The cases run in two worker processes (the same analysis, each on one
    BLAS thread), as the learning tests' sweeps and CV do with jobs=2."""
    from joblib import Parallel, delayed

    fast = set(FAST)
    cases = [c.case_id for c in family if full_or_bounded(True, c.case_id not in fast)]
    # one case per task: case costs range from 1 to 15 s, so batches would unbalance
    outcomes = Parallel(n_jobs=2, batch_size=1)(delayed(_outcome)(c) for c in cases)
    per_kind: dict[str, list[bool]] = defaultdict(list)
    misses = []
    for kind, described, right, why in outcomes:
        per_kind[kind].append(right)
        if not right:
            misses.append(f"{described} -> {why}")
    assert set(per_kind) == set(KINDS)
    rate = {k: sum(v) / len(v) for k, v in per_kind.items()}
    overall = sum(sum(v) for v in per_kind.values()) / len(cases)
    detail = f"{len(cases)} cases: overall {overall:.2f}, per kind {rate}; misses:\n"
    detail += "\n".join(misses)
    assert overall >= 0.90, detail
    assert rate["interaction"] >= 0.85, detail
    assert rate["time_beside_load"] >= 0.85, detail
    assert rate["null"] == 1.0, detail


def test_report_explains_the_structural_evidence(family, tmp_path):
    """The markdown report of a time-beside-load case says how each effect was found (the
    family, the parts it was preferred to, the held-out z, leave-one-condition-out CV)
    and lists the effects the start model had whose form was refined."""
    case = next(c for c in family if c.case_id in FAST and c.kind == "time_beside_load")
    result, _ = _run(case)
    text = result.write_report(tmp_path / "rep").read_text(encoding="utf-8")
    assert "the structural search over main effects and interactions" in text
    for step in result.steps:
        assert f"family *{step.evidence['family_label']}*" in text
    assert "leave one condition out" in text
    if result.refined_effects:
        assert "## Effects refined" in text
        for r in result.refined_effects:
            assert f"| {r['effect']} | {r['family_label']} |" in text
