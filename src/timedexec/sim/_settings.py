"""Settings of the simulated robots: control-box timing, servo physics, gyro, trial motion.

Every number here is a physical or timing parameter with its unit in its name. The
defaults per robot (:func:`default_settings`) are calibrated so that the *emerging* delays
match the published statistics (DESIGN.md §1); ``benchmarks/bench_sim_stats.py`` prints the
comparison. Settings round-trip through :meth:`SimSettings.to_dict` so a recording stores
the settings that produced it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from timedexec._validation import DictMixin, check_joint_tuple, check_non_negative, check_positive
from timedexec.errors import ConfigError
from timedexec.recording import GyroHeader, SweepProtocol, TrialProfile
from timedexec.robots import RobotSpec, get_robot, get_robot_entry, joint_inertia

__all__ = [
    "GyroModel",
    "ServoSettings",
    "SimSettings",
    "TimingSettings",
    "default_settings",
]


@dataclass(frozen=True, kw_only=True)
class TimingSettings(DictMixin):
    """Control-box and network timing.

    Parameters
    ----------
    pipeline_cycles : int
        Cycles between command intake (at a cycle boundary) and the reference reaching the
        drives (trajectory interpolation, script thread, drive bus).
    packing_phase_s : (float, float)
        Range of the delay from sampling the state (at a cycle boundary) to putting the
        package on the wire; drawn once per trial (the publisher's phase drifts slowly
        against the control cycle).
    cycle_jitter_s : float
        Standard deviation of the controller's cycle boundaries, s.
    to_host_latency_s, to_host_jitter_s : float
        Minimum one-way controller-to-host latency and the mean of its exponential excess, s.
    to_controller_latency_s, to_controller_jitter_s : float
        Same for host-to-controller.
    host_processing_s : float
        Host time from receiving the trigger package to sending the command, s.
    """

    pipeline_cycles: int
    packing_phase_s: tuple[float, float]
    cycle_jitter_s: float = 20e-6
    to_host_latency_s: float = 150e-6
    to_host_jitter_s: float = 60e-6
    to_controller_latency_s: float = 150e-6
    to_controller_jitter_s: float = 60e-6
    host_processing_s: float = 100e-6

    def __post_init__(self) -> None:
        if not isinstance(self.pipeline_cycles, int) or self.pipeline_cycles < 0:
            raise ConfigError(
                f"timing: pipeline_cycles={self.pipeline_cycles!r} must be an int >= 0"
            )
        lo, hi = (float(x) for x in self.packing_phase_s)
        if not 0 <= lo <= hi:
            raise ConfigError(f"timing: packing_phase_s=({lo}, {hi}) needs 0 <= low <= high")
        object.__setattr__(self, "packing_phase_s", (lo, hi))
        check_non_negative(
            "timing",
            cycle_jitter_s=self.cycle_jitter_s,
            to_host_latency_s=self.to_host_latency_s,
            to_host_jitter_s=self.to_host_jitter_s,
            to_controller_latency_s=self.to_controller_latency_s,
            to_controller_jitter_s=self.to_controller_jitter_s,
            host_processing_s=self.host_processing_s,
        )


@dataclass(frozen=True, kw_only=True)
class ServoSettings(DictMixin):
    """Per-joint drive physics: velocity loop, current loop, friction, torque limit.

    The velocity loop is a PI controller with gravity feed-forward, tuned for the joint's
    nominal inertia: ``kp = J_nom · 2π · bandwidth_hz``, ``ki = kp · 2π · bandwidth_hz /
    integral_ratio``. The current loop is a first-order lag. Static friction (breakaway)
    exceeds kinetic friction; a stuck joint moves only when the drive torque beyond the
    gravity torque exceeds breakaway.

    Parameters
    ----------
    bandwidth_hz : 6 floats
        Velocity-loop bandwidth per joint, Hz.
    integral_ratio : float
        Ratio of proportional to integral corner frequency (> 0).
    current_time_constant_s : float
        Current (torque) loop time constant, s.
    breakaway_nm : 6 floats
        Warm static friction per joint, N·m (before the effects scale it).
    kinetic_ratio : float
        Kinetic / static friction, in (0, 1].
    viscous_nms : 6 floats
        Viscous friction, N·m·s/rad.
    position_gain_1_s : float
        Position-loop gain for position-mode commands (servoj, movej), 1/s.
    onset_threshold_rad_s : float
        Speed at which the stepped controller's ground truth marks a joint's motion onset,
        rad/s (10 % of the calibration speed). Batch sweeps use
        ``timedexec._signal.ONSET_FRACTION`` of the commanded speed: the actuation delay is
        the onset minus the time the commanded ramp takes to reach the same speed after the
        command is sent — the delay of the rising edge where the speed is clearly non-zero
        (breakaway and the velocity loop's rise both show there).
    inertia_scheduling : float
        Fraction of the pose-dependent inertia change the velocity-loop gains follow (gain
        scheduling on the configuration), in [0, 1]; the rest shows as loop lag.
    """

    bandwidth_hz: tuple[float, ...]
    integral_ratio: float = 4.0
    current_time_constant_s: float = 0.0008
    breakaway_nm: tuple[float, ...]
    kinetic_ratio: float = 0.7
    viscous_nms: tuple[float, ...]
    position_gain_1_s: float = 40.0
    onset_threshold_rad_s: float = 0.04
    inertia_scheduling: float = 0.0

    def __post_init__(self) -> None:
        for name in ("bandwidth_hz", "breakaway_nm", "viscous_nms"):
            object.__setattr__(self, name, check_joint_tuple("servo", name, getattr(self, name)))
        if min(self.bandwidth_hz) <= 0 or min(self.breakaway_nm) < 0 or min(self.viscous_nms) < 0:
            raise ConfigError("servo: bandwidth_hz must be > 0, breakaway_nm and viscous_nms >= 0")
        check_positive(
            "servo",
            integral_ratio=self.integral_ratio,
            current_time_constant_s=self.current_time_constant_s,
            position_gain_1_s=self.position_gain_1_s,
            onset_threshold_rad_s=self.onset_threshold_rad_s,
        )
        if not 0 <= self.inertia_scheduling <= 1:
            raise ConfigError(
                f"servo: inertia_scheduling={self.inertia_scheduling} must lie in [0, 1]"
            )
        if not 0 < self.kinetic_ratio <= 1:
            raise ConfigError(f"servo: kinetic_ratio={self.kinetic_ratio} must lie in (0, 1]")


@dataclass(frozen=True, kw_only=True)
class GyroModel(DictMixin):
    """The MPU-6000 on the flange, as the simulator models it.

    Parameters
    ----------
    nominal_rate_hz : float
        Nominal output rate (8000 with the DLPF off).
    clock_error_ppm : float
        True rate = nominal · (1 + error); the MEMS clock is within about ±1 %.
    noise_density_dps_rthz : float
        Rate noise density, °/s/√Hz.
    full_scale_dps : int
        ±250/500/1000/2000 °/s; sensitivity 32768/full_scale LSB per °/s.
    bias_dps : float
        Zero-rate offsets are drawn per axis uniformly in ±bias_dps at sweep start.
    bias_drift_dps_per_hour : float
        Linear bias drift over the sweep (temperature), °/s per hour, per axis random sign.
    scale_error : float
        Sensitivity error per axis drawn uniformly in ±scale_error (0.03 = ±3 %).
    group_delay_s : float
        Fixed group delay of the sensor's internal filter (DLPF_CFG=0: 0.98 ms).
    block_samples : int
        Samples the host receives together (USB frames).
    usb_latency_s, usb_jitter_s : float
        Minimum latency of a block to the host and the mean of the exponential excess, s.
    """

    nominal_rate_hz: float = 8000.0
    clock_error_ppm: float = 3000.0
    noise_density_dps_rthz: float = 0.005
    full_scale_dps: int = 500
    bias_dps: float = 3.0
    bias_drift_dps_per_hour: float = 0.2
    scale_error: float = 0.03
    group_delay_s: float = 0.00098
    block_samples: int = 8
    usb_latency_s: float = 0.0008
    usb_jitter_s: float = 0.0004

    def __post_init__(self) -> None:
        if self.full_scale_dps not in (250, 500, 1000, 2000):
            raise ConfigError(
                f"gyro: full_scale_dps={self.full_scale_dps!r} is not one of 250, 500, 1000, 2000"
            )
        if abs(self.clock_error_ppm) > 20000:
            raise ConfigError(
                f"gyro: clock_error_ppm={self.clock_error_ppm} outside ±20000 ppm (±2 %)"
            )
        if not isinstance(self.block_samples, int) or self.block_samples < 1:
            raise ConfigError(f"gyro: block_samples={self.block_samples!r} must be an int >= 1")
        check_positive("gyro", nominal_rate_hz=self.nominal_rate_hz)
        check_non_negative(
            "gyro",
            noise_density_dps_rthz=self.noise_density_dps_rthz,
            bias_dps=self.bias_dps,
            bias_drift_dps_per_hour=self.bias_drift_dps_per_hour,
            scale_error=self.scale_error,
            group_delay_s=self.group_delay_s,
            usb_latency_s=self.usb_latency_s,
            usb_jitter_s=self.usb_jitter_s,
        )

    def header(self) -> GyroHeader:
        """What a recording states about this sensor (the ``gyro`` header entry)."""
        return GyroHeader(
            full_scale_dps=self.full_scale_dps,
            nominal_rate_hz=self.nominal_rate_hz,
            block_samples=self.block_samples,
            group_delay_s=self.group_delay_s,
            transport_latency_s=self.usb_latency_s,
        )

    @property
    def true_rate_hz(self) -> float:
        """The sensor's actual sample rate, Hz."""
        return self.nominal_rate_hz * (1.0 + 1e-6 * self.clock_error_ppm)

    @property
    def lsb_per_dps(self) -> float:
        """Sensitivity, LSB per °/s."""
        return 32768.0 / self.full_scale_dps


@dataclass(frozen=True, kw_only=True)
class SimSettings(DictMixin):
    """Everything the simulator needs beyond the robot spec and the effect set.

    Parameters
    ----------
    protocol : SweepProtocol
        The sweep it runs, as a live run would (robot, controller period, trial motion,
        pauses; :meth:`SweepProtocol.for_robot`). Its ``gyro`` entry is what the recording
        states about the sensor: the simulated sensor's own constants, ``gyro.header()``.
    timing : TimingSettings
        The simulated control box's timing.
    servo : ServoSettings
        The simulated drives' physics.
    gyro : GyroModel
        The simulated sensor.
    """

    protocol: SweepProtocol
    timing: TimingSettings
    servo: ServoSettings
    gyro: GyroModel = dataclasses.field(default_factory=GyroModel)

    def __post_init__(self) -> None:
        period = self.protocol.controller_period_s
        hi = self.timing.packing_phase_s[1]
        if hi >= period * 1.0000001 + 1e-12 and hi > 0:
            raise ConfigError(
                f"timing: packing_phase_s upper bound {hi} s must be below the controller period "
                f"{period} s (use response_extra_cycle for whole periods)"
            )
        if self.protocol.gyro != self.gyro.header():
            raise ConfigError(
                f"settings: the protocol states the gyro {self.protocol.gyro} but the simulated "
                f"sensor is {self.gyro.header()}; a simulated recording states its sensor's "
                "constants: change both together (protocol=dataclasses.replace(protocol, "
                "gyro=gyro.header()))"
            )

    @property
    def spec(self) -> RobotSpec:
        """The robot spec with this settings' controller period."""
        return self.protocol.spec

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict in the layout recordings store: the protocol's fields beside the
        simulator's (flat, as before the protocol was a field of its own); the protocol's
        gyro entry is the sensor model's header and is not stored twice."""
        protocol = self.protocol
        return {
            "robot": protocol.robot,
            "controller_period_s": protocol.controller_period_s,
            "timing": self.timing.to_dict(),
            "servo": self.servo.to_dict(),
            "gyro": self.gyro.to_dict(),
            "profile": protocol.profile.to_dict(),
            "still_s": protocol.still_s,
            "config_move_s": protocol.config_move_s,
            "trial_gap_s": protocol.trial_gap_s,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SimSettings:
        """Inverse of :meth:`to_dict` (reads every recording's stored settings)."""
        d = dict(data)
        timing = dict(d.pop("timing"))
        timing["packing_phase_s"] = tuple(timing["packing_phase_s"])
        servo = ServoSettings(**d.pop("servo"))
        gyro = GyroModel(**d.pop("gyro"))
        profile = TrialProfile(**d.pop("profile"))
        return cls(
            protocol=SweepProtocol(profile=profile, gyro=gyro.header(), **d),
            timing=TimingSettings(**timing),
            servo=servo,
            gyro=gyro,
        )

    def replace(self, **changes: Any) -> SimSettings:
        """A copy with fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)


def default_settings(robot: str | RobotSpec, *, period_s: float | None = None) -> SimSettings:
    """The calibrated default settings of a simulated robot.

    Parameters
    ----------
    robot : str or RobotSpec
        A name in :data:`~timedexec.robots.ROBOT_NAMES` (or its spec). The controller's
        timing (pipeline, packing phase, jitter, velocity loop, breakaway) is the robot's
        catalog entry's :class:`~timedexec.robots.ControllerTiming`.
    period_s : float, optional
        Controller period (the KR 5 also runs RSI at 0.004 s).

    Raises
    ------
    ConfigError
        For a robot the catalog does not hold (a spec of another name).
    """
    spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
    if period_s is not None:
        spec = spec.with_period(period_s)
    protocol = SweepProtocol.for_robot(spec)
    period = spec.controller_period_s
    profile = protocol.profile
    controller = get_robot_entry(spec.name).timing  # the catalog's numbers for this controller
    timing = TimingSettings(
        pipeline_cycles=controller.pipeline_cycles_at(period),
        packing_phase_s=controller.packing_phase_at(period),
        cycle_jitter_s=controller.cycle_jitter_s,
    )
    bandwidth = controller.bandwidth_hz
    breakaway_time = controller.breakaway_time_s
    # Warm breakaway torque per joint, N·m: what the nominal velocity loop (kp = J_nom·ω)
    # builds in `breakaway_time` under the calibration ramp. Published friction data of
    # these drives do not exist; this ties the torques to the drives' scale instead.
    j_nom = joint_inertia(spec, np.asarray(spec.home_q_rad, dtype=float))
    kp = j_nom * 2.0 * np.pi * np.asarray(bandwidth)
    breakaway = kp * profile.acceleration_rad_s2 * np.asarray(breakaway_time)
    servo = ServoSettings(
        bandwidth_hz=bandwidth,
        breakaway_nm=tuple(float(round(f, 3)) for f in breakaway),
        viscous_nms=tuple(float(round(0.05 * f, 4)) for f in breakaway),
    )
    return SimSettings(protocol=protocol, timing=timing, servo=servo)
