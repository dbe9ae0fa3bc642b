"""Delay models: estimators, exactness of the replicate collapse, CV as published, bundles."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.optimize import check_grad
from sklearn.base import clone

from conftest import full_or_bounded
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, ModelError
from timedexec.learning import (
    DEFAULT_METHODS,
    DELAYS,
    DelayGP,
    DelayModel,
    LinearLeafTree,
    LMNeuralNet,
    MedianDelay,
    build_predictor,
    collapse_replicates,
    condition_exact,
    condition_fitc,
    cross_validate,
    encode_inputs,
    feature_names,
    fold_of_configuration,
    neg_log_likelihood,
    noise_floor,
    train_delay_models,
)
from timedexec.robots import ROBOT_NAMES

NOISE_S = 0.002  # trial noise of the synthetic tables, s
EPS = float(np.finfo(np.float64).eps)


def gp_rounding_bounds(gp: Any, x: np.ndarray) -> tuple[float, float]:
    """How far two evaluations of one GP at the encoded input ``x`` (d,) may differ by
    rounding alone: (mean, s; latent variance, s²).

    The fast path (one row, fused constants), the batched path (a blocked matrix product
    whose summation order also depends on the BLAS thread count) and the fused pair of GPs
    compute the same formulas (R&W Alg. 2.1, ``B = (K + D)⁻¹`` stored):
    ``mean = y_mean + y_std·kᵀα`` and ``latent var = y_std²·(σ_f² - k_vᵀ B k_v)``, in
    different orders. First-order error bounds (Higham, *Accuracy and Stability of
    Numerical Algorithms*, 2nd ed., §3.1 and §3.5):

    * a dot or matrix-vector product of length m errs by at most ``γ_m·|a|ᵀ|b|``,
      ``γ_m = m·ε/(1 - m·ε)``: ``kᵀα`` by ``γ_m·|k|ᵀ|α|``, ``k_vᵀBk_v`` by
      ``2γ_s·|k_v|ᵀ|B||k_v|``;
    * ``k_i = σ_f²·exp(-½‖x - c_i‖²)`` carries the absolute rounding of its squared
      distance, formed from ``‖x‖²`` and ``‖c_i‖²`` (or ``x·c_i``) in every path: a
      relative error ``θ ≤ 4ε·(‖x‖² + max‖c_i‖²) + 2ε``, which moves the two forms by
      ``θ·|k|ᵀ|α|`` and ``2θ·|k_v|ᵀ|B||k_v|``;
    * two evaluations err independently: their difference is bounded by twice the sum;
      the final scalar steps add a few ε of the result.

    The ratios ``|k|ᵀ|α| / |kᵀα|`` and ``|k_v|ᵀ|B||k_v| / k_vᵀBk_v`` are the condition
    numbers of the two sums; B holds large entries of both signs, so where the latent
    variance is small next to σ_f² the second reaches 1e5 and the latent std agrees to
    ~1e-5 relative in the worst case (observed: ~1e-9; a fixed 1e-9 failed with some BLAS
    thread counts). A real difference between the paths (a wrong constant) is far larger.
    """
    xm = gp.map_inputs(np.atleast_2d(x))[0]
    centres = gp.centres
    k = gp.signal_var * np.exp(-0.5 * np.sum((xm - centres) ** 2, axis=1))
    B = gp.B
    if gp.var_centres is not None:  # FITC: its own inducing inputs for the variance
        kv = gp.signal_var * np.exp(-0.5 * np.sum((xm - gp.var_centres) ** 2, axis=1))
        spread = float(np.max(np.sum(gp.var_centres**2, axis=1)))
    elif gp.var_index is not None:  # a subset of the conditions
        kv, spread = k[gp.var_index], 0.0
    else:  # every condition, or the first len(B) of them
        kv, spread = k[: len(B)], 0.0
    spread = max(spread, float(np.max(np.sum(centres**2, axis=1))))
    theta = 4.0 * EPS * (float(xm @ xm) + spread) + 2.0 * EPS

    def gamma(n: int) -> float:
        return n * EPS / (1.0 - n * EPS)

    mean = gp.y_mean + gp.y_std * float(k @ gp.alpha)
    dot_abs = float(np.abs(k) @ np.abs(gp.alpha))
    tol_mean = 2.0 * (gamma(len(k)) + theta) * gp.y_std * dot_abs + 4.0 * EPS * abs(mean)
    quad_abs = float(np.abs(kv) @ np.abs(B) @ np.abs(kv))
    tol_var = 2.0 * (2.0 * gamma(len(kv)) + 2.0 * theta) * quad_abs * gp.y_std**2
    tol_var += 4.0 * EPS * gp.signal_var * gp.y_std**2  # σ_f² - (...) and the scaling
    return tol_mean, tol_var


def assert_fast_path_matches(
    model: DelayModel,
    one: Any,
    many: Any,
    i: int,
    *,
    joint: int,
    direction: int,
    q: np.ndarray,
    combined: bool = False,
    t_s: float | None = None,
) -> None:
    """``model.predict`` (``one``) equals row ``i`` of ``model.predict_many`` (``many``)
    within :func:`gp_rounding_bounds`: means directly, stds as squares (``|a² - b²|``
    bounds the variances' rounding without dividing by a latent std that cancellation made
    small). Trial std² = c²·(var + noise), latent std² = c²·var + (c² - 1)·noise: both move
    by c² times the latent variance's bound plus a few ε of std² (8ε)."""
    t_h = None
    if model.time_input:  # hours since the sweep started; default: the end of the sweep
        t_h = (model.time_default_s if t_s is None else t_s) / 3600.0
    if combined:
        x = encode_inputs(q[None, :], [direction], [joint], model.joints, t_h=t_h)[0]
    else:
        x = encode_inputs(q[None, :], [direction], t_h=t_h)[0]
    for short, delay in (("actuation", "actuation_delay"), ("response", "response_delay")):
        gp = model.gp_predictor(delay, None if combined else joint)
        tol_mean, tol_var = gp_rounding_bounds(gp, x)
        c2 = model.gp_std_scale(delay, None if combined else joint) ** 2
        std = getattr(one, f"{short}_std")
        mean = getattr(one, f"{short}_mean")
        assert abs(mean - getattr(many, f"{short}_mean")[i]) <= tol_mean, (short, i)
        for name in (f"{short}_std", f"{short}_latent_std"):
            diff = abs(getattr(one, name) ** 2 - getattr(many, name)[i] ** 2)
            assert diff <= c2 * tol_var + 8.0 * EPS * std**2, (name, i, diff, c2 * tol_var)


