"""The simulated robots: physics, effects, timing, determinism, calibration to the paper."""

from __future__ import annotations

import numpy as np
import pytest

from timedexec.effects import (
    EFFECT_NAMES,
    EffectSet,
    default_effects,
    make_effect,
    parse_effects,
)
from timedexec.errors import ConfigError
from timedexec.recording import SweepPlan
from timedexec.robots import get_robot
from timedexec.sim import (
    ControllerSim,
    MoveJ,
    ServoJ,
    SpeedJ,
    SpeedStop,
    default_settings,
    pulse_profile,
    simulate_block,
    sweep_clock,
)

N = 192  # trials per effect comparison: 24 configurations x 4 joints x 2 directions


def run(robot: str, effects: EffectSet, n: int = N, seed: int = 3, repeats: int = 1):
    spec = get_robot(robot)
    settings = default_settings(spec)
    plan = SweepPlan.generate(spec, n, seed=seed, repeats=repeats)
    clock = sweep_clock(plan, settings, seed)
    out = simulate_block(spec, settings, effects, plan, clock, np.arange(n), seed)
    return plan, out


@pytest.fixture(scope="module")
def base_ur10():
    return run("ur10", EffectSet())


def test_pulse_profile_shape():
    """The commanded pulse ramps at the given acceleration, holds, returns to rest and mirrors."""
    t = np.linspace(-0.1, 0.5, 60001)
    v = pulse_profile(t, speed_rad_s=0.4, acceleration_rad_s2=8.0, hold_s=0.05, pause_s=0.05)
    assert v.max() == pytest.approx(0.4)
    assert v.min() == pytest.approx(-0.4)
    assert v[t < 0].max() == 0.0
    # Net displacement over the whole motion is zero: the joint returns to its start pose.
    assert np.trapezoid(v, t) == pytest.approx(0.0, abs=1e-6)  # 1e-6 rad: grid quadrature error
    dv = np.diff(v) / np.diff(t)
    assert np.abs(dv).max() == pytest.approx(8.0, rel=1e-6)


def test_delays_emerge_within_published_ranges():
    """Default KR 5 and UR10 delays land in the issue's published bands (smaller sample)."""
    _, kr5 = run("kr5", default_effects("kr5"), n=512, seed=11)
    act = kr5["true_actuation_delay_s"] * 1e3
    resp = kr5["true_response_delay_s"] * 1e3
    assert 85 <= np.median(act) <= 95
    assert np.mean((act >= 75) & (act <= 110)) >= 0.95
    assert np.mean(resp > 12.0) > 0.5  # response above one 12 ms period in most trials
    _, ur = run("ur10", default_effects("ur10"), n=512, seed=11)
    act = ur["true_actuation_delay_s"] * 1e3
    resp = ur["true_response_delay_s"] * 1e3
    assert 15 <= np.median(act) <= 25
    assert np.mean((act >= 5) & (act <= 45)) >= 0.95
    assert resp.min() >= 0
    assert resp.max() <= 35


def test_kr5_joint2_has_highest_median_actuation():
    """Gravity load makes the shoulder (joint 2) the slowest joint, as published."""
    plan, out = run("kr5", default_effects("kr5"), n=1024, seed=5)
    act = out["true_actuation_delay_s"]
    medians = {j: np.median(act[plan.joint == j]) for j in (1, 2, 3, 5)}
    assert max(medians, key=medians.get) == 2


def test_first_package_showing_motion_is_on_the_period_grid():
    """Measured as the paper did (first package that shows motion), actuation + response is
    a whole number of periods: the command leaves on a package's arrival and the state is
    sampled at cycle boundaries."""
    spec = get_robot("ur10")
    plan, out = run("ur10", default_effects("ur10"), n=256)
    joint = plan.joint
    qd = out["state_qd_rad_s"][np.arange(len(joint)), :, joint - 1]
    first = np.argmax(np.abs(qd) > 1e-6, axis=1)
    t_first = out["state_host_time_s"][np.arange(len(joint)), first]
    total = t_first - out["cmd_send_time_s"]
    k = total / spec.controller_period_s
    # Off-grid residue comes from network jitter (exponential, mean 60 µs) and the
    # host processing time (~0.1 ms): within 0.6 ms of the grid for all but a few trials.
    residue = np.abs(k - np.round(k)) * spec.controller_period_s
    assert np.mean(residue < 0.6e-3) > 0.95


