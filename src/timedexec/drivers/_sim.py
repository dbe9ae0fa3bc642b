"""In-process simulated robot driver (``sim://ROBOT``), in virtual or real time.

The driver steps a :class:`~timedexec.sim.ControllerSim` one controller cycle at a time and
hands out its state packages at their host arrival times (send time plus network latency);
commands reach the controller after the host-to-controller latency. In **virtual time** the
host clock is the simulated one (:meth:`SimDriver.clock`), so a calibration runs as fast as
the CPU allows; in **real time** the driver sleeps until each package's arrival.

:meth:`SimDriver.gyro` gives the matching virtual gyro on the flange: samples on the
sensor's own (off-nominal) clock, the sensor's filter delay, noise, bias and scale error,
16-bit counts with a wrapping counter, delivered in USB-like blocks with latency — the same
:class:`~timedexec.sensors.GyroSamples` a real :class:`~timedexec.sensors.GyroReader` gives.

The driver emulates a UR-style controller watchdog (:meth:`SimDriver.arm_watchdog`): once
armed, a controller cycle that finds no command or kick arrived within the timeout stops
the "program" (a ``stopj`` at :data:`WATCHDOG_STOP_DECELERATION_RAD_S2`, capped by the
robot's smallest acceleration limit) and every later command raises
:class:`~timedexec.errors.DriverError` until it is re-armed.
"""

from __future__ import annotations

import heapq
import math
import time
from collections import deque

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.drivers._base import RobotDriver, RobotState
from timedexec.effects import EffectSet
from timedexec.errors import ConfigError, DriverError, DriverTimeout
from timedexec.sensors import GyroSamples
from timedexec.sim import (
    WARM_START_S,
    ControllerSim,
    SimSettings,
    SpeedJ,
    SpeedStop,
    StopJ,
    default_settings,
)

__all__ = ["WATCHDOG_STOP_DECELERATION_RAD_S2", "SimDriver", "VirtualGyro"]

#: Deceleration of the emulated program stop after a watchdog trip, rad/s² (the UR twin's).
WATCHDOG_STOP_DECELERATION_RAD_S2 = 4.0


#: Physics rate of a real-time SimDriver, Hz: 2.3x cheaper than 8 kHz (UR10: 3.2 vs 7.5 ms
#: per 8 ms cycle on the development VM); a speed step's onset moves by 0.4 ms (2 kHz vs
#: 8 kHz), which a real-time simulated robot (pre-flight, executor smoke tests) can spare:
#: timing claims are made on the virtual-time simulator at 8 kHz.
REALTIME_PHYSICS_RATE_HZ = 2000.0


