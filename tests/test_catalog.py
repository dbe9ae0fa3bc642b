"""Every robot of the catalog is complete and consistent (issue 33: a robot is one data
module, everything else iterates the registry).

Each test runs one consumer of the registry for every robot in ``ROBOT_NAMES``: the
simulator's default settings at every period the controller offers, a short simulated
batch, the default effects, the protocol twin's identity (and what the UR driver infers
from it), the calibration plan's ranges, the built-in weld cell's seam plan and the
shipped delay model. A new robot module with a gap fails here with its name and what to
fix, rather than with a KeyError at run time.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from timedexec.drivers import ur_robot_named
from timedexec.effects import EFFECT_NAMES, default_effects
from timedexec.errors import ConfigError
from timedexec.learning import PAPER_TABLES, DelayModel, bundled_model_dir, paper_family
from timedexec.recording import SweepPlan, calibration_ranges
from timedexec.robots import (
    INTERFACES,
    ROBOT_NAMES,
    TwinIdentity,
    WorkCell,
    check_configuration,
    get_robot,
    get_robot_entry,
)
from timedexec.sim import default_settings, simulate_delays
from timedexec.tasks import Seam, default_cell, plan_seam
from timedexec.twins import UR_CONTROLLER_VERSIONS, RSITwinConfig

#: RTDE rate the ur_rtde client asks for by the controller's software major (3: CB3, 5:
#: e-Series); the spec's controller period must agree with it.
_RTDE_PERIOD_S = {3: 0.008, 5: 0.002}


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_entry_is_registered_under_its_name(name: str) -> None:
    """The registry holds each robot under its spec's name, in any case or spacing; its
    home pose is inside the limits, its joint names are six distinct names and its
    sources declare the estimates."""
    entry = get_robot_entry(name)
    assert entry.name == name
    assert get_robot(f" {name.upper()} ") is entry.spec
    check_configuration(entry.spec, entry.spec.home_q_rad)
    assert len(set(entry.joint_names)) == 6
    assert "ESTIMATE" in entry.spec.sources, f"{name}: say in sources which numbers are estimates"


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_simulator_settings_at_every_period_and_a_short_batch(name: str) -> None:
    """``default_settings`` builds at every period the controller offers (pipeline of at
    least one cycle, packing phase inside the period), and a batch of one trial per joint
    and direction from the home pose gives finite positive delays: actuation within 40
    periods (the paper: 2.5 to 7.5), response within 3 periods (one packing phase plus an
    extra cycle at most, plus transport)."""
    spec = get_robot(name)
    for period in spec.period_options_s:
        settings = default_settings(name, period_s=period)
        assert settings.spec == spec.with_period(period)
        assert settings.timing.pipeline_cycles >= 1, name
        lo, hi = settings.timing.packing_phase_s
        assert 0.0 <= lo <= hi < period, (name, period)
    joints = np.repeat(np.arange(1, 7), 2)
    directions = np.tile([1, -1], 6)
    q = np.tile(spec.home_q_rad, (12, 1))
    table = simulate_delays(name, q, joints, directions, np.zeros(12), seed=1)
    period = spec.controller_period_s
    act, resp = table["actuation_delay"], table["response_delay"]
    assert np.all((act > 0) & (act < 40 * period)), (name, act)
    assert np.all((resp > 0) & (resp < 3 * period)), (name, resp)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_default_effects_are_in_the_vocabulary(name: str) -> None:
    """The entry names effects of the vocabulary, and the default set has exactly them."""
    names = get_robot_entry(name).default_effects
    assert set(names) <= set(EFFECT_NAMES), (
        f"{name}: unknown effects {set(names) - set(EFFECT_NAMES)}"
    )
    assert set(default_effects(name).names) == set(names)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_twin_identity_fits_the_interface_and_the_period(name: str) -> None:
    """A UR entry's identity is served by the UR twin, the driver maps the model name and
    software major it reports back to this robot (no two UR entries alike), and the RTDE
    rate the client picks by that major matches the spec's period. A KUKA entry is a KUKA
    robot the RSI twin accepts at every period it offers."""
    entry = get_robot_entry(name)
    twin, spec = entry.twin, entry.spec
    assert twin.interface in INTERFACES
    if twin.interface == "ur_rtde":
        assert spec.vendor == "universal_robots"
        assert UR_CONTROLLER_VERSIONS[name] == twin.controller_version
        major = twin.controller_version[0]
        assert ur_robot_named(twin.model_name, major) == name, (
            f"{name}: the UR driver maps model {twin.model_name!r} with software {major}.x to "
            f"{ur_robot_named(twin.model_name, major)!r}"
        )
        assert spec.period_options_s == (_RTDE_PERIOD_S[min(major, 5)],), name
    else:
        assert spec.vendor == "kuka"
        assert name not in UR_CONTROLLER_VERSIONS
        for period in spec.period_options_s:
            RSITwinConfig(robot=name, period_s=period)  # validates


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_calibration_plan_stays_in_the_sweep_ranges(name: str) -> None:
    """A sweep plan draws start poses inside the joint limits and the entry's sweep ranges."""
    entry = get_robot_entry(name)
    lo, hi = calibration_ranges(entry.spec)
    assert np.all(lo >= np.asarray(entry.sweep_q_min_rad)), name
    assert np.all(hi > lo), name
    plan = SweepPlan.generate(name, 64, seed=0)
    check_configuration(entry.spec, plan.q_start_rad)
    assert np.all(plan.q_start_rad >= lo - 1e-12)
    assert np.all(plan.q_start_rad <= hi + 1e-12)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_default_weld_cell_is_reachable(name: str) -> None:
    """The built-in weld cell derives from the entry's work cell: the torch reaches the
    work point, and a straight seam across the belt plans (every sample of the moving seam
    inside reach, joint limits and 90 % of the speed limits) with the torch on it (1 µm:
    the IK's spline between 2 ms samples)."""
    entry = get_robot_entry(name)
    cell = default_cell(name)
    assert cell.work_point_m == entry.cell.work_point_m
    sp = plan_seam(cell, Seam(), weld_s=0.8)
    t = np.linspace(sp.sync_s, sp.sync_s + sp.weld_s, 100)
    q, qd = sp.plan.sample_many(t)
    point, _, _ = sp.target(t - sp.sync_s)
    assert np.max(np.linalg.norm(sp.torch_m(q) - point, axis=1)) < 1e-6, name
    assert np.all(np.abs(qd) <= 0.9 * np.asarray(entry.spec.qd_max_rad_s)), name


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_shipped_model_loads_and_matches_the_robot(name: str) -> None:
    """The entry's shipped model is in the package, loads by name for this robot and was
    trained at its default period; its published comparison has a table."""
    entry = get_robot_entry(name)
    folder = bundled_model_dir(entry.shipped_model)
    assert (folder / "manifest.json").exists(), (
        f"{name}: shipped model {entry.shipped_model!r} is missing from models/; train it "
        f"with: python scripts/train_bundled_models.py --robots {name}"
    )
    model = DelayModel.load(entry.shipped_model, robot=entry.spec)
    assert model.robot == name
    assert model.period_s == pytest.approx(entry.spec.controller_period_s)
    assert paper_family(name) in PAPER_TABLES


