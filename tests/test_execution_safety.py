"""The executor's safety: the controller watchdog against a dead host, stop() to rest, and
staleness judged by time and the stream's measured jitter.

In-process (virtual-time ``SimDriver``, which emulates the UR watchdog) and, marked slow,
against the UR twin through the real ``ur_rtde`` client with the host running in a process
of its own that is SIGKILLed or SIGSTOPped mid-motion. The twin's new script semantics
(``speedj`` never expires, ``setWatchdog`` honoured) are being built concurrently; the kill
tests are written for them (on an older twin SIGKILL is caught by its disconnect stop and
SIGSTOP by the ``speedj`` duration).
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np
import pytest

from timedexec.drivers import RobotDriver, RobotState, SimDriver
from timedexec.errors import ConfigError, DriverError, DriverTimeout, StaleStateError
from timedexec.execution import (
    ExecutorSettings,
    FixedDelays,
    StalenessLimits,
    TimedExecutor,
)
from timedexec.robots import get_robot

PERIOD_S = 0.002
MODEL = FixedDelays(robot="ur10e", actuation_s=0.019, response_s=0.0011, actuation_std_s=6e-4)
#: The emulated and the twin's program stop decelerate at 4 rad/s² (SimDriver's
#: WATCHDOG_STOP_DECELERATION_RAD_S2, the UR twin's program stop).
PROGRAM_STOP_DECEL_RAD_S2 = 4.0
CRUISE_RAD_S = 0.5
#: From the program stop's arrival to three packages below 0.01 rad/s beyond the ramp
#: itself: the simulated UR10e's actuation delay (~20 ms), its velocity loop settling below
#: the rest threshold (~20 ms; 41 ms measured together) and 3 packages (6 ms).
SIM_STOP_LAG_S = 0.05


def start_pose() -> np.ndarray:
    q = np.array(get_robot("ur10e").home_q_rad)
    q[1] += 0.3
    return q


def sim(seed: int = 1) -> SimDriver:
    # 2 kHz physics: a quarter of the default 8 kHz's CPU, the same controller timing.
    return SimDriver("ur10e", seed=seed, q0_rad=start_pose(), physics_rate_hz=2000)


def cruise(ex: TimedExecutor, speed_rad_s: float = CRUISE_RAD_S) -> None:
    """Schedule joint 1 into a cruise at ``speed_rad_s`` and step until it is reached."""
    q0 = ex.estimate().q_rad
    target = q0.copy()
    target[0] += 0.1
    qd = np.zeros(6)
    qd[0] = speed_rad_s
    plan = ex.prepare(ex.plan(target, target_qd_rad_s=qd))
    ex.schedule(plan, ex.now() + ex.lead_time_s(plan) + 0.02)
    end = ex.now() + 2.0
    while ex.now() < end:
        state = ex.step()
        if abs(state.qd[0] - speed_rad_s) < 0.02:
            return
    raise AssertionError("the cruise speed was never reached")


def first_of_rest_run(samples: Iterable[tuple[float, Any]]) -> float:
    """Time of the first of three consecutive ``(time_s, qd)`` samples with every joint
    below 0.01 rad/s (NaN if the samples end first)."""
    run, first = 0, math.nan
    for time_s, qd in samples:
        if np.max(np.abs(qd)) < 0.01:
            first = time_s if run == 0 else first
            run += 1
            if run >= 3:
                return first
        else:
            run = 0
    return math.nan


def first_rest(driver: SimDriver, after_s: float, span_s: float) -> float:
    """Host time of the first of three packages at rest read straight from the driver
    (no command, no kick: the host is gone)."""

    def states() -> Iterator[tuple[float, Any]]:
        while driver.clock() < after_s + span_s:
            state = driver.read_state(timeout_s=1.0)
            yield state.host_time_s, state.qd

    return first_of_rest_run(states())


# ---------------------------------------------------------------------------- watchdog
def test_watchdog_stops_the_arm_of_a_host_that_stops_commanding() -> None:
    """The host stops stepping mid-cruise (dead, hung or paused): the emulated controller
    watchdog trips after its 0.1 s timeout and the program stop brings the arm to rest
    within timeout + speed / 4 rad/s² (+ one period of command latency and a package's
    age); the executor then refuses with a DriverError naming the watchdog, and recover()
    restarts the program so the next motion runs."""
    drv = sim()
    with TimedExecutor(drv, MODEL) as ex:
        assert ex.watchdog.armed_s == pytest.approx(0.1)
        cruise(ex)
        gone = ex.now()
        rest = first_rest(drv, gone, 1.0)
        assert drv.watchdog_trips, "the watchdog never tripped"
        bound = 0.1 + CRUISE_RAD_S / PROGRAM_STOP_DECEL_RAD_S2 + SIM_STOP_LAG_S
        # Lower bound: the arm cannot stop before the timeout plus most of the ramp.
        assert 0.1 + 0.8 * CRUISE_RAD_S / PROGRAM_STOP_DECEL_RAD_S2 <= rest - gone <= bound, (
            rest - gone
        )
        with pytest.raises(DriverError, match=r"watchdog stopped the program.*recover"):
            ex.step()
        with pytest.raises(DriverError, match="fault"):
            ex.step()
        ex.recover()
        assert not drv.watchdog_tripped()
        q = ex.estimate().q_rad.copy()
        q[0] -= 0.1
        plan = ex.prepare(ex.plan(q))
        ex.execute(plan, start_time_s=ex.now() + ex.lead_time_s(plan) + 0.02)
        assert abs(ex.estimate().q_rad[0] - q[0]) < 5e-3


def test_idle_reads_kick_and_an_idle_trip_is_rearmed_before_the_next_motion() -> None:
    """While the caller steps an idle executor it kicks the watchdog (no trip over 1 s);
    a caller who does not step for longer than the timeout lets it trip at rest (no harm)
    and the next motion re-arms it first, at a measured cost."""
    drv = sim(2)
    with TimedExecutor(drv, MODEL) as ex:
        ex.idle(ex.now() + 1.0)
        assert not drv.watchdog_trips
        # At most one kick per fifth of the timeout (20 ms): ~50 in 1 s.
        assert 40 <= ex.watchdog.kicks <= 55, ex.watchdog.kicks
        drv.read_state(timeout_s=1.0)
        t = drv.clock()
        while drv.clock() < t + 0.3:  # the caller is busy elsewhere
            drv.read_state(timeout_s=1.0)
        assert drv.watchdog_tripped()
        q = ex.estimate().q_rad.copy()
        q[0] += 0.05
        plan = ex.prepare(ex.plan(q))
        ex.execute(plan, start_time_s=ex.now() + ex.lead_time_s(plan) + 0.02)
        assert len(ex.watchdog.rearm_s) == 1
        assert abs(ex.estimate().q_rad[0] - q[0]) < 5e-3


def test_no_watchdog_when_disabled_or_unsupported() -> None:
    """watchdog_timeout_s=None arms nothing; a driver without a watchdog returns None;
    a timeout outside (0, 10] s is a ConfigError naming the value (when the settings are
    built, before any executor)."""
    drv = sim(3)
    with TimedExecutor(drv, MODEL, ExecutorSettings(watchdog_timeout_s=None)) as ex:
        assert ex.watchdog.armed_s is None
        assert not drv.watchdog_tripped()
    with pytest.raises(ConfigError, match=r"watchdog_timeout_s=0.0 outside \(0, 10\] s"):
        ExecutorSettings(watchdog_timeout_s=0.0)
    plain = PlainDriver(sim(3))
    with TimedExecutor(plain, MODEL) as ex:
        assert ex.watchdog.armed_s is None


# ---------------------------------------------------------------------------- stop()
def test_stop_returns_only_at_rest() -> None:
    """stop() mid-cruise returns once every joint reports < 0.01 rad/s for 3 packages: the
    simulator's true speed is zero then, and it took at least the ramp (speed over the
    stop deceleration) and at most the documented timeout."""
    drv = sim(4)
    with TimedExecutor(drv, MODEL) as ex:
        cruise(ex, 1.0)
        t = ex.now()
        state = ex.stop()
        took = ex.now() - t
        decel = min(get_robot("ur10e").qdd_max_rad_s2)
        assert np.max(np.abs(state.qd)) < 0.01
        assert np.max(np.abs(drv.controller.qd_rad_s)) < 0.01
        assert 1.0 / decel <= took <= 1.0 / decel + 0.25 + 4 * PERIOD_S, took
        assert not drv.watchdog_trips


class SpinningDriver(SimDriver):
    """Reports joint 1 still turning at 0.2 rad/s whatever it is told."""

    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        state = super().read_state(timeout_s)
        qd = state.qd.copy()
        qd[0] = 0.2
        return dataclasses.replace(state, qd=qd)


def test_stop_raises_when_the_arm_does_not_come_to_rest() -> None:
    """A stop that never sees rest raises a DriverError naming joint, speed and time."""
    drv = SpinningDriver("ur10e", seed=5, q0_rad=start_pose(), physics_rate_hz=2000)
    ex = TimedExecutor(drv, MODEL)
    ex.connect()
    try:
        with pytest.raises(DriverError, match=r"did not come to rest: joint 1.*0\.2 rad/s"):
            ex.stop(timeout_s=0.2)
    finally:
        drv.close()


# ---------------------------------------------------------------------------- staleness
def feed(limits: StalenessLimits, gaps_s: np.ndarray) -> Any:
    jitter = limits.jitter()
    for g in gaps_s:
        jitter.add(float(g), 0.0)
    return jitter


def test_adaptive_limits_follow_the_measured_gaps() -> None:
    """Quiet 2 ms stream: the 50 ms floor; 6-24 ms gaps: 2 x p99 = 48 ms, still the floor;
    10-35 ms gaps: 2 x p99 ~ 70 ms; a stream jittering beyond that is capped at the 80 ms
    ceiling; the legacy knob stays fixed."""
    rng = np.random.default_rng(0)
    lim = StalenessLimits()
    assert lim.stall_limit_s(PERIOD_S) == pytest.approx(0.05)
    quiet = feed(lim, rng.normal(PERIOD_S, 1e-4, 1000))
    assert lim.stall_limit_s(PERIOD_S, quiet) == pytest.approx(0.05)
    gappy = feed(lim, rng.uniform(0.006, 0.024, 1000))
    assert 0.046 <= 2 * gappy.gap_q_s <= 0.048
    assert lim.stall_limit_s(PERIOD_S, gappy) == pytest.approx(0.05)
    slower = feed(lim, rng.uniform(0.01, 0.035, 1000))
    assert 0.068 <= lim.stall_limit_s(PERIOD_S, slower) <= 0.070
    wild = feed(lim, rng.uniform(0.01, 0.09, 1000))
    assert lim.stall_limit_s(PERIOD_S, wild) == pytest.approx(0.08)
    legacy = StalenessLimits.from_stale_periods(3)
    assert legacy.stall_limit_s(PERIOD_S, wild) == pytest.approx(0.006)
    assert legacy.late_limit_s(PERIOD_S, wild) == pytest.approx(0.006)
    with pytest.raises(ConfigError, match=r"floor_s=0.2.*ceiling_s=0.08"):
        StalenessLimits(floor_s=0.2)
    with pytest.raises(ConfigError, match=r"staleness=3 is not a StalenessLimits.*from_stale"):
        ExecutorSettings(staleness=3)  # type: ignore[arg-type]


class PlainDriver(RobotDriver):
    """Delegates to another driver; no watchdog (the base class defaults)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.robot = inner.robot
        self.virtual = bool(getattr(inner, "virtual", False))
        if callable(getattr(inner, "clock", None)):
            self.clock = inner.clock

    @property
    def controller_period_s(self) -> float:
        return float(self.inner.controller_period_s)

    @property
    def spec(self) -> Any:
        return getattr(self.inner, "spec", None) or self.inner.settings.spec

    def connect(self) -> None:
        self.inner.connect()

    def close(self) -> None:
        self.inner.close()

    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        return self.inner.read_state(timeout_s)  # type: ignore[no-any-return]

    def speedj(self, qd_rad_s: Any, acceleration_rad_s2: float, duration_s: float) -> None:
        self.inner.speedj(qd_rad_s, acceleration_rad_s2, duration_s)

    def stop(self, deceleration_rad_s2: float = 10.0) -> None:
        self.inner.stop(deceleration_rad_s2)