@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_each_effect_changes_what_it_should_and_nothing_else(name, base_ur10):
    """Switching one effect on (same seed, same random draws) changes only the delay it acts
    on, in the direction and with the variable its physics says."""
    robot = "kr5" if name == "response_extra_cycle" else "ur10"
    plan, base = base_ur10 if robot == "ur10" else run(robot, EffectSet())
    _, on = run(robot, EffectSet((make_effect(name),)))
    d_act = on["true_actuation_delay_s"] - base["true_actuation_delay_s"]
    d_resp = on["true_response_delay_s"] - base["true_response_delay_s"]
    tau = base["true_gravity_torque_nm"]
    d = plan.direction
    period = get_robot(robot).controller_period_s
    # Things no actuation effect may touch: response delay, the command time, the packages.
    if name != "response_extra_cycle":
        np.testing.assert_array_equal(d_resp, 0.0)
        np.testing.assert_array_equal(on["state_host_time_s"], base["state_host_time_s"])
    np.testing.assert_array_equal(on["cmd_send_time_s"], base["cmd_send_time_s"])
    loaded = np.abs(tau) > 5.0
    if name == "gravity_load":
        assert np.all(d_act[loaded] > 0)
        for j in (2, 3):  # the loaded joints; each has its own loop gain, so compare within one
            m = loaded & (plan.joint == j)
            assert np.corrcoef(np.abs(tau[m]), d_act[m])[0, 1] > 0.8
        np.testing.assert_allclose(d_act[np.abs(tau) < 1e-9], 0.0, atol=1e-12)
    elif name == "gravity_direction":
        lifting = loaded & (d * tau > 0)
        lowering = loaded & (d * tau < 0)
        assert np.all(d_act[lifting] > 0)
        assert np.all(d_act[lowering] < 0)
    elif name == "direction":
        assert np.all(d_act[d > 0] > 0)
        assert np.all(d_act[d < 0] < 0)
    elif name == "inertia":
        j_nom = base["true_inertia_kgm2"]  # without the effect: the nominal inertia
        j_true = on["true_inertia_kgm2"]
        changed = np.abs(j_true - j_nom) > 0.05 * j_nom
        assert changed.sum() > 20
        assert np.all(np.sign(d_act[changed]) == np.sign((j_true - j_nom)[changed]))
    elif name == "thermal_drift":
        assert np.all(d_act > 0)  # cold friction: later everywhere
        early = plan.config_index < plan.config_index.max() / 3
        assert d_act[early].mean() > d_act[~early].mean()
    elif name == "joint_offset":
        offsets = np.asarray(make_effect("joint_offset").offsets_s)[plan.joint - 1]
        # The onset shifts by the drive offset; 15 µs covers re-discretisation of the
        # breakaway on the 125 µs physics grid (onsets are interpolated linearly in a step
        # where the speed rises quadratically).
        np.testing.assert_allclose(d_act, offsets, atol=1.5e-5)
    elif name == "response_extra_cycle":
        np.testing.assert_allclose(d_resp, period, atol=1e-12)
        np.testing.assert_allclose(d_act, 0.0, atol=1e-12)


def test_same_seed_same_output_other_seed_differs():
    """Determinism by seed; a different seed gives different trials."""
    _, a = run("ur10", default_effects("ur10"), n=64, seed=9)
    _, b = run("ur10", default_effects("ur10"), n=64, seed=9)
    _, c = run("ur10", default_effects("ur10"), n=64, seed=10)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["gyro_raw"], c["gyro_raw"])


def test_gyro_sees_the_joint_motion_on_its_axis():
    """The gyro's rate, converted to rad/s along the joint axis, matches the reported joint
    speed in amplitude (scale errors ±3 %, noise ~0.3 °/s)."""
    spec = get_robot("ur10")
    settings = default_settings(spec)
    _plan, out = run("ur10", default_effects("ur10"), n=16)
    raw = out["gyro_raw"].astype(float) / settings.gyro.lsb_per_dps
    rate = np.deg2rad(np.linalg.norm(raw - raw[:, :200].mean(axis=1, keepdims=True), axis=2))
    peak = np.percentile(rate, 99.5, axis=1)
    # Peak |rate| is the commanded 0.4 rad/s within the ±3 % scale error plus overshoot.
    assert np.all((peak > 0.37) & (peak < 0.5))


