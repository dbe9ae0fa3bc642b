"""What the catalog holds per robot beyond its :class:`~timedexec.robots.RobotSpec`.

A :class:`RobotEntry` is one robot of the catalog (``timedexec/robots/catalog/<name>.py``):
its spec (kinematics, inertial data, limits, controller periods; what a recording stores)
and, in small groups, everything the other layers need to know about it:

* :class:`ControllerTiming` — the controller's timing as the simulator models it (plain
  data that ``timedexec.sim`` reads: pipeline, packing phase, jitter, velocity loop,
  breakaway);
* :class:`TwinIdentity` — which protocol its controller speaks and what a protocol twin of
  it says about itself;
* :class:`WorkCell` — where its built-in weld cell puts the work (the conveyor task derives
  its default cell from it);
* the conventional joint names, the joint ranges a calibration sweep samples, the default
  simulated effects, the shipped delay model and which of the paper's two robots its
  figures are compared with.

Data only, validated once where it is built; nothing here imports another layer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from timedexec._validation import check_joint_tuple, check_non_negative, check_positive
from timedexec.errors import ConfigError
from timedexec.robots._spec import N_JOINTS, RobotSpec, check_configuration

__all__ = [
    "INTERFACES",
    "PAPER_FAMILIES",
    "ControllerTiming",
    "RobotEntry",
    "TwinIdentity",
    "WorkCell",
]

#: Controller interfaces a robot can speak: Universal Robots' RTDE (with the dashboard and
#: script ports; ``ur_rtde`` client, UR twin) and KUKA's RSI (UDP XML; RSI driver and twin).
INTERFACES: tuple[str, ...] = ("ur_rtde", "kuka_rsi")
#: The paper's two robots, whose published tables (``timedexec.learning.PAPER_TABLES``) a
#: robot's figures are compared with: ``"ur"`` (UR10, CB3) and ``"kuka"`` (KR 5 sixx).
PAPER_FAMILIES: tuple[str, ...] = ("ur", "kuka")


def _pair(owner: str, name: str, value: tuple[float, float], high: float) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{owner}: {name}={value!r} must be two numbers") from None
    if not (0.0 <= lo <= high and 0.0 <= hi <= high):
        raise ConfigError(f"{owner}: {name}=({lo:g}, {hi:g}) must lie in [0, {high:g}]")
    return lo, hi


@dataclass(frozen=True, kw_only=True)
class ControllerTiming:
    """The controller's timing as the simulator models it (``timedexec.sim`` reads it).

    The pipeline is either a number of cycles (``pipeline_cycles``: the same count at every
    period) or a time (``pipeline_s``: a fixed-time stage, so a shorter period holds more
    cycles); exactly one is given. The packing phase (sampling the state at a cycle
    boundary to putting the package on the wire) is drawn per trial from a range given as
    fractions of the period, each bound capped by ``packing_phase_max_s`` where given.

    Parameters
    ----------
    pipeline_cycles : int or None
        Cycles from command intake (at a cycle boundary) to the reference reaching the
        drives.
    pipeline_s : float or None
        The same as a time, s: ``max(1, round(pipeline_s / period))`` cycles.
    packing_phase_periods : (float, float)
        Bounds of the packing phase, fractions of the period (each in [0, 1]).
    packing_phase_max_s : (float, float) or None
        Caps of the two bounds, s (``None``: no cap).
    cycle_jitter_s : float
        Standard deviation of the controller's cycle boundaries, s.
    bandwidth_hz : 6 floats
        Velocity-loop bandwidth per joint, Hz.
    breakaway_time_s : 6 floats
        Time the nominal velocity loop takes under the calibration ramp to build each
        joint's warm breakaway torque, s (the simulator's static friction derives from it).
    state_velocity : bool
        The state stream carries joint speeds (RTDE ``actual_qd``); ``False``: positions
        only (RSI ``AIPos``), the host differentiates.
    """

    pipeline_cycles: int | None = None
    pipeline_s: float | None = None
    packing_phase_periods: tuple[float, float]
    packing_phase_max_s: tuple[float, float] | None = None
    cycle_jitter_s: float
    bandwidth_hz: tuple[float, ...]
    breakaway_time_s: tuple[float, ...]
    state_velocity: bool

    def __post_init__(self) -> None:
        owner = "controller timing"
        if (self.pipeline_cycles is None) == (self.pipeline_s is None):
            raise ConfigError(
                f"{owner}: give exactly one of pipeline_cycles (a count) and pipeline_s "
                f"(a time), got {self.pipeline_cycles!r} and {self.pipeline_s!r}"
            )
        if self.pipeline_cycles is not None and (
            isinstance(self.pipeline_cycles, bool)
            or not isinstance(self.pipeline_cycles, int)
            or self.pipeline_cycles < 0
        ):
            raise ConfigError(
                f"{owner}: pipeline_cycles={self.pipeline_cycles!r} must be an int >= 0"
            )
        if self.pipeline_s is not None:
            check_positive(owner, pipeline_s=self.pipeline_s)
        # Within one period: a whole period more is the response_extra_cycle effect.
        phase = _pair(owner, "packing_phase_periods", self.packing_phase_periods, 1.0)
        object.__setattr__(self, "packing_phase_periods", phase)
        if self.packing_phase_max_s is not None:
            caps = _pair(owner, "packing_phase_max_s", self.packing_phase_max_s, math.inf)
            object.__setattr__(self, "packing_phase_max_s", caps)
        check_non_negative(owner, cycle_jitter_s=self.cycle_jitter_s)
        for name in ("bandwidth_hz", "breakaway_time_s"):
            object.__setattr__(self, name, check_joint_tuple(owner, name, getattr(self, name)))
        if min(self.bandwidth_hz) <= 0.0 or min(self.breakaway_time_s) < 0.0:
            raise ConfigError(f"{owner}: bandwidth_hz must be > 0 and breakaway_time_s >= 0")
        if not isinstance(self.state_velocity, bool):
            raise ConfigError(f"{owner}: state_velocity={self.state_velocity!r} must be a bool")

    def pipeline_cycles_at(self, period_s: float) -> int:
        """Pipeline length in cycles at a controller period of ``period_s`` (s)."""
        if self.pipeline_cycles is not None:
            return self.pipeline_cycles
        assert self.pipeline_s is not None  # one of the two, checked when built
        return max(1, round(self.pipeline_s / period_s))

    def target_echo_cycles(self, period_s: float) -> int:
        """Cycles from the intake that takes a speed command to the first state package
        whose ``target_qd`` shows it, at a period of ``period_s`` (s), in the simulated
        controller and its protocol twins: the pipeline, then the cycle in which the
        reference ramps to the command, sampled at the boundary after it. The intake probe
        counts the packages to that echo, and this depth turns the count into the cycle
        the probe's packages were sampled in (``ExecutorSettings.echo_depth_cycles``).
        Not a fact about a real controller: the independent UR peer shows its targets
        five cycles sooner."""
        return self.pipeline_cycles_at(period_s) + 1

    def packing_phase_at(self, period_s: float) -> tuple[float, float]:
        """Range of the packing phase at a controller period of ``period_s``, s."""
        lo, hi = (f * period_s for f in self.packing_phase_periods)
        if self.packing_phase_max_s is None:
            return lo, hi
        return min(self.packing_phase_max_s[0], lo), min(self.packing_phase_max_s[1], hi)


@dataclass(frozen=True, kw_only=True)
class TwinIdentity:
    """The interface a robot's controller speaks and what a protocol twin of it reports.

    Parameters
    ----------
    interface : str
        One of :data:`INTERFACES`: ``"ur_rtde"`` or ``"kuka_rsi"``; the twin, the driver
        and the welding task's live run are chosen by it.
    controller : str
        The controller generation, for people (``"CB3"``, ``"e-Series"``, ``"KR C4"``).
    model_name : str
        UR: the dashboard server's answer to ``get robot model`` (``"UR10"`` on a UR10e as
        well: PolyScope 5 says the series through its version). RSI frames carry no
        identity: empty.
    controller_version : tuple of int
        UR: the software version the twin reports, (major, minor, bugfix, build); the
        client picks its RTDE rate from the major (3: CB3, 125 Hz; 5: e-Series, 500 Hz).
        Empty for RSI.
    serial_number : str
        UR: the dashboard's ``get serial number``; empty for RSI.
    """

    interface: str
    controller: str
    model_name: str = ""
    controller_version: tuple[int, ...] = ()
    serial_number: str = ""

    def __post_init__(self) -> None:
        if self.interface not in INTERFACES:
            raise ConfigError(
                f"twin identity: interface={self.interface!r} is not one of {', '.join(INTERFACES)}"
            )
        version = tuple(self.controller_version)
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in version):
            raise ConfigError(
                f"twin identity: controller_version={self.controller_version!r} must be "
                "non-negative ints"
            )
        object.__setattr__(self, "controller_version", version)
        if self.interface == "ur_rtde" and (
            len(version) != 4 or not self.model_name or not self.serial_number
        ):
            raise ConfigError(
                "twin identity: a UR (ur_rtde) twin needs model_name, serial_number and a "
                f"controller_version (major, minor, bugfix, build); got {self.model_name!r}, "
                f"{self.serial_number!r}, {version!r}"
            )


@dataclass(frozen=True, kw_only=True)
class WorkCell:
    """Where the robot's built-in weld cell puts the work.

    The belt runs along base y, across the front of the robot; the torch points down (tilted
    by the conveyor task's standard angle) at ``work_point_m``, the middle of the weld.

    Parameters
    ----------
    seed_q_rad : 6 floats
        A torch-down pose near the work point, rad (the inverse kinematics starts there and
        so picks the arm's branch).
    work_point_m : 3 floats
        The torch tip at the middle of the weld, base frame, m.
    """

    seed_q_rad: tuple[float, ...]
    work_point_m: tuple[float, float, float]

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "seed_q_rad", check_joint_tuple("work cell", "seed_q_rad", self.seed_q_rad)
        )
        point = tuple(float(x) for x in self.work_point_m)
        if len(point) != 3 or not all(math.isfinite(x) for x in point):
            raise ConfigError(
                f"work cell: work_point_m={self.work_point_m!r} must be 3 finite numbers (m)"
            )
        object.__setattr__(self, "work_point_m", point)


@dataclass(frozen=True, kw_only=True)
class RobotEntry:
    """One robot of the catalog: its spec and everything else about it, validated together.

    Parameters
    ----------
    spec : RobotSpec
        Kinematics, inertial data, limits and controller periods (what a recording stores).
    joint_names : 6 str
        The conventional joint names (ROS: UR ``shoulder_pan_joint`` ..., KUKA
        ``joint_a1`` ...), joint 1 first.
    timing : ControllerTiming
        The controller's timing as the simulator models it.
    twin : TwinIdentity
        Its controller interface and what a protocol twin of it reports.
    cell : WorkCell
        The built-in weld cell's geometry.
    sweep_q_min_rad, sweep_q_max_rad : 6 floats
        The joint ranges a calibration sweep samples from (before the trial motion's
        margin), rad: inside the joint limits and keeping the arm above its base plane.
    rated_payload_kg : float
        The data sheet's rated payload, kg (the spec's ``payload_kg`` is 0 by default; the
        peak torques must hold the arm with this much at the flange).
    default_effects : tuple of str
        Names of the effects the simulated robot has by default
        (``timedexec.effects.EFFECT_NAMES``; checked there).
    shipped_model : str
        Name of the delay model shipped for it in ``models/`` (``DelayModel.load(name)``).
    paper_family : str
        One of :data:`PAPER_FAMILIES`: whose published tables its figures sit beside.
    """

    spec: RobotSpec
    joint_names: tuple[str, ...]
    timing: ControllerTiming
    twin: TwinIdentity
    cell: WorkCell
    sweep_q_min_rad: tuple[float, ...]
    sweep_q_max_rad: tuple[float, ...]
    rated_payload_kg: float
    default_effects: tuple[str, ...]
    shipped_model: str
    paper_family: str

    def __post_init__(self) -> None:
        if not isinstance(self.spec, RobotSpec):
            raise ConfigError(
                f"robot entry: spec must be a RobotSpec, got {type(self.spec).__name__}"
            )
        who = f"robot {self.name!r}"
        names = tuple(self.joint_names)
        if (
            len(names) != N_JOINTS
            or len(set(names)) != N_JOINTS
            or not all(isinstance(n, str) and n for n in names)
        ):
            raise ConfigError(
                f"{who}: joint_names must be {N_JOINTS} distinct names, got {names!r}"
            )
        object.__setattr__(self, "joint_names", names)
        for name, kind in (
            ("timing", ControllerTiming),
            ("twin", TwinIdentity),
            ("cell", WorkCell),
        ):
            if not isinstance(getattr(self, name), kind):
                raise ConfigError(f"{who}: {name} must be a {kind.__name__}")
        lo = check_joint_tuple(who, "sweep_q_min_rad", self.sweep_q_min_rad)
        hi = check_joint_tuple(who, "sweep_q_max_rad", self.sweep_q_max_rad)
        object.__setattr__(self, "sweep_q_min_rad", lo)
        object.__setattr__(self, "sweep_q_max_rad", hi)
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ConfigError(f"{who}: sweep_q_min_rad must lie below sweep_q_max_rad per joint")
        for period in self.spec.period_options_s:
            lo_s, hi_s = self.timing.packing_phase_at(period)
            if lo_s > hi_s:
                raise ConfigError(
                    f"{who}: at a period of {period:g} s the packing phase would run from "
                    f"{lo_s:g} s to {hi_s:g} s; its low bound must not exceed the high one"
                )
        check_positive(who, rated_payload_kg=self.rated_payload_kg)
        try:
            check_configuration(self.spec, self.cell.seed_q_rad)
        except ConfigError as exc:
            raise ConfigError(
                f"{who}: the work cell's seed_q_rad is outside the joint limits: {exc}"
            ) from None
        effects = tuple(self.default_effects)
        if not all(isinstance(e, str) and e for e in effects):
            raise ConfigError(f"{who}: default_effects must be effect names, got {effects!r}")
        object.__setattr__(self, "default_effects", effects)
        if not isinstance(self.shipped_model, str) or not self.shipped_model:
            raise ConfigError(f"{who}: shipped_model must name a bundle in models/")
        if self.paper_family not in PAPER_FAMILIES:
            raise ConfigError(
                f"{who}: paper_family={self.paper_family!r} is not one of "
                f"{', '.join(PAPER_FAMILIES)}"
            )

    @property
    def name(self) -> str:
        """The robot's name (its spec's)."""
        return self.spec.name
