"""RSI sweeps that fit the cell (issue 34): against a robot side that starts RSI at its own
pose (``tests/lockstep_rsi_peer.py``, the public ``kuka_rsi_simulator`` ported without ROS:
lock-step, 1 s answer timeout, absolute corrections from the start pose), a sweep is
planned around that pose within ``max_correction_deg`` and calibrates to the end; a plan
that leaves the limits is refused before anything moves, naming the axis, the correction
it needs and the limit; a move that cannot converge says what it saw."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from lockstep_rsi_peer import SIMULATOR_START_DEG, LockStepRig, LockStepRSIPeer
from timedexec.cli import main
from timedexec.drivers import KukaRSIDriver, RobotURL
from timedexec.errors import ConfigError
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.twins import free_udp_port

GYRO_OPTIONS = ["--gyro-group-delay", "0.98", "--gyro-transport-latency", "0.8"]


def test_the_url_and_the_driver_know_rsis_correction_limit() -> None:
    """``rsi://PORT?max_correction_deg=D`` (or six, A1..A6) reaches the driver; a bad
    value is refused naming the parameter, the range and an example."""
    assert RobotURL.parse("rsi://49152?max_correction_deg=30").options == {
        "max_correction_deg": 30.0
    }
    six = RobotURL.parse("rsi://49152?max_correction_deg=30,20,20,90,90,90")
    assert six.options["max_correction_deg"] == (30.0, 20.0, 20.0, 90.0, 90.0, 90.0)
    for bad in ("0", "30,20", "x", "400"):
        with pytest.raises(ConfigError, match=r"max_correction_deg=.* must be one angle in "
                                              r"\(0, 360\] degrees or six.*e\.g\."):  # fmt: skip
            RobotURL.parse(f"rsi://49152?max_correction_deg={bad}")


def test_reach_is_the_start_pose_within_the_limit_and_a_plan_beyond_it_is_refused() -> None:
    """The driver's reach is the pose where RSI started (the peer's own) plus or minus the
    correction limit, inside the joint limits; a configuration beyond it is refused naming
    the axis, the angle, the correction it needs from the start pose and the limit."""
    port = free_udp_port()
    with KukaRSIDriver(port, max_correction_deg=30.0, progress=False) as drv, \
            LockStepRSIPeer(("127.0.0.1", port)):  # fmt: skip
        lo, hi = drv.reachable_range_rad()
        start = np.asarray(SIMULATOR_START_DEG)
        np.testing.assert_allclose(np.degrees(drv.start_pose_rad), start, atol=1e-3)
        # 1e-3°: the frame's four decimals; A5's joint limit (120° less 0.5°) binds
        spec = get_robot("kr5")
        q_lo = np.degrees(spec.q_min_rad) + 0.5
        q_hi = np.degrees(spec.q_max_rad) - 0.5
        np.testing.assert_allclose(np.degrees(lo), np.maximum(start - 30.0, q_lo), atol=1e-3)
        np.testing.assert_allclose(np.degrees(hi), np.minimum(start + 30.0, q_hi), atol=1e-3)
        assert np.degrees(hi[4]) == pytest.approx(119.5, abs=1e-3)
        drv.check_reachable(np.radians(start + 29.0 * (np.arange(6) != 4)))  # inside
        far = np.radians(start + np.array([0, 0, 0, 0, 45.0, 0]))
        with pytest.raises(ConfigError) as err:
            drv.check_reachable(np.stack([np.radians(start), far]), what="plan row")
    text = str(err.value)
    for part in ("plan row 1", "axis A5 needs 135.0°", "a correction of +45.0°",
                 "(90.0°)", "correction limit of 30.0°", "1 of 2 configurations",
                 "max_correction_deg"):  # fmt: skip
        assert part in text, text


def test_calibrate_refuses_a_plan_beyond_the_limits_before_anything_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``timedexec calibrate --robot-url rsi://PORT --max-correction-deg 30 --plan P`` with
    a plan of the published ranges (not around the pose where RSI started): exit 2 within
    1 s, the message names the axis, the needed correction and the limit, no command left
    the driver (the peer's arm never moved) and no recording was written."""
    plan = SweepPlan.generate("kr5", 8, seed=1, repeats=1)
    np.savez(tmp_path / "plan.npz", **plan.to_arrays())
    port = free_udp_port()
    master, slave = os.openpty()
    try:
        # the robot's first frame once the driver listens (a frame sent before is lost and
        # the lock-step peer waits out its 1 s answer timeout)
        with LockStepRSIPeer(("127.0.0.1", port), wait_for_listener=True) as peer:
            t = time.monotonic()
            code = main(["calibrate", "--robot-url", f"rsi://{port}", "--max-correction-deg",
                         "30", "--imu", os.ttyname(slave), "--plan", str(tmp_path / "plan.npz"),
                         "--out", str(tmp_path / "c.h5"), "--quiet", "--no-tracking-phases",
                         *GYRO_OPTIONS])  # fmt: skip
            took = time.monotonic() - t
            moved = float(np.max(np.abs(peer.pose_deg() - SIMULATOR_START_DEG)))
    finally:
        os.close(master)
        os.close(slave)
    err = capsys.readouterr().err
    assert code == 2, err
    # measured 0.05 s, 0.46 s on the first call of an interpreter (the lazy imports), at
    # load 14; the issue asks < 1 s
    assert took < 1.0, took
    assert "out of RSI's reach: axis A" in err, err
    assert "a correction of" in err, err
    assert "correction limit of 30.0°" in err, err
    assert moved < 1e-6  # nothing moved
    assert not (tmp_path / "c.h5").exists()