def synthetic_table(
    *,
    n_cfg: int = 30,
    joints: tuple[int, ...] = (1, 2, 3, 5),
    repeats: int = 5,
    seed: int = 0,
    robot: str = "ur10",
    drift_s: float = 0.0,
) -> DelayTable:
    """A sweep-shaped delay table: smooth pose/direction dependence plus Gaussian trial noise
    (and, with ``drift_s``, a warm-up drift that decays over the sweep)."""
    rng = np.random.default_rng(seed)
    cfg = rng.uniform(-2.5, 2.5, (n_cfg, 6))
    cfg[:, 5] = 0.0
    rows = [
        (c, j, d) for c in range(n_cfg) for j in joints for d in (1, -1) for _ in range(repeats)
    ]
    c_idx = np.array([r[0] for r in rows])
    joint = np.array([r[1] for r in rows])
    direction = np.array([r[2] for r in rows])
    q = cfg[c_idx]
    act = (
        0.020
        + 0.004 * np.sin(q[:, 1]) * direction
        + 0.003 * np.cos(q[:, 2])
        + 0.001 * joint
        + NOISE_S * rng.standard_normal(len(rows))
    )
    resp = 0.004 + NOISE_S * rng.standard_normal(len(rows))
    t_start = np.arange(len(rows)) * 1.0
    act += drift_s * np.exp(-t_start / (0.3 * len(rows)))
    cols: dict[str, Any] = {
        "trial": np.arange(len(rows)),
        "robot": robot,
        "joint": joint,
        "direction": direction,
        "t_start": t_start,
        "actuation_delay": act,
        "response_delay": resp,
    }
    for i in range(6):
        cols[f"q{i + 1}"] = q[:, i]
    return DelayTable(cols, source="synthetic")


@pytest.fixture(scope="module")
def table() -> DelayTable:
    return synthetic_table()


@pytest.fixture(scope="module")
def trained(table: DelayTable) -> Any:
    return train_delay_models(table, folds=5, jobs=1, random_state=0)