def test_stepped_controller_matches_batch_physics():
    """The protocol twins' stepped controller shows the same reference-to-onset time as the
    batch sweep for the same joint, pose and effects (same JointBank)."""
    spec = get_robot("ur10")
    q0 = np.array(spec.home_q_rad)
    effects = EffectSet()
    c = ControllerSim(spec, effects=effects)
    c.submit(SpeedJ((0, 0.4, 0, 0, 0, 0), 8.0))
    for _ in range(30):
        c.cycle()
    ev = c.truth[0]
    stepped = ev.onset_s[1] - ev.reference_start_s
    settings = default_settings(spec)
    plan = SweepPlan(
        robot="ur10",
        q_start_rad=q0[None, :],
        joint=np.array([2]),
        direction=np.array([1]),
        config_index=np.array([0]),
        repeat=np.array([0]),
    )
    clock = sweep_clock(plan, settings, 0)
    out = simulate_block(spec, settings, effects, plan, clock, np.arange(1), 0)
    batch = out["true_onset_s"][0] - out["true_reference_start_s"][0]
    # Same physics; the batch's speedj ramp differs only by starting between grid points
    # (one 125 µs step), so the times agree to a step.
    assert stepped == pytest.approx(batch, abs=2.5e-4)
    assert 0.003 < batch < 0.03


def test_stepped_controller_register_semantics_and_pipeline():
    """Commands are taken at the next cycle boundary and act after the pipeline; two commands
    in one cycle: only the last is seen (as on a real controller)."""
    c = ControllerSim("ur10e", effects=EffectSet())
    period = c.period_s
    c.cycle()
    first = c.submit(SpeedJ((0.2, 0, 0, 0, 0, 0), 5.0), arrival_s=c.time_s + 0.3 * period)
    second = c.submit(SpeedJ((0.3, 0, 0, 0, 0, 0), 5.0), arrival_s=c.time_s + 0.6 * period)
    for _ in range(40):
        c.cycle()
    ev1, ev2 = c.truth
    assert ev1.id == first
    assert ev1.superseded
    assert np.isnan(ev1.intake_s)
    assert ev2.id == second
    assert ev2.intake_s == pytest.approx(2 * period)
    pipeline = default_settings("ur10e").timing.pipeline_cycles
    assert ev2.reference_start_s == pytest.approx(ev2.intake_s + pipeline * period)
    assert ev2.onset_s[0] > ev2.reference_start_s
    c.submit(SpeedStop(5.0))
    for _ in range(200):
        c.cycle()
    assert c.is_steady()


def test_stepped_controller_movej_reaches_target_and_rejects_out_of_limits():
    """moveJ lands on target; targets outside the limits and over-speed commands are refused
    with the joint and limit named."""
    c = ControllerSim("kr5", effects=default_effects("kr5"))
    target = np.array(c.spec.home_q_rad) + np.array([0.1, 0.1, -0.1, 0.0, 0.1, 0.0])
    c.submit(MoveJ(tuple(target), 1.0, 2.0))
    for _ in range(120):
        c.cycle()
    # The position loop (40 1/s) settles to well under a milliradian once at rest.
    np.testing.assert_allclose(c.q_rad, target, atol=1e-3)
    bad = np.array(c.spec.home_q_rad)
    bad[1] = 2.0
    with pytest.raises(ConfigError, match="joint 2"):
        c.submit(MoveJ(tuple(bad), 1.0, 2.0))
    with pytest.raises(ConfigError, match=r"joint 1 speed .* exceeds the limit"):
        c.submit(SpeedJ((100.0, 0, 0, 0, 0, 0), 5.0))


