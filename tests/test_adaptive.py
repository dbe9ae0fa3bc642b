"""The adaptive calibration sweep (issue 39): design, workspace, resume, warm start."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from timedexec.calibration import (
    AdaptiveSettings,
    DriverRunner,
    Workspace,
    design_pool,
    plot_design_log,
    read_design_log,
    run_adaptive,
)
from timedexec.errors import ConfigError, RecordingError, ThermalStateWarning
from timedexec.learning import WARM_AFTER_S, thermal_mismatch, thermal_state
from timedexec.recording import RecordingReader, calibration_ranges
from timedexec.robots import get_robot
from timedexec.sim import WARM_START_S, SimulatedRunner, simulate_sweep, truth_table

# Small sweeps: 1-minute batches, a 5-minute budget (about 230 trials), a small pool.
SMALL = {"batch_s": 60.0, "budget_s": 300.0, "pool_size": 128, "reference_size": 64,
         "candidates": 128, "seed": 3}  # fmt: skip


def _contents(path: Path) -> dict[str, object]:
    """Every trial field and static of a recording, and its header (for equality)."""
    with RecordingReader(path) as r:
        order = np.argsort(r.read("trial"))
        out: dict[str, object] = {f"field:{k}": r.read(k)[order] for k in r.fields}
        out.update({f"static:{k}": r.static(k) for k in r.static_names})
        out["header"] = json.dumps(r.header, sort_keys=True)
    return out


def _assert_same(a: dict[str, object], b: dict[str, object]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if k == "header":
            assert a[k] == b[k]
        else:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)  # bit for bit: same seed


def test_settings_and_workspace_are_validated() -> None:
    """Bad settings and workspaces are ConfigErrors naming the value and the fix."""
    with pytest.raises(ConfigError, match="stop_fraction"):
        AdaptiveSettings(stop_fraction=1.5)
    with pytest.raises(ConfigError, match="joints"):
        AdaptiveSettings(joints=(1, 6))
    with pytest.raises(ConfigError, match="not both"):
        Workspace(q_min_rad=(0.0,) * 6, q_max_rad=(1.0,) * 6, configurations_rad=((0.0,) * 6,))
    with pytest.raises(ConfigError, match="low <= high"):
        Workspace(q_min_rad=(1.0,) * 6, q_max_rad=(0.0,) * 6)
    s = AdaptiveSettings(budget_s=600.0, joints=(1, 2))
    assert AdaptiveSettings.from_dict(s.to_dict()) == s
    w = Workspace(configurations_rad=((0.1, -1.0, 1.0, 0.0, 0.5, 0.0),))
    assert Workspace.from_dict(w.to_dict()) == w


def test_design_pool_stays_in_the_workspace() -> None:
    """A box workspace's pool lies inside the box and the calibration ranges; a listed
    workspace's pool is its configurations; every unit is 2 directions x repeats."""
    spec = get_robot("ur10e")
    lo, hi = calibration_ranges(spec)
    box = Workspace(q_min_rad=tuple(lo + 0.3), q_max_rad=tuple(lo + 0.6))
    plan = design_pool(spec, box, AdaptiveSettings(pool_size=64))
    q = plan.q_start_rad[:, :5]
    assert np.all(q >= lo[:5] + 0.3 - 1e-12)
    assert np.all(q <= np.minimum(lo + 0.6, hi)[:5] + 1e-12)
    assert np.all(plan.q_start_rad[:, 5] == 0.0)
    configs = ((0.1, -1.2, 1.0, -1.0, 0.5, 0.0), (0.4, -1.5, 1.2, -1.2, 0.6, 0.0))
    plan = design_pool(spec, Workspace(configurations_rad=configs), AdaptiveSettings())
    assert len(np.unique(plan.q_start_rad, axis=0)) == 2
    assert len(plan) == 2 * 4 * 2 * 2  # configurations x joints x directions x repeats


