"""How a calibration sweep runs, live or simulated: the trial motion and the sweep protocol.

:class:`SweepProtocol` is everything the live runner needs and a recording states (the
controller period, the trial motion, the gyro's constants, the pauses);
:meth:`SweepProtocol.for_robot` gives a robot's defaults from its spec alone, so a live run
never needs the simulator (the simulator holds one in its settings, ``SimSettings.protocol``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from timedexec._validation import DictMixin, check_non_negative, check_positive
from timedexec.errors import ConfigError
from timedexec.recording._gyro import GyroHeader
from timedexec.robots import RobotSpec, get_robot

__all__ = ["SweepProtocol", "TrialProfile"]


@dataclass(frozen=True, kw_only=True)
class TrialProfile(DictMixin):
    """The calibration motion of one trial and the recording window.

    One joint moves out and back: accelerate at ``acceleration_rad_s2`` to ``speed_rad_s``,
    hold for ``hold_s``, decelerate to rest, pause ``pause_s``, then the mirror image back to
    the start pose. Trial time 0 is the arrival of the state package that triggers the
    command; the recording covers ``[-pre_s, record_s)``.
    """

    speed_rad_s: float = 0.4
    acceleration_rad_s2: float = 8.0
    hold_s: float = 0.05
    pause_s: float = 0.15
    pre_s: float = 0.05
    record_s: float = 0.65

    def __post_init__(self) -> None:
        check_positive(
            "profile",
            speed_rad_s=self.speed_rad_s,
            acceleration_rad_s2=self.acceleration_rad_s2,
            record_s=self.record_s,
        )
        check_non_negative("profile", hold_s=self.hold_s, pause_s=self.pause_s, pre_s=self.pre_s)
        if self.pause_s + self.pulse_s < self.pulse_s + 0.14:
            raise ConfigError(
                f"profile: pause_s={self.pause_s} s must be >= 0.14 s so the out pulse can be "
                "aligned without the return pulse (delays up to 0.12 s)"
            )

    @property
    def pulse_s(self) -> float:
        """Duration of one pulse (out or back), s."""
        return 2.0 * self.speed_rad_s / self.acceleration_rad_s2 + self.hold_s

    @property
    def duration_s(self) -> float:
        """Commanded motion duration, out and back, s."""
        return 2.0 * self.pulse_s + self.pause_s

    @property
    def template(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~timedexec.sim.pulse_profile` for this motion."""
        return {
            "speed_rad_s": self.speed_rad_s,
            "acceleration_rad_s2": self.acceleration_rad_s2,
            "hold_s": self.hold_s,
            "pause_s": self.pause_s,
        }

    @property
    def displacement_rad(self) -> float:
        """Joint travel of the out pulse, rad."""
        return self.speed_rad_s * (self.speed_rad_s / self.acceleration_rad_s2 + self.hold_s)


@dataclass(frozen=True, kw_only=True)
class SweepProtocol(DictMixin):
    """How a calibration sweep runs on any robot, live or simulated.

    What the live runner needs and a recording states: the controller period, the trial
    motion, the gyro's constants and the pauses. :meth:`for_robot` gives a robot's
    defaults from its spec; a live run replaces the gyro's constants with measured ones;
    the simulator's settings hold one (``SimSettings.protocol``).

    Parameters
    ----------
    robot : str
        Robot name (``ur10``, ``ur10e``, ``kr5``).
    controller_period_s : float
        Controller cycle, s: one the robot's controller offers (``RobotSpec.period_options_s``).
    profile : TrialProfile
        The calibration motion and the recording window.
    gyro : GyroHeader
        The sensor's constants (filter group delay and transport latency included).
    still_s : float
        Stationary gyro recording before the sweep (filter design, zero-rate), s.
    config_move_s : float
        Time allowed to move to a new configuration, s.
    trial_gap_s : float
        Stillness required between trials, s.
    """

    robot: str
    controller_period_s: float
    profile: TrialProfile = field(default_factory=lambda: TrialProfile())
    gyro: GyroHeader = field(default_factory=lambda: GyroHeader())
    still_s: float = 10.0
    config_move_s: float = 3.0
    trial_gap_s: float = 0.3

    def __post_init__(self) -> None:
        check_positive("protocol", controller_period_s=self.controller_period_s)
        check_non_negative(
            "protocol",
            still_s=self.still_s,
            config_move_s=self.config_move_s,
            trial_gap_s=self.trial_gap_s,
        )
        spec = self.spec  # an unknown robot or a period its controller lacks: ConfigError
        slowest = min(spec.qd_max_rad_s)
        if self.profile.speed_rad_s > slowest:
            joint = spec.qd_max_rad_s.index(slowest) + 1
            raise ConfigError(
                f"protocol: profile speed_rad_s={self.profile.speed_rad_s} exceeds the "
                f"{spec.name}'s speed limit of joint {joint} ({slowest} rad/s); use at most "
                f"{slowest} rad/s (the published sweeps used 0.4)"
            )

    @classmethod
    def for_robot(
        cls, robot: str | RobotSpec, *, period_s: float | None = None, **changes: Any
    ) -> SweepProtocol:
        """The default protocol of a robot, from its spec alone (no simulator).

        Parameters
        ----------
        robot : str or RobotSpec
            ``"ur10"``, ``"ur10e"``, ``"kr5"`` (or its spec: its controller period is used).
        period_s : float, optional
            Controller period, s, one the controller offers (the KR 5 also runs RSI at
            0.004 s); default: the spec's.
        **changes
            Fields to set instead of the defaults (``gyro=GyroHeader.from_json(...)``,
            ``still_s=2.0`` ...).

        Raises
        ------
        ConfigError
            An unknown robot, a period its controller does not offer, or a field out of range.
        """
        spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
        if period_s is not None:
            spec = spec.with_period(period_s)
        return cls(robot=spec.name, controller_period_s=spec.controller_period_s, **changes)

    @property
    def spec(self) -> RobotSpec:
        """The robot spec with this protocol's controller period."""
        return get_robot(self.robot, period_s=self.controller_period_s)
