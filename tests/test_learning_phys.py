"""The "phys" method: Bayesian linear regression on the physics of the start pose.

What it must do beyond what every method does (tests/test_learning_registry.py): recover
delays that are linear in the gravity torque and inertia of the actuated joint, with a
posterior that covers the truth; agree with scikit-learn's BayesianRidge (the same
evidence fixed point); give predictive intervals that cover held-out trials; see a pose
and the pose 2π away as one; refuse a bundle whose robot model no longer matches; and on
a simulated sweep come within a few percent of the noise floor.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, ModelError
from timedexec.learning import (
    DelayModel,
    ModelInputs,
    cross_validate,
    encode_inputs,
    get_method,
    make_estimator,
    train_delay_models,
)
from timedexec.robots import get_robot, gravity_torque, joint_inertia

JOINTS = (1, 2, 3, 5)
NOISE_S = 0.002
#: True per-unit effects of the synthetic delays: s per (1, N·m, N·m, 1, √(kg·m²)).
TRUTH = {"direction": 0.001, "abs_tau_nm": 4e-5, "dir_x_tau_nm": 2e-5, "sqrt_inertia": 0.003}


def physical_table(n_cfg: int, repeats: int, seed: int) -> DelayTable:
    """UR10 delays linear in the physics of the actuated joint at the start pose (terms of
    :data:`TRUTH`, computed here with timedexec.robots), plus Gaussian trial noise."""
    rng = np.random.default_rng(seed)
    spec = get_robot("ur10")
    cfg = rng.uniform(-2.5, 2.5, (n_cfg, 6))
    cfg[:, 5] = 0.0
    rows = [
        (c, j, d) for c in range(n_cfg) for j in JOINTS for d in (1, -1) for _ in range(repeats)
    ]
    c_idx, joint, direction = (np.array(v) for v in zip(*rows, strict=True))
    q = cfg[c_idx]
    i = np.arange(len(rows))
    tau = gravity_torque(spec, q)[i, joint - 1]
    inertia = joint_inertia(spec, q)[i, joint - 1]
    act = (
        0.015
        + TRUTH["direction"] * direction
        + TRUTH["abs_tau_nm"] * np.abs(tau)
        + TRUTH["dir_x_tau_nm"] * direction * tau
        + TRUTH["sqrt_inertia"] * np.sqrt(inertia)
        + NOISE_S * rng.standard_normal(len(rows))
    )
    cols: dict[str, Any] = {
        "trial": i,
        "robot": "ur10",
        "joint": joint,
        "direction": direction,
        "t_start": i * 1.0,
        "actuation_delay": act,
        "response_delay": 0.004 + 0.001 * rng.standard_normal(len(rows)),
    }
    for k in range(6):
        cols[f"q{k + 1}"] = q[:, k]
    return DelayTable(cols, source="physical")


@pytest.fixture(scope="module")
def table() -> DelayTable:
    return physical_table(n_cfg=60, repeats=5, seed=11)


def joint_data(table: DelayTable, joint: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows = np.flatnonzero(table["joint"] == joint)
    X = encode_inputs(table.q[rows], table["direction"][rows])
    return X, table["actuation_delay"][rows], rows


def fitted(table: DelayTable, joint: int = 2) -> Any:
    X, y, _ = joint_data(table, joint)
    inputs = ModelInputs.of("ur10", str(joint), JOINTS, False)
    return make_estimator("phys", inputs=inputs).fit(X, y)


def test_recovers_the_physical_effects_within_their_posterior(table: DelayTable) -> None:
    """Delays made linear in |τ|, d·τ, √I and d: every slope of joint 2 (in s per unit) lies
    within 4 posterior standard deviations of the truth (zero for the terms the data do
    not use), and the trial noise is found to 10 %."""
    est = fitted(table)
    info = get_method("phys").info(est)
    json.dumps(info)
    slopes = np.array(info["slope_s_per_unit"]["2"])
    k = len(est.terms_)
    # posterior std of each slope in physical units: the covariance of the standardised
    # weights (each block: intercept first) scaled like the slopes
    sd = np.sqrt(np.diag(est.cov_))[1 : k + 1] * est.y_std_ / est.x_scale_[0]
    truth = np.array([TRUTH.get(term, 0.0) for term in est.terms_])
    z = (slopes - truth) / sd
    # Gaussian posterior: |z| > 4 has probability 6e-5 per term; a wrong design (another
    # torque, a sign) puts the z of a true effect in the tens
    assert np.all(np.abs(z) < 4.0), dict(zip(est.terms_, z.round(2), strict=True))
    # 600 trials: the noise std's relative standard error is 1/sqrt(2·600) = 2.9 %
    assert est.noise_std_ == pytest.approx(NOISE_S, rel=0.10)


def test_agrees_with_scikit_learn_bayesian_ridge(table: DelayTable) -> None:
    """The same model through scikit-learn's BayesianRidge (MacKay's updates on every trial,
    not collapsed) on the same standardised terms: the same predictions and stds."""
    from sklearn.linear_model import BayesianRidge

    est = fitted(table)
    X, y, rows = joint_data(table, 2)
    spec = get_robot("ur10")
    q, d = table.q[rows], table["direction"][rows].astype(float)
    tau = gravity_torque(spec, q)[:, 1]
    inertia = joint_inertia(spec, q)[:, 1]
    terms = np.column_stack([d, tau, np.abs(tau), d * tau, inertia, np.sqrt(inertia)])
    mu, sd = terms.mean(axis=0), terms.std(axis=0)
    tiny = 1e-12  # no hyperprior: the plain evidence maximum, as ours
    ridge = BayesianRidge(
        tol=1e-12, max_iter=2000, alpha_1=tiny, alpha_2=tiny, lambda_1=tiny, lambda_2=tiny
    )
    ridge.fit((terms - mu) / sd, y)
    mean_sk, std_sk = ridge.predict((terms - mu) / sd, return_std=True)
    mean, std = est.predict(X, return_std=True)
    # Two differences, both O(1/N) with N = 600 trials: scikit-learn's noise degrees of
    # freedom are N - γ (ours N - γ - 1: the intercept is a parameter too) and its std
    # leaves out the intercept's uncertainty (σ²/N). The means differ through the
    # shrinkage α/β only. Measured: means 1.2e-7 s apart (of delays ~0.02 s), stds 0.17 %.
    # Bounds: 1e-6 s on means, 1 % on stds (six times the measured, far below a wrong term).
    np.testing.assert_allclose(mean, mean_sk, rtol=0, atol=1e-6)
    np.testing.assert_allclose(std, std_sk, rtol=0.01)


def test_predictive_intervals_cover_held_out_trials(table: DelayTable) -> None:
    """95 % Gaussian intervals from the predictive std cover 95 % of trials at start poses
    the model never saw (the noise here is Gaussian, so Gaussian intervals are exact)."""
    est = fitted(table)
    fresh = physical_table(n_cfg=120, repeats=5, seed=12)
    X, y, _ = joint_data(fresh, 2)
    mean, std = est.predict(X, return_std=True)
    inside = float(np.mean(np.abs(y - mean) <= 1.96 * std))
    # 1,200 trials in 120 poses: binomial std 0.6 %, and poses cluster their trials; ±2.5 %
    assert 0.925 <= inside <= 0.975, inside


def test_a_pose_and_the_pose_two_pi_away_predict_alike(table: DelayTable) -> None:
    """UR joints turn ±2π: q and q + 2π are one pose, and the deployed model says so."""
    model = train_delay_models(table, methods=("phys",), folds=0).model
    q = np.array([[-2.0, -1.2, 1.0, -1.4, -1.5, 0.0]])
    q2 = q + np.array([[2 * np.pi, 0, 0, 2 * np.pi, 2 * np.pi, 0]])  # inside the ±2π limits
    a = model.predict_many(2, 1, q, method="phys")
    b = model.predict_many(2, 1, q2, method="phys")
    for name, value in a._asdict().items():
        # sin/cos of q + 2π round to within 1e-15 of those of q
        np.testing.assert_allclose(getattr(b, name), value, rtol=1e-9, err_msg=name)


def test_refuses_a_bundle_whose_robot_model_differs(table: DelayTable, tmp_path: Path) -> None:
    """The bundle keeps the physical terms at a few training inputs; recomputed for another
    robot model they differ, and the bundle is refused with a fix."""
    out = train_delay_models(table, methods=("phys",), folds=0).model.save(tmp_path / "b")
    DelayModel.load(out, robot="ur10")
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["robot"] = "ur10e"  # the same arrays, read as another robot's
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match=r"robot 'ur10e' .* differ .* retrain"):
        DelayModel.load(out)


def test_refuses_inputs_it_cannot_read(table: DelayTable) -> None:
    """No inputs, another column count, a direction other than ±1, a combined row without a
    single joint: ConfigError naming the value and the fix."""
    X, y, _ = joint_data(table, 2)
    with pytest.raises(ConfigError, match=r"needs the model's inputs .* make_estimator\('phys'"):
        make_estimator("phys").fit(X, y)
    inputs = ModelInputs.of("ur10", "2", JOINTS, True)  # expects a time column
    with pytest.raises(ConfigError, match=r"X has 13 columns; the inputs .* have 14"):
        make_estimator("phys", inputs=inputs).fit(X, y)
    bad = X.copy()
    bad[3, 12] = 0.5
    inputs = ModelInputs.of("ur10", "2", JOINTS, False)
    with pytest.raises(ConfigError, match=r"X row 3: direction 0.5 must be \+1 or -1"):
        make_estimator("phys", inputs=inputs).fit(bad, y)
    Xc = encode_inputs(table.q[:8], table["direction"][:8], table["joint"][:8], JOINTS)
    Xc[5, 13:17] = 0.0
    combined = ModelInputs.of("ur10", "combined", JOINTS, False)
    with pytest.raises(ConfigError, match=r"row 5 has no single joint"):
        make_estimator("phys", inputs=combined).fit(Xc, table["actuation_delay"][:8])


@pytest.mark.slow
def test_simulated_sweep_reaches_the_noise_floor() -> None:
    """On a simulated UR10 sweep (3,200 trials, 40 poses, true delays) the physical model's
    actuation error is within 4 % of the noise floor on every joint and combined, and below
    the median's (the 8,000-trial sweeps of docs/models.md: within 1-2 %)."""
    from timedexec.recording import SweepPlan
    from timedexec.sim import simulate_delays

    spec = get_robot("ur10")
    plan = SweepPlan.generate(spec, 3200, seed=5)
    table = simulate_delays(spec, plan.q_start_rad, plan.joint, plan.direction,
                            np.arange(len(plan)) * 1.05, seed=5)  # fmt: skip
    cv = cross_validate(table, methods=("median", "phys"), folds=5, random_state=0)
    act = cv.to_dict()["actuation_delay"]
    floor = cv.noise_floor_ms["actuation_delay"]
    for key in ("1", "2", "3", "5", "combined"):
        assert act["phys"][key] <= 1.04 * floor[key], (key, act["phys"][key], floor[key])
        assert act["phys"][key] < act["median"][key], key