class GappyDriver(PlainDriver):
    """Delivers the newest package only every 6-24 ms (uniform, seeded), stamped on
    delivery: a loaded host's view of a 500 Hz stream. ``dead_at_s``: from that host time
    on, nothing arrives; ``stop_sent_s``: when the first zero-speed command went out after
    that (the executor's fault stop; its ``stop()`` then waits for the arm). Keeps the inner
    driver's watchdog."""

    def __init__(self, inner: Any, seed: int = 0, gaps_s: tuple[float, float] = (0.006, 0.024)):
        super().__init__(inner)
        self.rng = np.random.default_rng(seed)
        self.gaps_s = gaps_s
        self.dead_at_s = math.inf
        self.stop_sent_s = math.nan
        self._next_s = -math.inf
        self.delivered = 0
        self.max_wake_late_s = 0.0

    def speedj(self, qd_rad_s: Any, acceleration_rad_s2: float, duration_s: float) -> None:
        now = self.now()
        if now >= self.dead_at_s and math.isnan(self.stop_sent_s) and not np.any(qd_rad_s):
            self.stop_sent_s = now
        self.inner.speedj(qd_rad_s, acceleration_rad_s2, duration_s)

    def now(self) -> float:
        return float(self.clock()) if callable(getattr(self, "clock", None)) else time.monotonic()

    def wait_until(self, t_s: float) -> None:
        if hasattr(self.inner, "wait_until"):
            self.inner.wait_until(t_s)
        else:
            time.sleep(max(0.0, t_s - self.now()))

    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        now = self.now()
        target = max(now, self._next_s)
        if target >= self.dead_at_s or target - now > timeout_s:
            self.wait_until(now + timeout_s)
            raise DriverTimeout(f"no package within {timeout_s} s (gap injected)")
        self.wait_until(target)
        self.max_wake_late_s = max(self.max_wake_late_s, self.now() - target)
        newest = None
        while True:  # drain: the newest package that has arrived by now
            try:
                newest = self.inner.read_state(timeout_s=0.0)
            except DriverTimeout:
                break
        if newest is None:
            newest = self.inner.read_state(timeout_s=max(timeout_s - (self.now() - now), 0.0))
        stamped: RobotState = dataclasses.replace(newest, host_time_s=self.now())
        self._next_s = stamped.host_time_s + float(self.rng.uniform(*self.gaps_s))
        self.delivered += 1
        return stamped

    def arm_watchdog(self, timeout_s: float) -> float | None:
        return self.inner.arm_watchdog(timeout_s)  # type: ignore[no-any-return]

    def kick_watchdog(self) -> None:
        self.inner.kick_watchdog()

    def watchdog_tripped(self) -> bool:
        return bool(self.inner.watchdog_tripped())