def test_effect_vocabulary_and_errors():
    """The vocabulary is DESIGN.md's; unknown names list it; effect sets round-trip."""
    assert EFFECT_NAMES == (
        "gravity_load",
        "gravity_direction",
        "direction",
        "inertia",
        "thermal_drift",
        "joint_offset",
        "response_extra_cycle",
    )
    with pytest.raises(ConfigError, match="the vocabulary is: gravity_load, gravity_direction"):
        make_effect("friction")
    with pytest.raises(ConfigError, match="must be >= 0"):
        make_effect("gravity_load", friction_per_load=-1.0)
    s = default_effects("kr5")
    assert EffectSet.from_dict(s.to_dict()) == s
    assert parse_effects("base", "ur10") == EffectSet()
    assert parse_effects("inertia,direction", "ur10").names == ("direction", "inertia")
    assert "response_extra_cycle" not in default_effects("ur10")


def test_plan_layout_and_bad_input():
    """Plans follow the published protocol (joints 1,2,3,5, both directions, repeats) and
    reject bad sizes with a clear message."""
    plan = SweepPlan.generate("ur10", 33_500, seed=0)
    assert len(plan) == 33_500
    assert set(np.unique(plan.joint)) == {1, 2, 3, 5}
    assert set(np.unique(plan.direction)) == {-1, 1}
    assert plan.repeat.max() == 9
    assert plan.meta()["n_configurations"] == 419
    with pytest.raises(ConfigError, match="positive integer"):
        SweepPlan.generate("ur10", 0)
    with pytest.raises(ConfigError, match="unknown robot 'ur5'"):
        SweepPlan.generate("ur5", 10)


def test_stepped_controller_takes_commands_at_their_own_boundary():
    """A command that arrives after a boundary must not replace one that arrived before it,
    even when both are submitted before that boundary is cycled (a twin running late)."""
    c = ControllerSim("ur10", effects=EffectSet())
    period = c.period_s
    first = c.submit(SpeedJ((0.1, 0, 0, 0, 0, 0), 5.0), arrival_s=0.5 * period)
    second = c.submit(SpeedJ((0.2, 0, 0, 0, 0, 0), 5.0), arrival_s=1.5 * period)
    for _ in range(4):
        c.cycle()
    by_id = {e.id: e for e in c.truth}
    assert by_id[first].intake_s == pytest.approx(period)
    assert not by_id[first].superseded
    assert by_id[second].intake_s == pytest.approx(2 * period)


@pytest.mark.parametrize("reissue", [False, True])
def test_a_joint_offset_delays_that_joint_only_under_a_multi_joint_speedj(reissue: bool):
    """``joint_offset``: each drive takes the setpoint later. Three joints started together
    by speedj, the control script's way (the same speedj re-issued every cycle) or once:
    +2 ms on joint 2 moves joint 2's true onset by 2 ms and the others not at all. Before,
    each joint's share of a command was activated late and speedj's lead axis was recomputed
    at each activation from the others' current references: re-issued, joint 2 lagging made
    it the lead and joints 1 and 3 ramped slower (+0.26 / +0.29 ms); through the UR twin
    about half of joint 2's offset was undone. Tolerance: one 8 kHz physics substep
    (0.125 ms) is the resolution of the onset and of the delay line."""
    from timedexec.effects import JointOffset

    def onsets(extra_s: float) -> np.ndarray:
        eff = default_effects("ur10e")
        off = list(eff.get("joint_offset").offsets_s)  # type: ignore[union-attr]
        off[1] += extra_s
        c = ControllerSim(
            "ur10e", effects=eff.with_effect(JointOffset(offsets_s=tuple(off))), seed=1
        )
        for _ in range(20):
            c.cycle()
        first = None
        for k in range(150):
            if reissue or k == 0:
                cid = c.submit(SpeedJ((0.3, 0.3, 0.3, 0, 0, 0), 2.0, 0.0))
                first = first or cid
            c.cycle()
        event = next(e for e in c.truth if e.id == first)
        return np.asarray(event.onset_s[:3])

    shift_ms = (onsets(0.002) - onsets(0.0)) * 1e3
    assert shift_ms[1] == pytest.approx(2.0, abs=0.13), shift_ms
    assert np.abs(shift_ms[[0, 2]]).max() < 0.05, shift_ms