def test_adaptive_sweep_keeps_its_budget_and_logs_its_design(tmp_path: Path) -> None:
    """A simulated adaptive sweep stops at its budget of robot time, records each batch
    (rows and figures) before it runs, and its figure is drawn."""
    out = tmp_path / "a.h5"
    res = run_adaptive(SimulatedRunner("kr5", seed=3, warm=True), out,
                       settings=AdaptiveSettings(**SMALL, stop_fraction=0.0), progress=False)  # fmt: skip
    assert res.stopped == "budget"
    # the last trial ends within the budget; less than two units' time is left unused
    assert 300.0 - 2 * 4 * 16 * 1.05 <= res.robot_time_s <= 300.0
    with RecordingReader(out) as r:
        log = read_design_log(r)
        assert r.header["power_on_s"] == -WARM_START_S
        trials = set(r.read("trial").tolist())
    planned = {int(i) for b in range(len(log)) for i in RecordingReader(out).static(
        f"adaptive_batch_{b:04d}").tolist()}  # fmt: skip
    assert trials <= planned
    chosen = [n for n in log if np.isfinite(n["error_s"])]
    assert chosen
    assert all(n["floor_s"] > 0 and n["error_s"] >= n["floor_s"] for n in chosen)
    assert plot_design_log(out, tmp_path / "d.png") == tmp_path / "d.png"


_SWEEP = """
import sys
from timedexec.calibration import AdaptiveSettings, run_adaptive
from timedexec.sim import SimulatedRunner
settings = AdaptiveSettings(batch_s=40.0, budget_s=200.0, pool_size=64, reference_size=32,
                            candidates=64, joints=(1, 2), seed=5)
run_adaptive(SimulatedRunner("ur10e", seed=5, warm=True), sys.argv[1], settings=settings,
             resume=sys.argv[2] == "1", progress=False)
"""


@pytest.mark.slow
def test_resume_after_sigkill_gives_the_same_recording(tmp_path: Path) -> None:
    """An adaptive sweep killed with SIGKILL mid-sweep and resumed records exactly what an
    uninterrupted run with the same seed records (trials, design log, header). (Small
    settings keep it to a minute; ``benchmarks/bench_adaptive_resume.py`` does the same
    through the CLI on a full-size sweep.)"""

    def cmd(out: Path, resume: bool) -> list[str]:
        return [sys.executable, "-c", _SWEEP, str(out), "1" if resume else "0"]

    whole = tmp_path / "whole.h5"
    subprocess.run(cmd(whole, False), check=True, timeout=240)
    cut = tmp_path / "cut.h5"
    proc = subprocess.Popen(cmd(cut, False))
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:  # kill once the third batch is being recorded
        time.sleep(0.1)
        try:
            with RecordingReader(cut) as r:
                if r.has_static("adaptive_batch_0003") and r.n_trials > 80:
                    break
        except (RecordingError, OSError):
            continue
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with RecordingReader(cut) as r:
        assert r.n_trials > 0  # killed mid-sweep, not before it
    with RecordingReader(whole) as r:
        n_whole = r.n_trials
    with RecordingReader(cut) as r:
        assert r.n_trials < n_whole  # ... and not after it
    subprocess.run(cmd(cut, True), check=True, timeout=240)
    _assert_same(_contents(whole), _contents(cut))


def test_warm_start_is_recorded_and_the_bundle_says_so(tmp_path: Path) -> None:
    """A warm sweep's header puts power-on WARM_START_S before the sweep, its truth table
    carries t_since_power_on, and the thermal state of a model trained on it is "warm";
    a query about a cold robot warns, one about a warm robot does not."""
    res = simulate_sweep("ur10e", 16, tmp_path / "w.h5", seed=1, progress=False, warm=True)
    with RecordingReader(res.path) as r:
        assert r.header["power_on_s"] == -WARM_START_S
        t = truth_table(r)
    np.testing.assert_allclose(t["t_since_power_on"], t["t_start"] + WARM_START_S)
    state = thermal_state(np.asarray(t["t_since_power_on"]), power_on_clock=True)
    assert state["state"] == "warm"
    assert state["clock"] == "power-on"
    assert thermal_mismatch(state, [WARM_AFTER_S + 7200.0]) is None  # warm robots alike
    assert "min after power-on" in str(thermal_mismatch(state, [600.0]))


