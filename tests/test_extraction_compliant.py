"""The response delay on compliant joints read by motor-side encoders (issue 37).

Recordings from tests/compliant_sweep.py (hysteretic, stiffening gears between a motor-side
encoder and a gravity-loaded link; its own sensor, oscillator and USB). Small sweeps keep
this fast; benchmarks/bench_extract_compliant.py measures the same on 200 trials per
condition, before and after.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from compliant_sweep import CompliantConditions, write_compliant_sweep
from independent_sweep import Conditions, write_independent_sweep
from timedexec.extraction import extract_recording


def _response(t: Any, joints: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Response errors and standard errors (s) of the unflagged trials of ``joints``."""
    ok = np.array([not f for f in t["flag"]]) & np.isin(t["joint"], joints)
    return (t["response_delay"] - t["true_response_delay"])[ok], t["response_delay_se"][ok]


@pytest.fixture(scope="module")
def ur10_table(tmp_path_factory: pytest.TempPathFactory) -> Any:
    p = tmp_path_factory.mktemp("compliant") / "ur10.h5"
    write_compliant_sweep(p, "ur10", 64, CompliantConditions(), seed=3)
    return extract_recording(p, progress=False).table


def test_heavy_joints_response_is_the_motor_age_with_honest_errors(ur10_table: Any) -> None:
    """UR10 with hysteretic harmonic drives, 64 trials: the response delay of the heavy
    joints (2 and 3) is the motor sample's age within ±0.2 ms of bias per joint, and the
    95 % intervals cover it on >= 85 % of their trials. Measured here: -0.037 / +0.034 ms,
    94 % (36 trials); on 200 trials -0.068 / +0.030 ms, 88 / 100 %. Before the deflection
    was separated the fit read -0.73 / -0.36 ms with intervals covering 3 % (200 trials:
    -0.78 / -0.48 ms, 0 %): confident and wrong. The band: ~18 trials per joint put a
    standard error of ~0.05 ms on each mean, and the gear law's unknown part leaves up to
    ±0.07 ms on 200 trials; 36 trials put a binomial sd of ~4 % on the coverage."""
    t = ur10_table
    for joint in (2, 3):
        err, _ = _response(t, (joint,))
        assert err.size >= 10
        assert abs(float(np.mean(err))) <= 0.2e-3, (joint, np.mean(err))
    err, se = _response(t, (2, 3))
    assert np.mean(np.abs(err) <= 1.96 * se) >= 0.85
    deflected = np.isin(t["joint"], (2, 3))
    assert np.all(np.isfinite(t["response_deflection_s"][deflected]))
    # The separation moved the heavy joints' ages later (the link lags the motor).
    assert np.median(t["response_deflection_s"][deflected]) > 0.2e-3


def test_actuation_unchanged_by_compliance(ur10_table: Any) -> None:
    """The actuation delay is timed on the link's speed, which the gyro sees, so the
    motor-side encoder does not touch it: RMSE <= 0.2 ms on these 64 trials (200 trials:
    0.130 ms clean), nothing flagged."""
    t = ur10_table
    ok = np.array([not f for f in t["flag"]])
    e = (t["actuation_delay"] - t["true_actuation_delay"])[ok]
    assert ok.all()
    assert np.sqrt(np.mean(e**2)) <= 0.2e-3


def test_a_rigid_joint_gets_no_deflection_terms(tmp_path: Path) -> None:
    """A recording whose reported angle is the link's (tests/independent_sweep.py: the gear
    is between motor and link, the encoder on the link) has no deflection to separate: no
    joint gets the terms (they would only add variance: response RMSE 0.023 -> 0.060 ms on
    our simulator), so its response delays are the fit's as before."""
    p = write_independent_sweep(tmp_path / "rigid.h5", "ur10", 48, Conditions(), seed=3)
    t = extract_recording(p, progress=False).table
    assert np.all(np.isnan(t["response_deflection_s"]))
    err, _ = _response(t, (1, 2, 3, 5))
    assert np.sqrt(np.mean(err**2)) <= 0.15e-3


@pytest.mark.slow
@pytest.mark.parametrize(
    ("robot", "cond"),
    [("ur10", CompliantConditions(noise_factor=5.0)), ("kr5", CompliantConditions())],
)
def test_compliant_conditions_bounded(tmp_path: Path, robot: str, cond: Any) -> None:
    """Two of the benchmark's conditions, 96 trials each: UR10 at 5x noise and a KR 5
    (cycloidal gears with a soft zone). Every joint's response bias within ±0.3 ms and the
    intervals covering >= 85 % of all trials. Measured (joints 1/2/3/5): UR10 +0.11 /
    +0.20 / +0.06 / -0.01 ms, 99 %; KR 5 -0.01 / +0.00 / +0.03 / +0.03 ms, 98 %; before
    the change -0.24 / -0.70 / -0.33 / -0.01 ms, 42 % and -0.41 / -0.29 / -0.19 / -0.05 ms,
    39 % (fails both). 96 trials put ~0.06 ms of sampling error on a joint's mean, and the
    lightly loaded base joints keep up to ~0.27 ms of bias on 200 trials (README)."""
    p = write_compliant_sweep(tmp_path / f"{robot}.h5", robot, 96, cond, seed=2)
    t = extract_recording(p, progress=False).table
    for joint in (1, 2, 3, 5):
        err, _ = _response(t, (joint,))
        assert abs(float(np.mean(err))) <= 0.3e-3, (joint, np.mean(err))
    err, se = _response(t, (1, 2, 3, 5))
    assert np.mean(np.abs(err) <= 1.96 * se) >= 0.85