def test_set_joint_offsets_changes_a_drive_in_service():
    """A drive that changes while the controller runs (the monitor's drift studies):
    +2 ms on joint 2 from now moves joint 2's next onset by 2 ms (one 8 kHz substep of
    resolution) and leaves the others; out-of-range offsets are refused."""

    def onsets(extra_s: float) -> np.ndarray:
        c = ControllerSim("ur10e", seed=1)
        for _ in range(20):
            c.cycle()
        if extra_s:
            c.set_joint_offsets(np.asarray(c._offset_s) + np.array([0, extra_s, 0, 0, 0, 0]))
        cid = c.submit(SpeedJ((0.3, 0.3, 0.3, 0, 0, 0), 2.0, 0.0))
        for _ in range(100):
            c.cycle()
        return np.asarray(next(e for e in c.truth if e.id == cid).onset_s[:3])

    shift_ms = (onsets(0.002) - onsets(0.0)) * 1e3
    assert shift_ms[1] == pytest.approx(2.0, abs=0.13), shift_ms
    assert np.abs(shift_ms[[0, 2]]).max() < 0.05, shift_ms
    with pytest.raises(ConfigError, match="offsets_s"):
        ControllerSim("ur10e").set_joint_offsets([0, 0.1, 0, 0, 0, 0])


def test_servoj_stream_from_rest_keeps_the_cycle_cost_flat():
    """A servoJ stream that crawls a joint from rest re-arms the onset watch every cycle;
    the controller checks its onset watch per joint, not per command, so 1,500 commands
    cost per cycle what the first 100 did. Before, the watch list grew by one entry per
    command and the cycle cost rose ~10x after 1,000 (the UR twin fell behind real time).
    The band (3x) is far below that growth and wide for a shared machine's timing noise;
    the newest command still gets the onset when the joint finally moves."""
    import time

    c = ControllerSim("ur10e", effects=EffectSet())
    q0 = np.array(c.q_rad)
    times = []
    for k in range(1500):
        target = q0.copy()
        target[0] += 1e-7 * k  # a crawl far below the onset threshold
        c.submit(ServoJ(tuple(target), time_s=c.period_s), arrival_s=c.time_s + 0.1 * c.period_s)
        t0 = time.perf_counter()
        c.cycle()
        times.append(time.perf_counter() - t0)
    early, late = np.median(times[:100]), np.median(times[-100:])
    assert late < 3 * early, (early, late)
    last = c.submit(
        ServoJ(tuple(q0 + np.array([0.05, 0, 0, 0, 0, 0])), time_s=0.1), arrival_s=c.time_s
    )
    for _ in range(100):
        c.cycle()
    event = next(e for e in c.truth if e.id == last)
    assert np.isfinite(event.onset_s[0])


@pytest.mark.parametrize("robot", ["ur10", "kr5"])
def test_joint_chain_steps_bit_identical_to_the_joint_bank(robot: str) -> None:
    """The stepped controller's float-by-float JointChain (the step as Python) and the
    batch's JointBank (the same step compiled by Numba, looped over its elements) give the
    same bits (q, v, stuck, onsets), through breakaway, reversals, torque saturation, rest
    and onset watches. A joint left at rest is skipped by the chain, so this also checks
    that skipping is exact."""
    from timedexec.effects import default_effects
    from timedexec.sim import JointBank, JointChain, joint_params

    spec = get_robot(robot)
    settings = default_settings(spec)
    rng = np.random.default_rng(11)
    q0 = np.array(spec.home_q_rad) + rng.uniform(-0.3, 0.3, 6)
    joints = np.arange(1, 7)
    params, _, _ = joint_params(
        spec, settings, default_effects(spec.name), np.broadcast_to(q0, (6, 6)), joints, np.zeros(6)
    )
    dt, thr = 1.25e-4, settings.servo.onset_threshold_rad_s
    bank, chain = JointBank(params, q0, dt, thr), JointChain(params, q0, dt, thr)
    v_ref = np.zeros(6)
    for k in range(6000):
        if k % 400 == 0:  # new segment: some joints rest, some move, some reverse or saturate
            v_ref = rng.choice([0.0, 0.0, 0.05, -0.2, 1.0, -3.0], 6) * rng.uniform(0.5, 1.0, 6)
            mask = rng.uniform(size=6) < 0.5
            bank.arm_onset(mask)
            chain.arm_onset(mask)
        t = k * dt
        bank.step(v_ref, t)
        chain.step(v_ref, t)
        assert np.array_equal(bank.q, chain.q), k
        assert np.array_equal(bank.v, chain.v), k
        assert np.array_equal(bank.stuck, chain.stuck), k
        assert np.array_equal(bank.onset_s, chain.onset_s, equal_nan=True), k
    assert np.isfinite(chain.onset_s).any()  # onsets were stamped, not only NaN compared