def back_and_forth(ex: TimedExecutor, seconds: float) -> int:
    """Joint 1 moves ±0.3 rad back and forth for ``seconds``; returns the moves made."""
    q0 = ex.estimate().q_rad.copy()
    end = ex.now() + seconds
    k = 0
    while ex.now() < end:
        target = q0.copy()
        target[0] += 0.3 if k % 2 == 0 else 0.0
        plan = ex.prepare(ex.plan(target))
        ex.execute(plan, start_time_s=ex.now() + ex.lead_time_s(plan) + 0.03, settle_s=0.02)
        k += 1
    return k


def stream_until_fault(ex: TimedExecutor) -> None:
    """Step until the executor raises."""
    while True:
        ex.step()


def run_gappy_then_dead(driver: GappyDriver, seconds: float) -> tuple[TimedExecutor, float, float]:
    """Stream for ``seconds`` through 6-24 ms gaps (no fault allowed), then kill the stream
    mid-motion; return the executor, the detection time (the fault's stop command minus the
    last delivery, minus the stall limit in force) and the host time of that command."""
    with TimedExecutor(driver, MODEL) as ex:
        back_and_forth(ex, seconds)
        q = ex.estimate().q_rad.copy()
        q[0] -= 0.3
        plan = ex.prepare(ex.plan(q))
        ex.schedule(plan, ex.now() + ex.lead_time_s(plan) + 0.03)
        for _ in range(20):
            ex.step()
        driver.dead_at_s = ex.now()
        with pytest.raises(StaleStateError, match="stall"):
            stream_until_fault(ex)
        last = ex.last_state
        assert last is not None
        fault_s = driver.stop_sent_s
        detected = fault_s - last.host_time_s
        # The limit the failing read used: the jitter has not changed since that package.
        return ex, detected - ex.stall_limit_s, fault_s