def _gp_data(n_cond: int = 40, repeats: int = 5, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = rng.uniform(-2, 2, (n_cond, 3))
    X = np.repeat(base, repeats, axis=0)
    y = 0.02 + 0.003 * np.sin(X[:, 0]) * X[:, 1] + NOISE_S * rng.standard_normal(len(X))
    return X, y


# ------------------------------------------------------------------ features


def test_encode_inputs_layout() -> None:
    """Angles enter as sin/cos pairs, then the direction, then one-hot joints (combined)."""
    q = np.array([[0.5, -1.0, 2.0, 0.0, 1.0, 0.0]])
    X = encode_inputs(q, [-1], [3], (1, 2, 3, 5))
    names = feature_names((1, 2, 3, 5))
    assert X.shape == (1, len(names)) == (1, 17)
    assert X[0, names.index("sin_q1")] == pytest.approx(np.sin(0.5))  # exact arithmetic
    assert X[0, names.index("cos_q3")] == pytest.approx(np.cos(2.0))
    assert X[0, names.index("direction")] == -1
    assert X[0, 13:].tolist() == [0, 0, 1, 0]


def test_encode_inputs_unknown_joint_names_the_row() -> None:
    """A combined model refuses a joint it was not trained on, naming row and joints."""
    with pytest.raises(ConfigError, match=r"row 1: joint 4 is not one of .*1, 2, 3, 5"):
        encode_inputs(np.zeros((2, 6)), [1, 1], [1, 4], (1, 2, 3, 5))


def test_collapse_replicates_is_exact() -> None:
    """Means, counts and the within sum of squares reproduce the trial-level SSE exactly."""
    X, y = _gp_data()
    col = collapse_replicates(X, y)
    assert len(col.X) == 40
    assert col.n == 200
    f = np.random.default_rng(3).normal(size=len(col.X))  # any per-condition prediction
    sse_trials = np.sum((y - f[col.inverse]) ** 2)
    sse_collapsed = col.within_ss + np.sum(col.count * (col.mean - f) ** 2)
    # same quantity summed in a different order: agreement to rounding
    assert sse_collapsed == pytest.approx(sse_trials, rel=1e-12)


# ------------------------------------------------------------------ GP


def test_gp_equals_sklearn_on_all_trials() -> None:
    """The collapsed GP gives scikit-learn's exact GP on every trial: same likelihood,
    means and standard deviations (sufficient statistics, not an approximation)."""
    X, y = _gp_data()
    gp = DelayGP(random_state=0).fit(X, y)
    sk = gp.to_sklearn().fit(X, y)
    # Same quantity through an N³ and an M³ Cholesky: rounding only (1e-9 relative).
    assert gp.log_marginal_likelihood(X, y) == pytest.approx(
        sk.log_marginal_likelihood_value_, rel=1e-9
    )
    Xq = np.random.default_rng(5).uniform(-2, 2, (25, 3))
    m1, s1 = gp.predict(Xq, return_std=True)
    m2, s2 = sk.predict(Xq, return_std=True)
    np.testing.assert_allclose(m1, m2, rtol=0, atol=1e-9)  # 1e-9 s: the required agreement
    np.testing.assert_allclose(s1, s2, rtol=0, atol=1e-9)
    one = np.array([gp.predictor_.predict_one(x) for x in Xq])
    # fast path = batch path, to rounding (bound derived in gp_rounding_bounds)
    for x, fast, batch in zip(Xq, one[:, 0], m1, strict=True):
        assert abs(fast - batch) <= gp_rounding_bounds(gp.predictor_, x)[0]


def test_gp_likelihood_gradient_is_analytic() -> None:
    """The likelihood gradient matches finite differences (L-BFGS depends on it)."""
    X, y = _gp_data(n_cond=25)
    col = collapse_replicates(X, y)
    ys = (col.mean - y.mean()) / y.std()
    theta = np.array([0.3, -0.2, 0.5, -0.5, -0.7])
    args = (col.X, ys, col.count, col.within_ss / y.var(), col.n)
    err = check_grad(
        lambda t: neg_log_likelihood(t, *args)[0], lambda t: neg_log_likelihood(t, *args)[1], theta
    )
    grad_norm = np.linalg.norm(neg_log_likelihood(theta, *args)[1])
    assert err < 1e-5 * max(grad_norm, 1.0)  # finite differences with step 1.5e-8: ~1e-6 relative


def test_gp_std_kinds_and_variance_subset_bound() -> None:
    """Trial std = sqrt(latent var + noise var); the variance from a subset of conditions
    never falls below the exact one (conditioning on less data cannot shrink it)."""
    X, y = _gp_data(n_cond=60)
    exact = DelayGP(random_state=0, max_variance_conditions=None).fit(X, y)
    _, trial = exact.predict(X[:50], return_std=True)
    _, latent = exact.predict(X[:50], return_std=True, include_noise=False)
    np.testing.assert_allclose(trial**2, latent**2 + exact.noise_std_**2, rtol=1e-12)
    sub = clone(exact).set_params(max_variance_conditions=15).fit(X, y)
    Xq = np.random.default_rng(2).uniform(-2.5, 2.5, (200, 3))
    m_e, s_e = exact.predict(Xq, return_std=True, include_noise=False)
    m_s, s_s = sub.predict(Xq, return_std=True, include_noise=False)
    np.testing.assert_allclose(m_s, m_e, rtol=0, atol=1e-12)  # the mean uses every condition
    assert np.all(s_s >= s_e - 1e-12)  # upper bound, up to rounding


def test_fitc_with_all_conditions_as_inducing_is_exact() -> None:
    """FITC with the conditions themselves as inducing inputs is the exact GP (Q = K)."""
    X, y = _gp_data(n_cond=30)
    col = collapse_replicates(X, y)
    ys = (col.mean - y.mean()) / y.std()
    ell = np.array([0.8, 1.5, 3.0])
    _cx, ax, Lx = condition_exact(col.X, ys, col.count, ell, 0.7, 0.4)
    _cz, az, Bz = condition_fitc(col.X, ys, col.count, col.X, ell, 0.7, 0.4)
    # 1e-8 jitter on K_mm perturbs the solution at about that level
    np.testing.assert_allclose(az, ax, atol=1e-5 * np.abs(ax).max())
    Bx = np.linalg.inv(Lx @ Lx.T)
    np.testing.assert_allclose(Bz, Bx, atol=1e-5 * np.abs(Bx).max())


def test_gp_sparse_path_is_close_to_exact() -> None:
    """Above max_exact_conditions the GP switches to FITC on k-means centres; on a smooth
    function with enough inducing inputs it stays close to the exact model."""
    X, y = _gp_data(n_cond=120, repeats=3)
    exact = DelayGP(random_state=0).fit(X, y)
    sparse = DelayGP(random_state=0, max_exact_conditions=50, n_inducing=60).fit(X, y)
    assert sparse.sparse_
    assert not exact.sparse_
    Xq = np.random.default_rng(7).uniform(-2, 2, (100, 3))
    # both near the same posterior mean: within a tenth of the trial noise
    assert np.max(np.abs(sparse.predict(Xq) - exact.predict(Xq))) < 0.1 * NOISE_S


def test_build_predictor_round_trip_through_arrays() -> None:
    """to_arrays + build_predictor (what a bundle does) reproduce the fitted predictor."""
    from timedexec.learning import predictor_from_arrays

    X, y = _gp_data()
    gp = DelayGP(random_state=0).fit(X, y)
    pred = predictor_from_arrays(gp.to_arrays())
    Xq = np.random.default_rng(9).uniform(-2, 2, (10, 3))
    np.testing.assert_array_equal(pred.predict(Xq)[0], gp.predictor_.predict(Xq)[0])
    assert build_predictor is not None


# --------------------------------------------------------- other estimators


@pytest.mark.parametrize("cls", [MedianDelay, LMNeuralNet, LinearLeafTree, DelayGP])
def test_estimator_contract(cls: type) -> None:
    """scikit-learn contract: __init__ stores, clone/get_params/set_params work, fit returns
    self, learned state ends in '_', predict needs fit."""
    from sklearn.exceptions import NotFittedError

    est = cls()
    params = est.get_params()
    assert clone(est).get_params() == params
    X, y = _gp_data(n_cond=20)
    with pytest.raises(NotFittedError):
        est.predict(X)
    assert est.fit(X, y) is est
    assert est.n_features_in_ == 3
    assert est.predict(X).shape == (len(X),)
    with pytest.raises(ConfigError, match="shape"):
        est.predict(np.zeros((2, 4)))


@pytest.mark.parametrize("cls", [MedianDelay, LMNeuralNet, LinearLeafTree, DelayGP])
def test_estimators_refuse_non_finite_training_data(cls: type) -> None:
    """NaN/inf in X or y: ConfigError naming the row (and column)."""
    X, y = _gp_data(n_cond=10)
    Xb = X.copy()
    Xb[4, 2] = np.nan
    with pytest.raises(ConfigError, match="X row 4 column 2 is nan"):
        cls().fit(Xb, y)
    yb = y.copy()
    yb[7] = np.inf
    with pytest.raises(ConfigError, match="y row 7 is inf"):
        cls().fit(X, yb)
    with pytest.raises(ConfigError, match="empty"):
        cls().fit(np.zeros((0, 3)), np.zeros(0))


def test_lm_net_fits_a_smooth_function_and_matches_minpack() -> None:
    """The BLAS Levenberg-Marquardt reaches MINPACK's objective on the same problem."""
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (300, 2))
    y = np.sin(X[:, 0]) + 0.5 * X[:, 1] ** 2 + 0.05 * rng.standard_normal(300)
    kw: dict[str, Any] = {
        "hidden_units": 8,
        "alpha": 1e-4,
        "validation_fraction": 0.0,
        "n_restarts": 1,
        "max_iter": 300,
        "tol": 1e-9,
        "random_state": 1,
    }
    fast = LMNeuralNet(**kw).fit(X, y)
    ref = LMNeuralNet(solver="scipy-lm", **kw).fit(X, y)
    rmse = np.sqrt(np.mean((fast.predict(X) - y) ** 2))
    assert rmse < 0.08  # noise 0.05; 8 tanh units capture sin + square
    # both converge to a local minimum from the same start; objectives within 2 %
    assert fast.objective_ == pytest.approx(ref.objective_, rel=0.02)


