"""``payload``: a tool on the flange that the robot's model leaves out."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from timedexec._types import FloatArray
from timedexec.effects._base import Effect, FitParam, MassChange, Pose, TermInputs, Variable
from timedexec.effects._registry import register_effect
from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec, gravity_torque_coefficients, joint_inertia

__all__ = ["Payload"]


def _with_tool(spec: RobotSpec, mass_kg: float) -> RobotSpec:
    return dataclasses.replace(spec, payload_kg=spec.payload_kg + mass_kg)


def _mass_change(pose: Pose, mass_kg: float) -> MassChange:
    """The tool's gravity-torque coefficients and reflected inertia about each moving
    joint: the robot's with the tool minus without (both linear in the tool's mass)."""
    loaded = _with_tool(pose.spec, mass_kg)
    a0, b0 = gravity_torque_coefficients(pose.spec, pose.q_start_rad, pose.joint)
    a1, b1 = gravity_torque_coefficients(loaded, pose.q_start_rad, pose.joint)
    rows = np.arange(len(pose.joint))
    inertia = joint_inertia(loaded, pose.q_start_rad)[rows, pose.joint - 1] - pose.inertia_kgm2
    return MassChange(a1 - a0, b1 - b0, inertia)


@register_effect
@dataclass(frozen=True, kw_only=True)
class Payload(Effect):
    """A tool of ``mass_kg`` on the flange that the robot's model (and its drives' tuning)
    leaves out: a gripper, a welding torch, the gyro's thermal enclosure.

    The tool is a point mass at the flange, as the robot spec models a payload. It adds its
    gravity torque to what each joint holds at the start pose (so with load-dependent gear
    friction, ``gravity_load``, the breakaway torque of the loaded joints grows with the
    tool's torque, and lifting it differs from lowering it with ``gravity_direction``) and
    its inertia to what each joint accelerates (a slower rise after breakaway). The delay
    therefore follows the tool's own lever arm: on the wrist (joint 5) the tool's torque is
    most of what the joint holds, so the wrist slows down far more than the arm's own
    gravity torque predicts, and joint 1, which holds no gravity, only through the tool's
    inertia. Not in DESIGN.md's table: a cell whose tool mass is not configured on the
    controller, or was changed, shows exactly this; none of the seven effects has its
    shape.

    Parameters
    ----------
    mass_kg : float
        Tool mass, kg, in [0, 50].
    """

    name: ClassVar[str] = "payload"
    order: ClassVar[float] = 8
    meaning: ClassVar[str] = (
        "a tool on the flange the robot model lacks: the loaded joints' actuation delay grows "
        "with the tool's gravity torque and inertia"
    )
    variable: ClassVar[str] = "|gravity torque of a 1 kg tool at the flange| (N·m/kg)"
    variable_key: ClassVar[str] = "tool_torque"
    fit_params: ClassVar[tuple[FitParam, ...]] = (FitParam("mass_kg", 0.0, 20.0, 0.2),)
    named_after_shapes: ClassVar[bool] = True
    mass_kg: float = 3.0

    def __post_init__(self) -> None:
        self._check_finite()
        if not 0.0 <= self.mass_kg <= 50.0:
            raise ConfigError(
                f"payload: mass_kg={self.mass_kg} must lie in [0, 50] kg (a tool on the flange)"
            )

    def mass_change(self, pose: Pose) -> MassChange:
        return _mass_change(pose, self.mass_kg)

    @classmethod
    def signature_effect(cls, sweep_span_s: float) -> Effect:
        """A 1 kg tool: small enough that no joint of a calibrated model is pushed past its
        torque limit by it (one such condition, no longer breaking away in the window,
        would be the whole signature), large enough to stand clear of the 0.25 ms physics
        grid (~0.5 ms on the loaded joints)."""
        return cls(mass_kg=1.0)

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        return cls(mass_kg=float(np.clip(amplitude[0], 0.1, 20.0)))

    def scaled(self, f: float) -> Effect:
        return Payload(mass_kg=self.mass_kg * f)

    @classmethod
    def own_variable(cls, pose: Pose) -> Variable:
        unit = _mass_change(pose, 1.0)
        q = pose.q_start_rad[np.arange(len(pose.joint)), pose.joint - 1]
        torque = np.abs(unit.grav_a_nm * np.cos(q) + unit.grav_b_nm * np.sin(q))
        return Variable(
            "tool_torque",
            "|gravity torque of a 1 kg tool at the flange|",
            "N·m/kg",
            "linear",
            torque,
        )

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        return {"mass_kg": self.mass_kg, "unit": "kg of tool at the flange, beyond the robot model"}

    def explain(
        self, x: TermInputs, contrib_ms: FloatArray, *, shaped: bool
    ) -> tuple[dict[str, Any], str]:
        mean = {j: float(contrib_ms[x.joint == j].mean()) for j in x.joints}
        top = {j: float(contrib_ms[x.joint == j].max()) for j in x.joints}
        ranked = sorted(x.joints, key=lambda j: -mean[j])
        parts = [f"joint {j} {mean[j]:+.2f} ms on average (up to {top[j]:+.2f} ms)" for j in ranked]
        return (
            {
                "mass_kg": self.mass_kg,
                "mean_ms": {f"joint {j}": mean[j] for j in x.joints},
                "max_ms": {f"joint {j}": top[j] for j in x.joints},
            },
            f"a {self.mass_kg:.1f} kg tool on the flange that the robot model lacks lengthens "
            "the actuation delay of the joints that carry it: " + ", ".join(parts),
        )