class SimDriver(RobotDriver):
    """The embedded simulated robot behind the :class:`RobotDriver` interface.

    Parameters
    ----------
    robot : str
        A name in :data:`~timedexec.robots.ROBOT_NAMES`.
    virtual : bool
        Virtual time (default) or real time.
    warm : bool
        Start warm: the robot was powered on :data:`~timedexec.sim.WARM_START_S` before
        the driver's clock starts (a robot taken out of production); default cold, powered
        on at the clock's zero. :attr:`power_on_s` says when.
    effects, settings, seed, q0_rad, physics_rate_hz
        Passed to :class:`~timedexec.sim.ControllerSim` (``physics_rate_hz``: physics
        integration rate, Hz). Default: the gyro's 8 kHz in virtual time; in real time
        :data:`REALTIME_PHYSICS_RATE_HZ`, because real time computes each cycle when its
        package is due and at 8 kHz a cycle costs about its own period on a slow 2-core VM
        (UR10: 7.5 ms per 8 ms cycle), so the robot fell seconds behind the host clock and
        a calibration's move to the start pose diverged on stale states.
    """

    def __init__(
        self,
        robot: str = "ur10",
        *,
        virtual: bool = True,
        warm: bool = False,
        effects: EffectSet | None = None,
        settings: SimSettings | None = None,
        seed: int = 0,
        q0_rad: ArrayLike | None = None,
        physics_rate_hz: float | None = None,
    ) -> None:
        self.settings = settings or default_settings(robot)
        if physics_rate_hz is None and not virtual:
            physics_rate_hz = REALTIME_PHYSICS_RATE_HZ
        self._physics_rate_hz = physics_rate_hz
        self.warm = bool(warm)
        self.robot = self.settings.protocol.robot
        self.virtual = virtual
        self._effects = effects
        self._seed = seed
        self._q0 = q0_rad
        self._sim: ControllerSim | None = None
        self._rng = np.random.default_rng([seed, 7])
        self._queue: list[tuple[float, int, RobotState, float]] = []
        self._sequence = 0
        self._now = 0.0  # virtual host clock, s (host time == controller time + offset)
        self._wall0 = 0.0
        self._last_send_s = -math.inf
        self._gyro: VirtualGyro | None = None
        # (host arrival, sampling instant) of every package handed out: ground truth.
        self._delivered: deque[tuple[float, float]] = deque(maxlen=100_000)
        # The emulated watchdog: timeout (s; None: not armed), controller time of the last
        # command or kick that reached the controller, and whether it stopped the program.
        self._wd_timeout_s: float | None = None
        self._wd_fed_s = -math.inf
        self._wd_tripped = False
        self.watchdog_trips: list[float] = []

    # ------------------------------------------------------------------ interface
    @property
    def controller_period_s(self) -> float:
        return self.settings.protocol.controller_period_s

    @property
    def controller(self) -> ControllerSim:
        """The simulated controller (ground truth lives in ``controller.truth``)."""
        if self._sim is None:
            raise DriverError("sim driver is not connected; use it as a context manager")
        return self._sim

    def connect(self) -> None:
        if self._sim is None:
            self._sim = ControllerSim(
                self.robot,
                effects=self._effects,
                settings=self.settings,
                seed=self._seed,
                q0_rad=self._q0,
                physics_rate_hz=self._physics_rate_hz,
                power_on_s=-WARM_START_S if self.warm else 0.0,
            )
            self._wall0 = time.monotonic()

    def close(self) -> None:
        self._sim = None
        self._queue.clear()
        self._wd_timeout_s = None
        self._wd_tripped = False

    @property
    def power_on_s(self) -> float:
        """Host time of the robot's power-on, s: what the calibration runner records so
        that a recording (and a model trained on it) says which thermal state it saw."""
        power_on = -WARM_START_S if self.warm else 0.0
        return self._host_from_controller(power_on)

    def clock(self) -> float:
        """Host clock, s: virtual time, or ``time.monotonic()`` in real time."""
        return self._now if self.virtual else time.monotonic()

    def wait_until(self, host_time_s: float) -> None:
        """Let the host clock run to ``host_time_s`` without reading (a host busy
        elsewhere): virtual time jumps there, real time sleeps."""
        if self.virtual:
            self._now = max(self._now, float(host_time_s))
        else:
            time.sleep(max(0.0, host_time_s - time.monotonic()))

    def _host_from_controller(self, t: float) -> float:
        return t if self.virtual else self._wall0 + t

    def _advance(self) -> None:
        """Run one controller cycle and queue its package at its host arrival time."""
        sim = self.controller
        res = sim.cycle()
        self._check_watchdog(sim)
        pkt = res.packet
        timing = self.settings.timing
        latency = timing.to_host_latency_s + self._rng.exponential(timing.to_host_jitter_s or 1e-12)
        arrival = self._host_from_controller(pkt.send_time_s + latency)
        state = RobotState(
            host_time_s=arrival,
            controller_time_s=pkt.sample_time_s,
            q=pkt.q_rad,
            qd=pkt.qd_rad_s,
            sequence=pkt.cycle,
            target_qd=pkt.qd_target_rad_s,
        )
        heapq.heappush(self._queue, (arrival, pkt.cycle, state, pkt.sample_time_s))
        if self._gyro is not None:
            self._gyro._feed(res.substep_time_s, res.flange_rate_rad_s)

    def read_state(self, timeout_s: float = 0.1) -> RobotState:
        """Next package in arrival order (virtual time jumps to its arrival)."""
        sim = self.controller
        # A package is final once the controller has passed its arrival time.
        while not self._queue or self._queue[0][0] > self._host_from_controller(sim.time_s):
            self._advance()
        arrival = self._queue[0][0]
        if self.virtual:
            if arrival - self._now > timeout_s:
                raise DriverTimeout(f"sim://{self.robot}: no state package within {timeout_s} s")
            self._now = max(self._now, arrival)
        else:
            wait = arrival - time.monotonic()
            if wait > timeout_s:
                # The package stays queued (a short read timeout loses nothing).
                if timeout_s > 0:
                    time.sleep(timeout_s)
                raise DriverTimeout(f"sim://{self.robot}: no state package within {timeout_s} s")
            if wait > 0:
                time.sleep(wait)
        arrival, _, state, sampled = heapq.heappop(self._queue)
        self._delivered.append((arrival, self._host_from_controller(sampled)))
        self._sequence += 1
        return RobotState(
            host_time_s=arrival,
            controller_time_s=state.controller_time_s,
            q=state.q,
            qd=state.qd,
            sequence=self._sequence - 1,
            target_qd=state.target_qd,
        )

    def _send(self, command: SpeedJ | SpeedStop) -> float:
        sim = self.controller
        self._refuse_if_tripped(type(command).__name__)
        timing = self.settings.timing
        send = self.clock() + (timing.host_processing_s if self.virtual else 0.0)
        if self.virtual:
            self._now = send
        arrival_ctrl = self._arrival_ctrl(send)
        sim.submit(command, arrival_s=max(arrival_ctrl, sim.time_s))
        self._wd_fed_s = max(self._wd_fed_s, arrival_ctrl)
        self._last_send_s = send
        return send

    def _arrival_ctrl(self, send: float, *, jitter: bool = True) -> float:
        # Kicks and arming draw no jitter: the command stream's random draws stay as they
        # were without a watchdog (seeded runs reproduce).
        timing = self.settings.timing
        latency = timing.to_controller_latency_s
        if jitter:
            latency += self._rng.exponential(timing.to_controller_jitter_s or 1e-12)
        return (send - (0.0 if self.virtual else self._wall0)) + latency

    # ------------------------------------------------------------------ watchdog
    def _check_watchdog(self, sim: ControllerSim) -> None:
        timeout = self._wd_timeout_s
        if timeout is None or self._wd_tripped or sim.time_s - self._wd_fed_s <= timeout:
            return
        self._wd_tripped = True
        self.watchdog_trips.append(sim.time_s)
        decel = min(WATCHDOG_STOP_DECELERATION_RAD_S2, min(self.settings.spec.qdd_max_rad_s2))
        sim.submit(StopJ(float(decel)), arrival_s=sim.time_s)

    def _refuse_if_tripped(self, what: str) -> None:
        if self._wd_tripped:
            timeout = self._wd_timeout_s or math.nan
            raise DriverError(
                f"sim://{self.robot} did not accept {what}: its watchdog stopped the program "
                f"because no command reached it for more than {timeout * 1e3:.0f} ms; the "
                "program stop decelerated the arm. Recover with TimedExecutor.recover() or "
                f"SimDriver.arm_watchdog({timeout:g}), or close() and connect() again"
            )

    def arm_watchdog(self, timeout_s: float) -> float:
        """Emulated controller watchdog (see the module docstring): stop the program when
        no command or kick arrives for ``timeout_s`` (s, >= two controller periods);
        re-arming after a trip restarts the program."""
        sim = self.controller
        period = self.controller_period_s
        if not 2 * period <= timeout_s <= 10.0:
            raise ConfigError(
                f"watchdog timeout_s={timeout_s!r} outside [{2 * period:g}, 10] s (at least two "
                f"controller periods of {period * 1e3:g} ms); e.g. 0.1"
            )
        self._wd_tripped = False
        self._wd_timeout_s = float(timeout_s)
        self._wd_fed_s = max(sim.time_s, self._arrival_ctrl(self.clock(), jitter=False))
        return self._wd_timeout_s

    def kick_watchdog(self) -> None:
        """Feed the emulated watchdog (no-op when not armed)."""
        if self._wd_timeout_s is None:
            return
        self._refuse_if_tripped("kickWatchdog")
        self._wd_fed_s = max(self._wd_fed_s, self._arrival_ctrl(self.clock(), jitter=False))

    def watchdog_tripped(self) -> bool:
        """Whether the emulated watchdog stopped the program."""
        return self._wd_tripped

    def speedj(self, qd_rad_s: FloatArray, acceleration_rad_s2: float, duration_s: float) -> None:
        self._send(
            SpeedJ(tuple(np.asarray(qd_rad_s, dtype=float)), acceleration_rad_s2, duration_s)
        )

    def stop(self, deceleration_rad_s2: float = 10.0) -> None:
        if self._sim is not None:
            self._send(SpeedStop(deceleration_rad_s2))

    @property
    def last_send_s(self) -> float:
        """Host time at which the last command left (virtual: after the processing time)."""
        return self._last_send_s

    # ------------------------------------------------------------------ ground truth
    def true_response_delay_s(self, t_from: float, t_to: float) -> float:
        """Mean age on arrival of the packages delivered in [t_from, t_to] (host time)."""
        ages = [a - s for a, s in self._delivered if t_from <= a <= t_to]
        return float(np.mean(ages)) if ages else math.nan

    def true_onset_s(self, joint: int, after_s: float) -> float:
        """Host time at which ``joint`` (1-based) first started to move after ``after_s``."""
        onsets = [
            self._host_from_controller(float(e.onset_s[joint - 1]))
            for e in self.controller.truth
            if np.isfinite(e.onset_s[joint - 1])
        ]
        later = [t for t in onsets if t >= after_s]
        return min(later) if later else math.nan

    def gyro(self, *, seed: int = 0) -> VirtualGyro:
        """The virtual gyro on this robot's flange (one per driver)."""
        if self._gyro is None:
            self._gyro = VirtualGyro(self, seed=seed)
        return self._gyro


