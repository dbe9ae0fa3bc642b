"""`timedexec simulate`: determinism, the truth table, bad input."""

from __future__ import annotations

import os

import numpy as np
import pytest

from timedexec.cli import main
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError
from timedexec.recording import RecordingReader, SweepPlan
from timedexec.robots import ROBOT_NAMES, get_robot


def simulate(tmp_path, name, *extra):
    out = tmp_path / f"{name}.h5"
    code = main(["simulate", "--robot", "ur10", "--trials", "600", "--seed", "7",
                 "--out", str(out), "--quiet", *extra])  # fmt: skip
    assert code == 0
    return out


def test_same_seed_same_recording_whatever_the_workers(tmp_path):
    """Same seed, same output: every per-trial dataset is identical with one worker and
    with two (random streams are keyed by trial block, not by worker)."""
    a = simulate(tmp_path, "a")
    b = simulate(tmp_path, "b", "--jobs", "2")
    with RecordingReader(a) as ra, RecordingReader(b) as rb:
        assert ra.n_trials == rb.n_trials == 600
        for name in ra.fields:
            np.testing.assert_array_equal(ra.read(name), rb.read(name), err_msg=name)
        np.testing.assert_array_equal(ra.static("still_gyro_raw"), rb.static("still_gyro_raw"))


def test_truth_table_follows_the_delay_table_contract(tmp_path):
    """--truth writes a delay table with the true delays in the delay columns."""
    truth = tmp_path / "truth.csv"
    simulate(tmp_path, "t", "--truth", str(truth))
    table = DelayTable.read_csv(truth)
    assert len(table) == 600
    np.testing.assert_array_equal(table["actuation_delay"], table["true_actuation_delay"])
    assert set(table.robots) == {"ur10"}
    # Delays are seconds: the UR10's actuation lies in the published 5-45 ms band.
    assert 0.005 < np.median(table["actuation_delay"]) < 0.045


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--robot", "ur5", "--trials", "10"], f"unknown robot 'ur5'; choose one of {', '.join(ROBOT_NAMES)}"),
        (["--robot", "ur10", "--trials", "0"], "argument --trials: 0 is out of range; use an integer from 1 to 10000000"),
        (["--robot", "ur10", "--trials", "-3"], "-3 is out of range"),
        (["--robot", "ur10", "--trials", "20000000"], "20000000 is out of range"),
        (["--robot", "kr5", "--trials", "10", "--period", "0.005"], "0.012, 0.004"),
        (["--robot", "ur10", "--trials", "10", "--effects", "friction"], "the vocabulary is"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message_and_writes_nothing(tmp_path, capsys, args, message):
    """Unknown robot, non-positive trial count, a period the robot does not have, an
    unknown effect: exit code 2, a message naming the value and the allowed range, and no
    file left behind."""
    out = tmp_path / "x.h5"
    assert main(["simulate", *args, "--seed", "1", "--out", str(out), "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_unwritable_output_exits_2_and_leaves_nothing(tmp_path, capsys):
    """An output in a missing or read-only folder: exit 2, the path named, nothing created."""
    missing = tmp_path / "no" / "such" / "dir" / "x.h5"
    assert main(["simulate", "--robot", "ur10", "--trials", "5", "--out", str(missing),
                 "--quiet"]) == 2  # fmt: skip
    assert str(missing.parent) in capsys.readouterr().err
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders; the missing-folder case covers it")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        assert main(["simulate", "--robot", "ur10", "--trials", "5", "--out", str(ro / "x.h5"),
                     "--quiet"]) == 2  # fmt: skip
        assert not any(ro.iterdir())
    finally:
        ro.chmod(0o700)


def test_existing_recording_is_not_overwritten(tmp_path, capsys):
    """A second run onto the same file is refused unless --resume (no data lost)."""
    out = simulate(tmp_path, "a")
    before = out.stat().st_size
    assert main(["simulate", "--robot", "ur10", "--trials", "600", "--seed", "7", "--out",
                 str(out), "--quiet"]) == 2  # fmt: skip
    assert "--resume" in capsys.readouterr().err
    assert out.stat().st_size == before
    assert main(["simulate", "--robot", "ur10", "--trials", "600", "--seed", "7", "--out",
                 str(out), "--quiet", "--resume"]) == 0  # fmt: skip


def test_configuration_outside_the_joint_limits_is_refused():
    """A plan configuration outside the limits names the joint, the value and the range."""
    spec = get_robot("kr5")
    q = np.array([spec.home_q_rad])
    q[0, 1] = 1.0  # A2 limit is +45°
    with pytest.raises(ConfigError, match=r"joint 2 = 1 rad .* outside the allowed range"):
        SweepPlan(robot="kr5", q_start_rad=q, joint=np.array([2]), direction=np.array([1]),
                  config_index=np.array([0]), repeat=np.array([0]))  # fmt: skip