def test_model_warns_when_asked_about_another_thermal_state(tmp_path: Path) -> None:
    """A bundle trained warm warns (ThermalStateWarning, once) when asked about a robot
    10 minutes after power-on, and answers."""
    from timedexec.learning import train_delay_models

    res = simulate_sweep("ur10e", 160, tmp_path / "w.h5", seed=2, progress=False, warm=True)
    with RecordingReader(res.path) as r:
        table = truth_table(r)
    model = train_delay_models(table, methods=("median",), folds=0).model
    assert model.thermal_state["state"] == "warm"
    q = table.q[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.predict(joint=1, direction=1, q=q, t_s=WARM_START_S + 100.0, method="median")
    with pytest.warns(ThermalStateWarning, match="10 min after power-on"):
        model.predict(joint=1, direction=1, q=q, t_s=600.0, method="median")
    assert model.check_thermal_state(WARM_START_S) is None
    with pytest.warns(ThermalStateWarning):
        assert model.check_thermal_state(300.0) is not None


@pytest.mark.slow
def test_adaptive_through_a_driver(tmp_path: Path) -> None:
    """``run_adaptive`` on a DriverRunner (the sim:// driver, its virtual gyro, warm):
    the recording holds live fields, the warm power-on and the design log."""
    from timedexec.drivers import open_driver
    from timedexec.recording import SweepProtocol

    with open_driver("sim://kr5?warm=1", seed=4) as driver:
        protocol = SweepProtocol.for_robot("kr5", period_s=driver.controller_period_s)
        runner = DriverRunner(driver, driver.gyro(seed=4), protocol, source="sim://kr5?warm=1")
        settings = AdaptiveSettings(**{**SMALL, "budget_s": 150.0, "batch_s": 30.0,
                                       "joints": (1, 2)})  # fmt: skip
        res = run_adaptive(runner, tmp_path / "d.h5", settings=settings, progress=False)
    assert res.stopped == "budget"
    assert res.trials > 40
    with RecordingReader(tmp_path / "d.h5") as r:
        assert r.header["power_on_s"] == pytest.approx(-WARM_START_S, abs=60.0)
        assert "session" in r.fields
        assert len(read_design_log(r)) >= 3


def test_cli_refuses_trials_with_adaptive(tmp_path: Path) -> None:
    """``calibrate --adaptive --trials`` is refused (the sweep chooses its own trials)."""
    from timedexec.cli import main

    code = main(["calibrate", "--robot-url", "sim://kr5", "--adaptive", "--trials", "10",
                 "--out", str(tmp_path / "x.h5")])  # fmt: skip
    assert code != 0
    assert not (tmp_path / "x.h5").exists()


def test_calibrate_is_adaptive_by_default(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``calibrate`` without ``--trials`` or ``--plan`` runs the adaptive sweep (the best we
    know for a first hour: docs/calibration.md), with its budget; a CSV workspace of two
    configurations keeps it to seconds (the sweep ends at "workspace")."""
    from timedexec.cli import main

    csv = tmp_path / "cell.csv"
    csv.write_text("0.1,-1.2,1.0,-1.0,0.5,0\n0.4,-1.5,1.2,-1.2,0.6,0\n")
    out = tmp_path / "cal.h5"
    code = main(["calibrate", "--robot-url", "sim://ur10e", "--workspace", str(csv),
                 "--no-tracking-phases", "--out", str(out), "--json", "-", "--quiet"])  # fmt: skip
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert info["stopped"] == "workspace"
    assert info["trials"] == 2 * 4 * 2 * 2  # the whole workspace, as simulate's below
    with RecordingReader(out) as r:
        assert len(read_design_log(r)) >= 1


def test_a_listed_workspace_is_measured_in_minutes(tmp_path: Path) -> None:
    """A workspace of three listed configurations (a task's cell) is measured whole, every
    joint of every configuration, and the sweep ends there ("workspace") within minutes of
    robot time."""
    configs = ((0.1, -1.2, 1.0, -1.0, 0.5, 0.0), (0.4, -1.5, 1.2, -1.2, 0.6, 0.0),
               (0.7, -1.0, 0.8, -1.4, 0.4, 0.0))  # fmt: skip
    res = run_adaptive(SimulatedRunner("ur10e", seed=1, warm=True), tmp_path / "w.h5",
                       settings=AdaptiveSettings(seed=1),
                       workspace=Workspace(configurations_rad=configs), progress=False)  # fmt: skip
    assert res.stopped == "workspace"
    assert res.trials == 3 * 4 * 2 * 2  # configurations x joints x directions x repeats
    assert res.robot_time_s < 5 * 60.0  # 48 trials of ~1.04 s, three moves, the still recording
    with RecordingReader(tmp_path / "w.h5") as r:
        q = r.read("trial")
        assert len(np.unique(q)) == res.trials


class _Interrupted(SimulatedRunner):
    """The batch simulator, interrupted (Ctrl-C) before its ``stop_at``-th unit."""

    def __init__(self, *args: object, stop_at: int, **kw: object) -> None:
        super().__init__(*args, **kw)  # type: ignore[arg-type]
        self.units = 0
        self.stop_at = stop_at

    def run(self, plan, rows, until_s):  # type: ignore[no-untyped-def]
        self.units += 1
        if self.units == self.stop_at:
            raise KeyboardInterrupt
        yield from super().run(plan, rows, until_s)


@pytest.mark.parametrize("stop_at", [3, 25])
def test_resume_in_any_batch_gives_the_same_recording(tmp_path: Path, stop_at: int) -> None:
    """Interrupted in the first batches (chosen without a model, their notes NaN: the WIP
    took NaN for "the stopping rule fired" and a resumed sweep stopped at once) or later,
    and resumed, an adaptive sweep records what an uninterrupted one records."""
    settings = AdaptiveSettings(**{**SMALL, "budget_s": 240.0, "joints": (1, 2)})
    run_adaptive(SimulatedRunner("ur10e", seed=3, warm=True), tmp_path / "whole.h5",
                 settings=settings, progress=False)  # fmt: skip
    cut = tmp_path / "cut.h5"
    with pytest.raises(KeyboardInterrupt):
        run_adaptive(_Interrupted("ur10e", seed=3, warm=True, stop_at=stop_at), cut,
                     settings=settings, progress=False)  # fmt: skip
    res = run_adaptive(SimulatedRunner("ur10e", seed=3, warm=True), cut, settings=settings,
                       resume=True, progress=False)  # fmt: skip
    assert res.stopped == "budget"
    _assert_same(_contents(tmp_path / "whole.h5"), _contents(cut))


def test_cli_workspace_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``simulate --adaptive --workspace``: a CSV of configurations is measured whole (the
    sweep ends at "workspace"); a JSON file of another form is refused (exit 2) naming the
    file and the forms allowed, before anything is written."""
    from timedexec.cli import main

    csv = tmp_path / "cell.csv"
    csv.write_text("# q1..q6, rad\n0.1,-1.2,1.0,-1.0,0.5,0\n0.4,-1.5,1.2,-1.2,0.6,0\n")
    out = tmp_path / "cell.h5"
    code = main(["simulate", "--robot", "ur10e", "--warm", "--adaptive", "--workspace",
                 str(csv), "--out", str(out), "--json", "-", "--quiet"])  # fmt: skip
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert info["stopped"] == "workspace"
    assert info["trials"] == 2 * 4 * 2 * 2
    bad = tmp_path / "bad.json"
    bad.write_text('{"q_low": [0, 0, 0, 0, 0, 0]}')
    code = main(["simulate", "--robot", "ur10e", "--adaptive", "--workspace", str(bad),
                 "--out", str(tmp_path / "no.h5")])  # fmt: skip
    assert code == 2
    assert "configurations_rad" in capsys.readouterr().err
    assert not (tmp_path / "no.h5").exists()