@pytest.mark.parametrize(
    "seconds", [3.0, pytest.param(10.0, marks=pytest.mark.slow)], ids=["3s", "10s"]
)
def test_jittery_stream_runs_without_false_stop_and_a_dead_one_is_caught(seconds: float) -> None:
    """Back-and-forth moves through a stream delivered every 6-24 ms (virtual time; 3 s,
    10 s under slow): no stale fault (the legacy 3-period limit faults within 1 s); then
    the stream dies mid-motion and the fault comes within the stall limit in force (~48
    ms floor, above 2 x p99 of the gaps; the read waits exactly until it, virtual time
    adds no wake-up), at most the 80 ms ceiling."""
    drv = GappyDriver(sim(6), seed=6)
    ex, late_s, _ = run_gappy_then_dead(drv, seconds)
    assert drv.delivered > 40 * seconds
    assert -1e-6 <= late_s <= 0.001, late_s
    assert 0.05 <= ex.stall_limit_s <= 0.08, ex.stall_limit_s
    legacy = GappyDriver(sim(6), seed=6)
    fixed = ExecutorSettings(staleness=StalenessLimits.from_stale_periods(3))
    with TimedExecutor(legacy, MODEL, fixed) as ex3, pytest.raises(StaleStateError):
        back_and_forth(ex3, 1.0)


class LateDriver(PlainDriver):
    """A real-time driver whose every ``every``-th package arrives ``late_s`` late (held,
    then stamped on delivery: a controller or network hiccup); ``dead``: nothing arrives.
    ``held_cycles``: the controller times of the packages held back."""

    def __init__(self, inner: Any, every: int, late_s: float) -> None:
        super().__init__(inner)
        self.every, self.late_s = every, late_s
        self.count = 0
        self.dead = False
        self.held_cycles: list[float] = []
        self._held: tuple[RobotState, float] | None = None

    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        start = time.monotonic()
        if self.dead:
            time.sleep(max(timeout_s, 0.0))
            raise DriverTimeout("no package (stream dead)")
        if self._held is None:
            state = self.inner.read_state(timeout_s)
            self.count += 1
            if self.count % self.every:
                return state  # type: ignore[no-any-return]
            self._held = (state, state.host_time_s + self.late_s)
            self.held_cycles.append(state.controller_time_s)
        state, release = self._held
        if release - time.monotonic() > timeout_s - (time.monotonic() - start):
            time.sleep(max(timeout_s - (time.monotonic() - start), 0.0))
            raise DriverTimeout(f"no package within {timeout_s} s (held back)")
        time.sleep(max(release - time.monotonic(), 0.0))
        self._held = None
        return dataclasses.replace(state, host_time_s=time.monotonic())


def _send_lateness_ms(ex: TimedExecutor, cycles: list[float]) -> np.ndarray:
    """For the cycles given (controller times), how long after the cycle's earliest package
    arrival (lower envelope of arrival minus controller time) its command left, ms."""
    log = ex.log.arrays()
    on_time = ~log["coasted"] & np.isfinite(log["arrival_s"])
    earliest = float(np.min((log["arrival_s"] - log["controller_s"])[on_time]))
    sent = np.isfinite(log["send_s"])
    period = ex.period_s
    k_sent = np.round(log["controller_s"][sent] / period).astype(np.int64)
    late = (log["send_s"] - log["controller_s"] - earliest)[sent] * 1e3
    by_cycle = dict(zip(k_sent.tolist(), late.tolist(), strict=True))
    return np.array([by_cycle[k] for k in np.round(np.array(cycles) / period).astype(int).tolist()
                     if k in by_cycle])  # fmt: skip


