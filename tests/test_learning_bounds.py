"""The GP's 95 % prediction bounds: a split-conformal quantile of the CV's held-out |z|."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from timedexec.errors import ModelError
from timedexec.learning import DELAYS, DelayModel, bound_quantile, train_delay_models

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_learning import synthetic_table

Z95 = 1.959963984540054  # the Gaussian two-sided 95 % quantile


@pytest.fixture(scope="module")
def small() -> Any:
    """A GP trained with 8-fold CV on 8 configurations (80 held-out trials per joint)."""
    table = synthetic_table(n_cfg=8, repeats=5, seed=1)
    return table, train_delay_models(table, methods="median,gpr", folds=8, random_state=0)


# ---------------------------------------------------------------------- rule


def test_quantile_is_the_conformal_rank_of_abs_z() -> None:
    """q is the ceil((n+1)·0.95)-th smallest |residual / std|; NaN when n is too small for
    that rank; rows with an unusable std are skipped; a confidence outside (0, 1) refused."""
    rng = np.random.default_rng(0)
    std = rng.uniform(0.001, 0.003, 999)
    r = std * rng.uniform(-math.sqrt(3), math.sqrt(3), 999)  # unit-variance uniform z
    q = bound_quantile(r, std)
    z = np.sort(np.abs(r / std))
    assert q == z[math.ceil(1000 * 0.95) - 1]  # rank 950 of 999, exactly
    # a uniform z of unit variance has its 95 % |z| quantile at 0.95·sqrt(3) = 1.645; 999
    # draws: the order statistic's SE is ~0.012 (sqrt(p(1-p)/n) / density 1/(2·sqrt 3))
    assert q == pytest.approx(0.95 * math.sqrt(3), abs=0.04)
    assert math.isnan(bound_quantile(r[:18], std[:18]))  # rank ceil(19·0.95) = 19 > 18
    assert bound_quantile(r[:19], std[:19]) == np.max(np.abs(r[:19] / std[:19]))
    bad = np.concatenate([r, [1.0, np.nan]])
    assert bound_quantile(bad, np.concatenate([std, [0.0, 0.002]])) == q
    with pytest.raises(ValueError, match="confidence"):
        bound_quantile(r, std, confidence=1.0)


# -------------------------------------------------------------------- bundle


def test_training_stores_a_quantile_per_delay_and_model(small: Any, tmp_path: Path) -> None:
    """Training with CV writes bound_z for every delay and model, equal to the rule applied
    to the held-out residuals over the calibrated std; it survives save and load, and
    predict_bounds is mean ± bound_z · std for the GP."""
    table, res = small
    model = res.model
    assert set(model.manifest["bound_z"]) == set(DELAYS)
    assert model.manifest["std_calibration"]["bounds"]["confidence"] == 0.95
    assert res.cv.bound_z == model.manifest["bound_z"]
    loaded = DelayModel.load(model.save(tmp_path / "b"))
    j, d, q = table["joint"][:40], table["direction"][:40], table.q[:40]
    p = loaded.predict_many(j, d, q)
    b = loaded.predict_bounds(j, d, q)
    for delay, short in (("actuation_delay", "actuation"), ("response_delay", "response")):
        zs = model.manifest["bound_z"][delay]
        assert set(zs) == {"1", "2", "3", "5", "combined"}
        z = np.array([zs[str(int(x))] for x in j])
        assert np.all(z > 0)
        assert loaded.bound_z(delay, int(j[0])) == zs[str(int(j[0]))]
        assert loaded.bound_z(delay, None) == zs["combined"]
        mean, std = getattr(p, f"{short}_mean"), getattr(p, f"{short}_std")
        np.testing.assert_array_equal(getattr(b, f"{short}_lower_s"), mean - z * std)
        np.testing.assert_array_equal(getattr(b, f"{short}_upper_s"), mean + z * std)


def test_old_bundles_and_other_methods_keep_the_gaussian_bound(small: Any, tmp_path: Path) -> None:
    """A bundle without bound_z (older versions, or folds=0) and methods other than the
    GP give mean ± 1.96 std, today's behaviour."""
    table, res = small
    manifest = {k: v for k, v in res.model.manifest.items() if k != "bound_z"}
    old = DelayModel.load(DelayModel(manifest, res.model._arrays).save(tmp_path / "old"))
    j, d, q = table["joint"][:20], table["direction"][:20], table.q[:20]
    for model, method in ((old, "gpr"), (res.model, "median")):
        p = model.predict_many(j, d, q, method=method)
        b = model.predict_bounds(j, d, q, method=method)
        assert model.bound_z("actuation_delay", 1, method=method) == pytest.approx(Z95, rel=1e-12)
        np.testing.assert_allclose(
            b.actuation_upper_s, p.actuation_mean + Z95 * p.actuation_std, rtol=1e-12
        )
    no_cv = train_delay_models(synthetic_table(n_cfg=8, repeats=3), methods="gpr", folds=0)
    assert "bound_z" not in no_cv.model.manifest
    assert no_cv.model.bound_z("response_delay", 2) == pytest.approx(Z95, rel=1e-12)