def test_tree_finds_regimes_and_prunes_a_linear_target() -> None:
    """Two linear regimes need a split; a single linear target is pruned to one leaf."""
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (400, 3))
    y2 = np.where(X[:, 0] > 0.2, 1.0 + 2.0 * X[:, 1], -1.0 - X[:, 2]) + 0.01 * rng.standard_normal(
        400
    )
    tree = LinearLeafTree(min_samples_leaf=20).fit(X, y2)
    assert tree.n_leaves_ >= 2
    assert np.sqrt(np.mean((tree.predict(X) - y2) ** 2)) < 0.1  # noise 0.01; few leaves
    y1 = 0.5 + X @ np.array([1.0, -2.0, 0.5]) + 0.01 * rng.standard_normal(400)
    assert LinearLeafTree(min_samples_leaf=20).fit(X, y1).n_leaves_ == 1


# ----------------------------------------------------------------------- CV


def test_folds_keep_each_configuration_together(table: DelayTable) -> None:
    """All trials of a start configuration (every joint, direction, repeat) share a fold."""
    config = np.unique(table.q, axis=0, return_inverse=True)[1].reshape(-1)
    fold = fold_of_configuration(config, 5, 0)
    for c in np.unique(config):
        assert len(np.unique(fold[config == c])) == 1
    sizes = np.bincount(fold)
    assert sizes.max() - sizes.min() <= 40  # one configuration = 4 joints x 2 dirs x 5 repeats