class VirtualGyro:
    """A simulated MPU-6000 fed by a :class:`SimDriver`'s flange rates (virtual time)."""

    def __init__(self, driver: SimDriver, *, seed: int = 0) -> None:
        g = driver.settings.gyro
        self.settings = g
        self._driver = driver
        rng = np.random.default_rng([seed, 8])
        self._rng = rng
        self.period_s = 1.0 / g.true_rate_hz
        self._bias_dps = rng.uniform(-g.bias_dps, g.bias_dps, 3)
        self._scale = 1.0 + rng.uniform(-g.scale_error, g.scale_error, 3)
        self._sigma = g.noise_density_dps_rthz * math.sqrt(g.true_rate_hz / 2.0)
        self._counter0 = int(rng.integers(0, 65536))
        self._next_n = 0
        self._last_arrival = -math.inf
        self._t_hist: deque[FloatArray] = deque(maxlen=64)
        self._r_hist: deque[FloatArray] = deque(maxlen=64)
        self._ready: list[GyroSamples] = []
        if driver.virtual is False:
            raise ConfigError("the virtual gyro needs a virtual-time SimDriver")

    @property
    def group_delay_s(self) -> float:
        """The sensor filter's constant delay, s."""
        return self.settings.group_delay_s

    def _feed(self, t: FloatArray, rate: FloatArray) -> None:
        self._t_hist.append(t)
        self._r_hist.append(rate)
        t_all = np.concatenate(self._t_hist)
        r_all = np.concatenate(self._r_hist)
        g = self.settings
        # Samples whose (delayed) physical instant is inside the history.
        t_last = t_all[-1] + g.group_delay_s
        n_end = math.floor(t_last / self.period_s)
        n_end -= (n_end - self._next_n) % g.block_samples
        if n_end <= self._next_n:
            return
        n = np.arange(self._next_n, n_end)
        t_s = n * self.period_s
        phys = t_s - g.group_delay_s
        rate_now = np.stack(
            [np.interp(phys, t_all, r_all[:, k], left=0.0) for k in range(3)], axis=1
        )
        dps = np.rad2deg(rate_now) * self._scale + self._bias_dps
        counts = (dps + self._rng.standard_normal(dps.shape) * self._sigma) * g.lsb_per_dps
        raw = np.clip(np.rint(counts), -32768, 32767).astype(np.int16)
        blocks = len(n) // g.block_samples
        last = t_s[g.block_samples - 1 :: g.block_samples][:blocks]
        arrival = last + g.usb_latency_s + self._rng.exponential(g.usb_jitter_s or 1e-12, blocks)
        # USB delivers in order, also across feeds.
        arrival = np.maximum.accumulate(np.maximum(arrival, self._last_arrival))
        self._last_arrival = float(arrival[-1])
        arrival = np.repeat(arrival, g.block_samples)
        self._ready.append(
            GyroSamples(
                counter_unwrapped=(self._counter0 + n).astype(np.int64),
                host_time_s=np.asarray(t_s + g.usb_latency_s, dtype=np.float64),
                rate_rad_s=np.deg2rad(dps),
                raw=raw,
                arrival_s=arrival,
            )
        )
        self._next_n = n_end

    def read(self, n: int | None = None, *, timeout_s: float | None = 1.0) -> GyroSamples:
        """Every sample that has arrived by the driver's current host time."""
        now = self._driver.clock()
        parts = self._ready
        if not parts:
            return _empty()
        allp = GyroSamples.concatenate(parts)
        keep = allp.arrival_s <= now
        out = allp.select(keep)
        rest = allp.select(~keep)
        self._ready = [rest] if len(rest) else []
        return out

    def discard(self) -> int:
        """Drop what has arrived; return how many samples."""
        return len(self.read())


def _empty() -> GyroSamples:
    z = np.zeros(0)
    return GyroSamples(
        counter_unwrapped=np.zeros(0, np.int64),
        host_time_s=z,
        rate_rad_s=np.zeros((0, 3)),
        raw=np.zeros((0, 3), np.int16),
        arrival_s=z,
    )
