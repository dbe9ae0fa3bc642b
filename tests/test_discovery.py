"""Discovery beyond the vocabulary (issue 36) on the independent family of
``discovery_cases.py``: effects no name of the vocabulary describes (cables, periodic drive
terms, local contacts in one or two angles, one-direction terms, terms two joints share,
another joint's gravity torque, steps and products the library does not hold), nulls and
vocabulary controls.

Three layers:

* the data term itself: what the batch simulator applies is its closed form;
* fixed cases end to end (fast suite, ~20 s): an out-of-vocabulary term discovered with
  the right joint, input and size and the gap closed, written as a formula, in words, in
  the JSON contract and in the report with its figure; a case the vocabulary used to be
  pinned on refused a name; a null and a control;
* the randomised family (``slow``; bounded for CI, every case with
  ``TIMEDEXEC_FULL_TESTS=1``) with the rates the issue asks for.

Every analysis runs with BLAS on one thread (as in test_discrepancy_independent.py: the
same result, several times faster in wall time on a shared two-core VM).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from conftest import full_or_bounded
from discovery_cases import DiscoveryCase, discovery_family, judge
from timedexec.cli import main as run_cli
from timedexec.discrepancy import DiscrepancyResult, analyse_discrepancy, deterministic_settings
from timedexec.effects import EFFECTS, DataTerm, EffectSet, Pose, register_term
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.sim import default_settings, simulate_delays

FAMILY_SEED = 36


@pytest.fixture(scope="module")
def family() -> dict[str, DiscoveryCase]:
    return {c.case_id: c for c in discovery_family(30, 10, 8, seed=FAMILY_SEED)}


_RESULTS: dict[str, DiscrepancyResult] = {}


def _run(case: DiscoveryCase) -> DiscrepancyResult:
    """The analysis of ``case`` (cached per session: several tests read one result)."""
    if case.case_id not in _RESULTS:
        with threadpool_limits(1):
            _RESULTS[case.case_id] = analyse_discrepancy(
                case.table(), start=case.start_effects, seed=0
            )
    return _RESULTS[case.case_id]


# ------------------------------------------------------------------ the data term
def test_simulator_applies_the_data_terms_closed_form():
    """A registered data term (a cable hinge on joint 3's positive direction) delays the
    batch simulator's actuation by exactly its formula: the simulated difference with and
    without it equals ``basis @ coef`` to the physics grid (the workflow's closed form is
    what a re-run applies)."""
    spec = get_robot("ur10")
    plan = SweepPlan.generate("ur10", 240, seed=4)
    t = np.arange(240, dtype=float)
    term = register_term(
        joints=(3,), inputs=("q5",), form="hinge_up", shape=(0.2,), direction=1
    ).with_coefficients(np.array([2.5e-3]))
    settings, _ = deterministic_settings(default_settings(spec))
    args = (spec, plan.q_start_rad, plan.joint, plan.direction, t)
    try:
        base = simulate_delays(*args, effects=EffectSet(), settings=settings, seed=1)
        with_term = simulate_delays(*args, effects=EffectSet((term,)), settings=settings, seed=1)
    finally:
        EFFECTS.unregister(term.name)
    pose = Pose(
        spec=spec,
        q_start_rad=plan.q_start_rad,
        joint=plan.joint,
        t_start_s=t,
        direction=plan.direction.astype(float),
    )
    want = term.drive_delay_s(pose)
    got = with_term["actuation_delay"] - base["actuation_delay"]
    assert np.any(want > 1e-3)  # the term is on somewhere (2.5 ms/rad beyond q5 = 0.2)
    # The onset is interpolated between physics samples, so a dead time that is not a
    # multiple of the step moves it by the delay to within the interpolation's error
    # (measured 6 µs at most here); 20 µs is a hundredth of the term's size.
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert isinstance(term, DataTerm)
    assert term.data_driven


# ------------------------------------------------------------------ fixed cases
def test_periodic_drive_term_is_discovered_with_its_size(family):
    """d012: 4.6 ms · sin(3 q2 + 2.9) on joint 3, from base timing (a periodic drive term
    the vocabulary cannot express): nothing named; one term on joint 3 following q2 in the
    harmonic form of order 3, its amplitude within 20 % of the generator's, the actuation
    gap closed to the noise floor (<= 1.25 x); in words and as a formula."""
    case = family["d012"]
    result = _run(case)
    verdict = judge(case, result)
    assert verdict.right, verdict.reasons
    assert result.added_effects == []
    [term] = result.discovered
    assert term.joints == [3]
    assert term.inputs == ["q2"]
    assert term.effect.form == "harmonic"
    assert term.effect.shape == (3.0,)
    # The size is a least-squares amplitude over 320 condition means at ~0.4 ms each:
    # its standard error is ~0.05 ms, so 20 % (0.9 ms) is the bound, not noise.
    assert verdict.size_error is not None
    assert verdict.size_error <= 0.2
    assert "joint 3's actuation delay varies by" in term.description
    assert "sin(3 q2" in term.formula
    assert term.gap_closed_ms > 0.5 * (result.gap_before_ms["actuation_delay"])


def test_a_name_the_vocabulary_would_pin_is_refused(family):
    """d042: the gravity torque of joint 5 drives joints 2 and 3 (a load path through a
    shared cable): inertia, thermal drift and joint offsets pass their own tests on these
    residuals, but a data-driven term explains what each would, and more, so none is
    named; the term is discovered on joints 2 and 3 following tau5 and closes the gap."""
    case = family["d042"]
    result = _run(case)
    verdict = judge(case, result)
    assert verdict.right, verdict.reasons
    assert result.added_effects == []
    refused = [r for r in result.rejected if "vocabulary_check" in r.get("rejected_because", "")]
    assert refused, "the acceptance test must have refused at least one name"
    assert any(t.inputs == ["tau5"] and {2, 3} <= set(t.joints) for t in result.discovered)


def test_null_names_and_discovers_nothing(family):
    """d011: nothing hidden (UR5e, base timing): no name, no discovered term, nothing
    unexplained; the gap stays at the floor."""
    result = _run(family["d011"])
    assert result.added_effects == []
    assert result.discovered == []
    assert result.unexplained == []


def test_vocabulary_control_is_named_and_nothing_discovered(family):
    """d006: gravity_load left out of the default model: it is named (a vocabulary effect
    explains the residuals at least as well as any data term) and nothing is discovered."""
    case = family["d006"]
    result = _run(case)
    verdict = judge(case, result)
    assert verdict.right, verdict.reasons
    assert result.added_effects == ["gravity_load"]
    assert result.discovered == []


def test_json_contract_and_report_figure(family, tmp_path, capsys):
    """The command on a table with a two-angle contact (d001, local bump in q4 and q2 on
    joint 1's positive direction): OUT.json lists it under ``discovered`` with joints,
    inputs, formula, gap_closed_ms and evidence; ``added_effects`` stays empty (vocabulary
    names only) and ``gap_after_ms`` counts the discovered term (below the gap before);
    the report has its section and its figure (residual against each input)."""
    case = family["d001"]
    assert case.start_label == "base"
    csv = case.table().to_csv(tmp_path / "measured.csv")
    out = tmp_path / "out.json"
    report = tmp_path / "report"
    with threadpool_limits(1):
        code = run_cli(
            ["discrepancy", str(csv), "--start", "base", "--json", str(out),
             "--report", str(report), "--quiet"]
        )  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "discovered (outside the vocabulary)" in text
    doc = json.loads(out.read_text())
    assert doc["added_effects"] == []
    [d] = doc["discovered"]
    assert {"joints", "inputs", "formula", "gap_closed_ms", "evidence"} <= set(d)
    assert d["joints"] == [1]
    assert set(d["inputs"]) == {"q2", "q4"}
    assert d["gap_closed_ms"] > 0
    assert d["evidence"]["p_value"] < d["evidence"]["library_size_threshold_p"]
    a = "actuation_delay"
    # Gap after with the term: at the floor (1.25 x), far below the gap before.
    assert doc["gap_after_ms"][a] <= 1.25 * doc["noise_floor_ms"][a]
    assert doc["gap_after_ms"][a] < 0.7 * doc["gap_before_ms"][a]
    # The re-run through the batch simulator shows the same gap as the closed form (to the
    # physics grid: 0.125 ms at worst per condition, far less in the RMS).
    assert abs(d["gap_after_resimulated_ms"][a] - d["gap_after_ms"][a]) < 0.05
    md = (report / "report.md").read_text()
    assert "## Discovered outside the vocabulary" in md
    assert "![discovered term 1](discovered1.png)" in md
    assert (report / "discovered1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------ the family
def _outcome(case: DiscoveryCase) -> tuple[str, str, bool, bool, float | None, float, str]:
    with threadpool_limits(1):
        result = analyse_discrepancy(case.table(), start=case.start_effects, seed=0)
    v = judge(case, result)
    return (
        case.kind,
        case.describe(),
        v.right,
        v.pinned,
        v.size_error,
        result.runtime_s,
        "; ".join(v.reasons),
    )


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_family_rates():
    """A randomised family (issue 36's acceptance): out of vocabulary, right (no name, a
    discovered term containing the true joints and inputs, actuation gap after <= 1.25 x
    the floor or <= 0.4 x the gap before) in >= 80 %; nulls name and discover nothing in
    all but at most one of 8 (here: all); controls named right with nothing discovered;
    the discovered size within 20 % where the form is in the library. Misses are listed
    in the failure message.

    Bounded form (CI, ~1.5 min on two busy cores): a family of its own seed, 10 out of
    vocabulary, 3 nulls and 3 controls, at most 2 outside misses (the 80 % over 10) and
    none among nulls and controls. ``TIMEDEXEC_FULL_TESTS=1``: 30 / 8 / 8 (as the
    benchmark, ~5 min)."""
    from joblib import Parallel, delayed

    n_out, n_null, n_ctl = full_or_bounded((30, 8, 8), (10, 3, 3))
    cases = discovery_family(n_out, n_null, n_ctl, seed=full_or_bounded(36, 3601))
    outcomes = Parallel(n_jobs=2, batch_size=1)(delayed(_outcome)(c) for c in cases)
    per_kind: dict[str, list[bool]] = defaultdict(list)
    misses, sizes = [], []
    for kind, described, right, _, size_error, _, why in outcomes:
        per_kind[kind].append(right)
        if size_error is not None:
            sizes.append(size_error)
        if not right:
            misses.append(f"{described} -> {why}")
    rate = {k: sum(v) / len(v) for k, v in per_kind.items()}
    detail = f"{len(cases)} cases, per kind {rate}; size errors {sizes}; misses:\n"
    detail += "\n".join(misses)
    assert rate["outside"] >= 0.8, detail
    # Nulls: all right in the bounded form (3); at most one miss in 8 or more (the issue).
    n_null = len(per_kind["null"])
    assert sum(per_kind["null"]) >= n_null - (n_null >= 8), detail
    assert rate["control"] == 1.0, detail
    assert sizes, detail
    assert all(e <= 0.2 for e in sizes), detail
    assert all(math.isfinite(o[5]) for o in outcomes)