def test_cv_layout_error_formula_and_noise_floor(trained: Any, table: DelayTable) -> None:
    """CV.json has exactly {delay: {method: {joints..., combined, average}}}; the median's
    error is sqrt(mean of fold MSEs); the floor recovers the synthetic trial noise."""
    cv = trained.cv
    d = cv.to_dict()
    assert list(d) == list(DELAYS)
    for delay in DELAYS:
        assert list(d[delay]) == list(DEFAULT_METHODS)
        for m in DEFAULT_METHODS:
            assert list(d[delay][m]) == ["1", "2", "3", "5", "combined", "average"]
    json.dumps(d)  # JSON-safe
    config = np.unique(table.q, axis=0, return_inverse=True)[1].reshape(-1)
    fold = fold_of_configuration(config, 5, 0)
    y = table["actuation_delay"]
    mses = []
    for k in range(5):
        test = fold == k
        mses.append(np.mean((y[test] - np.median(y[~test])) ** 2))
    assert d["actuation_delay"]["median"]["combined"] == pytest.approx(
        1e3 * np.sqrt(np.mean(mses)), rel=1e-12
    )
    row = d["actuation_delay"]["median"]
    assert row["average"] == pytest.approx(
        np.mean([row[k] for k in ("1", "2", "3", "5", "combined")])
    )
    # 1,200 trials, 960 degrees of freedom: the estimated sigma is within ~5 % of the truth
    assert cv.noise_floor_ms["actuation_delay"]["combined"] == pytest.approx(
        1e3 * NOISE_S, rel=0.08
    )


def test_learned_models_beat_the_median_on_structured_delays(trained: Any) -> None:
    """With pose- and direction-dependent actuation delays every learned model beats the
    median on every joint, and the GP is within 10 % of the noise floor."""
    act = trained.cv.to_dict()["actuation_delay"]
    floor = trained.cv.noise_floor_ms["actuation_delay"]
    for key in ("1", "2", "3", "5", "combined"):
        for m in ("nn", "rt", "gpr"):
            assert act[m][key] < act["median"][key], (m, key)
        assert act["gpr"][key] < 1.10 * floor[key], key


def test_noise_floor_needs_replicates() -> None:
    """Without replicates there is no within-condition scatter: NaN, not 0."""
    assert np.isnan(noise_floor(np.array([1.0, 2.0]), np.array([0, 1])))


def test_cross_validate_refuses_too_few_configurations() -> None:
    """10 folds need 10 configurations; the message says what to do."""
    small = synthetic_table(n_cfg=4)
    with pytest.raises(
        ConfigError, match=r"at least 10 distinct start configurations; the table has 4"
    ):
        cross_validate(small, folds=10)


def test_training_refuses_nan_delays_naming_column_and_row(table: DelayTable) -> None:
    """An unflagged NaN delay is refused with its column and row (flagged ones are dropped)."""
    cols = {k: v.copy() for k, v in table.columns.items()}
    cols["response_delay"][17] = np.nan
    bad = DelayTable(cols, source="t.csv")
    with pytest.raises(ConfigError, match=r"t.csv: column 'response_delay' row 17 is nan"):
        train_delay_models(bad, folds=0, methods="median")
    cols["flag"] = np.array(
        ["" if i != 17 else "no onset" for i in range(len(table))], dtype=object
    )
    result = train_delay_models(DelayTable(cols, source="t.csv"), folds=0, methods="median")
    assert result.model.manifest["training_data"]["trials"] == len(table) - 1


def test_training_refuses_unknown_methods_and_mixed_robots(table: DelayTable) -> None:
    """Unknown method names and tables mixing robots are configuration errors."""
    with pytest.raises(ConfigError, match=r"unknown or no method.*svm"):
        train_delay_models(table, methods="median,svm")
    cols = {k: v.copy() for k, v in table.columns.items()}
    cols["robot"] = np.array(["ur10"] * (len(table) - 1) + ["kr5"], dtype=object)
    with pytest.raises(ConfigError, match="mixes robots"):
        train_delay_models(DelayTable(cols), folds=0)


def test_parallel_cv_gives_the_same_scores(table: DelayTable, trained: Any) -> None:
    """joblib workers change nothing: the scores do not depend on --jobs."""
    par = cross_validate(table, folds=5, jobs=2, random_state=0, methods=("median", "rt", "gpr"))
    for delay in DELAYS:
        for m in ("median", "rt", "gpr"):
            for k, v in par.to_dict()[delay][m].items():
                assert v == pytest.approx(trained.cv.to_dict()[delay][m][k], rel=1e-9)


def test_table_text_shows_paper_numbers(trained: Any) -> None:
    """The printed tables put ours beside the paper's UR numbers and add the floor row."""
    text = trained.cv.table_text()
    assert "Table I: actuation delay" in text
    assert "Table II: response delay" in text
    assert "/  6.18" in text  # paper: UR actuation median, joint 1
    assert "floor" in text


# ------------------------------------------------------------------ bundles


