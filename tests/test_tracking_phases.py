"""The tracking model from a sweep's constant-speed phases (issue 39 item 3): the phases,
their fit, the model's file beside a bundle, and the conveyor evaluation that uses it."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from timedexec.drivers import SimDriver
from timedexec.effects import default_effects
from timedexec.errors import ConfigError
from timedexec.evaluation import evaluate_conveyor, sweep_tracking_model
from timedexec.execution import ExecutorSettings, FrictionFeed, TimedExecutor
from timedexec.learning import bundled_model_dir
from timedexec.tasks import (
    TRACKING_FILE,
    PhaseRun,
    TrackingDelays,
    TrackingPhases,
    fit_tracking_phases,
    run_tracking_phases,
)


class _Cruise:
    """A plan that starts at rest at ``q0`` and moves at constant speed ``v`` from plan
    time 0 (what :func:`fit_tracking` reads of a plan: ``sample_many``, ``start_time_s``)."""

    def __init__(self, q0: np.ndarray, v: np.ndarray, start_s: float) -> None:
        self.q0, self.v, self.start_time_s = q0, v, start_s
        self.meta = {"actuation_s": np.zeros(6), "response_s": 0.0}

    def sample_many(self, t_plan_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.maximum(np.atleast_1d(t_plan_s), 0.0)[:, None]
        moving = (np.atleast_1d(t_plan_s) > 0)[:, None]
        return self.q0 + self.v * t, np.where(moving, self.v, 0.0)


def _synthetic_phases(dead_s: float, fric: tuple[float, float], noise_rad: float) -> list[PhaseRun]:
    """Joint 2's phases at 0.05 and 0.25 rad/s both ways, its reported positions
    ``plan(t - D) - e± · sign(v)`` plus white noise (8 ms packages, the fit's 0.4 s window
    after 0.4 s at speed), seeded."""
    rng = np.random.default_rng(7)
    runs = []
    for k, (speed, sign) in enumerate([(s, d) for s in (0.05, 0.25) for d in (1.0, -1.0)]):
        v = np.zeros(6)
        v[1] = sign * speed
        start = 10.0 * (k + 1)
        plan = _Cruise(np.zeros(6), v, start)
        t = start + np.arange(0.0, 0.9, 0.008)
        q, qd = plan.sample_many(t - start - dead_s)
        e = fric[0] if sign > 0 else fric[1]
        q = q - e * FrictionFeed.sign(qd) + rng.normal(0.0, noise_rad, q.shape)
        runs.append(PhaseRun(joint=2, speed_rad_s=sign * speed, plan=plan,  # type: ignore[arg-type]
                             window_s=(start + 0.4, start + 0.8), host_s=t, controller_s=t - start,
                             reported_q=q, truth_s=t, truth_q=q))  # fmt: skip
    return runs


def test_phase_fit_recovers_a_known_dead_time_and_friction() -> None:
    """Positions that trail the command by D = 12 ms and e+ = 0.8, e- = 1.1 mrad at two
    speeds give them back: exactly (1 µs / 1 µrad, Gauss-Newton) without noise, and with
    an encoder count of noise (1e-5 rad, 50 samples per phase) within 0.1 ms / 0.01 mrad:
    the standard error of D from two speeds' lags, each known to 1e-5 / sqrt(50) / |v|
    (0.03 ms at 0.05 rad/s), amplified ~1.25x by separating it from e/|v|; 3 sigma. The
    joint counts as separable; joints no phase moves are NaN."""
    exact = fit_tracking_phases(_synthetic_phases(0.012, (8e-4, 1.1e-3), 0.0))
    assert exact.dead_time_s[1] == pytest.approx(0.012, abs=1e-6)
    np.testing.assert_allclose(exact.friction_rad[:, 1], [8e-4, 1.1e-3], atol=1e-6)
    assert np.isnan(exact.dead_time_s[[0, 2, 3, 4, 5]]).all()
    noisy = fit_tracking_phases(_synthetic_phases(0.012, (8e-4, 1.1e-3), 1e-5))
    assert noisy.dead_time_s[1] == pytest.approx(0.012, abs=1e-4)
    np.testing.assert_allclose(noisy.friction_rad[:, 1], [8e-4, 1.1e-3], atol=1e-5)
    assert noisy.separable[1]
    model = TrackingDelays.calibrate_phases(
        "ur10-sim", _synthetic_phases(0.012, (8e-4, 1.1e-3), 0.0)
    )
    # A joint no phase moves gets the others' median dead time (here joint 2's) and no offset.
    np.testing.assert_allclose(model.dead_time_s, 0.012, atol=1e-6)
    assert model.source == "sweep"
    assert model.friction_rad is not None
    assert model.friction_rad[0][0] == 0.0
    with pytest.raises(ConfigError, match="at least one tracking phase"):
        fit_tracking_phases([])


def test_phases_are_checked_and_say_their_robot_time() -> None:
    """Two distinct speeds are needed (one cannot separate D from e/|v|); the default
    phases (6 joints, 0.05 and 0.25 rad/s, 0.4 s to settle and 0.4 s fitted) cost about
    half a minute of robot time."""
    with pytest.raises(ConfigError, match="two distinct speeds"):
        TrackingPhases(speeds_rad_s=(0.1, 0.1))
    with pytest.raises(ConfigError, match="hold_s"):
        TrackingPhases(hold_s=0.0)
    with pytest.raises(ConfigError, match="joints"):
        TrackingPhases(joints=(0, 1))
    phases = TrackingPhases()
    assert phases.count == 24
    assert 20.0 < phases.robot_time_s() < 40.0
    assert TrackingPhases(**phases.to_dict()) == phases


def test_phases_on_the_simulator_read_the_physical_lag_from_reported_positions() -> None:
    """Joint 1 of the warm simulated UR10 (4 phases, ~1.5 s wall): the model fitted on the
    reported positions, dated by the probed intake, matches the one fitted on the
    simulator's physical angles within 0.3 ms of dead time and 0.02 mrad of offset
    (measured 0.2 ms / 0.000 mrad: the intake's dating of the sampling instant); the
    joint's lag is separable (two speeds); the joint ends within 0.1 rad of its start."""
    q0 = np.array([0.0, -1.6, 1.2, -1.2, -1.5, 0.0])
    drv = SimDriver(
        "ur10", q0_rad=q0, effects=default_effects("ur10").without("thermal_drift"), seed=3
    )
    settings = ExecutorSettings(compensate=False, cycle_lock=True)
    with TimedExecutor(drv, "ur10-sim", settings) as ex:
        runs = run_tracking_phases(ex, TrackingPhases(joints=(1,)))
        q_end = ex.estimate().q_rad
    assert [r.speed_rad_s for r in runs] == [0.05, -0.05, 0.25, -0.25]
    reported, physical = fit_tracking_phases(runs), fit_tracking_phases(runs, physical=True)
    assert abs(reported.dead_time_s[0] - physical.dead_time_s[0]) < 3e-4
    np.testing.assert_allclose(reported.friction_rad[:, 0], physical.friction_rad[:, 0], atol=2e-5)
    assert reported.separable[0]
    assert 0.005 < reported.dead_time_s[0] < 0.03  # a UR10's cruise lag: ~10-15 ms
    assert abs(q_end[0] - q0[0]) < 0.1


def test_tracking_model_round_trips_beside_a_bundle(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """TrackingDelays.save writes tracking.json into a bundle's folder and of_bundle reads
    it back on that bundle (every field); a bundle without one has none; a broken file is
    a ConfigError naming it."""
    bundle = tmp_path / "ur10"
    shutil.copytree(bundled_model_dir("ur10-sim"), bundle)
    assert TrackingDelays.of_bundle(str(bundle)) is None
    assert TrackingDelays.of_bundle("ur10-sim") is None  # the shipped models have none
    model = TrackingDelays(base=str(bundle), dead_time_s=[0.011] * 6,
                           friction_rad=[[1e-3] * 6, [2e-3] * 6], fit_rms_rad=[1e-5] * 6,
                           notes=("n",), source="sweep")  # fmt: skip
    assert model.save(bundle) == bundle / TRACKING_FILE
    back = TrackingDelays.of_bundle(str(bundle))  # a folder is loaded
    assert back is not None
    assert back.to_dict() == model.to_dict()
    (bundle / TRACKING_FILE).write_text("{")
    with pytest.raises(ConfigError, match=r"tracking\.json"):
        TrackingDelays.of_bundle(model.base)
    with pytest.raises(ConfigError, match="dead_time_s"):
        TrackingDelays.from_dict(model.base, {"friction_rad": None})


@pytest.mark.slow
def test_evaluate_conveyor_uses_the_sweep_model_by_default(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`evaluate --task conveyor`'s model strategy runs the model of the bundle's
    tracking.json when it has one (its dead times, and the JSON says so), and the dry-run
    model is evaluated beside it; with tracking='dry runs' the model is the dry runs'.
    One work point, one phase, one calibration weld, twice (50 s on a loaded 2-core
    machine): both models within 1 mm of the seam on the UR10 at 0.5 m/s (the full
    evaluation, 8 welds each: 0.63 / 0.12 mm, none 6.8; docs/welding.md)."""
    bundle = tmp_path / "ur10"
    shutil.copytree(bundled_model_dir("ur10-sim"), bundle)
    sweep_tracking_model("ur10", str(bundle), seed=3).save(bundle)
    small = {"cells": 1, "seeds": 1, "oracle_draws": 1, "calibration_runs": 1,
             "onset": False, "feedback": False}  # fmt: skip
    ev = evaluate_conveyor("ur10", str(bundle), **small)
    stored = TrackingDelays.of_bundle(str(bundle))
    assert stored is not None
    assert ev.details["tracking_source"] == "sweep (the model bundle's tracking.json)"
    assert ev.tracking_model is not None
    assert ev.tracking_model.source == "sweep"
    np.testing.assert_allclose(ev.tracking_model.dead_time_s, stored.dead_time_s)
    for name in ("model", "model (dry runs)"):
        assert ev.strategies[name]["torch_mean_mm"] < 1.0, ev.strategies[name]
    dry = evaluate_conveyor("ur10", str(bundle), tracking="dry runs", **small)
    assert dry.details["tracking_source"] == "dry runs"
    assert "model (dry runs)" not in dry.strategies
    with pytest.raises(ConfigError, match="tracking='gyro'"):
        evaluate_conveyor("ur10", tracking="gyro")


@pytest.mark.slow
def test_calibrate_fits_the_tracking_phases_and_train_puts_them_into_the_bundle(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`calibrate` runs the tracking phases after the sweep (default on; ~33 s of the
    simulated UR10's virtual time; the test 15-90 s wall, loaded) and writes OUT.tracking.json,
    the phases' positions dated with the sweep's median response delay; `train --tracking`
    checks it (another robot's file is refused) and writes it into the bundle as
    tracking.json, which TrackingDelays.of_bundle then reads on that bundle."""
    import json

    from timedexec.cli import main
    from timedexec.learning import DelayModel

    out = tmp_path / "cal.h5"
    assert main(["calibrate", "--robot-url", "sim://ur10?warm=1", "--trials", "40", "--seed",
                 "39", "--out", str(out), "--quiet"]) == 0  # fmt: skip
    written = json.loads((tmp_path / "cal.tracking.json").read_text())
    assert written["robot"] == "ur10"
    assert 20.0 < written["robot_time_s"] < 45.0
    assert len(written["lags"]) == 24
    # The simulated UR10's response is spread over its 8 ms cycle (0.4-7.9 ms), the median
    # mid-cycle (measured 4.7 ms). Dated with no response (0), this seed's probe put every
    # position a cycle late: joint 1 lagged 20.7 ms at 0.25 rad/s for ~12.7 physical (its
    # physical lag 12.3-13.1 ms at the poses tried); within 3 ms of that, a cycle apart.
    assert 0.002 < written["response_s"] < 0.006
    fast = [lag["lag_ms"] for lag in written["lags"] if lag["joint"] == 1
            and abs(lag["speed_rad_s"]) == 0.25]  # fmt: skip
    assert all(10.0 < lag < 16.0 for lag in fast), fast
    # The probes that chose their cycle with a quarter period to spare imply the
    # controller's echo depth; their majority is the simulated UR10's, known by
    # construction (pipeline + 1 = 2), and goes into the model
    from timedexec.robots import get_robot_entry

    truth = get_robot_entry("ur10").timing.target_echo_cycles(0.008)
    assert written["echo_depth"]["cycles"] == truth == 2, written["echo_depth"]
    assert written["tracking"]["echo_depth_cycles"] == truth
    assert main(["extract", str(out), "--out", str(tmp_path / "d.csv"), "--quiet"]) == 0
    bundle = tmp_path / "bundle"
    argv = ["train", str(tmp_path / "d.csv"), "--out", str(bundle), "--folds", "0",
            "--methods", "median", "--quiet", "--tracking"]  # fmt: skip
    other = tmp_path / "kr5.tracking.json"
    other.write_text(json.dumps({**written, "robot": "kr5"}))
    assert main([*argv, str(other)]) == 2
    assert main([*argv, str(tmp_path / "cal.tracking.json")]) == 0
    stored = TrackingDelays.of_bundle(DelayModel.load(bundle))
    assert stored is not None
    assert stored.to_dict() == written["tracking"]
    # ... and the executor on that model dates its probe by counting packages
    from timedexec.drivers import open_driver
    from timedexec.execution import ExecutorSettings, TimedExecutor

    with TimedExecutor(open_driver("sim://ur10?seed=3"), stored,
                       ExecutorSettings(cycle_lock=True)) as ex:  # fmt: skip
        assert ex.intake is not None, ex.intake_error
        assert ex.intake.dated_by == "echo"