@pytest.mark.slow
def test_a_move_that_cannot_converge_says_the_correction_saturated(tmp_path: Path) -> None:
    """``run_calibration`` (the library, no plan check) with a plan whose first
    configuration lies 10° beyond a 5° correction limit, the failure a sweep unchecked
    against the limits met ('moving to the start configuration took over 60 s ... check
    the robot is enabled'): the move to it gives up within seconds of its last progress and
    says the correction is saturated, on which axis, at which limit."""
    from timedexec.calibration import run_calibration
    from timedexec.errors import DriverTimeout
    from timedexec.recording import SweepProtocol
    from timedexec.sensors import open_gyro
    from timedexec.twins import GyroTwin

    port = free_udp_port()
    start = np.radians(SIMULATOR_START_DEG)
    plan = SweepPlan(robot="kr5", q_start_rad=(start + np.radians([0, 10.0, 0, 0, 0, 0]))[None],
                     joint=[2], direction=[1], config_index=[0], repeat=[0])  # fmt: skip
    with KukaRSIDriver(port, max_correction_deg=5.0, progress=False) as drv, \
            LockStepRSIPeer(("127.0.0.1", port)), GyroTwin(seed=1) as gyro_twin, \
            open_gyro(gyro_twin.slave_path) as gyro:  # fmt: skip
        t = time.monotonic()
        with pytest.raises(DriverTimeout) as err:
            run_calibration(drv, gyro, plan, tmp_path / "c.h5",
                            protocol=SweepProtocol.for_robot("kr5"), progress=False)  # fmt: skip
        took = time.monotonic() - t
    # the stream check (~1-2 s), the move (~0.3 s to the limit), 3 s without progress;
    # measured ~5 s: not the 60 s it was
    assert took < 15.0, took
    text = str(err.value)
    assert "stopped converging" in text, text
    assert "the correction is saturated: A2 at +5.0° (limit +5.0°)" in text, text
    assert "enabled" not in text


