"""Calibrated GP uncertainty: the std scale from cross-validation, in bundles and predictions."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from timedexec.errors import ModelError
from timedexec.learning import (
    DELAYS,
    DelayModel,
    gaussian_coverage,
    std_scale_factor,
    train_delay_models,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_learning import assert_fast_path_matches, synthetic_table


@pytest.fixture(scope="module")
def small() -> Any:
    """A GP trained on 8 configurations: few enough that some CV ratios exceed 1."""
    table = synthetic_table(n_cfg=8, repeats=5, seed=1)
    return table, train_delay_models(table, methods="median,gpr", folds=8, random_state=0)


# ---------------------------------------------------------------------- rule


def test_scale_is_the_rms_of_standardised_errors_floored_at_one() -> None:
    """The factor is sqrt(mean(z²)) when the GP is overconfident, exactly 1 when it is not,
    and rows with a non-finite or non-positive std are skipped."""
    rng = np.random.default_rng(0)
    std = rng.uniform(0.001, 0.003, 4000)
    r = 1.5 * std * rng.standard_normal(4000)
    c = std_scale_factor(r, std)
    # exact formula on the same numbers (no sampling tolerance involved)
    assert c == pytest.approx(math.sqrt(float(np.mean((r / std) ** 2))), rel=1e-12)
    # 4,000 draws: the RMS of N(0, 1.5²) is within 3 % of 1.5 (its relative SE is ~1.1 %)
    assert c == pytest.approx(1.5, rel=0.03)
    assert std_scale_factor(0.5 * r, 2 * std) == 1.0  # conservative GP: never shrunk
    assert std_scale_factor([], []) == 1.0
    bad = np.concatenate([r, [1.0, 1.0, np.nan]])
    bad_std = np.concatenate([std, [0.0, np.nan, 0.002]])
    assert std_scale_factor(bad, bad_std) == c


def test_scaled_gaussian_interval_covers_95_percent_of_gaussian_errors() -> None:
    """With Gaussian errors 1.5x larger than the predicted std, the raw 95 % interval covers
    ~80 % and the calibrated one ~95 % of 4,000 trials."""
    rng = np.random.default_rng(1)
    std = np.full(4000, 0.002)
    r = 1.5 * std * rng.standard_normal(4000)
    raw = gaussian_coverage(r, std)
    cal = gaussian_coverage(r, std, scale=std_scale_factor(r, std))
    # P(|N(0,1.5²)| < 1.96) = 0.809; 4,000 trials: binomial SE 0.6 %, bands of ±2 % = 3 SE
    assert raw == pytest.approx(0.809, abs=0.02)
    # the scale itself is estimated from the same draws: ±2 % still holds (SE ~0.5 %)
    assert cal == pytest.approx(0.95, abs=0.02)
    assert abs(cal - 0.95) < abs(raw - 0.95)


# -------------------------------------------------------------------- bundle


def test_training_stores_factors_for_every_delay_and_model(small: Any) -> None:
    """Training with CV writes a factor >= 1 per delay and model (joints and combined), the
    rule and the held-out statistics into the manifest; the CV table shows the factors."""
    _, res = small
    model = res.model
    scale = model.manifest["std_scale"]
    assert set(scale) == set(DELAYS)
    for delay in DELAYS:
        assert set(scale[delay]) == {"1", "2", "3", "5", "combined"}
        for key, c in scale[delay].items():
            assert c >= 1.0
            held = model.manifest["std_calibration"]["held_out"][delay][key]
            assert c == max(1.0, held["rms_z"])
            assert held["trials"] == (320 if key == "combined" else 80)  # 8 cfg x 2 dir x 5 rep
            assert held["coverage_95_calibrated"] >= held["coverage_95_gp"]
    # 8 configurations leave the GP overconfident somewhere (the point of calibrating)
    assert max(max(v.values()) for v in scale.values()) > 1.05
    assert model.manifest["std_calibration"]["method"] == "gpr"
    assert res.cv.std_scale == scale
    assert "GP std scale, actuation delay: J1 x" in res.cv.table_text()


def test_factors_survive_save_and_load(small: Any, tmp_path: Path) -> None:
    """Saved and reloaded, the bundle has the same factors and the same predictions."""
    table, res = small
    loaded = DelayModel.load(res.model.save(tmp_path / "b"))
    assert loaded.std_scale == res.model.std_scale
    for delay in DELAYS:
        for joint in (1, 2, 3, 5, None):
            key = "combined" if joint is None else str(joint)
            assert loaded.gp_std_scale(delay, joint) == res.model.std_scale[delay][key]
    a = res.model.predict_many(table["joint"][:10], table["direction"][:10], table.q[:10])
    b = loaded.predict_many(table["joint"][:10], table["direction"][:10], table.q[:10])
    for name, value in a._asdict().items():
        np.testing.assert_array_equal(value, getattr(b, name))


def _raw(model: DelayModel) -> DelayModel:
    """The same bundle as an old manifest without std_scale (what earlier versions wrote)."""
    manifest = {
        k: v for k, v in model.manifest.items() if k not in ("std_scale", "std_calibration")
    }
    return DelayModel(manifest, model._arrays)


def test_old_bundles_without_factors_load_with_one(small: Any, tmp_path: Path) -> None:
    """A bundle whose manifest has no std_scale loads, reports factor 1.0 and predicts the
    GP's own std (sqrt(latent var + noise var)) exactly."""
    table, res = small
    path = _raw(res.model).save(tmp_path / "old")
    manifest = json.loads((path / "manifest.json").read_text())
    assert "std_scale" not in manifest
    old = DelayModel.load(path)
    assert old.gp_std_scale("actuation_delay", 1) == 1.0
    assert old.gp_std_scale("response_delay", None) == 1.0
    x = table.q[3]
    p = old.predict(joint=2, direction=-1, q=x)
    gp = old.gp_predictor("actuation_delay", 2)
    from timedexec.learning import encode_inputs

    _, var = gp.predict(encode_inputs(x[None, :], [-1]))
    assert p.actuation_std == pytest.approx(math.sqrt(var[0] + gp.noise_var_s2), rel=1e-12)
    assert p.actuation_latent_std == pytest.approx(math.sqrt(var[0]), rel=1e-12)


