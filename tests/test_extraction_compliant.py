"""The response delay on compliant joints read by motor-side encoders (issue 37).

Recordings from tests/compliant_sweep.py (hysteretic, stiffening gears between a motor-side
encoder and a gravity-loaded link; its own sensor, oscillator and USB). Small sweeps keep
this fast; benchmarks/bench_extract_compliant.py measures the same on 200 trials per
condition, before and after.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from compliant_sweep import CompliantConditions, write_compliant_sweep
from independent_sweep import Conditions, write_independent_sweep
from timedexec.cli import main
from timedexec.extraction import extract_recording


def _usable(t: Any) -> np.ndarray:
    """Trials whose response delay may be used: no ``flag``, no ``response_flag``."""
    return np.asarray(t.usable("response_delay"))


def _response(t: Any, joints: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Response errors and standard errors (s) of the usable trials of ``joints``."""
    ok = _usable(t) & np.isin(t["joint"], joints)
    return (t["response_delay"] - t["true_response_delay"])[ok], t["response_delay_se"][ok]


@pytest.fixture(scope="module")
def ur10_table(tmp_path_factory: pytest.TempPathFactory) -> Any:
    p = tmp_path_factory.mktemp("compliant") / "ur10.h5"
    write_compliant_sweep(p, "ur10", 128, CompliantConditions(), seed=3)
    return extract_recording(p, progress=False).table


def test_compliant_response_meets_the_targets_on_the_unflagged_trials(ur10_table: Any) -> None:
    """UR10 with hysteretic harmonic drives, 128 trials (~30 per joint): on the trials
    without a response flag every joint's response delay is the motor sample's age within
    0.2 ms RMS and 0.12 ms of bias (issue 37: 0.2 / 0.1 ms on 200 trials; ~30 trials put
    ~0.02-0.03 ms of sampling error on a joint's mean). Measured here (joints 1/2/3/5):
    0.12 (+0.07) / 0.17 (+0.04) / 0.09 (+0.01) / 0.05 (-0.03) ms (before the sharpening:
    0.12 (+0.09) / 0.17 (+0.07) / 0.10 (+0.04) / 0.05 (-0.03)); round 1's extractor read
    0.21 (+0.15) / 0.24 (+0.07) / 0.11 / 0.05 ms with nothing flagged (joints 1 and 2 fail).
    Before the deflection was separated at all: -0.7 ms on joint 2."""
    t = ur10_table
    for joint in (1, 2, 3, 5):
        err, _ = _response(t, (joint,))
        assert err.size >= 15
        assert np.sqrt(np.mean(err**2)) <= 0.2e-3, (joint, np.sqrt(np.mean(err**2)))
        assert abs(float(np.mean(err))) <= 0.12e-3, (joint, np.mean(err))
    # The 95 % intervals: 93 % of the usable trials here (main's uniform gear law 95 %);
    # heavy joints 2 and 3 89 % (94 %). ~100 trials put a binomial sd of ~2.3 % on the pooled
    # coverage, ~60 trials ~2.8 % on the heavy joints'.
    err, se = _response(t, (1, 2, 3, 5))
    assert 0.88 <= np.mean(np.abs(err) <= 1.96 * se) <= 0.99
    err, se = _response(t, (2, 3))
    assert np.mean(np.abs(err) <= 1.96 * se) >= 0.85


def test_response_flag_keeps_the_actuation_and_says_why(ur10_table: Any) -> None:
    """Where a trial's age depends on the unknown gear law by more than the tolerance
    (half its own hysteresis bracket > 0.2 ms), its response gets ``response_flag =
    "deflection"`` (16 of 36 base-joint trials here) and nothing else: the trial keeps its
    ``flag`` empty and both delays (the value with its standard error, for diagnosis), and
    its actuation delay — timed on the link, which the gyro sees — is as good as the
    others' (RMSE <= 0.25 ms; 0.12 ms on them, 0.135 ms on all trials). Only joints whose deflection was
    separated can carry it."""
    t = ur10_table
    rf = np.array([f == "deflection" for f in t["response_flag"]])
    assert rf.sum() >= 3
    # The UR10's lag is mostly elastic on every joint: no joint is flagged as a whole.
    assert {str(f) for f in t["response_flag"]} <= {"", "deflection"}
    assert all(not f for f in t["flag"][rf])
    assert np.all(np.isfinite(t["response_delay"][rf]))
    assert np.all(np.isfinite(t["response_deflection_s"][rf]))
    e = (t["actuation_delay"] - t["true_actuation_delay"])[rf]
    assert np.sqrt(np.mean(e**2)) <= 0.25e-3
    # The separation moved the heavy joints' ages later (the link lags the motor).
    deflected = np.isin(t["joint"], (2, 3))
    assert np.all(np.isfinite(t["response_deflection_s"][deflected]))
    assert np.median(t["response_deflection_s"][deflected]) > 0.2e-3


