"""Discrepancy workflow: conditions and noise floor, the simulator as the model, naming a
hidden effect on small tables, bad input, the command line and its outputs.

The end-to-end matrix (every effect hidden in turn, two hidden, effects outside the
vocabulary, the KR 5) is in ``test_discrepancy_hidden.py`` (slow).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from timedexec.delays import DelayTable
from timedexec.discrepancy import (
    SimModel,
    analyse_discrepancy,
    calibrate,
    deterministic_settings,
    group_conditions,
    replicate_noise,
)
from timedexec.effects import EFFECT_NAMES, EffectSet, GravityLoad, default_effects, make_effect
from timedexec.errors import ConfigError
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.sim import default_settings, simulate_delays


def make_table(
    robot: str,
    n_trials: int,
    effects: EffectSet,
    *,
    seed: int = 1,
    repeats: int = 10,
    extra_actuation_s: Callable[[SweepPlan], np.ndarray] | None = None,
) -> DelayTable:
    """A measured table as a sweep produces it: each condition repeated ``repeats`` times
    in a row (same configuration, joint and direction; later sweep times), true delays of
    the simulator with ``effects`` on, plus an optional actuation term of our own."""
    plan = SweepPlan.generate(robot, n_trials, seed=seed, repeats=repeats)
    new_config = np.r_[True, plan.config_index[1:] != plan.config_index[:-1]]
    # About 1 s per trial and 3 s per move to a new configuration, as sweep_clock lays out.
    t_start = 10.0 + np.cumsum(1.0 + np.where(new_config, 3.0, 0.0))
    table = simulate_delays(
        robot, plan.q_start_rad, plan.joint, plan.direction, t_start, effects=effects, seed=seed
    )
    if extra_actuation_s is None:
        return table
    cols = dict(table.columns)
    cols["actuation_delay"] = cols["actuation_delay"] + extra_actuation_s(plan)
    return DelayTable(cols, source="test table with an extra actuation term")


def _all_finite(obj: Any) -> bool:
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(_all_finite(v) for v in obj.values())
    if isinstance(obj, list):
        return all(_all_finite(v) for v in obj)
    return True


def run_cli(argv: list[str]) -> int:
    """The ``timedexec`` command line, in process."""
    from timedexec.cli import main

    return main(argv)


@pytest.fixture(scope="module")
def base_table() -> DelayTable:
    return make_table("ur10", 1200, EffectSet(), seed=3)


@pytest.fixture(scope="module")
def gravity_table() -> DelayTable:
    return make_table("ur10", 2000, EffectSet((GravityLoad(),)), seed=4)


# ------------------------------------------------------------------ conditions, noise
def test_group_conditions_means_and_variances(base_table):
    """Conditions are the distinct (configuration, joint, direction); their means and
    sample variances are those of the repeats, in sweep order."""
    cond = group_conditions(base_table)
    assert len(cond) == 120  # 1200 trials / 10 repeats
    assert np.all(cond.n == 10)
    rows = cond.row_condition == 0
    act = base_table["actuation_delay"][rows]
    assert cond.mean_s["actuation_delay"][0] == pytest.approx(act.mean(), rel=1e-12)
    assert cond.var_s2["actuation_delay"][0] == pytest.approx(act.var(ddof=1), rel=1e-9)
    assert np.all(np.diff(cond.t_start_s) > 0)  # the sweep's order is kept
    assert cond.joints == (1, 2, 3, 5)


def test_group_conditions_drops_flagged_and_rejects_mixed_robots(base_table):
    """Flagged trials and NaN delays are left out and counted; a table of two robots
    needs --robot."""
    cols = dict(base_table.columns)
    cols["flag"] = np.array(
        ["onset_not_found" if i % 50 == 0 else "" for i in range(len(base_table))], dtype=object
    )
    act = cols["actuation_delay"].copy()
    act[1] = np.nan
    cols["actuation_delay"] = act
    cond = group_conditions(DelayTable(cols))
    assert cond.n_dropped == 24 + 1
    assert cond.n_trials == 1200 - 25
    robots = np.array(["ur10"] * 600 + ["kr5"] * 600, dtype=object)
    mixed = DelayTable({**base_table.columns, "robot": robots})
    with pytest.raises(ConfigError, match="pick one with --robot"):
        group_conditions(mixed)
    assert len(group_conditions(mixed, robot="ur10")) == 60


def test_noise_floor_is_the_gap_of_pure_error(base_table):
    """noise floor = sqrt(mean_i s_i²/n_i); and it is what the gap of two independent
    replicate means of the same conditions gives, divided by sqrt 2."""
    cond = group_conditions(base_table)
    noise = replicate_noise(cond)
    for d in ("actuation_delay", "response_delay"):
        expected = math.sqrt(np.mean(cond.var_s2[d] / cond.n))
        assert noise.floor_s[d] == pytest.approx(expected, rel=1e-12)
    assert noise.source == "replicates"
    assert noise.df == 120 * 9
    # UR10: intake waits uniformly over one 8 ms period -> trial sd ~ 8/sqrt(12) = 2.3 ms;
    # floor ~ 2.3/sqrt(10) = 0.73 ms. 120 conditions estimate it to a few per cent.
    assert 0.6e-3 < noise.floor_s["actuation_delay"] < 0.85e-3


def test_too_few_repeats_raise_without_fallback():
    """A table without repeats cannot give a pure-error noise floor: ConfigError saying
    what to do, unless a fallback variance is given."""
    table = make_table("ur10", 200, EffectSet(), seed=5, repeats=1)
    cond = group_conditions(table)
    with pytest.raises(ConfigError, match=r"too few repeats.*Repeat each condition"):
        replicate_noise(cond)
    noise = replicate_noise(cond, fallback_var_s2={"actuation_delay": 4e-6, "response_delay": 4e-6})
    assert noise.source.startswith("fallback")
    assert noise.floor_s["actuation_delay"] == pytest.approx(2e-3)  # sqrt(4e-6 / 1)


# ------------------------------------------------------------------ the model
def test_linear_effects_are_additive():
    """joint_offset shifts the actuation delay of each joint by exactly its offset and
    response_extra_cycle the response delay by whole periods, as the model applies them
    in closed form (to the simulator's 0.25 ms physics grid and 20 µs host noise)."""
    spec = get_robot("ur10")
    settings, _ = deterministic_settings(default_settings(spec))
    plan = SweepPlan.generate(spec, 64, seed=2, repeats=1)
    t = np.arange(64) * 5.0
    args = (spec, plan.q_start_rad, plan.joint, plan.direction, t)
    base = simulate_delays(*args, effects=EffectSet(), settings=settings, seed=1)
    offsets = (0.0, 0.004, 0.002, 0.001, 0.003, 0.0)
    shifted = simulate_delays(
        *args,
        effects=EffectSet((make_effect("joint_offset", offsets_s=offsets),)),
        settings=settings,
        seed=1,
    )
    diff = shifted["actuation_delay"] - base["actuation_delay"]
    np.testing.assert_allclose(diff, np.asarray(offsets)[plan.joint - 1], atol=2e-4)
    extra = simulate_delays(
        *args,
        effects=EffectSet((make_effect("response_extra_cycle", cycles=2),)),
        settings=settings,
        seed=1,
    )
    np.testing.assert_allclose(
        extra["response_delay"] - base["response_delay"], 2 * spec.controller_period_s, atol=1e-9
    )
    np.testing.assert_allclose(extra["actuation_delay"], base["actuation_delay"], atol=1e-9)


def test_model_predicts_condition_means_to_the_noise_floor():
    """One deterministic simulation per condition predicts the mean of the condition's
    random-timing repeats up to a constant: measured-minus-model scatters like pure error
    (RMS within 0.85-1.2 x the noise floor; 150 conditions estimate an RMS to ~6 %)."""
    table = make_table("ur10", 1500, default_effects("ur10"), seed=6)
    cond = group_conditions(table)
    noise = replicate_noise(cond)
    model = SimModel(get_robot("ur10"), cond)
    fitted = calibrate(model, default_effects("ur10"), fit_simulated=False)
    for d in ("actuation_delay", "response_delay"):
        ratio = fitted.gap_s(d) / noise.floor_s[d]
        assert 0.85 < ratio < 1.2, (d, ratio)


def test_calibration_recovers_a_physical_parameter():
    """Data with gravity_load friction_per_load = 0.35 N·m/N·m, model started at the
    vocabulary's 0.2: the calibration finds 0.35 within 0.07 (a 2,000-trial table
    determines it to about ±0.03, the 0.25 ms physics grid adds a little)."""
    truth = GravityLoad(friction_per_load=0.35)
    table = make_table("ur10", 2000, EffectSet((truth,)), seed=7)
    cond = group_conditions(table)
    model = SimModel(get_robot("ur10"), cond)
    fitted = calibrate(model, EffectSet((GravityLoad(),)))
    got = fitted.effects.get("gravity_load").friction_per_load
    assert got == pytest.approx(0.35, abs=0.07)
    assert fitted.parameters()["effects"][0]["name"] == "gravity_load"


# ------------------------------------------------------------------ the workflow
def test_hidden_gravity_load_is_named_and_closes_the_gap(gravity_table):
    """Base-timing data plus gravity_load, analysed from base: gravity_load is named,
    first and alone, in words with its variable and units, and the actuation gap falls to
    within 25 % of the noise floor."""
    result = analyse_discrepancy(gravity_table, start="base")
    assert result.added_effects == ["gravity_load"]
    step = result.steps[0]
    assert "per N·m" in step.explanation
    assert "explains" in step.explanation
    assert step.parameters["friction_per_load"] == pytest.approx(0.2, abs=0.07)
    floor = result.noise_floor_ms["actuation_delay"]
    assert result.gap_before_ms["actuation_delay"] > 1.05 * floor
    assert result.gap_after_ms["actuation_delay"] <= 1.25 * floor
    assert result.unexplained == []


def test_nothing_hidden_nothing_named(base_table):
    """Data from exactly the start model: no effect is named, nothing is unexplained and
    the gap is at the noise floor."""
    result = analyse_discrepancy(base_table, start="base")
    assert result.added_effects == []
    assert result.steps == []
    assert result.unexplained == []
    for d, floor in result.noise_floor_ms.items():
        assert result.gap_after_ms[d] <= 1.25 * floor


def test_a_tool_the_model_lacks_is_named_payload():
    """Default effects plus a 3 kg tool on the flange (``payload``, an effect added after
    DESIGN.md's seven), analysed from the default model: exactly ``payload`` is named, the
    actuation gap closes to the noise floor and nothing is left unexplained (1,200 trials;
    seeds 21-23 all named, gap 0.92-1.02 x the floor)."""
    effects = default_effects("ur10").with_effect(make_effect("payload", mass_kg=3.0))
    table = make_table("ur10", 1200, effects, seed=21)
    result = analyse_discrepancy(table, start="default")
    assert result.added_effects == ["payload"]
    floor = result.noise_floor_ms["actuation_delay"]
    assert result.gap_after_ms["actuation_delay"] <= 1.25 * floor
    assert result.unexplained == []
    assert result.steps[0].parameters["mass_kg"] > 0


def test_no_tool_nothing_named():
    """The same sweep without the tool, from the default model: ``payload`` is scored as a
    candidate and not named; nothing is."""
    table = make_table("ur10", 1200, default_effects("ur10"), seed=21)
    result = analyse_discrepancy(table, start="default")
    assert "payload" in [c["effect"] for c in result.final_candidates]
    assert result.added_effects == []
    assert result.unexplained == []


def test_effect_outside_the_vocabulary_is_reported_where_it_sits():
    """An actuation term the vocabulary cannot express (1.5 ms · sin q1, all joints): no
    effect is named. By default it is discovered (issue 36): one periodic term in q1
    shared by the four joints, each amplitude near 1.5 ms, the gap closed. With the
    vocabulary only (``discover=False``) the unexplained entry names the actuation delay,
    the joints and q1."""
    table = make_table(
        "ur10",
        1200,
        EffectSet(),
        seed=8,
        extra_actuation_s=lambda plan: 1.5e-3 * np.sin(plan.q_start_rad[:, 0]),
    )
    found = analyse_discrepancy(table, start="base")
    assert found.added_effects == []
    assert found.unexplained == []
    [term] = found.discovered
    assert term.inputs == ["q1"]
    assert set(term.joints) == {1, 2, 3, 5}
    assert term.effect.form == "harmonic"
    # Each amplitude from ~30 condition means at ~0.7 ms: standard error ~0.2 ms, so
    # 1.5 ± 0.5 ms is 2.5 standard errors either side.
    for size in term.parameters["size_per_joint"].values():
        assert abs(size["value"] - 1.5) < 0.5
    a = "actuation_delay"
    assert found.gap_after_ms[a] <= 1.25 * found.noise_floor_ms[a]
    result = analyse_discrepancy(table, start="base", discover=False)
    assert result.added_effects == []
    assert result.unexplained, "the disagreement must be reported"
    entry = result.unexplained[0]
    assert entry["delay"] == "actuation_delay"
    assert entry["variable"] == "q1"
    assert set(entry["joints"]) == {1, 2, 3, 5}
    assert entry["direction"] == "both"
    assert "No effect of the vocabulary explains it" in entry["description"]
    assert all(u["delay"] == "actuation_delay" for u in result.unexplained)


def test_too_few_repeats_warn_and_fall_back():
    """A table without repeats: the analysis still runs, on the simulator's timing
    scatter as the noise floor, and the output says so (warning and source)."""
    table = make_table("ur10", 300, EffectSet(), seed=9, repeats=1)
    result = analyse_discrepancy(table, start="base")
    out = result.to_dict()
    assert out["noise_floor"]["source"].startswith("fallback")
    assert any("too few repeats" in w for w in out["warnings"])
    # The simulator's own scatter at these conditions: ~2.3 ms per trial (one UR10 period
    # over sqrt 12), one trial per condition.
    assert 1.8 < out["noise_floor_ms"]["actuation_delay"] < 2.8
    assert out["added_effects"] == []


def test_unknown_start_effect_lists_the_vocabulary(base_table, capsys, tmp_path):
    """--start with a name outside the vocabulary: ConfigError naming it and listing every
    effect; the command exits 2 with that message."""
    with pytest.raises(ConfigError) as info:
        analyse_discrepancy(base_table, start="gravity_load,backlash")
    msg = str(info.value)
    assert "backlash" in msg
    assert all(name in msg for name in EFFECT_NAMES)
    csv = base_table.to_csv(tmp_path / "t.csv")
    code = run_cli(["discrepancy", str(csv), "--start", "backlash", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "backlash" in err
    assert "response_extra_cycle" in err


def test_cli_writes_json_and_report(gravity_table, tmp_path, capsys):
    """The command reads the CSV, prints a summary, writes OUT.json with the contract's
    keys (all numbers finite, gaps and floors in ms per delay) and a markdown report with
    the gap-per-step and before/after residual figures."""
    csv = gravity_table.to_csv(tmp_path / "measured.csv")
    out = tmp_path / "out.json"
    report = tmp_path / "report"
    code = run_cli(
        [
            "discrepancy",
            str(csv),
            "--start",
            "base",
            "--json",
            str(out),
            "--report",
            str(report),
            "--quiet",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "gravity_load" in text
    assert "noise floor" in text
    doc = json.loads(out.read_text())
    for key in (
        "added_effects",
        "gap_before_ms",
        "gap_after_ms",
        "noise_floor_ms",
        "steps",
        "unexplained",
    ):
        assert key in doc
    for key in ("gap_before_ms", "gap_after_ms", "noise_floor_ms"):
        assert set(doc[key]) == {"actuation_delay", "response_delay"}
    assert doc["added_effects"] == ["gravity_load"]
    step = doc["steps"][0]
    assert {"evidence", "parameters", "gap_after_ms", "explanation"} <= set(step)
    assert step["evidence"]["p_value"] < 0.01
    assert doc["unexplained"] == []
    assert _all_finite(doc)
    md = (report / "report.md").read_text()
    assert "## Step 1: gravity_load" in md
    # The evidence line is formatted, not the literal f-string source.
    assert "{ev[" not in md
    assert re.search(r"falls from \d+\.\d{3} to \d+\.\d{3} ms²", md)
    assert "noise floor" in md
    for png in ("gap_per_step.png", "where.png", "step1_gravity_load.png"):
        assert (report / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # '-' puts the JSON on stdout.
    assert run_cli(["discrepancy", str(csv), "--start", "base", "--json", "-", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["added_effects"] == ["gravity_load"]


def test_missing_measured_file_exits_2(tmp_path, capsys):
    """A MEASURED path that does not exist: exit 2 and a message naming it."""
    code = run_cli(["discrepancy", str(tmp_path / "nope.csv"), "--quiet"])
    assert code == 2
    assert "nope.csv" in capsys.readouterr().err


def test_recording_is_extracted_first(tmp_path):
    """MEASURED may be a recording: the delay table is extracted from it (gyro onset and
    reported-state shift) and analysed; the result names the recording as its source."""
    from timedexec.sim import simulate_sweep

    rec = tmp_path / "sweep.h5"
    simulate_sweep("ur10", 160, rec, seed=3, progress=False)
    result = analyse_discrepancy(rec, start="default")
    assert result.source == str(rec)
    assert result.n_conditions == 16  # 2 configurations x 4 joints x 2 directions
    assert 150 <= result.n_trials <= 160  # a few trials may be flagged by the extraction
    assert all(math.isfinite(v) for v in result.gap_after_ms.values())