def test_coasting_commands_a_late_packages_cycle_on_time_and_a_dead_stream_still_faults() -> None:
    """Real time (the simulator on the host clock), every 10th package held back 1.5 ms:
    past the cycle-locked send target (0.6 ms after the cycle's earliest arrival). With
    ``coast`` those cycles get their command from the estimate at the target, once (the
    late package is then only read); without it their command waits for the package.
    Then the stream dies mid-motion: coasting does not hide it, the stall fault comes at
    the stall limit. Bands: the target is 0.6 ms; the held package comes at >= 1.5 ms, so
    a median below 1.2 ms is the coasted send and above 1.4 ms the waiting one (a few
    tenths of a ms of wake-up jitter on a loaded machine either way). Measured here: medians
    0.81-0.82 ms with coast, 1.78-1.79 ms without; 15-30 % of the coasted sends came 1-2.3
    ms late: their read returned 0.3-1.4 ms after its timeout, the in-process simulator
    stepping its physics inside ``read_state`` (the same with a 0.2 ms GIL switch interval;
    against ur_rtde and the peer the coasting p99 was 0.24-0.35 ms)."""
    late_ms = {}
    for coast in (True, False):
        inner = SimDriver("ur10e", seed=1, q0_rad=start_pose(), physics_rate_hz=2000, virtual=False)
        drv = LateDriver(inner, every=10, late_s=0.0015)
        with TimedExecutor(drv, MODEL, ExecutorSettings(cycle_lock=True, coast=coast)) as ex:
            drv.held_cycles.clear()
            back_and_forth(ex, 1.0)
            held = list(drv.held_cycles)
            late_ms[coast] = _send_lateness_ms(ex, held)
            log = ex.log.arrays()
            sent = np.isfinite(log["send_s"])
            cycles = np.round(log["controller_s"][sent] / ex.period_s).astype(np.int64)
            assert len(np.unique(cycles)) == len(cycles), "a cycle got two commands"
            if coast:
                # most held packages fell inside streaming and were coasted over
                assert ex.coasted >= 0.5 * len(late_ms[coast]) > 10, (ex.coasted, len(held))
                q = ex.estimate().q_rad.copy()
                q[0] -= 0.3
                ex.schedule(ex.prepare(ex.plan(q)), ex.now() + 0.05)
                for _ in range(40):
                    ex.step()
                drv.dead = True
                with pytest.raises(StaleStateError, match="stall"):
                    stream_until_fault(ex)
                last = ex.last_state
                assert last is not None
                # the fault at the stall limit, not later (coasting kept sending meanwhile)
                assert ex.now() - last.host_time_s <= ex.stall_limit_s + 0.02
            else:
                assert ex.coasted == 0
    assert np.median(late_ms[True]) < 1.2, late_ms[True]
    assert np.median(late_ms[False]) > 1.4, late_ms[False]


# ---------------------------------------------------------------------------- the UR twin
CHILD = r"""
import sys, time
import numpy as np
from timedexec.drivers import URDriver
from timedexec.execution import ExecutorSettings, FixedDelays, StalenessLimits, TimedExecutor
host, speed = sys.argv[1], float(sys.argv[2])
# argv[3], if given: the pendant program holding the External Control URCap's node
program = sys.argv[3] if len(sys.argv) > 3 else None
model = FixedDelays(robot="ur10e", actuation_s=0.019, response_s=0.0011, actuation_std_s=6e-4)
# The ceiling's tolerance from the start: this test is about the watchdog, and a test
# process on a loaded two-core machine sees 50 ms stalls now and then.
settings = ExecutorSettings(staleness=StalenessLimits(floor_s=0.08))
with TimedExecutor(URDriver(host, robot="ur10e", program=program), model, settings) as ex:
    ex.idle(ex.now() + 0.2)
    q0 = ex.estimate().q_rad
    target = q0.copy(); target[0] += 0.1
    qd = np.zeros(6); qd[0] = speed
    plan = ex.prepare(ex.plan(target, target_qd_rad_s=qd))
    said = False
    def report(state):
        global said
        if not said and abs(state.qd[0] - speed) < 0.02:
            print("CRUISING", flush=True)
            said = True
    ex.execute(plan, start_time_s=ex.now() + ex.lead_time_s(plan) + 0.15,
               until_s=ex.now() + 20.0, on_step=report)
"""


@pytest.fixture(scope="module")
def ur_twin():  # type: ignore[no-untyped-def]
    pytest.importorskip("rtde_receive")
    pytest.importorskip("rtde_control")
    from timedexec.twins import URTwin

    with URTwin("ur10e", "127.0.0.43", seed=3, q0_rad=start_pose()) as twin:
        yield twin


