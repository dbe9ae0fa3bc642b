"""A stepped simulated robot controller, one call per controller cycle.

The protocol twins (UR RTDE, KUKA RSI) drive the same joint physics as the batch sweep
through this class: commands arrive at a controller time, are taken at the next cycle
boundary (like a register sampled once per cycle: of two commands within one cycle only the
last is seen), act after the controller's pipeline (each joint's drive takes the reference its offset
later), and the
state sampled at each boundary is put on the wire after the packing phase (plus whole
periods with ``response_extra_cycle``). Ground truth is kept per command.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._types import FloatArray
from timedexec._validation import check_joint_array
from timedexec.effects import EffectSet, Pose, default_effects
from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec, check_configuration, get_robot, joint_axis_in_tool
from timedexec.sim._physics import JointChain, drive_delay_s, joint_params, response_delay_s
from timedexec.sim._settings import SimSettings, default_settings

__all__ = [
    "ControllerSim",
    "CycleResult",
    "MoveJ",
    "ServoJ",
    "SpeedJ",
    "SpeedStop",
    "StatePacket",
    "StopJ",
    "TruthEvent",
]

_JOINTS = np.arange(1, 7)
#: Period of the slow drift of the state publisher's phase against the control cycle, s.
#: A triangle wave: within one trial (< 1 s) the phase moves by < 0.3 ms, never jumps.
PHASE_DRIFT_PERIOD_S = 47.0


@dataclass(frozen=True)
class SpeedJ:
    """Joint speed command (URScript ``speedj``): rad/s, rad/s² of the leading axis, s.

    ``duration_s`` > 0: decelerate to rest if no new command arrives within it; 0: hold.
    """

    qd_rad_s: tuple[float, ...]
    acceleration_rad_s2: float
    duration_s: float = 0.0


@dataclass(frozen=True)
class SpeedStop:
    """Decelerate all joints to rest (rad/s²)."""

    deceleration_rad_s2: float = 10.0


@dataclass(frozen=True)
class StopJ:
    """Decelerate all joints to rest (rad/s²), URScript ``stopj``."""

    deceleration_rad_s2: float = 10.0


@dataclass(frozen=True)
class ServoJ:
    """Position setpoint reached linearly over ``time_s`` (URScript ``servoj``)."""

    q_rad: tuple[float, ...]
    time_s: float = 0.008
    lookahead_s: float = 0.1
    gain: float = 300.0


@dataclass(frozen=True)
class MoveJ:
    """Synchronised trapezoidal joint move to ``q_rad`` (URScript ``movej``)."""

    q_rad: tuple[float, ...]
    speed_rad_s: float = 1.05
    acceleration_rad_s2: float = 1.4


Command = SpeedJ | SpeedStop | StopJ | ServoJ | MoveJ


@dataclass(frozen=True)
class StatePacket:
    """The state sampled at a cycle boundary and when it goes on the wire (controller time)."""

    cycle: int
    sample_time_s: float
    send_time_s: float
    q_rad: FloatArray
    qd_rad_s: FloatArray
    q_target_rad: FloatArray
    qd_target_rad_s: FloatArray
    moving: bool


@dataclass(frozen=True)
class CycleResult:
    """One controller cycle: the packet to publish and the flange rate at the substeps."""

    packet: StatePacket
    substep_time_s: FloatArray
    flange_rate_rad_s: FloatArray


@dataclass(eq=False)
class TruthEvent:
    """Ground truth of one command (controller times, s); compared by identity."""

    id: int
    kind: str
    arrival_s: float
    intake_s: float = math.nan
    reference_start_s: float = math.nan
    onset_s: FloatArray = field(default_factory=lambda: np.full(6, np.nan))
    armed: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(6, dtype=bool))
    superseded: bool = False

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (NaN becomes None)."""

        def clean(x: float) -> float | None:
            return None if math.isnan(x) else float(x)

        return {
            "id": self.id,
            "kind": self.kind,
            "arrival_s": clean(self.arrival_s),
            "intake_s": clean(self.intake_s),
            "reference_start_s": clean(self.reference_start_s),
            "onset_s": [clean(float(x)) for x in self.onset_s],
            "moved_joints": [int(j) for j in _JOINTS[self.armed]],
            "superseded": self.superseded,
        }