def test_bad_entries_are_refused_with_the_fix() -> None:
    """The entry's groups validate where they are built; the messages name the value and
    what is allowed."""
    entry = get_robot_entry(ROBOT_NAMES[0])
    timing = entry.timing
    with pytest.raises(ConfigError, match="exactly one of pipeline_cycles"):
        dataclasses.replace(timing, pipeline_s=0.05)
    with pytest.raises(
        ConfigError, match=re.escape("packing_phase_periods=(0.5, 1.2) must lie in [0, 1]")
    ):
        dataclasses.replace(timing, packing_phase_periods=(0.5, 1.2))
    with pytest.raises(ConfigError, match="bandwidth_hz needs 6 values"):
        dataclasses.replace(timing, bandwidth_hz=(25.0,) * 5)
    with pytest.raises(ConfigError, match="interface='profinet' is not one of ur_rtde, kuka_rsi"):
        TwinIdentity(interface="profinet", controller="X")
    with pytest.raises(ConfigError, match=r"a UR .* needs model_name, serial_number"):
        TwinIdentity(interface="ur_rtde", controller="e-Series", model_name="UR5")
    with pytest.raises(ConfigError, match=r"work_point_m=.* must be 3 finite numbers"):
        WorkCell(seed_q_rad=(0.0,) * 6, work_point_m=(0.5, 0.0))
    with pytest.raises(ConfigError, match="seed_q_rad is outside the joint limits"):
        dataclasses.replace(entry, cell=WorkCell(seed_q_rad=(7.0,) * 6, work_point_m=(0.5, 0, 0)))
    with pytest.raises(ConfigError, match="paper_family='abb' is not one of ur, kuka"):
        dataclasses.replace(entry, paper_family="abb")
    with pytest.raises(ConfigError, match="sweep_q_min_rad must lie below sweep_q_max_rad"):
        dataclasses.replace(entry, sweep_q_min_rad=entry.sweep_q_max_rad)