def watch_rest(host: str, since_s: float, span_s: float) -> float:
    """Host time of the first of three packages with every joint below 0.01 rad/s, seen by
    an independent RTDE receiver (NaN if none within ``span_s``)."""
    import rtde_receive

    recv = rtde_receive.RTDEReceiveInterface(host)

    def packages() -> Iterator[tuple[float, Any]]:
        last_ts = None
        while time.monotonic() < since_s + span_s:
            ts = recv.getTimestamp()
            if ts == last_ts:
                time.sleep(2e-4)
                continue
            last_ts = ts
            yield time.monotonic(), recv.getActualQd()

    try:
        return first_of_rest_run(packages())
    finally:
        recv.disconnect()


def _cruising_host(
    host: str, program: str | None = None
) -> tuple[subprocess.Popen[str], str | None]:
    """Start a host process (CHILD) cruising through ur_rtde against ``host`` (through the
    External Control URCap when ``program`` names its pendant program); return it and None
    once it says CRUISING, or it (ended) and the tail of its stderr."""
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, host, str(CRUISE_RAD_S), *([program] if program else [])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    assert child.stdout is not None
    if "CRUISING" in child.stdout.readline():
        return child, None
    child.wait(10)
    return child, (child.stderr.read() if child.stderr is not None else "")[-400:]


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["SIGKILL", "SIGSTOP"])
def test_killed_or_paused_host_process_stops_the_twin_arm(ur_twin: Any, sig: int) -> None:
    """A host process streaming a 0.5 rad/s cruise through ur_rtde is SIGKILLed / SIGSTOPped
    (through the External Control program: the independent peer's case below):
    the twin's reported speed is zero within the watchdog timeout (0.1 s) + the program
    stop's ramp (0.5 / 4 rad/s² = 0.125 s) + SIM_STOP_LAG_S (actuation delay, velocity
    loop settling, 3 packages) + 100 ms (the last command's age at the signal, the
    observer's polling and, on a loaded two-core machine, a late twin or observer
    wake-up; see the bound): 0.375 s."""
    failures = []
    for _attempt in range(3):  # a host stall before the cruise is not what this tests
        child, failure = _cruising_host(ur_twin.host)
        try:
            if failure is not None:
                failures.append(failure)
                continue
            time.sleep(0.3)
            t_signal = time.monotonic()
            os.kill(child.pid, sig)
            rest = watch_rest(ur_twin.host, t_signal, 2.0)
        finally:
            if child.poll() is None:
                child.kill()
            child.wait(10)
        break
    else:
        pytest.fail(f"the host process never reached the cruise: {failures}")
    # load allowance 0.1 s, not 0.06: on a VM where the twin's simulator costs 0.5-0.64 of
    # real time, 2 of 20 runs of these kill tests ended 0.365 s after the signal (a late
    # twin or observer wake-up) while the rest stayed under 0.3 s
    bound = 0.1 + CRUISE_RAD_S / PROGRAM_STOP_DECEL_RAD_S2 + SIM_STOP_LAG_S + 0.1
    assert rest - t_signal <= bound, rest - t_signal


@pytest.mark.slow
@pytest.mark.realtime_twin
def test_stop_through_ur_rtde_returns_at_rest(ur_twin: Any) -> None:
    """stop() mid-cruise on the twin returns when the reported speed is zero; an
    independent receiver confirms the arm is still at rest; it took at least the ramp."""
    from timedexec.drivers import URDriver

    with TimedExecutor(URDriver(ur_twin.host, robot="ur10e"), MODEL) as ex:
        ex.idle(ex.now() + 0.2)
        cruise(ex, 1.0)
        t = ex.now()
        state = ex.stop()
        took = ex.now() - t
        assert np.max(np.abs(state.qd)) < 0.01
        after = ex.driver.read_state(timeout_s=0.5)
        assert np.max(np.abs(after.qd)) < 0.01
        decel = min(get_robot("ur10e").qdd_max_rad_s2)
        assert 1.0 / decel <= took <= 1.0 / decel + 0.25 + 4 * PERIOD_S, took


@pytest.mark.realtime_twin
@pytest.mark.slow
def test_jittery_ur_stream_then_dead(ur_twin: Any) -> None:
    """20 s through ur_rtde with deliveries every 6-24 ms: no false stale stop; then the
    stream dies and the fault comes within the stall limit in force (+ 10 ms of wake-up
    on a loaded machine). The minute runs against the independent peer (next test, not
    gated: the peer is cheap); here the same path against our twin, shorter for CI's time."""
    from timedexec.drivers import URDriver

    drv = GappyDriver(URDriver(ur_twin.host, robot="ur10e"), seed=7)
    before = float(ur_twin.stats()["max_lateness_s"])
    try:
        _, late_s, _ = run_gappy_then_dead(drv, 20.0)
    except DriverError as exc:  # a stale fault, or a watchdog trip after a >100 ms stall
        worst = float(ur_twin.stats()["max_lateness_s"])
        # Beyond the scenario: the twin put a package on the wire, or this process woke,
        # more than 25 ms late (a loaded two-core machine); that package really was stale.
        if worst > max(before, 0.025) or drv.max_wake_late_s > 0.025:
            pytest.skip(
                f"beyond 6-24 ms gaps: twin {worst * 1e3:.0f} ms late, this host woke "
                f"{drv.max_wake_late_s * 1e3:.0f} ms late: {exc}"
            )
        raise
    assert -1e-4 <= late_s <= 0.010, late_s