EPS = float(np.finfo(np.float64).eps)


def test_predictions_scale_in_every_path(small: Any) -> None:
    """predict (fused fast path), predict_many and the combined model multiply the GP's
    trial std by the factor and keep std² = latent_std² + noise²; means are unchanged;
    non-GP methods keep their CV error as std."""
    table, res = small
    cal = res.model
    raw = _raw(cal)
    q = table.q[:12]
    j, d = table["joint"][:12], table["direction"][:12]
    for combined in (False, True):
        a = cal.predict_many(j, d, q, combined=combined)
        b = raw.predict_many(j, d, q, combined=combined)
        for short, delay in (("actuation", "actuation_delay"), ("response", "response_delay")):
            c = np.array([cal.gp_std_scale(delay, None if combined else int(x)) for x in j])
            noise = np.array(
                [cal.gp_predictor(delay, None if combined else int(x)).noise_var_s2 for x in j]
            )
            np.testing.assert_array_equal(getattr(a, f"{short}_mean"), getattr(b, f"{short}_mean"))
            # Same path, same variance v (one BLAS call pattern for both bundles, so the
            # thread count cannot tell them apart): rounding of the final scalar steps only.
            # c·sqrt(v + n) vs sqrt(c²(v + n)): a sum, one or two products and a square root
            # on each side, at most ε each (half of it through the root): 8ε bounds it.
            np.testing.assert_allclose(
                getattr(a, f"{short}_std"), c * getattr(b, f"{short}_std"), rtol=8 * EPS
            )
            # latent² + n = c²v + (c² - 1)n + n against c²(v + n): the products, sums, the
            # root and the squaring of latent std, each at most ε of a term <= std²: 16ε.
            np.testing.assert_allclose(
                getattr(a, f"{short}_latent_std") ** 2 + noise,
                getattr(a, f"{short}_std") ** 2,
                rtol=16 * EPS,
            )
        for i in range(12):
            one = cal.predict(joint=int(j[i]), direction=int(d[i]), q=q[i], combined=combined)
            # the fused fast path folds constants differently: rounding only. The latent
            # variance σ_f² - kᵀBk cancels (by 166,000 x for the combined actuation GP here),
            # so a fixed relative tolerance fails with some BLAS thread counts; the bound is
            # derived from the computation in test_learning.gp_rounding_bounds
            assert_fast_path_matches(
                cal, one, a, i, joint=int(j[i]), direction=int(d[i]), q=q[i], combined=combined
            )
    med = cal.predict_many(j, d, q, method="median")
    np.testing.assert_array_equal(
        med.actuation_std, raw.predict_many(j, d, q, method="median").actuation_std
    )
    assert np.isnan(med.actuation_latent_std).all()