@pytest.mark.slow
def test_a_sweep_over_rsi_planned_around_the_start_pose_calibrates_and_extracts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The Must-show: ``calibrate --robot-url rsi://PORT?max_correction_deg=60 --trials 8``
    against the peer that starts RSI at its own pose (A2 -90°, A5 90°: the published sweep
    lies up to 150° from it) with a gyro twin fed by the peer's motion: the sweep is
    planned around the start pose within 60° less a trial's excursion (stderr says where),
    every trial is recorded and extracted (on a loaded machine some flagged, below);
    ``--resume`` against RSI started elsewhere continues the recording's own plan."""
    from timedexec.extraction import extract_recording
    from timedexec.recording import RecordingReader

    port = free_udp_port()
    out = tmp_path / "c.h5"
    with LockStepRig(("127.0.0.1", port), gyro_seed=1) as rig:
        with rig.peer(wait_for_listener=True):
            code = main(["calibrate", "--robot-url", f"rsi://{port}?max_correction_deg=60",
                         "--imu", rig.slave_path, "--trials", "8", "--seed", "1",
                         "--out", str(out), "--no-tracking-phases", *GYRO_OPTIONS])  # fmt: skip
        late = rig.late
        # --resume continues the recording's own plan (nothing left to do here), checked
        # against the reach of RSI started 5° further along A1
        shifted = np.add(SIMULATOR_START_DEG, [5.0, 0, 0, 0, 0, 0])
        with rig.peer(start_deg=shifted, wait_for_listener=True):
            again = main(["calibrate", "--robot-url", f"rsi://{port}?max_correction_deg=60",
                          "--imu", rig.slave_path, "--trials", "8", "--seed", "1", "--out",
                          str(out), "--resume", "--no-tracking-phases", "--json", str(tmp_path / "r.json"),
                          *GYRO_OPTIONS])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert again == 0, err
    assert '"recorded_now": 0' in (tmp_path / "r.json").read_text()
    assert "RSI started at (0.0, -90.0, 90.0, 0.0, 90.0, 0.0)°" in err, err
    assert "configurations (8 trials) lie within" in err, err
    assert late < 100  # RSI ran to the end
    with RecordingReader(out) as rec:
        q = np.degrees(rec.static("plan_q_start_rad"))
        assert len(rec.completed_trials) == 8
    start = np.asarray(SIMULATOR_START_DEG)
    excursion = math.degrees(0.4 * (0.4 / 8.0 + 0.05)) + 0.5
    assert np.all(np.abs(q[:, :5] - start[:5]) <= 60.0 - excursion + 1e-6)
    table = extract_recording(out, progress=False).table
    assert len(table) == 8
    flags = [f for f in table["flag"] if f]
    # Every trial extracted on a quiet machine. A loaded host answers late, the lock-step
    # peer's arm then holds for a cycle mid-pulse (as a KRC's does), and the onset's fit
    # windows disagree: 'uncertain' (or 'package_gap': the driver's thread late). With the
    # peer in its own process, beside two SCHED_FIFO burners (0.5-4 ms every 5-30 ms) and
    # four spinners, 0-2 of 8 were flagged in three runs (1-3 with the peer in the test's
    # process, 4 in one CI run at load 11-15): at most half may be flagged, and only so.
    assert len(flags) <= 4, flags
    assert set(flags) <= {"uncertain", "package_gap"}, flags
    act = np.asarray(table["actuation_delay"], float)
    # The peer's arm moves the cycle after the one that took the answer: an answer up to
    # one 12 ms cycle after the command, two cycles of pipeline, the ramp to the onset
    # level; measured 29-46 ms
    act = act[np.isfinite(act)]
    assert np.all((act > 0.012) & (act < 0.08)), act


def test_the_adaptive_sweep_over_rsi_stays_within_reach() -> None:
    """``calibrate`` over RSI is adaptive by default: its workspace box is cut to what the
    correction reaches from the pose where RSI started (the calibration ranges when none
    is given, ``Workspace.cut_to``), and a box with no room on some joint is refused
    naming the joint, both ranges and the fix."""
    from timedexec.calibration import Workspace

    start = np.radians(SIMULATOR_START_DEG)
    lo, hi = start - np.radians(60.0), start + np.radians(60.0)
    words = {"reach": "RSI's reach", "fix": "raise max_correction_deg"}
    ws = Workspace().cut_to(lo, hi, **words)
    np.testing.assert_allclose(ws.q_min_rad, lo)
    np.testing.assert_allclose(ws.q_max_rad, hi)
    box = Workspace(q_min_rad=(-0.2, -2.0, -0.2, -0.2, -0.2, -0.2), q_max_rad=(3.0,) * 6)
    ws = box.cut_to(lo, hi, **words)
    np.testing.assert_allclose(ws.q_min_rad, np.maximum(lo, box.q_min_rad))
    np.testing.assert_allclose(ws.q_max_rad, np.minimum(hi, 3.0))
    box = Workspace(q_min_rad=(-0.2,) * 6, q_max_rad=(3.0,) * 6)  # joint 2 above its reach
    with pytest.raises(ConfigError, match=r"joint 2: .*RSI's reach \(-150\.0\.\.-30\.0 deg\)"
                                          r".*--workspace -11\.5\.\.171\.9 deg.*max_correction_deg"):  # fmt: skip
        box.cut_to(lo, hi, **words)