@dataclass
class _Active:
    """The reference generator state of one joint set (after the pipeline)."""

    mode: str = "speed"  # "speed" | "traj"
    target_v: FloatArray = field(default_factory=lambda: np.zeros(6))
    accel: FloatArray = field(default_factory=lambda: np.full(6, 10.0))
    deadline_s: float = math.inf
    traj_start_s: float = 0.0
    traj_q0: FloatArray = field(default_factory=lambda: np.zeros(6))
    traj_dq: FloatArray = field(default_factory=lambda: np.zeros(6))
    traj_time: tuple[float, float, float] = (0.0, 0.0, 0.0)  # accel time, cruise time, peak speed
    traj_linear_s: float = 0.0  # servoj: reach the target linearly over this time
    traj_dist: float = 0.0  # movej: distance of the leading joint, rad


class ControllerSim:
    """Simulated controller stepped one cycle at a time (see the module docstring).

    Parameters
    ----------
    robot : str or RobotSpec
        A name in :data:`~timedexec.robots.ROBOT_NAMES` (or its spec).
    effects : EffectSet, optional
        Defaults to the robot's default effect set.
    q0_rad : array (6,), optional
        Start configuration (default: the spec's home pose).
    seed : int
        Seeds the publisher phase.
    period_s : float, optional
        Controller period (KR 5: 0.012 or 0.004).
    settings : SimSettings, optional
        Defaults to :func:`default_settings`.
    physics_rate_hz : float, optional
        Integration rate; defaults to the gyro's nominal rate (8 kHz). Real-time twins may
        use 4 kHz to halve the CPU cost (the gyro twin interpolates to its own clock).
    power_on_s : float
        Controller time of the robot's power-on, s (<= 0): the thermal state
        (``thermal_drift``) runs on ``time_s - power_on_s``. 0: cold at time 0;
        ``-WARM_START_S``: warm.
    """

    #: Pose change (rad, any joint) after which gravity/inertia parameters are refreshed.
    REFRESH_RAD = 0.005

    def __init__(
        self,
        robot: str | RobotSpec,
        *,
        effects: EffectSet | None = None,
        q0_rad: ArrayLike | None = None,
        seed: int = 0,
        period_s: float | None = None,
        settings: SimSettings | None = None,
        physics_rate_hz: float | None = None,
        power_on_s: float = 0.0,
    ) -> None:
        spec = robot if isinstance(robot, RobotSpec) else get_robot(robot, period_s=period_s)
        if not (math.isfinite(power_on_s) and power_on_s <= 0.0):
            raise ConfigError(
                f"power_on_s={power_on_s!r} must be finite and <= 0 s (the controller time of "
                "power-on: 0 cold, -WARM_START_S warm)"
            )
        self.power_on_s = float(power_on_s)
        self.settings = settings or default_settings(spec, period_s=period_s)
        self.spec = self.settings.spec
        self.effects = effects if effects is not None else default_effects(self.spec.name)
        self.period_s = self.settings.protocol.controller_period_s
        rate = physics_rate_hz or self.settings.gyro.nominal_rate_hz
        if not rate > 0:
            raise ConfigError(f"physics_rate_hz={physics_rate_hz!r} must be > 0")
        self.n_sub = max(1, round(self.period_s * rate))
        self.dt_s = self.period_s / self.n_sub
        q0 = np.asarray(self.spec.home_q_rad if q0_rad is None else q0_rad, dtype=float)
        q0 = check_configuration(self.spec, q0)
        self.time_s = 0.0
        self.cycle_index = 0
        rng = np.random.default_rng(seed)
        self._phase0 = float(rng.uniform())
        self._extra_s = response_delay_s(self.effects, self.period_s)
        # Each drive's dead time, asked of the effects once per joint at the start pose.
        start = Pose(
            spec=self.spec,
            q_start_rad=np.broadcast_to(q0, (6, 6)),
            joint=_JOINTS,
            t_start_s=np.full(6, -self.power_on_s),
        )
        self._offset_s = np.zeros(6) + drive_delay_s(self.effects, start)
        self._bank = JointChain(
            self._params(q0), q0, self.dt_s, self.settings.servo.onset_threshold_rad_s
        )
        # Each joint's drive takes the interpolator's reference ``offsets_s[j]`` later (the
        # effect's meaning): one reference for the arm, computed once (so speedj's lead axis
        # sees every joint's undelayed reference), and per joint a delay line of whole
        # substeps (q, v, position mode) between it and the drive.
        self._delay_n = [math.ceil(o / self.dt_s - 1e-9) for o in self._offset_s.tolist()]
        self._lines = [
            deque([(float(q), 0.0, False)] * n)
            for q, n in zip(q0.tolist(), self._delay_n, strict=True)
        ]
        self._lines_busy_until_s = 0.0  # a non-zero reference is in some delay line until then
        self._params_q = q0.copy()
        self._params_time_s = 0.0
        self._axes = joint_axis_in_tool(self.spec, np.broadcast_to(q0, (6, 6)), _JOINTS)
        self._ref_q = q0.copy()
        self._ref_v = np.zeros(6)
        # Per joint: the active reference program; pending activations per joint.
        self._active = [_Active() for _ in range(6)]
        for a in self._active:
            a.traj_q0 = q0.copy()
        # Commands that reached the controller, in arrival order, not yet taken at a boundary.
        self._pending: list[tuple[float, Command, int]] = []
        self._pipeline: deque[tuple[int, Command, int]] = deque()
        self._activations: list[tuple[FloatArray, Command, int, NDArray[np.bool_]]] = []
        self._next_activation_s = math.inf  # earliest start among the joints left to activate
        self._next_id = 1
        self.truth: list[TruthEvent] = []
        self._truth_by_id: dict[int, TruthEvent] = {}
        # Commands waiting for each joint's next onset, per joint: the onset goes to every
        # command that armed the joint before it (as the bank has one onset slot per joint).
        # Checked per joint, not per command: a servoJ stream from rest arms every cycle,
        # and a list scanned per command grew the cycle cost 7x after 1,500 commands.
        self._waiting: list[list[TruthEvent]] = [[] for _ in range(6)]

    # ------------------------------------------------------------------ state
    @property
    def q_rad(self) -> FloatArray:
        """Physical joint positions now, rad."""
        return self._bank.q.copy()

    @property
    def qd_rad_s(self) -> FloatArray:
        """Physical joint speeds now, rad/s."""
        return self._bank.v.copy()

    def is_steady(self) -> bool:
        """True when every joint is at rest and no command is pending or ramping."""
        return bool(
            np.all(self._bank.stuck)
            and not self._pipeline
            and not self._activations
            and not self._pending
            and np.all(np.abs(self._ref_v) < 1e-9)
            and self.time_s >= self._lines_busy_until_s
        )

    def packing_phase_s(self, t_s: float) -> float:
        """Delay from sampling to sending at controller time ``t_s`` (drifts slowly), s."""
        lo, hi = self.settings.timing.packing_phase_s
        frac = (t_s / PHASE_DRIFT_PERIOD_S + self._phase0) % 1.0
        return lo + (hi - lo) * (1.0 - abs(2.0 * frac - 1.0))

    def set_joint_offsets(self, offsets_s: ArrayLike) -> None:
        """Change each drive's offset (``joint_offset``) from now on, s (each in [0, 0.05]):
        a drive that changes in service (firmware, filter, wear), for drift studies. A longer
        delay holds the drive's oldest setpoint for the added substeps; a shorter one drops
        the oldest."""
        from timedexec.effects import JointOffset

        offsets = np.asarray(JointOffset(offsets_s=tuple(np.asarray(offsets_s, float))).offsets_s)
        for j, o in enumerate(offsets.tolist()):
            n = math.ceil(o / self.dt_s - 1e-9)
            line = self._lines[j]
            while len(line) > n:
                line.popleft()
            if n > len(line):
                oldest = line[0] if line else (float(self._ref_q[j]), float(self._ref_v[j]), False)
                line.extendleft([oldest] * (n - len(line)))
            self._delay_n[j] = n
        self._offset_s = offsets

    def _params(self, q: FloatArray):  # type: ignore[no-untyped-def]
        rows = np.broadcast_to(q, (6, 6))
        params, _, _ = joint_params(
            self.spec,
            self.settings,
            self.effects,
            rows,
            _JOINTS,
            np.full(6, self.time_s - self.power_on_s),
        )
        return params

    # ------------------------------------------------------------------ commands
    def _validate(self, command: Command) -> Command:
        spec = self.spec
        if isinstance(command, SpeedJ):
            qd = check_joint_array("speedj qd_rad_s", command.qd_rad_s)
            over = np.abs(qd) > np.asarray(spec.qd_max_rad_s) * (1 + 1e-9)
            if over.any():
                j = int(np.flatnonzero(over)[0])
                raise ConfigError(
                    f"speedj: joint {j + 1} speed {qd[j]:.4g} rad/s exceeds the limit "
                    f"±{spec.qd_max_rad_s[j]:.4g} rad/s of {spec.name}; command a lower speed"
                )
            self._check_accel("speedj", command.acceleration_rad_s2)
            if not command.duration_s >= 0:
                raise ConfigError(f"speedj: duration_s={command.duration_s} must be >= 0")
            return SpeedJ(tuple(qd), float(command.acceleration_rad_s2), float(command.duration_s))
        if isinstance(command, SpeedStop | StopJ):
            self._check_accel(type(command).__name__.lower(), command.deceleration_rad_s2)
            return command
        if isinstance(command, ServoJ | MoveJ):
            q = check_configuration(
                spec, check_joint_array(f"{type(command).__name__.lower()} q_rad", command.q_rad)
            )
            if isinstance(command, MoveJ):
                self._check_accel("movej", command.acceleration_rad_s2)
                if not 0 < command.speed_rad_s <= max(spec.qd_max_rad_s):
                    raise ConfigError(
                        f"movej: speed {command.speed_rad_s} rad/s outside (0, "
                        f"{max(spec.qd_max_rad_s):.4g}]"
                    )
                return MoveJ(
                    tuple(q), float(command.speed_rad_s), float(command.acceleration_rad_s2)
                )
            if not command.time_s > 0:
                raise ConfigError(f"servoj: time_s={command.time_s} must be > 0")
            return ServoJ(tuple(q), float(command.time_s), command.lookahead_s, command.gain)
        raise ConfigError(f"unknown command {command!r}")

    def _check_accel(self, what: str, a: float) -> None:
        limit = max(self.spec.qdd_max_rad_s2) * 4.0
        if not 0 < a <= limit:
            raise ConfigError(
                f"{what}: acceleration {a!r} rad/s² outside (0, {limit:.4g}] for {self.spec.name}"
            )

    def submit(self, command: Command, *, arrival_s: float | None = None) -> int:
        """Hand a command to the controller; see the module docstring. Returns its id."""
        cmd = self._validate(command)
        arrival = self.time_s if arrival_s is None else float(arrival_s)
        cid = self._next_id
        self._next_id += 1
        self._pending.append((arrival, cmd, cid))
        self._pending.sort(key=lambda item: item[0])
        event = TruthEvent(id=cid, kind=type(cmd).__name__, arrival_s=arrival)
        self.truth.append(event)
        self._truth_by_id[cid] = event
        if len(self.truth) > 10000:
            for old in self.truth[:5000]:
                self._truth_by_id.pop(old.id, None)
            del self.truth[:5000]
        return cid

    def truth_records(self) -> list[dict[str, Any]]:
        """JSON-safe ground truth of every command so far."""
        return [e.to_dict() for e in self.truth]

    # ------------------------------------------------------------------ reference generation
    def _activate(self, joints: NDArray[np.bool_], cmd: Command, cid: int, t_s: float) -> None:
        event = self._truth_by_id.get(cid)
        was_still = np.abs(self._ref_v) < 1e-9
        for j in np.flatnonzero(joints):
            act = self._active[j]
            if isinstance(cmd, SpeedJ):
                act.mode = "speed"
                act.target_v = np.asarray(cmd.qd_rad_s)
                dv = np.abs(act.target_v - self._ref_v)
                lead = max(float(dv.max()), 1e-12)
                act.accel = np.maximum(cmd.acceleration_rad_s2 * dv / lead, 1e-6)
                act.deadline_s = t_s + cmd.duration_s if cmd.duration_s > 0 else math.inf
            elif isinstance(cmd, SpeedStop | StopJ):
                act.mode = "speed"
                act.target_v = np.zeros(6)
                act.accel = np.full(6, cmd.deceleration_rad_s2)
                act.deadline_s = math.inf
            else:
                act.mode = "traj"
                act.traj_start_s = t_s
                act.traj_q0 = self._ref_q.copy()
                act.traj_dq = np.asarray(cmd.q_rad) - self._ref_q
                if isinstance(cmd, MoveJ):
                    dist = act.traj_dist = float(np.abs(act.traj_dq).max())
                    v, a = cmd.speed_rad_s, cmd.acceleration_rad_s2
                    if dist <= v * v / a:  # triangular profile
                        t_acc = math.sqrt(dist / a) if dist > 0 else 0.0
                        act.traj_time = (t_acc, 0.0, a * t_acc)
                    else:
                        act.traj_time = (v / a, dist / v - v / a, v)
                    act.traj_linear_s = 0.0
                else:
                    act.traj_linear_s = cmd.time_s
            if event is not None:
                target = self._target_speed_hint(cmd, int(j))
                if was_still[j] and target != 0.0:
                    event.armed[j] = True
                    event.onset_s[j] = np.nan
        if event is not None:
            if math.isnan(event.reference_start_s):
                event.reference_start_s = t_s
            mask = np.zeros(6, dtype=bool)
            mask[joints] = event.armed[joints]
            if mask.any():
                self._bank.arm_onset(mask)
                for j in np.flatnonzero(mask):
                    waiting = self._waiting[j]
                    if not waiting or waiting[-1] is not event:
                        waiting.append(event)

    def _target_speed_hint(self, cmd: Command, j: int) -> float:
        if isinstance(cmd, SpeedJ):
            return float(cmd.qd_rad_s[j])
        if isinstance(cmd, ServoJ | MoveJ):
            return float(cmd.q_rad[j] - self._ref_q[j])
        return 0.0

    def _reference(
        self, j: int, t_s: float, q_rad: float, v_rad_s: float
    ) -> tuple[float, float, bool]:
        """Advance joint ``j``'s reference (now ``q_rad``, ``v_rad_s``) by the substep that
        starts at ``t_s``; returns (ref_q, ref_v, position_mode)."""
        dt = self.dt_s
        act = self._active[j]
        if act.mode == "speed":
            target = float(act.target_v[j]) if t_s < act.deadline_s else 0.0
            step = float(act.accel[j]) * dt
            new_v = min(max(target, v_rad_s - step), v_rad_s + step)
            return q_rad + 0.5 * (v_rad_s + new_v) * dt, new_v, False
        tau = t_s + dt - act.traj_start_s
        dq = float(act.traj_dq[j])
        q0 = float(act.traj_q0[j])
        if act.traj_linear_s > 0:
            frac = min(1.0, tau / act.traj_linear_s)
            return q0 + frac * dq, (dq / act.traj_linear_s if frac < 1.0 else 0.0), True
        s, sd = _trapezoid(tau, *act.traj_time)
        scale = dq / act.traj_dist if act.traj_dist > 0 else 0.0
        return q0 + scale * s, scale * sd, True

    # ------------------------------------------------------------------ the cycle
    def peek_packet(self) -> StatePacket:
        """The package the next :meth:`cycle` returns: the state sampled at the current
        boundary and its send time. Twins use it to put a package on the wire before the
        cycle's physics is computed when the packing phase is shorter than that."""
        t = self.time_s
        bank = self._bank
        return StatePacket(
            cycle=self.cycle_index,
            sample_time_s=t,
            send_time_s=t + self.packing_phase_s(t) + self._extra_s,
            q_rad=bank.q,  # fresh arrays (JointChain)
            qd_rad_s=bank.v,
            q_target_rad=self._ref_q.copy(),
            qd_target_rad_s=self._ref_v.copy(),
            moving=bool(np.any(np.abs(self._ref_v) > 1e-9) or not np.all(bank.stuck)),
        )

    def cycle(self) -> CycleResult:
        """Advance one controller period; see :class:`CycleResult`."""
        period, k = self.period_s, self.cycle_index
        t_boundary = self.time_s
        bank = self._bank
        packet = self.peek_packet()
        # Intake: the register as it stands at this boundary.
        # Like a register sampled once per cycle: of the commands that arrived by this
        # boundary only the last is seen; later arrivals wait for their own boundary.
        due = [p for p in self._pending if p[0] <= t_boundary + 1e-12]
        if due:
            self._pending = self._pending[len(due) :]
            for _, _, old_id in due[:-1]:
                self._truth_by_id[old_id].superseded = True
            _, cmd, cid = due[-1]
            self._truth_by_id[cid].intake_s = t_boundary
            self._pipeline.append((k + self.settings.timing.pipeline_cycles, cmd, cid))
        while self._pipeline and self._pipeline[0][0] <= k:
            _, cmd, cid = self._pipeline.popleft()
            starts = np.full(6, t_boundary)
            self._activations.append((starts, cmd, cid, np.ones(6, dtype=bool)))
            self._next_activation_s = min(self._next_activation_s, float(starts.min()))
        if (
            np.abs(bank.q - self._params_q).max() > self.REFRESH_RAD
            or t_boundary - self._params_time_s > 10.0  # thermal drift is slow
        ):
            bank.set_params(self._params(bank.q))
            self._axes = joint_axis_in_tool(self.spec, np.broadcast_to(bank.q, (6, 6)), _JOINTS)
            self._params_q = bank.q.copy()
            self._params_time_s = t_boundary
        axes = self._axes
        kpos = self.settings.servo.position_gain_1_s
        times = (t_boundary + np.arange(self.n_sub) * self.dt_s).astype(np.float64)
        # Joint by joint in floats (the joints are independent drives; see JointChain).
        ref_q, ref_v = self._ref_q.tolist(), self._ref_v.tolist()
        speeds: list[list[float]] = []
        delay_n, lines, dt = self._delay_n, self._lines, self.dt_s
        busy_until = self._lines_busy_until_s
        for t in times.tolist():
            if t + 1e-12 >= self._next_activation_s:
                self._ref_q, self._ref_v = np.array(ref_q), np.array(ref_v)  # _activate reads
                still: list[tuple[FloatArray, Command, int, NDArray[np.bool_]]] = []
                for starts, cmd, cid, left in self._activations:
                    due = left & (starts <= t + 1e-12)
                    if due.any():
                        self._activate(due, cmd, cid, t)
                        left = left & ~due
                    if left.any():
                        still.append((starts, cmd, cid, left))
                self._activations = still
                self._next_activation_s = min(
                    (float(starts[left].min()) for starts, _, _, left in still), default=math.inf
                )
            row = [0.0] * 6
            for j in range(6):
                q_j, v_j, pos_mode = self._reference(j, t, ref_q[j], ref_v[j])
                ref_v[j] = v_j
                if pos_mode:
                    ref_q[j] = q_j
                drive_q, drive_v, drive_pos = q_j, v_j, pos_mode
                if delay_n[j]:
                    line = lines[j]
                    line.append((q_j, v_j, pos_mode))
                    drive_q, drive_v, drive_pos = line.popleft()
                    if v_j != 0.0:
                        busy_until = t + delay_n[j] * dt
                if drive_pos:
                    row[j] = bank.step_joint(j, drive_v + kpos * (drive_q - bank.angle(j)), t)
                else:
                    row[j] = bank.step_joint(j, drive_v, t)
                if not pos_mode:
                    # In speed mode the reference position follows the joint: no catch-up of
                    # lost time (speedj is a velocity interface), and position commands
                    # start from here.
                    ref_q[j] = bank.angle(j)
            speeds.append(row)
        self._ref_q, self._ref_v = np.array(ref_q), np.array(ref_v)
        self._lines_busy_until_s = busy_until
        # row by row: one (n_sub, 6) @ (6, 3) product sums in another order (other bits)
        rates = np.array([np.array(row) @ axes for row in speeds])
        onsets = bank.onset_s
        for j, waiting in enumerate(self._waiting):
            if waiting and not math.isnan(onsets[j]):
                for event in waiting:
                    event.onset_s[j] = onsets[j]
                waiting.clear()
        self.cycle_index = k + 1
        self.time_s = (k + 1) * period
        # Each rate is the joint speed at the end of its step.
        return CycleResult(packet=packet, substep_time_s=times + self.dt_s, flange_rate_rad_s=rates)


def _trapezoid(t: float, t_acc: float, t_cruise: float, v_peak: float) -> tuple[float, float]:
    """Distance and speed along a trapezoidal (or triangular) profile at time ``t``."""
    if t <= 0 or v_peak <= 0:
        return 0.0, 0.0
    a = v_peak / t_acc if t_acc > 0 else 0.0
    if t < t_acc:
        return 0.5 * a * t * t, a * t
    d_acc = 0.5 * v_peak * t_acc
    if t < t_acc + t_cruise:
        return d_acc + v_peak * (t - t_acc), v_peak
    td = t - t_acc - t_cruise
    total = 2 * d_acc + v_peak * t_cruise
    if td < t_acc:
        return d_acc + v_peak * t_cruise + v_peak * td - 0.5 * a * td * td, v_peak - a * td
    return total, 0.0
