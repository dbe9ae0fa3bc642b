"""The response-only verdict of a delay table (issue 37): ``response_flag``.

A trial whose response delay is not trustworthy while its actuation delay is (extraction
writes ``deflection`` where a compliant gear's deflection cannot be separated from the
state's age) keeps both values; everything that uses response delays leaves its response
out and still uses its actuation delay. Tables without the column read as before.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from timedexec.delays import JOINT_RESPONSE_FLAGS, RESPONSE_FLAG_WHY, DelayTable
from timedexec.errors import ConfigError
from timedexec.extraction import RESPONSE_FLAGS
from timedexec.learning import cross_validate, train_delay_models
from timedexec.report import delay_summary

#: Response delay written into the flagged rows: a value a model must not learn, s.
BAD_RESPONSE_S = 0.5
#: Actuation delay of the flagged rows, s (the others' is 0.020 s): it must be learnt.
FLAGGED_ACTUATION_S = 0.030


def _table(flagged: int = 2, *, column: bool = True, seed: int = 4) -> DelayTable:
    """A UR10 sweep-shaped table (16 poses x joints 1, 2 x both directions x 3 repeats) whose
    first ``flagged`` repeats of each condition carry ``response_flag = "deflection"`` with
    a response delay of ``BAD_RESPONSE_S`` and an actuation delay of
    ``FLAGGED_ACTUATION_S``; ``column=False`` leaves the column out (and flags nothing)."""
    rng = np.random.default_rng(seed)
    cfg = rng.uniform(-2.0, 2.0, (16, 6))
    cfg[:, 5] = 0.0
    rows = [(c, j, d) for c in range(16) for j in (1, 2) for d in (1, -1) for _ in range(3)]
    n = len(rows)
    q = cfg[[r[0] for r in rows]]
    flagged = column & (np.arange(n) % 3 < flagged)
    cols: dict[str, Any] = {
        "trial": np.arange(n),
        "robot": "ur10",
        "joint": np.array([r[1] for r in rows]),
        "direction": np.array([r[2] for r in rows]),
        "t_start": np.arange(n, dtype=float),
        "actuation_delay": np.where(flagged, FLAGGED_ACTUATION_S, 0.020)
        + 1e-4 * rng.standard_normal(n),
        "response_delay": np.where(flagged, BAD_RESPONSE_S, 0.004)
        + 1e-4 * rng.standard_normal(n),
        **{f"q{i + 1}": q[:, i] for i in range(6)},
    }
    if column:
        cols["response_flag"] = np.where(flagged, "deflection", "").astype(object)
    return DelayTable(cols, source="synthetic")


def test_learning_trains_actuation_on_response_flagged_rows_but_not_response() -> None:
    """With two of three repeats response-flagged (their response 0.5 s, their actuation
    30 ms), the median models answer the others' response (4 ms) and the actuation of all
    rows (the median of a 2:1 mix of 30 and 20 ms: 30 ms). Tolerance: the synthetic
    noise is 0.1 ms; a model trained on the flagged responses would answer 500 ms."""
    t = _table()
    n_flagged = int(np.sum(t["response_flag"] == "deflection"))
    model = train_delay_models(t, folds=0, methods="median").model
    for joint in (1, 2):
        p = model.predict(joint=joint, direction=1, q=t.q[0], method="median")
        assert abs(p.response_mean - 0.004) < 1e-3
        assert abs(p.actuation_mean - FLAGGED_ACTUATION_S) < 1e-3
    training = model.manifest["training_data"]
    assert training["trials"] == len(t)  # every row trains the actuation models
    assert training["response_flagged"] == n_flagged


def test_cross_validation_scores_the_response_on_usable_rows_only() -> None:
    """The response column of the CV table is the median's error on unflagged rows
    (~0.1 ms of noise), not one dominated by the flagged 0.5 s values."""
    cv = cross_validate(_table(), folds=4, methods="median")
    assert cv.scores_ms["response_delay"]["median"]["average"] < 0.5


def test_a_joint_whose_every_response_is_flagged_is_refused() -> None:
    """Nothing to learn a joint's response from is a ConfigError naming the joint and the
    reasons, not a crash inside an estimator."""
    t = _table(flagged=0)
    flags = np.where(t["joint"] == 2, "deflection", "").astype(object)
    cols = {**t.columns, "response_flag": flags}
    with pytest.raises(ConfigError, match=r"every response delay of joint 2 .*deflection: 96"):
        train_delay_models(DelayTable(cols, source="t.csv"), folds=0, methods="median")


def test_a_joint_flagged_as_a_whole_trains_on_its_responses_with_a_warning() -> None:
    """A joint whose every trial is flagged ``deflection_joint`` (its lag mostly gear play,
    the age its trials share known to ~0.15 ms only) still gets a response model from its
    own trials, with a warning naming the joint: refusing would leave a compliant arm (the
    benchmark's KR 5 base joint) with no model at all. Tolerance: 0.1 ms synthetic noise."""
    t = _table(flagged=0)
    flags = np.where(t["joint"] == 2, "deflection_joint", "").astype(object)
    cols = {**t.columns, "response_flag": flags}
    with pytest.warns(UserWarning, match=r"every response delay of joint 2 is flagged"):
        model = train_delay_models(
            DelayTable(cols, source="t.csv"), folds=0, methods="median"
        ).model
    p = model.predict(joint=2, direction=1, q=t.q[0], method="median")
    assert abs(p.response_mean - 0.004) < 1e-3


def test_a_joint_flagged_for_the_gyros_noise_trains_with_a_warning_that_says_so() -> None:
    """A joint whose trials are all flagged ``deflection_noise`` (the gyro's noise hid the
    gear's deflection terms: its ages read short) — some chunks of it may carry
    ``deflection_joint`` instead — trains on its own responses like a play-flagged joint,
    and the warning names the cause and the fix (a quieter gyro). A joint flagged
    per trial (``deflection``) on every row still refuses (above)."""
    t = _table(flagged=0)
    on_2 = np.flatnonzero(t["joint"] == 2)
    flags = np.full(len(t), "", dtype=object)
    flags[on_2] = "deflection_noise"
    flags[on_2[:5]] = "deflection_joint"
    cols = {**t.columns, "response_flag": flags}
    with pytest.warns(UserWarning, match=r"joint 2 is flagged .*deflection_noise.*quieter gyro"):
        train_delay_models(DelayTable(cols, source="t.csv"), folds=0, methods="median")


def test_a_table_without_the_column_trains_as_before(tmp_path: Path) -> None:
    """An old table (no ``response_flag``) and the same table with an empty column train
    the same bundle: the training data's hash and the manifest are unchanged (no
    ``response_flagged`` entry)."""
    old = _table(column=False)
    cols = {**old.columns, "response_flag": np.full(len(old), "", dtype=object)}
    new = DelayTable(cols, source="synthetic")
    a = train_delay_models(old, folds=0, methods="median").model.manifest["training_data"]
    b = train_delay_models(new, folds=0, methods="median").model.manifest["training_data"]
    assert a["arrays_sha256"] == b["arrays_sha256"]
    assert "response_flagged" not in a
    assert "response_flagged" not in b


def test_the_column_round_trips_and_says_what_is_usable(tmp_path: Path) -> None:
    """CSV keeps the reasons (empty fields stay empty); ``usable`` rules out the response
    delay of a response-flagged row and both delays of a flagged one; ``reason_counts``
    counts them; an old CSV without the column flags nothing."""
    t = _table(flagged=1)
    cols = {**t.columns, "flag": np.where(np.arange(len(t)) == 0, "no_onset", "").astype(object)}
    t = DelayTable(cols, source="synthetic")
    back = DelayTable.read_csv(t.to_csv(tmp_path / "d.csv"))
    assert list(back["response_flag"]) == list(t["response_flag"])
    rf = np.array([bool(f) for f in t["response_flag"]])
    assert np.array_equal(back.usable("response_delay"), ~rf & (np.arange(len(t)) != 0))
    assert np.array_equal(back.usable("actuation_delay"), np.arange(len(t)) != 0)
    assert back.reason_counts("response_flag") == {"deflection": int(rf.sum())}
    assert back.reason_counts("flag") == {"no_onset": 1}
    old = _table(column=False)
    old_back = DelayTable.read_csv(old.to_csv(tmp_path / "old.csv"))
    assert old_back.usable("response_delay").all()
    assert old_back.reason_counts("response_flag") == {}
    with pytest.raises(ConfigError, match=r"unknown delay 'latency'; choose one of"):
        old_back.usable("latency")


def test_report_summary_counts_response_flags_and_leaves_their_response_out() -> None:
    """The report's per-joint response statistics use the unflagged rows only (4 ms, not
    a median pulled towards 0.5 s), and it counts the response flags by reason."""
    s = delay_summary(_table())
    assert s["response_flagged"] == s["response_flag_reasons"]["deflection"] > 0
    for row in s["joints"].values():
        assert abs(row["response_delay"]["median_ms"] - 4.0) < 1.0
        assert abs(row["actuation_delay"]["median_ms"] - 30.0) < 1.0


def test_every_response_flag_extraction_writes_is_explained() -> None:
    """The extraction summary and training's warnings explain a flag from
    ``timedexec.delays.RESPONSE_FLAG_WHY``: a new reason the extraction writes without its
    entry there would be named unexplained. The joint-wide ones, which training accepts as
    a joint's only measurement, are among them."""
    assert set(RESPONSE_FLAGS) == set(RESPONSE_FLAG_WHY)
    assert set(JOINT_RESPONSE_FLAGS) <= set(RESPONSE_FLAGS)