@pytest.mark.slow
def test_jittery_stream_from_the_independent_peer_then_dead() -> None:
    """The same 20 s against the independently written UR peer (real script semantics;
    it costs a quarter of a core where the twin's real-time tests need a faster machine),
    through real ur_rtde, the packages delivered every 6-24 ms: no false stale stop; the
    stream dies mid-motion, the fault comes within the stall limit in force (+ 10 ms of
    wake-up on a loaded machine), and the peer's truth has the arm at rest within the
    stop ramp from its speed at the fault + 0.1 s (the stop's acknowledgement, pipeline,
    load)."""
    pytest.importorskip("rtde_receive")
    pytest.importorskip("rtde_control")
    peer_mod = pytest.importorskip("independent_ur_peer")
    from timedexec.drivers import URDriver

    with peer_mod.run_peer("127.0.0.45", model="UR10", version="5.11.1") as peer:
        drv = GappyDriver(URDriver(peer.host, robot="ur10e"), seed=7)
        try:
            # 20 s (about 1,300 gappy deliveries; a minute before the CI budget was cut):
            # a false stale stop at these gaps shows within seconds, as on the twin above.
            _, late_s, fault_s = run_gappy_then_dead(drv, 20.0)
        except DriverError as exc:
            # Beyond the scenario (as for the twin above): this process woke > 25 ms late.
            if drv.max_wake_late_s > 0.025:
                pytest.skip(f"this host woke {drv.max_wake_late_s * 1e3:.0f} ms late: {exc}")
            raise
        t_fault = peer.to_peer_time(fault_s)
        truth = peer.wait_truth_until(t_fault + 1.0)
    assert drv.delivered > 40 * 20
    assert -1e-4 <= late_s <= 0.010, late_s
    at_fault = np.searchsorted(truth.t, t_fault)
    speed = float(np.max(np.abs(truth.qd[at_fault])))
    rest = truth.rest_time_after(t_fault)
    assert rest is not None, "the peer's arm still moves"
    decel = min(get_robot("ur10e").qdd_max_rad_s2)  # the executor's stop deceleration
    assert rest - t_fault <= speed / decel + 0.1, (rest - t_fault, speed)


#: The independent peer's program stop decelerates at 3 rad/s² (its --stop-decel default)
#: after a 3-cycle actuation pipeline.
PEER_STOP_DECEL_RAD_S2 = 3.0


@pytest.mark.slow
@pytest.mark.parametrize(
    ("sig", "program"),
    [
        (signal.SIGKILL, None),
        (signal.SIGSTOP, None),
        (signal.SIGKILL, "/programs/external_control.urp"),
    ],
    ids=["SIGKILL", "SIGSTOP", "SIGKILL-external-control"],
)
def test_killed_or_paused_host_stops_the_independent_peer_arm(
    sig: int, program: str | None
) -> None:
    """The same against the independently written UR peer (tests/independent_ur_peer/,
    real script semantics: speedj never expires, setWatchdog honoured, no stop on
    disconnect; its script uploaded, or fetched by the peer's External Control program):
    its watchdog trips 0.1 s after the last command (the signal lands at most a few periods
    after it: -10 / +40 ms for the signal's and the peer's own timing on a loaded machine)
    and its truth shows every joint at rest within the timeout + 0.5 rad/s / 3 rad/s² + 100
    ms (pipeline 6 ms, the last command's age, load)."""
    pytest.importorskip("rtde_receive")
    pytest.importorskip("rtde_control")
    peer_mod = pytest.importorskip("independent_ur_peer")
    with peer_mod.run_peer("127.0.0.44", model="UR10", version="5.11.1") as peer:
        child, failure = _cruising_host(peer.host, program)
        try:
            if failure is not None:
                pytest.fail(f"the host never reached the cruise: {failure}")
            time.sleep(0.3)
            t_signal = peer.to_peer_time(time.monotonic())
            os.kill(child.pid, sig)
            trip = peer.wait_event("watchdog_trip", timeout=3.0, after=t_signal - 0.05)
            truth = peer.wait_truth_until(trip.time_s + 0.5)
        finally:
            if child.poll() is None:
                child.kill()
            child.wait(10)
        rest = truth.rest_time_after(t_signal)
        sources = [ev.fields["source"] for ev in peer.events("program_started")]
    assert sources == ["external_control" if program else "upload"], sources
    assert rest is not None, "the peer's arm still moves"
    assert 0.1 - 0.01 <= trip.time_s - t_signal <= 0.1 + 0.04, trip.time_s - t_signal
    bound = 0.1 + CRUISE_RAD_S / PEER_STOP_DECEL_RAD_S2 + 0.1  # load allowance as above
    assert rest - t_signal <= bound, rest - t_signal