def test_bundle_round_trip_and_fast_predict(
    trained: Any, tmp_path: Path, table: DelayTable
) -> None:
    """Save/load keeps every number; predict (fast path) equals predict_many; the GP std
    includes the trial noise."""
    model = trained.model
    out = model.save(tmp_path / "b")
    loaded = DelayModel.load(out, robot="ur10", period_s=0.008)
    q = table.q[:20]
    j, d = table["joint"][:20], table["direction"][:20]
    for method in DEFAULT_METHODS:
        a = model.predict_many(j, d, q, method=method)
        b = loaded.predict_many(j, d, q, method=method)
        for name, value in a._asdict().items():
            np.testing.assert_array_equal(value, getattr(b, name))
    for i in range(5):
        p = loaded.predict(joint=int(j[i]), direction=int(d[i]), q=q[i])
        many = loaded.predict_many(j[i : i + 1], d[i : i + 1], q[i : i + 1])
        # fast path folds constants differently: rounding only (gp_rounding_bounds)
        assert_fast_path_matches(loaded, p, many, 0, joint=int(j[i]), direction=int(d[i]), q=q[i])
        assert p.actuation_std > p.actuation_latent_std > 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["robot"] == "ur10"
    assert manifest["controller_period_s"] == 0.008
    assert manifest["feature_order"]["per_joint"][:2] == ["sin_q1", "cos_q1"]
    assert manifest["cv"]["scores_ms"] == trained.cv.to_dict()
    assert len(manifest["training_data"]["arrays_sha256"]) == 64


def test_bundle_bytes_are_deterministic(trained: Any, tmp_path: Path) -> None:
    """Saving the same model twice gives identical arrays (rerunning a script diffs clean)."""
    a = trained.model.save(tmp_path / "a")
    b = trained.model.save(tmp_path / "b")
    assert (a / "arrays.npz").read_bytes() == (b / "arrays.npz").read_bytes()