def test_bad_quantiles_in_a_manifest_are_refused(small: Any, tmp_path: Path) -> None:
    """A hand-edited bound_z that is not a finite number > 0 is refused, naming the entry."""
    _, res = small
    path = res.model.save(tmp_path / "b")
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["bound_z"]["actuation_delay"]["3"] = -1.0
    (path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match=r"bound_z\['actuation_delay'\]\['3'\]"):
        DelayModel.load(path)


# ---------------------------------------------------------------- end to end


@pytest.mark.slow
def test_bounds_cover_95_percent_of_new_configurations_on_simulated_kr5() -> None:
    """(~10 s: three GP trainings with 5-fold CV.) On the simulated KR 5 (12 ms cycle, a
    warm robot), a GP trained on 2,000 trials covers 93.5-98 % of 2,000 fresh trials on
    other configurations with its 95 % bounds (mean of three), where the Gaussian mean ± 1.96 std covered
    over 98.5 %: the cycle's uniform wait has short tails.

    Three training sweeps (seeds 0-2); true delays (simulate_delays), warm (4 h after
    power-on), laid out in time like the training sweep.
    """
    from timedexec.recording import SweepPlan
    from timedexec.sim import simulate_delays

    n = 2000
    t = 14400.0 + np.arange(n) * 1.05  # warm: 4 h after power-on, the sweep's spacing
    gauss, bounds = [], []
    for seed in range(3):
        plan = SweepPlan.generate("kr5", n, seed=seed)
        table = simulate_delays("kr5", plan.q_start_rad, plan.joint, plan.direction, t, seed=seed)
        model = train_delay_models(table, methods="gpr", folds=5, random_state=0).model
        held = SweepPlan.generate("kr5", n, seed=1000 + seed)
        truth = simulate_delays(
            "kr5", held.q_start_rad, held.joint, held.direction, t, seed=500 + seed
        )
        y = truth["actuation_delay"]
        p = model.predict_many(truth["joint"], truth["direction"], truth.q)
        b = model.predict_bounds(truth["joint"], truth["direction"], truth.q)
        gauss.append(float(np.mean(np.abs(y - p.actuation_mean) <= Z95 * p.actuation_std)))
        bounds.append(float(np.mean((y >= b.actuation_lower_s) & (y <= b.actuation_upper_s))))
    print(f"coverage Gaussian {gauss} -> bounds {bounds}")
    # Measured 97.3 / 95.1 / 96.5 % (Gaussian 99.3 / 98.9 / 99.6 %). The conformal rank
    # guarantees >= 95 % for trials exchangeable with the CV's held-out ones; the CV models
    # see 4/5 of the configurations and err a little more than the final one, so the mean
    # sits above 95 %. 6,000 trials in 75 configurations that share the GP's error there:
    # per-sweep coverage scatters by ~1 %, the mean of three by ~0.7 %; the band is 95 %
    # - 2 SE .. the measured mean (96.3 %) + 2.5 SE (a point above the 97 %: the
    # CV's bias).
    mean = float(np.mean(bounds))
    assert 0.935 <= mean <= 0.98, (gauss, bounds)
    assert float(np.mean(gauss)) >= 0.985, (gauss, bounds)