def _arrivals(phase_of, seconds: float, drift_ppm: float, seed: int):
    """(host arrival, arrival - controller time) of a 500 Hz stream: controller cycle
    boundaries k·T, a publisher phase ``phase_of(t)`` (s) after each, an exponential wire
    time (0.05 ms + mean 0.1 ms), and a host clock running ``drift_ppm`` fast, offset 3 s."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, PERIOD_S)
    wire = 5e-5 + rng.exponential(1e-4, t.size)
    arrival_ctrl = t + phase_of(t) + wire
    host = 3.0 + arrival_ctrl * (1 + drift_ppm * 1e-6)
    return t, host, host - t


@pytest.mark.parametrize("shape", ["triangle", "sawtooth", "constant"])
def test_boundary_line_finds_the_cycle_under_a_wandering_publisher(shape: str) -> None:
    """The long-term clock line recovers the host time of the cycle boundaries (plus the
    shortest publish + wire time) when the publisher's phase wanders through the whole
    period: a 47 s triangle like the twin's, or a sawtooth that wraps every 31 s (a
    publisher on its own timer, not written after the twin), with the host clock 80 ppm
    fast. The short envelope follows the phase (off by up to ~1.9 ms); the line stays
    within 0.1 ms of the truth over the last 80 s (the wire's shortest 0.05 ms and the
    phase's least value within one 0.5 s bucket: < 0.05 ms each). A steady publisher gives
    the same line as the envelope. Before 100 s of arrivals: no line."""
    from timedexec.execution import BoundaryLine

    lo, hi = 0.02 * PERIOD_S, 0.97 * PERIOD_S
    phase_of = {
        "triangle": lambda t: lo + (hi - lo) * (1 - np.abs(2 * ((t / 47.0 + 0.3) % 1.0) - 1)),
        "sawtooth": lambda t: lo + (hi - lo) * ((t / 31.0 + 0.6) % 1.0),
        "constant": lambda t: np.full_like(t, 0.7 * PERIOD_S),
    }[shape]
    t, host, off = _arrivals(phase_of, 200.0, 80.0, seed=4)
    # The truth: the host time of boundary + least phase + shortest wire, minus the
    # controller time.
    least = (lo if shape != "constant" else 0.7 * PERIOD_S) + 5e-5
    true = 3.0 + (t + least) * (1 + 80e-6) - t
    line = BoundaryLine()
    errors, envelope_errors = [], []
    for i, (h, o) in enumerate(zip(host.tolist(), off.tolist(), strict=True)):
        line.add(h, o)
        if h - host[0] < 99.0:  # the span is short of 100 s
            assert line.line is None
        elif h - host[0] > 120.0 and i % 50 == 0:
            errors.append(line.offset_s(h) - true[i])
            envelope_errors.append(off[max(0, i - 250) : i + 1].min() - true[i])
    err = np.abs(np.array(errors))
    assert err.max() < 1e-4, err.max()
    # A stalled package (100 ms late) is not a new clock; a controller that restarts (its
    # clock from 0 again) is: the line starts over, not aims by the old clock.
    t2, host2, off2 = _arrivals(phase_of, 204.0, 80.0, seed=5)
    for k in range(t.size, t2.size):  # 2 s more of the same stream, one package stalled
        line.add(host2[k], off2[k] + (0.1 if k == t.size + 300 else 0.0))
    assert line.line is not None
    h = host2[-1]
    for k in range(1, 600):
        line.add(h + k * PERIOD_S, h + k * PERIOD_S)
    assert line.line is None
    if shape == "constant":
        assert np.abs(np.array(envelope_errors)).max() < 1e-4
    else:
        assert np.abs(np.array(envelope_errors)).max() > 1e-3  # what the line fixes


def test_send_phase_aims_at_the_middle_of_the_intake_window() -> None:
    """The cycle-locked sender leaves half a period minus the round trip after the earliest
    package arrival (0.6 ms at 500 Hz with the default 0.4 ms); a round trip outside
    [0, period) is a ConfigError naming it (at connect, when the period is known; the
    driver is closed again); a virtual-time driver without ``wait_until`` cannot be waited
    on, so the lock is off."""
    from timedexec.execution import SendPhase

    phase = SendPhase(PERIOD_S)
    assert phase.offset_s == pytest.approx(0.0006)
    assert phase.target_s(10.0) == pytest.approx(10.0006)
    with pytest.raises(ConfigError, match=r"round_trip_s=0.003 outside \[0, 0.002\)"):
        SendPhase(PERIOD_S, 0.003)
    locked = ExecutorSettings(cycle_lock=True)
    with TimedExecutor(sim(), MODEL, locked) as ex:
        assert ex.send_phase is not None
    with TimedExecutor(PlainDriver(sim()), MODEL, locked) as ex:
        assert ex.send_phase is None
    drv = sim()
    with pytest.raises(ConfigError, match=r"round_trip_s=0.003 outside \[0, 0.002\)"):
        TimedExecutor(drv, MODEL, locked.replace(round_trip_s=0.003)).connect()
    assert drv._sim is None  # closed again