def test_bad_factors_in_a_manifest_are_refused(small: Any, tmp_path: Path) -> None:
    """A hand-edited manifest with a non-finite, non-positive or non-numeric factor, or an
    unknown delay, is refused with a ModelError naming the entry."""
    _, res = small
    path = res.model.save(tmp_path / "b")
    for delay, key, value in (
        ("actuation_delay", "1", float("nan")),
        ("actuation_delay", "2", -1.0),
        ("response_delay", "combined", "big"),
        ("warmup_delay", "1", 1.0),
    ):
        bad = tmp_path / f"bad-{delay}-{key}"
        shutil.copytree(path, bad)
        manifest = json.loads((bad / "manifest.json").read_text())
        manifest["std_scale"].setdefault(delay, {})[key] = value
        (bad / "manifest.json").write_text(json.dumps(manifest))
        with pytest.raises(ModelError, match=delay if delay == "warmup_delay" else key):
            DelayModel.load(bad)


def test_no_factors_without_cross_validation() -> None:
    """folds=0 leaves nothing to calibrate from: no std_scale, factor 1.0."""
    model = train_delay_models(synthetic_table(n_cfg=8, repeats=3), methods="gpr", folds=0).model
    assert "std_scale" not in model.manifest
    assert model.gp_std_scale("actuation_delay", 3) == 1.0


# ---------------------------------------------------------------- end to end


@pytest.mark.slow
def test_calibrated_bounds_cover_95_percent_on_simulated_ur10() -> None:
    """(~10 s: four GP trainings with 10-fold CV.) On the simulated UR10 trained with 800 trials (10 configurations x 4 joints x 2
    directions x 10 repeats, a 14-minute cold sweep), the executor's 95 % timing bounds
    (uniform wait + Gaussian) built from the calibrated std cover close to 95 % of fresh
    trials on configurations never trained on, and the uncalibrated GP's covered less.

    Four training sweeps (seeds 0-3), each checked on 800 fresh trials laid out in the same
    sweep time. The Gaussian interval is not the measure here: the delays are quantised by
    the 8 ms cycle, their tails are shorter than a Gaussian's, and a Gaussian interval at
    the right std covers more than 95 %.
    """
    from timedexec.execution import TimingBounds
    from timedexec.recording import SweepPlan
    from timedexec.sim import simulate_delays

    n = 800
    t = np.arange(n) * 1.05  # the sweep clock's trial spacing: a 14-minute sweep
    raw_cov, cal_cov = [], []
    for seed in range(4):
        plan = SweepPlan.generate("ur10", n, seed=seed)
        table = simulate_delays("ur10", plan.q_start_rad, plan.joint, plan.direction, t, seed=seed)
        cal = train_delay_models(table, methods="gpr", folds=10, random_state=0).model
        raw = _raw(cal)
        q, j, d, tt = [], [], [], []
        for k in range(10):  # 10 fresh plans of 10 configurations, one trial per condition
            held = SweepPlan.generate("ur10", n, seed=1000 + 10 * seed + k)
            first = held.repeat == 0
            q.append(held.q_start_rad[first])
            j.append(held.joint[first])
            d.append(held.direction[first])
            tt.append(t[first])
        truth = simulate_delays(
            "ur10", np.concatenate(q), np.concatenate(j), np.concatenate(d),
            np.concatenate(tt), seed=500 + seed,
        )  # fmt: skip
        y = truth["actuation_delay"]
        for model, out in ((raw, raw_cov), (cal, cal_cov)):
            p = model.predict_many(truth["joint"], truth["direction"], truth.q)
            b = TimingBounds.around(p.actuation_mean, p.actuation_std, 0.95, 0.008)
            out.append(float(np.mean(b.contains(y))))
    raw_mean, cal_mean = float(np.mean(raw_cov)), float(np.mean(cal_cov))
    print(f"coverage raw {raw_cov} -> calibrated {cal_cov}")
    # 3,200 trials per mean, but trials of a configuration share the GP's error there: the
    # per-sweep coverage scattered by ~2 % over ten sweeps (docs/models.md), so the mean of
    # four has an SE of ~1 %; a ±2.5 % band is 2.5 SE. The raw GP measured 90.3 % on ten.
    assert cal_mean == pytest.approx(0.95, abs=0.025), (raw_cov, cal_cov)
    assert raw_mean < cal_mean - 0.02, (raw_cov, cal_cov)
    assert abs(cal_mean - 0.95) < abs(raw_mean - 0.95)