def test_float_and_numpy_trigonometry_agree_bit_for_bit() -> None:
    """math.cos/sin (the chain's step; the bank's compiled step calls the same C library)
    and numpy's (the holding torques both start from) give the same bits on this platform:
    checked on its own so a numpy build with other vector maths names the cause."""
    import math

    x = np.random.default_rng(2).uniform(-2 * np.pi, 2 * np.pi, 20000)
    assert np.array_equal(np.cos(x), [math.cos(v) for v in x])
    assert np.array_equal(np.sin(x), [math.sin(v) for v in x])


def test_ctrl_c_inside_the_compiled_bank_step_is_a_keyboard_interrupt(monkeypatch) -> None:
    """A Ctrl-C while Numba loads a kernel's cached constants arrives as SystemErrors whose
    root cause is the KeyboardInterrupt; the bank raises the KeyboardInterrupt (so the CLI
    exits 130 with its resume command), and any other SystemError unchanged."""
    from timedexec.effects import default_effects
    from timedexec.sim import JointBank, joint_params

    spec = get_robot("ur10")
    settings = default_settings(spec)
    q0 = np.array(spec.home_q_rad)
    params, _, _ = joint_params(
        spec, settings, default_effects("ur10"), np.broadcast_to(q0, (6, 6)), np.arange(1, 7),
        np.zeros(6),
    )  # fmt: skip
    bank = JointBank(params, q0, 1.25e-4, settings.servo.onset_threshold_rad_s)

    def kernel_interrupted(*args):
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as ki:
                raise SystemError("<function _numba_unpickle> returned a result") from ki
        except SystemError as inner:
            raise SystemError("CPUDispatcher(bank_step) returned a result") from inner

    # the fault goes in where the bank looks its kernel up (its module's globals)
    monkeypatch.setitem(JointBank.step.__globals__, "_bank_step", lambda: kernel_interrupted)
    with pytest.raises(KeyboardInterrupt):
        bank.step(np.zeros(6), 0.0)

    def kernel_broken(*args):
        raise SystemError("something else")

    monkeypatch.setitem(JointBank.step.__globals__, "_bank_step", lambda: kernel_broken)
    with pytest.raises(SystemError, match="something else"):
        bank.step(np.zeros(6), 0.0)


def test_settings_hold_a_protocol_and_store_the_layout_recordings_hold() -> None:
    """SimSettings holds a SweepProtocol (the robot's defaults, from its spec alone) instead
    of repeating its fields; ``to_dict`` keeps the flat layout every recording's header
    stored, and ``from_dict`` reads it back equal (through JSON, as a header holds it); a
    protocol stating another gyro than the simulated sensor is refused."""
    import dataclasses
    import json

    from timedexec.recording import SweepProtocol
    from timedexec.sim import SimSettings

    settings = default_settings("kr5", period_s=0.004)
    assert settings.protocol == SweepProtocol.for_robot("kr5", period_s=0.004)
    assert settings.protocol.gyro == settings.gyro.header()
    stored = settings.to_dict()
    assert list(stored) == [
        "robot", "controller_period_s", "timing", "servo", "gyro", "profile", "still_s",
        "config_move_s", "trial_gap_s",
    ]  # fmt: skip
    assert (stored["robot"], stored["controller_period_s"]) == ("kr5", 0.004)
    assert stored["gyro"] == settings.gyro.to_dict()  # the sensor model, not its header
    assert SimSettings.from_dict(json.loads(json.dumps(stored))) == settings
    louder = dataclasses.replace(settings.gyro, usb_latency_s=0.002)
    with pytest.raises(ConfigError, match=r"the protocol states the gyro .* but the simulated"):
        settings.replace(gyro=louder)
    moved = settings.replace(
        gyro=louder, protocol=dataclasses.replace(settings.protocol, gyro=louder.header())
    )
    assert moved.protocol.gyro.transport_latency_s == 0.002