def test_bundle_refuses_tampered_arrays(trained: Any, tmp_path: Path) -> None:
    """Arrays that fail the manifest's sha256 are refused."""
    out = trained.model.save(tmp_path / "b")
    data = bytearray((out / "arrays.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (out / "arrays.npz").write_bytes(bytes(data))
    with pytest.raises(ModelError, match=r"sha256 .* does not match"):
        DelayModel.load(out)


def test_bundle_refuses_other_robot_or_period(trained: Any, tmp_path: Path) -> None:
    """A bundle for the UR10 at 8 ms is refused for the KR 5 or at 2 ms, with a fix."""
    from timedexec.robots import get_robot

    out = trained.model.save(tmp_path / "b")
    with pytest.raises(ModelError, match=r"for robot 'ur10' .* refusing it for robot 'kr5'"):
        DelayModel.load(out, robot="kr5")
    with pytest.raises(ModelError, match=r"refusing it at 2 ms"):
        DelayModel.load(out, robot="ur10", period_s=0.002)
    with pytest.raises(ModelError, match="refusing it for robot 'kr5'"):
        DelayModel.load(out, robot=get_robot("kr5"))
    DelayModel.load(out, robot=get_robot("ur10")).check("ur10", 0.008)


def test_bundle_refuses_missing_files_and_bad_queries(trained: Any, tmp_path: Path) -> None:
    """Missing bundle, unknown joint, bad direction, NaN or mis-shaped q: clear errors."""
    with pytest.raises(ModelError, match="no model bundle"):
        DelayModel.load(tmp_path / "nothing")
    model = trained.model
    with pytest.raises(
        ModelError, match="joint 4 is unknown to this bundle; it models joints 1, 2, 3, 5"
    ):
        model.predict(joint=4, direction=1, q=np.zeros(6))
    with pytest.raises(ConfigError, match="direction 0 must be"):
        model.predict(joint=1, direction=0, q=np.zeros(6))
    with pytest.raises(ConfigError, match=r"q3 is nan"):
        model.predict(joint=1, direction=1, q=[0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ConfigError, match=r"6 joint angles"):
        model.predict(joint=1, direction=1, q=np.zeros(5))
    with pytest.raises(ConfigError, match=r"q row 1: q2 is inf"):
        model.predict_many(1, 1, np.array([[0.0] * 6, [0, np.inf, 0, 0, 0, 0]]))
    with pytest.raises(ModelError, match="method 'svm' is not in this bundle"):
        model.predict_many(1, 1, np.zeros((1, 6)), method="svm")


def test_bundle_loads_without_pickle_or_sklearn(trained: Any, tmp_path: Path) -> None:
    """The arrays load with allow_pickle=False, and predicting imports no scikit-learn."""
    import subprocess
    import sys

    out = trained.model.save(tmp_path / "b")
    with np.load(out / "arrays.npz", allow_pickle=False) as npz:
        assert all(npz[k].dtype != object for k in npz.files)
    code = (
        "import sys; from timedexec.learning._bundle import DelayModel; "
        f"m = DelayModel.load({str(out)!r}); m.predict(joint=2, direction=1, q=[0]*6); "
        "m.predict_many([1, 2], [1, -1], [[0]*6, [0.1]*6], method='nn'); "
        "m.predict_many([1], [1], [[0]*6], method='rt'); "
        "print('sklearn' in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"


def test_non_gp_methods_report_their_cv_error_as_std(trained: Any) -> None:
    """Median/NN/tree give their cross-validated RMS error as the trial std, NaN latent."""
    p = trained.model.predict(joint=2, direction=1, q=np.zeros(6), method="rt")
    assert p.actuation_std == pytest.approx(
        trained.cv.to_dict()["actuation_delay"]["rt"]["2"] * 1e-3
    )
    assert np.isnan(p.actuation_latent_std)


def test_combined_model_prediction(trained: Any) -> None:
    """The combined model answers for every trained joint and refuses others."""
    p = trained.model.predict(joint=5, direction=-1, q=np.zeros(6), combined=True)
    assert 0.0 < p.actuation_mean < 0.1
    with pytest.raises(ModelError, match="joint 6 is unknown"):
        trained.model.predict(joint=6, direction=1, q=np.zeros(6), combined=True)


def test_time_input_separates_drift_and_predicts_warm(tmp_path: Path) -> None:
    """With a warm-up drift the sweep time as an input lowers the CV error; the bundle
    predicts at the end of the sweep by default, takes t_s, and a bundle without a time
    input refuses t_s."""
    drifting = synthetic_table(drift_s=0.006, seed=4)
    plain = cross_validate(drifting, folds=5, methods=("gpr",), random_state=0)
    timed = train_delay_models(drifting, folds=5, methods=("gpr",), random_state=0, time_input=True)
    assert timed.cv is not None
    e_plain = plain.to_dict()["actuation_delay"]["gpr"]["combined"]
    e_timed = timed.cv.to_dict()["actuation_delay"]["gpr"]["combined"]
    assert e_timed < 0.9 * e_plain  # a 6 ms drift against 2 ms noise: clearly resolved
    assert "sweep time" in timed.cv.table_text()
    model = DelayModel.load(timed.model.save(tmp_path / "t"))
    assert model.manifest["feature_order"]["per_joint"][-1] == "t_h"
    assert model.time_default_s == pytest.approx(float(drifting["t_start"].max()), rel=0.01)
    q = drifting.q[0]
    warm = model.predict(joint=2, direction=1, q=q)
    cold = model.predict(joint=2, direction=1, q=q, t_s=0.0)
    assert cold.actuation_mean - warm.actuation_mean > 0.003  # the 6 ms drift, mostly decayed
    many = model.predict_many([2, 2], [1, 1], np.vstack([q, q]), t_s=[0.0, model.time_default_s])
    # the batched path against the fast one, to rounding (gp_rounding_bounds)
    for i, (one, t_s) in enumerate(((cold, 0.0), (warm, None))):
        assert_fast_path_matches(model, one, many, i, joint=2, direction=1, q=q, t_s=t_s)
    plain_model = train_delay_models(drifting, folds=0, methods=("median",)).model
    with pytest.raises(ConfigError, match="no time input"):
        plain_model.predict(joint=2, direction=1, q=q, t_s=10.0, method="median")


def test_estimators_warn_nothing(table: DelayTable) -> None:
    """Fitting on a sweep-shaped table emits no warnings (no ill-conditioning, no overflow)."""
    X = encode_inputs(table.q, table["direction"], table["joint"], (1, 2, 3, 5))
    y = table["actuation_delay"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for cls in (LMNeuralNet, LinearLeafTree, DelayGP):
            cls(random_state=0).fit(X, y) if cls is not LinearLeafTree else cls().fit(X, y)


# ------------------------------------------------------- simulated robots

MODELS = Path(__file__).resolve().parent.parent / "models"


@pytest.mark.parametrize("robot", ROBOT_NAMES)
def test_bundled_models_load_and_meet_the_targets(robot: str) -> None:
    """The bundled model of every robot of the catalog loads for its robot and period, and
    its recorded CV (measured delays of a simulated sweep) shows every learned model beating
    the median on every actuation column, with the GP within 10 % of the noise floor."""
    from timedexec.robots import get_robot, get_robot_entry

    path = MODELS / get_robot_entry(robot).shipped_model
    # The bundles ship with the package: a missing one is a packaging error, not a skip.
    assert (path / "manifest.json").exists(), f"{path} missing (scripts/train_bundled_models.py)"
    model = DelayModel.load(path, robot=get_robot(robot))
    assert (path / "arrays.npz").stat().st_size < 2_000_000  # bundles stay small
    cv = model.cv_scores_ms
    floor = model.noise_floor_ms
    assert cv is not None
    assert floor is not None
    act = cv["actuation_delay"]
    for key in act["median"]:
        for m in ("nn", "rt", "gpr"):
            assert act[m][key] < act["median"][key], (m, key)
        assert act["gpr"][key] <= 1.10 * floor["actuation_delay"][key], key
    p = model.predict(joint=2, direction=1, q=[0.0, -1.2, 1.0, -1.4, -1.5, 0.0])
    period = get_robot(robot).controller_period_s
    assert 0.5 * period < p.actuation_mean < 15 * period  # paper: 2.5 (UR) to 7.5 (KUKA) periods
    assert 0.0 < p.actuation_std < period


@pytest.mark.slow
def test_simulated_sweep_models_beat_the_median_and_gp_reaches_the_floor() -> None:
    """A fresh simulated UR10 sweep (8,000 trials, ground-truth delays; about 20 s on two
    cores): on every joint and combined, every learned model beats the median on the
    actuation delay, and the GP is within 10 % of the noise floor.

    Bounded form (CI): 5-fold CV; the published 10 folds with TIMEDEXEC_FULL_TESTS=1 (the
    shipped bundles' recorded 10-fold scores are checked in the fast tier,
    test_bundled_models_load_and_meet_the_targets). The CV took 39 of the test's 42 s at 10
    folds and 16 s at 5 (jobs=2). Every trial is still held out exactly once, so each score
    is an RMS over the same 8,000 held-out predictions (~2,000 per joint) and its sampling
    noise is unchanged; only the training sets shrink from 90 % to 80 % of the 100
    configurations, which raises the learned models' errors in expectation: the assertions
    get harder to pass, not easier. Measured on this sweep, 10 -> 5 folds: GP /
    floor 1.025-1.044 -> 1.027-1.047 (bound 1.10), worst learned / median 0.984 -> 0.980
    (joint 5; bound 1), response delay / floor <= 1.0040 -> 1.0029 (bound 1.03)."""
    from timedexec.recording import SweepPlan
    from timedexec.sim import simulate_delays

    plan = SweepPlan.generate("ur10", 8000, seed=11)
    table = simulate_delays(
        "ur10", plan.q_start_rad, plan.joint, plan.direction, np.arange(8000) * 1.05,
        seed=11, jobs=2,
    )  # fmt: skip
    folds = full_or_bounded(10, 5)
    cv = cross_validate(table, folds=folds, jobs=2, random_state=0)
    act = cv.to_dict()["actuation_delay"]
    floor = cv.noise_floor_ms["actuation_delay"]
    for key in ("1", "2", "3", "5", "combined"):
        for m in ("nn", "rt", "gpr"):
            assert act[m][key] < act["median"][key], (m, key, act[m][key], act["median"][key])
        assert act["gpr"][key] <= 1.10 * floor[key], (key, act["gpr"][key], floor[key])
    # response delay carries no pose signal in the simulator: every model sits at the floor
    resp = cv.to_dict()["response_delay"]
    for m in DEFAULT_METHODS:
        # within 3 % of the replicate scatter (CV noise on ~2,000 held-out trials per joint,
        # whatever the number of folds)
        assert resp[m]["combined"] <= 1.03 * cv.noise_floor_ms["response_delay"]["combined"]


def test_fused_pair_predictor_matches_separate_predictors() -> None:
    """A joint's actuation and response GPs evaluated together (one kernel product) give the
    numbers of the separate predictors, exact or with a variance subset."""
    from timedexec.learning import GPPairPredictor

    table = synthetic_table(n_cfg=60, repeats=3)
    for mvc in (None, 40):
        model = train_delay_models(table, folds=0, methods="gpr", time_input=True).model
        for k in list(model._arrays):
            if k.endswith(".max_variance_conditions"):
                model._arrays[k] = np.array(0 if mvc is None else mvc)
        a = model.gp_predictor("actuation_delay", 3)
        b = model.gp_predictor("response_delay", 3)
        pair = GPPairPredictor.from_pair(a, b)
        assert pair is not None
        assert (a.var_index is None) == (mvc is None)
        for q in table.q[:10]:
            x = encode_inputs(q[None, :], [1], t_h=0.1)[0]
            fused = pair.predict_one(x)
            sep = (*a.predict_one(x), *b.predict_one(x))
            # rounding only: (mean, latent var) of each GP within gp_rounding_bounds
            tol = (*gp_rounding_bounds(a, x), *gp_rounding_bounds(b, x))
            assert np.all(np.abs(np.subtract(fused, sep)) <= tol), (fused, sep, tol)


def test_fits_run_every_blas_on_one_thread_and_restore_it() -> None:
    """The fits' BLAS pin covers numpy's and SciPy's own OpenBLAS (two libraries here),
    nests, and restores the previous thread counts; it keeps its library handles, so a fit
    no longer pays threadpoolctl's library lookup (2.3 ms) on every call."""
    import scipy.linalg  # noqa: F401  (SciPy's BLAS loaded, as in a fit)
    from threadpoolctl import threadpool_info, threadpool_limits

    from timedexec.learning import single_threaded_blas

    def blas_threads() -> dict[str, int]:
        return {lib["filepath"]: lib["num_threads"] for lib in threadpool_info()
                if lib["user_api"] == "blas"}  # fmt: skip

    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        assert set(before.values()) == {2}
        with single_threaded_blas():
            assert set(blas_threads()) == set(before)
            assert set(blas_threads().values()) == {1}
            with single_threaded_blas():
                pass
            assert set(blas_threads().values()) == {1}  # the inner block left it pinned
        assert blas_threads() == before
