"""The method registry: every registered delay-model method is complete.

One module per method declares it (``timedexec.learning.DelayMethod``); these tests run
every registered method through everything a method must support, so a new method with a
gap fails here with a message naming it: its declaration, the estimator contract, its
export against its declared arrays, its deployed predictor against its estimator, a bundle
round trip (arrays bit-equal, predictions through ``predict_many`` and the fast
``predict``), cross-validation and training through ``train_delay_models``, and loading
and predicting without scikit-learn.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError

from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, ModelError
from timedexec.learning import (
    DEFAULT_METHODS,
    DELAYS,
    METHODS,
    DelayMethod,
    DelayModel,
    ModelInputs,
    check_methods,
    describe_methods,
    encode_inputs,
    get_method,
    make_estimator,
    train_delay_models,
)

JOINTS = (1, 2, 3, 5)
# Two evaluations of the same formulas in another order (one row at a time, a fused pair of
# GPs) differ by rounding: ~1e-17 s on delays of ~0.02 s (measured: GP 3.8e-17 s,
# docs/models.md). 1e-12 s is ten thousand times that and a billionth of a period; a real
# disagreement (a wrong constant, a dropped array, another standardisation) errs by more
# than 1e-6 s.
ATOL_S = 1e-12
# Standard deviations: the same, relative. A GP's variance sums terms of both signs
# (σ_f² - kᵀBk): its rounding is ~1e-9 of the trial variance at worst
# (tests/test_learning.py, gp_rounding_bounds), so 1e-7 leaves a margin of 100.
RTOL_STD = 1e-7


def sweep_table(n_cfg: int = 12, repeats: int = 3, seed: int = 3) -> DelayTable:
    """A small sweep-shaped UR10 table: pose-, joint- and direction-dependent actuation
    delay, a constant response delay, trial noise and a warm-up drift."""
    rng = np.random.default_rng(seed)
    cfg = rng.uniform(-2.5, 2.5, (n_cfg, 6))
    cfg[:, 5] = 0.0
    rows = [
        (c, j, d) for c in range(n_cfg) for j in JOINTS for d in (1, -1) for _ in range(repeats)
    ]
    c_idx, joint, direction = (np.array(v) for v in zip(*rows, strict=True))
    q = cfg[c_idx]
    t_start = np.arange(len(rows)) * 2.0
    act = (
        0.020
        + 0.004 * np.sin(q[:, 1]) * direction
        + 0.003 * np.cos(q[:, 2])
        + 0.001 * joint
        + 0.003 * np.exp(-t_start / 300.0)
        + 0.002 * rng.standard_normal(len(rows))
    )
    resp = 0.004 + 0.001 * rng.standard_normal(len(rows))
    cols: dict[str, Any] = {
        "trial": np.arange(len(rows)),
        "robot": "ur10",
        "joint": joint,
        "direction": direction,
        "t_start": t_start,
        "actuation_delay": act,
        "response_delay": resp,
    }
    for i in range(6):
        cols[f"q{i + 1}"] = q[:, i]
    return DelayTable(cols, source="registry-test")


@pytest.fixture(scope="module")
def table() -> DelayTable:
    return sweep_table()


def model_data(table: DelayTable, key: str, time_input: bool) -> tuple[np.ndarray, ...]:
    """Encoded inputs, both delays and the query rows (the table's own poses, both
    directions) of the model ``key``."""
    rows = (
        np.arange(len(table)) if key == "combined" else np.flatnonzero(table["joint"] == int(key))
    )
    t_h = table["t_start"][rows] / 3600.0 if time_input else None
    joints = JOINTS if key == "combined" else None
    jt = table["joint"][rows] if key == "combined" else None
    X = encode_inputs(table.q[rows], table["direction"][rows], jt, joints, t_h=t_h)
    return X, table["actuation_delay"][rows], table["response_delay"][rows], rows


def fit_bundle(
    name: str, table: DelayTable, time_input: bool
) -> tuple[DelayModel, dict[tuple[str, str], Any]]:
    """Fit ``name``'s estimators directly (per-joint model of joint 2 and the combined
    model, both delays) and assemble them into a bundle as training does."""
    method = get_method(name)
    finals: dict[tuple[str, str, str], Any] = {}
    estimators: dict[tuple[str, str], Any] = {}
    for key in ("2", "combined"):
        inputs = ModelInputs.of("ur10", key, JOINTS, time_input)
        X, act, resp, _ = model_data(table, key, time_input)
        for delay, y in zip(DELAYS, (act, resp), strict=True):
            est = make_estimator(name, random_state=0, inputs=inputs)
            assert est.fit(X, y) is est, f"{name}: fit must return self"
            arrays = est.to_arrays()
            problem = method.check_arrays(arrays, inputs)
            assert problem == "", (
                f"{name}: to_arrays() does not match its declared arrays: {problem}"
            )
            rmse = float(np.sqrt(np.mean((est.predict(X) - y) ** 2)))
            info = method.info(est)
            json.dumps(info)  # the manifest is JSON
            finals[(name, delay, key)] = {"arrays": arrays, "train_rmse_s": rmse, "info": info}
            estimators[(delay, key)] = est
    t = table["t_start"]
    model = DelayModel.from_training(
        finals,
        robot="ur10",
        period_s=0.008,
        joints=JOINTS,
        keys=["2", "combined"],
        methods=[name],
        cv=None,
        training={"trials": len(table)},
        time_input=time_input,
        time_range_s=(float(t.min()), float(t.max())),
    )
    return model, estimators


# ---------------------------------------------------------------- declarations


def test_registry_lists_each_method_once_with_the_papers_four_as_default() -> None:
    """The registry names every method once; the default is the paper's four, in the
    published order; each is described for --help; unknown names are refused."""
    assert len(set(METHODS)) == len(METHODS)
    assert DEFAULT_METHODS == ("median", "nn", "rt", "gpr")
    assert METHODS[:4] == DEFAULT_METHODS
    text = describe_methods()
    for name in METHODS:
        method = get_method(name)
        assert isinstance(method, DelayMethod)
        assert method.name == name
        assert f"  {name} " in text
        assert method.description in text
    assert check_methods(",".join(METHODS)) == METHODS
    with pytest.raises(ConfigError, match=r"unknown method 'svm'; choose from median, nn"):
        get_method("svm")
    with pytest.raises(ConfigError, match=r"unknown or no method\(s\) svm"):
        check_methods("median,svm")


def test_a_method_declaration_is_checked_where_it_is_written() -> None:
    """A DelayMethod with an unusable name, cost or array list fails on import of its
    module, naming the method and the fix."""
    gpr = get_method("gpr")
    with pytest.raises(ConfigError, match="lower case letters"):
        dataclasses.replace(gpr, name="GP.2")
    with pytest.raises(ConfigError, match="fit_cost=0"):
        dataclasses.replace(gpr, fit_cost=0)
    with pytest.raises(ConfigError, match="distinct names"):
        dataclasses.replace(gpr, arrays=(("a", ("n",)), ("a", ("n",))))
    with pytest.raises(ConfigError, match="a pair predictor needs a variance"):
        dataclasses.replace(gpr, variance=False)


# ---------------------------------------------------------------- every method


@pytest.mark.parametrize("name", METHODS)
def test_method_follows_the_estimator_contract(name: str, table: DelayTable) -> None:
    """The research estimator: parameters round-trip (scikit-learn's clone), predicting
    before fit raises NotFittedError, learned state ends in '_'."""
    inputs = ModelInputs.of("ur10", "2", JOINTS, False)
    est = make_estimator(name, random_state=0, inputs=inputs)
    params = est.get_params()
    assert clone(est).get_params() == params
    assert est.set_params(**params) is est
    X, y, _, _ = model_data(table, "2", False)
    with pytest.raises(NotFittedError):
        est.predict(X)
    before = set(vars(est))
    est.fit(X, y)
    learned = set(vars(est)) - before
    assert learned
    assert all(k.endswith("_") for k in learned), sorted(learned)


@pytest.mark.parametrize("time_input", [False, True], ids=["published-inputs", "time-input"])
@pytest.mark.parametrize("name", METHODS)
def test_method_round_trips_through_a_bundle(
    name: str, time_input: bool, table: DelayTable, tmp_path: Path
) -> None:
    """Export -> bundle -> load: the arrays come back bit for bit, and the loaded bundle's
    predictions (batched and the one-command fast path, per-joint and combined) equal the
    estimator's own, means and (with a variance) standard deviations, within rounding."""
    method = get_method(name)
    model, estimators = fit_bundle(name, table, time_input)
    out = model.save(tmp_path / "a")
    loaded = DelayModel.load(out, robot="ur10", period_s=0.008)
    again = loaded.save(tmp_path / "b")
    assert (again / "arrays.npz").read_bytes() == (out / "arrays.npz").read_bytes()
    for key in ("2", "combined"):
        combined = key == "combined"
        _, _, _, rows = model_data(table, key, time_input)
        rows = rows[table["joint"][rows] == 2][:24]  # joint 2's trials: both models answer
        q, d = table.q[rows], table["direction"][rows]
        t_s = table["t_start"][rows] if time_input else None
        many = loaded.predict_many(2, d, q, t_s=t_s, method=name, combined=combined)
        t_h = None if t_s is None else t_s / 3600.0
        X = encode_inputs(q, d, 2 if combined else None, JOINTS if combined else None, t_h=t_h)
        for short, delay in (("actuation", "actuation_delay"), ("response", "response_delay")):
            est = estimators[(delay, key)]
            mean = getattr(many, f"{short}_mean")
            std = getattr(many, f"{short}_std")
            np.testing.assert_allclose(mean, est.predict(X), rtol=0, atol=ATOL_S, err_msg=name)
            if method.variance:
                _, est_std = est.predict(X, return_std=True)
                np.testing.assert_allclose(std, est_std, rtol=RTOL_STD, err_msg=name)
                assert np.all(getattr(many, f"{short}_latent_std") <= std)
            else:  # no CV: the training RMS error, NaN latent std
                rmse = model.manifest["model_info"][name][delay][key]["train_rmse_ms"] * 1e-3
                np.testing.assert_array_equal(std, rmse)
                assert np.all(np.isnan(getattr(many, f"{short}_latent_std")))
        for i in range(3):
            one = loaded.predict(
                joint=2,
                direction=int(d[i]),
                q=q[i],
                t_s=None if t_s is None else float(t_s[i]),
                method=name,
                combined=combined,
            )
            for field, value in one._asdict().items():
                ref = getattr(many, field)[i]
                if np.isnan(ref):
                    assert np.isnan(value), (name, field)
                elif field.endswith("mean"):
                    assert abs(value - ref) <= ATOL_S, (name, field, value, ref)
                else:
                    assert value == pytest.approx(ref, rel=RTOL_STD), (name, field)


@pytest.mark.parametrize("name", METHODS)
def test_method_trains_and_cross_validates(name: str, table: DelayTable, tmp_path: Path) -> None:
    """train_delay_models with only this method: CV scores for every column (in the JSON
    and the printed table), a bundle that loads and answers for every joint."""
    res = train_delay_models(table, methods=(name,), folds=3, random_state=0, time_input=True)
    assert res.cv is not None
    for delay in DELAYS:
        scores = res.cv.to_dict()[delay][name]
        assert list(scores) == [*map(str, JOINTS), "combined", "average"]
        assert all(np.isfinite(v) and v > 0 for v in scores.values()), scores
    assert f"\n{name:8}" in res.cv.table_text()
    model = DelayModel.load(res.model.save(tmp_path / "m"), robot="ur10")
    assert model.methods == (name,)
    assert set(model.manifest["model_info"][name]["actuation_delay"]) == {
        "1",
        "2",
        "3",
        "5",
        "combined",
    }
    p = model.predict_many(list(JOINTS), 1, table.q[:4], method=name)
    assert np.all(np.isfinite(p.actuation_mean))
    assert np.all(p.actuation_std > 0)


def test_every_method_loads_and_predicts_without_scikit_learn(
    table: DelayTable, tmp_path: Path
) -> None:
    """A bundle holding every registered method loads and predicts with each of them
    (one command and a batch) without importing scikit-learn or unpickling anything."""
    res = train_delay_models(table, methods=METHODS, folds=0, random_state=0)
    out = res.model.save(tmp_path / "all")
    with np.load(out / "arrays.npz", allow_pickle=False) as npz:
        assert all(npz[k].dtype != object for k in npz.files)
    code = (
        "import sys; from timedexec.learning import DelayModel, METHODS; "
        f"m = DelayModel.load({str(out)!r}); "
        "[m.predict(joint=2, direction=1, q=[0.1]*6, method=n) for n in METHODS]; "
        "[m.predict_many([1, 5], [1, -1], [[0]*6, [0.2]*6], method=n) for n in METHODS]; "
        "print(sorted(m.methods) == sorted(METHODS), 'sklearn' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["True", "False"]


# ---------------------------------------------------------------- the checks bite


def test_a_method_with_a_gap_fails_these_checks(table: DelayTable, tmp_path: Path) -> None:
    """What the tests above catch: a declared array its estimator does not export, a
    predictor that disagrees with its estimator, and (at load) arrays that do not fit the
    declared shapes."""
    median = get_method("median")
    inputs = ModelInputs.of("ur10", "2", JOINTS, False)
    X, y, _, _ = model_data(table, "2", False)
    est = median.estimator(inputs, 0).fit(X, y)
    declares_more = dataclasses.replace(median, arrays=(("scalars", ("1",)), ("spread", ("1",))))
    assert declares_more.check_arrays(est.to_arrays(), inputs) == "array 'spread' is missing"
    wrong_shape = dataclasses.replace(median, arrays=(("scalars", ("2",)),))
    assert "axis 0 should be 2" in wrong_shape.check_arrays(est.to_arrays(), inputs)
    off = dataclasses.replace(
        median, predictor=lambda a, i: median.predictor({"scalars": a["scalars"] + 1e-6}, i)
    )
    mean, _ = off.predictor(est.to_arrays(), inputs).predict(X)
    assert np.max(np.abs(mean - est.predict(X))) > ATOL_S
    # a bundle whose median arrays were rewritten with another shape (hash updated)
    model, _ = fit_bundle("median", table, False)
    out = model.save(tmp_path / "b")
    with np.load(out / "arrays.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["median.actuation_delay.2.scalars"] = np.zeros(2)
    broken = DelayModel(model.manifest, arrays)
    with pytest.raises(ModelError, match=r"median model of the actuation_delay \(2\) is corrupt"):
        DelayModel.load(broken.save(tmp_path / "c"))