def test_actuation_unchanged_by_compliance(ur10_table: Any) -> None:
    """The actuation delay is timed on the link's speed, which the gyro sees, so the
    motor-side encoder does not touch it: RMSE <= 0.2 ms on these 128 trials (200 trials:
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
    assert not any(t["response_flag"])
    # Nothing deflects, so no error is shared by a joint's trials beyond the fit's own.
    assert np.all(t["response_delay_shared_se"] == 0.0)
    err, _ = _response(t, (1, 2, 3, 5))
    assert np.sqrt(np.mean(err**2)) <= 0.15e-3


@pytest.fixture(scope="module")
def kr5_table(tmp_path_factory: pytest.TempPathFactory) -> Any:
    p = tmp_path_factory.mktemp("compliant") / "kr5.h5"
    write_compliant_sweep(p, "kr5", 96, CompliantConditions(), seed=2)
    return extract_recording(p, progress=False).table


@pytest.mark.slow
def test_a_play_dominated_joint_is_flagged_as_a_whole(kr5_table: Any) -> None:
    """The KR 5's cycloidal base gear has a soft zone: the hysteresis terms make most of its
    correction (the median change they make over the median change all terms make: 0.82-
    1.11 on 200-trial sweeps, 0.84 here), so its trials share an age that hangs on the
    gear's law (main read
    -0.09 to -0.13 ms of bias there on the benchmark's seed, no flag). Every one of its
    trials gets ``response_flag = "deflection_joint"`` and keeps its flag empty, both
    delays and its actuation delay (timed on the link, which the gyro sees: bit-identical to
    main's; RMSE 0.23 ms on these ~25 trials, bound 0.3 ms; 0.126-0.155 ms over all joints
    on 200-trial sweeps). On this small sweep the elbow is flagged too (share 0.83 on its
    ~26 trials, the median's noise; 0.38-0.75 on 200-trial sweeps, where it is not): not
    asserted. The UR10's joints (0.45-0.64) never are (test above)."""
    t = kr5_table
    reason = np.array([str(f) for f in t["response_flag"]])
    base = np.asarray(t["joint"]) == 1
    assert base.sum() >= 10
    assert np.all(reason[base] == "deflection_joint")
    assert all(not f for f in t["flag"][base])
    assert np.all(np.isfinite(t["response_delay"][base]))
    e = (t["actuation_delay"] - t["true_actuation_delay"])[base]
    assert np.sqrt(np.mean(e**2)) <= 0.3e-3


@pytest.fixture(scope="module")
def ur10_noisy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 96-trial UR10 sweep at 5x the gyro noise (seed 2)."""
    p = tmp_path_factory.mktemp("ur10-5x") / "ur10.h5"
    write_compliant_sweep(p, "ur10", 96, CompliantConditions(noise_factor=5.0), seed=2)
    return p


@pytest.mark.slow
@pytest.mark.parametrize("robot", ["ur10", "kr5"])
def test_compliant_conditions_bounded(ur10_noisy: Path, kr5_table: Any, robot: str) -> None:
    """Two of the benchmark's conditions, 96 trials each: UR10 at 5x noise and a KR 5
    (cycloidal gears with a soft zone). On the trials without a response flag every
    joint's response bias within ±0.3 ms and the intervals covering >= 85 % of them; a
    joint whose every trial is flagged is flagged as a whole (``deflection_joint``, or
    ``deflection_noise`` where the gyro's noise pulled the age with the deflection terms
    by more than 0.05 ms and a quarter of their correction). At 5x noise the UR10's three
    heavy joints are flagged for the noise (on 1000-trial sweeps their pull read
    0.14-0.24 ms, 0.30-0.66 of the correction), never at 1x (the KR 5 here); its wrist (no
    terms) is kept. On this sweep (19-26 trials per joint) the base and joint 3 are (pull
    0.08 and 0.18 ms, 0.46 and 0.54 of the correction), the elbow not, at 0.24 (0.20 of
    its 0.86 ms), so at least two of the three must be. Measured (joints 1/2/3/5): KR 5
    base and elbow flagged as a whole (the elbow by the medians' noise on ~26 trials),
    joints 3 / 5 -0.01 / -0.05 ms, 100 %. ~25 trials per joint put ~0.06 ms of sampling
    error on a joint's mean."""
    t = extract_recording(ur10_noisy, progress=False).table if robot == "ur10" else kr5_table
    reason = np.array([str(f) for f in t["response_flag"]])
    noisy = 0
    for joint in (1, 2, 3, 5):
        err, _ = _response(t, (joint,))
        on_joint = reason[np.asarray(t["joint"]) == joint]
        noisy += int(np.all(on_joint == "deflection_noise"))
        if err.size == 0:
            assert np.all(np.isin(on_joint, ["deflection_joint", "deflection_noise"]))
            continue
        assert abs(float(np.mean(err))) <= 0.3e-3, (joint, np.mean(err))
    assert noisy >= (2 if robot == "ur10" else 0)
    if robot == "kr5":
        assert "deflection_noise" not in set(reason)
    err, se = _response(t, (1, 2, 3, 5))
    assert np.mean(np.abs(err) <= 1.96 * se) >= 0.85


@pytest.mark.slow
def test_extract_says_what_the_noise_flag_means_and_how_to_fix_it(
    ur10_noisy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`timedexec extract` on the noisy sweep counts the ``deflection_noise`` trials and
    says what the flag means and what removes it (a quieter gyro or mount)."""
    assert main(["extract", str(ur10_noisy), "--out", str(tmp_path / "d.csv")]) == 0
    out = capsys.readouterr().out
    assert re.search(r"deflection_noise \d+", out), out
    assert "deflection_noise: the gyro's noise hid" in out
    assert "quieter gyro" in out


def test_a_pose_that_loads_the_gear_is_within_its_interval(kr5_table: Any) -> None:
    """On a KR 5 a few poses load a joint's gear far more than its others (the wrist: a
    trial whose deflection makes the fit +0.3 ms early while the joint's median change is
    +0.02 ms). Its age is off by about that much, so its standard error must say so: a
    trial whose own evidence of a deflection (the probe, or the correction the shrinkage
    took away) stands out of its joint's counts it. Here (96 trials, seed 2) one usable
    wrist trial reads 0.3 ms short: main's interval missed it at -7.8 standard errors, now
    -1.1. Every usable trial off by more than 0.25 ms must lie within 1.96 standard errors
    (the rule's offset is the probe itself, ~1/1.3 of the error it predicts: about 1.3 sd
    expected), and the intervals still cover >= 85 % of all usable trials (100 % here)."""
    t = kr5_table
    err, se = _response(t, (1, 2, 3, 5))
    big = np.abs(err) > 0.25e-3
    assert big.sum() >= 1
    assert np.all(np.abs(err[big]) <= 1.96 * se[big]), err[big] / se[big]
    assert np.mean(np.abs(err) <= 1.96 * se) >= 0.85


def test_an_unseparated_joints_shared_bound_holds_under_gyro_noise(
    kr5_table: Any, tmp_path: Path
) -> None:
    """A joint fitted without the deflection terms (the KR 5 wrist: its deflection is below
    the detection threshold) shares an offset bounded by its trials' probe, which the gyro's
    noise attenuates (its terms are derivatives of the noisy rate) while the offset stays:
    the wrist reads ~0.05 ms short at 1x and at 5x noise alike. The bound comes from the
    probe extrapolated to zero noise (refit with the recording's own noise added), so it
    must not shrink with the noise: on these 96 trials (seed 2) the wrist's shared error at
    5x over 1x was 0.60 before (0.058 / 0.097 ms), 0.80 now (0.083 / 0.104 ms); 0.7 is the
    bound (1000-trial sweeps, seeds 2 / 3: 0.76 / 0.66 before, 1.00 / 0.88 now)."""
    p = write_compliant_sweep(tmp_path / "kr5-5x.h5", "kr5", 96,
                              CompliantConditions(noise_factor=5.0), seed=2)  # fmt: skip
    noisy = extract_recording(p, progress=False).table

    def shared(t: Any) -> float:
        ok = _usable(t) & (t["joint"] == 5)
        assert ok.sum() >= 15  # ~25 usable wrist trials of 96
        assert np.all(np.isnan(t["response_deflection_s"][ok]))  # fitted without the terms
        return float(np.median(t["response_delay_shared_se"][ok]))

    assert shared(noisy) >= 0.7 * shared(kr5_table)


@pytest.fixture(scope="module")
def sweep_512(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One extraction chunk (512 trials) of each arm, clean, seed 7 (neither a seed the
    standard error's rules were chosen on, 2 and 3, nor the benchmark's scoring seeds)."""
    out = {}
    for arm in ("ur10", "kr5"):
        p = tmp_path_factory.mktemp("compliant") / f"{arm}-512.h5"
        write_compliant_sweep(p, arm, 512, CompliantConditions(), seed=7)
        out[arm] = extract_recording(p, progress=False).table
    return out


@pytest.mark.slow
def test_response_intervals_cover_and_the_shared_error_is_the_joints(
    sweep_512: dict[str, Any],
) -> None:
    """The response delay's 95 % interval (``delay ± 1.96·response_delay_se``) covers the
    truth on 95 % of trials over trials *and* sweeps; within one sweep part of its error is
    one draw for all of a joint's trials (``response_delay_shared_se``: the gear law's
    part, the pooled median's), so one joint's coverage in one sweep is not binomial.

    What is asserted, on 512 trials per arm (seven joints with usable responses, ~90-135
    trials each; measured values in brackets):

    * Pooled over both arms' 854 usable trials, coverage within 0.92-0.985 (95.6 %). A
      calibrated interval's binomial 90 % range on 850 trials is 93.8-96.2 %; each joint's
      shared draw moves its trials together, which widens that by a few % (seven draws).
    * Every joint's coverage within 0.90-1.00 (UR10 joints 1/2/3/5 97.7 / 94.5 / 98.3 /
      95.5 %, KR 5 joints 2/3/5 93.0 / 94.2 / 96.3 %): where the joint's draw is near zero
      the interval is wider than the trial's own error needs (the UR10's joint 3 covered
      91-99.6 % per sweep of 1000 trials, benchmarks/bench_extract_compliant.py).
    * The shared part is the joints': each joint's mean error within 2.5 of its standard
      error (the shared part with the own parts' mean over its trials: z +1.16 / -0.26 /
      -0.06 / -1.03 and -0.75 / -1.62 / -1.32; 2.5 leaves room for seven draws).
    * The own part (``se`` without the shared part) covers the trials' errors about their
      joint's mean on >= 0.80 of each joint's trials (92.2-97.7 %; the UR10's elbow, 85.2 %
      before the own part was the shrunk age's, 94.5 %) and 0.90-0.985 pooled (95.6 %).
    * Every usable trial has 0 < shared_se < se (the shared part is 0.24-0.54 of ``se``
      in median per joint).
    """
    errs, covered, own_covered = [], [], []
    for arm, t in sweep_512.items():
        ok = np.asarray(t.usable("response_delay"))
        err = np.asarray(t["response_delay"] - t["true_response_delay"])
        se = np.asarray(t["response_delay_se"])
        shared = np.asarray(t["response_delay_shared_se"])
        own = np.sqrt(se**2 - shared**2)
        for joint in (1, 2, 3, 5):
            m = ok & (np.asarray(t["joint"]) == joint)
            if not m.any():
                continue  # the KR 5's base: flagged as a whole (deflection_joint)
            assert np.all((shared[m] > 0) & (shared[m] < se[m])), (arm, joint)
            hit = np.abs(err[m]) <= 1.96 * se[m]
            assert 0.90 <= hit.mean() <= 1.0, (arm, joint, hit.mean())
            mean = float(np.mean(err[m]))
            sd = np.sqrt(np.mean(shared[m] ** 2) + np.mean(own[m] ** 2) / m.sum())
            assert abs(mean / sd) <= 2.5, (arm, joint, mean / sd)
            own_hit = np.abs(err[m] - mean) <= 1.96 * own[m]
            assert own_hit.mean() >= 0.80, (arm, joint, own_hit.mean())
            errs.append(err[m])
            covered.append(hit)
            own_covered.append(own_hit)
    assert len(errs) == 7
    assert 0.92 <= np.mean(np.concatenate(covered)) <= 0.985
    assert 0.90 <= np.mean(np.concatenate(own_covered)) <= 0.985
