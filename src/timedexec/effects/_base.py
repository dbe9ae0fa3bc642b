"""The effect base class and what the simulator and the discrepancy workflow hand an effect.

An effect is one class that says everything about itself:

* **what the simulator applies**: pure functions of arrays that :mod:`timedexec.sim` calls
  in a fixed order while it sets up each joint's drive (the robot's mass, the inertia that
  acts, breakaway friction added and scaled, viscous friction) and the control box's
  timing (a drive's dead time, whole periods of state latency). Each returns ``None``
  (or 0) when the effect does not act there; the simulator never asks for a name.
* **what the discrepancy workflow locates and fits**: the delay it acts on, the condition
  variable it follows, how the workflow's model holds it (simulated, or a closed-form
  shift), its free parameters with their bounds, the magnitude its candidate signature is
  simulated at, the term families of its measured shape;
* **how it is explained**: its parameters in physical units and, where the generic
  "slope per unit of its variable" does not say it well, a sentence of its own.

Nothing here imports the simulator or the workflow: both consume effects through these
hooks and the registry (:mod:`timedexec.effects._registry`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, ClassVar, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray, IntArray
from timedexec.errors import ConfigError
from timedexec.robots import RobotSpec, joint_inertia

__all__ = [
    "ClosedForm",
    "Effect",
    "FitParam",
    "MassChange",
    "Pose",
    "TermInputs",
    "TermSpec",
    "Variable",
]

#: How the discrepancy workflow's model holds a closed-form effect (:attr:`Effect.closed_form`).
ClosedForm = Literal["joint_levels", "response_periods", "term"]


@dataclass(frozen=True, eq=False)
class Pose:
    """The start poses an effect acts at: ``n`` elements, each one joint moving from one
    start configuration (a simulated trial, a joint of the stepped controller or a measured
    condition).

    Attributes
    ----------
    spec : RobotSpec
    q_start_rad : ndarray (n, 6)
        Start configuration, rad.
    joint : ndarray of int (n,)
        The joint that moves, 1-based.
    t_start_s : ndarray (n,)
        Time since the sweep (or the controller) started, s.
    direction : ndarray (n,), optional
        +1/-1 where the motion's direction is known (a batch trial, a measured condition);
        None where it is not (the stepped controller sets a drive up before any command).
    """

    spec: RobotSpec
    q_start_rad: FloatArray
    joint: IntArray
    t_start_s: FloatArray
    direction: FloatArray | None = None

    @cached_property
    def rotor_kgm2(self) -> FloatArray:
        """Rotor (motor and gear) inertia of each moving joint, kg·m² (n,)."""
        out: FloatArray = np.asarray(self.spec.rotor_inertia_kgm2)[self.joint - 1]
        return out

    @cached_property
    def inertia_kgm2(self) -> FloatArray:
        """The arm's true reflected inertia about each moving joint at its start pose
        (links, payload of the spec and rotor), kg·m² (n,)."""
        rows = np.arange(len(self.joint))
        out: FloatArray = joint_inertia(self.spec, self.q_start_rad)[rows, self.joint - 1]
        return out


class MassChange(NamedTuple):
    """What an effect adds to the arm's mass model at a pose (:meth:`Effect.mass_change`):
    the gravity-torque coefficients ``A cos x + B sin x`` of each moving joint (N·m) and its
    reflected inertia (kg·m²), arrays (n,)."""

    grav_a_nm: FloatArray
    grav_b_nm: FloatArray
    inertia_kgm2: FloatArray


@dataclass(frozen=True)
class FitParam:
    """One free parameter of a simulated effect, as the discrepancy calibration fits it.

    Attributes
    ----------
    field : str
        The effect's dataclass field.
    lower, upper : float
        Physical bounds of the fit.
    step : float
        Finite-difference step (and the solver's scale) in the fitted coordinate: the value,
        or its logarithm when ``log``.
    log : bool
        Fit the logarithm (a scale parameter).
    per_joint : bool
        The field is a 6-tuple: one parameter per measured joint, each changing only that
        joint's conditions.
    group : str
        Suffix of its finite-difference group (parameters of one group change disjoint
        conditions and are perturbed in one simulation).
    """

    field: str
    lower: float
    upper: float
    step: float
    log: bool = False
    per_joint: bool = False
    group: str = ""


@dataclass(frozen=True, eq=False)
class Variable:
    """A variable of the measured conditions the residuals may follow: its values per
    condition and how to fit it (``kind``: ``angle``, ``linear`` or ``binary``)."""

    key: str
    label: str
    unit: str
    kind: str
    values: FloatArray


@dataclass(frozen=True, eq=False)
class TermInputs:
    """The measured conditions as the discrepancy workflow hands them to an effect (``m``
    conditions, one start configuration, joint and direction each).

    Attributes
    ----------
    joint, direction : ndarray (m,)
        Actuated joint (1-based) and direction (+1/-1).
    joints : tuple of int
        The joints present, sorted.
    q_rad : ndarray (m, 6)
        Start configurations, rad.
    t_start_s : ndarray (m,)
        Mean sweep time of each condition, s.
    gravity_torque_nm : ndarray (m,)
        Holding torque of the actuated joint at the start pose (the robot alone), N·m.
    inertia_kgm2, nominal_inertia_kgm2 : ndarray (m,)
        True reflected inertia of the actuated joint and the one at the home pose, kg·m².
    resid_ms : ndarray (m,), optional
        The current actuation residuals (a time family chooses its change point on them).
    period_s : float
        Controller period, s (NaN where not needed).
    mean_s : mapping delay -> ndarray (m,)
        Measured condition means, s (empty where not needed).
    """

    joint: IntArray
    direction: NDArray[Any]
    joints: tuple[int, ...]
    q_rad: FloatArray
    t_start_s: FloatArray
    gravity_torque_nm: FloatArray
    inertia_kgm2: FloatArray
    nominal_inertia_kgm2: FloatArray
    resid_ms: FloatArray | None = None
    period_s: float = math.nan
    mean_s: Mapping[str, FloatArray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.joint)

    @property
    def masks(self) -> list[FloatArray]:
        """One indicator column (0/1) per joint present."""
        return [(self.joint == j).astype(float) for j in self.joints]


@dataclass(frozen=True, eq=False)
class TermSpec:
    """A term family an effect declares: columns over the conditions that its measured
    shape may follow (the discrepancy workflow scores them against the residuals).

    Attributes
    ----------
    key, label : str
        Identifier (``load``, ``direction_x_joint``) and the shape in words.
    columns : ndarray (m, k)
        The columns, each scaled to unit RMS (:func:`timedexec._columns.stack_columns`).
    parents : tuple of str
        Keys of its main effects (for an interaction).
    variable : str or None
        The condition variable it follows, for reports.
    joints : tuple of int
        Joints whose conditions it can change (empty: all).
    extra_df : int
        Degrees of freedom beyond its columns (a change point chosen on the residuals).
    signature : bool
        The simulator's signature of the effect joins the family (the simulator's own form
        is always among the shapes tried).
    positive : bool
        The effect only lengthens the delay: the family passes only when the residuals'
        mean is positive.
    """

    key: str
    label: str
    columns: FloatArray
    parents: tuple[str, ...] = ()
    variable: str | None = None
    joints: tuple[int, ...] = ()
    extra_df: int = 0
    signature: bool = False
    positive: bool = False


@dataclass(frozen=True, kw_only=True)
class Effect:
    """Base class of the effects: a frozen, keyword-only dataclass of physical parameters.

    A subclass sets the class attributes below, overrides the simulator hooks it acts
    through, and registers itself (:func:`timedexec.effects.register_effect`).
    """

    name: ClassVar[str] = ""
    #: What the effect means physically (one sentence, for reports).
    meaning: ClassVar[str] = ""
    #: The variable whose value the effect follows, in words (for reports).
    variable: ClassVar[str] = ""
    #: Which delay it acts on: "actuation_delay" or "response_delay".
    acts_on: ClassVar[str] = "actuation_delay"
    #: Its place in the vocabulary's order (DESIGN.md's table: 1, 2, ...; effects built
    #: at run time: after those, in the order they were registered).
    order: ClassVar[float] = math.inf
    #: A term found in data (:class:`timedexec.effects.DataTerm`), registered at run time:
    #: simulated like any effect, but not part of the vocabulary the workflow names.
    data_driven: ClassVar[bool] = False

    # -- the discrepancy workflow ---------------------------------------------------------
    #: Key of the condition variable its residual plots and its explanation use (``q1``..
    #: ``q6``, ``gravity_torque``, ``direction_x_gravity``, ``inertia``, ``time``,
    #: ``direction``, ``joint``, or one of :meth:`own_variable`).
    variable_key: ClassVar[str] = ""
    #: How the workflow's model holds it: None, the simulator runs it (its parameters are
    #: calibrated with the simulator in the loop); ``"joint_levels"``, a constant per
    #: joint on the actuation delay; ``"response_periods"``, whole controller periods on
    #: the response delay; ``"term"``, a data-driven term whose coefficients are fitted
    #: with the model's constants (:class:`timedexec.effects.DataTerm`: its ``basis`` and
    #: ``with_coefficients``). A closed-form effect must be an exact additive shift of the
    #: simulator's output through its timing hooks (:meth:`drive_delay_s`,
    #: :meth:`response_delay_s`), which the workflow applies without simulating.
    closed_form: ClassVar[ClosedForm | None] = None
    #: Bounds of the amplitude of its candidate signature (an effect that only adds
    #: friction or inertia acts with the sign it was simulated with).
    signature_bounds: ClassVar[tuple[float, float]] = (0.0, math.inf)
    #: Its signature has one column per joint (an amplitude of its own for each).
    signature_per_joint: ClassVar[bool] = False
    #: The free parameters the calibration fits (simulated effects).
    fit_params: ClassVar[tuple[FitParam, ...]] = ()
    #: The key of the term family its measured shape is made of, when the simulator's
    #: form does not reproduce the measured dependence (one of :meth:`term_families`).
    shape_family: ClassVar[str | None] = None
    #: Its signature resembles a reshaped effect the model may already have (a tool's
    #: load looks like more load): it is named only when it explains the residuals better
    #: (held out) than the best measured shape of the model's own effects would.
    named_after_shapes: ClassVar[bool] = False
    #: The verb of its generic explanation: "grows" for an effect that only lengthens the
    #: delay along its variable.
    explain_verb: ClassVar[str] = "changes"

    @property
    def simulated(self) -> bool:
        """The simulator runs it (not a closed-form shift)."""
        return self.closed_form is None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form: ``{"name": ..., **parameters}``."""
        out: dict[str, Any] = {"name": self.name}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    def _check_finite(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            for v in values:
                if not isinstance(v, int | float) or v != v or v in (float("inf"), float("-inf")):
                    raise ConfigError(
                        f"effect {self.name!r}: parameter {f.name}={value!r} must be finite numbers"
                    )

    # -- the simulator: the joint physics, in this order (timedexec.sim.joint_params) ------
    def mass_change(self, pose: Pose) -> MassChange | None:
        """What it adds to the arm's gravity-torque coefficients and inertia at ``pose``."""
        return None

    def acting_inertia_kgm2(self, pose: Pose) -> FloatArray | None:
        """The reflected inertia that acts instead of the nominal one (the one the velocity
        loop is tuned for), kg·m² (n,)."""
        return None

    def breakaway_extra_nm(
        self, pose: Pose, holding_nm: FloatArray
    ) -> tuple[FloatArray, FloatArray] | None:
        """Breakaway torque added for motion in + and in -, N·m (n,) each, given the
        holding torque at the start pose (N·m, the mass changes included). The sum over
        the effects is floored at a fifth of the drive's base breakaway."""
        return None

    def breakaway_factors(self, pose: Pose) -> tuple[FloatArray, FloatArray] | None:
        """Factors on the breakaway torque for motion in + and in - (after the floor);
        kinetic friction follows the breakaway."""
        return None

    def viscous_factor(self, pose: Pose) -> FloatArray | None:
        """Factor on the viscous friction (n,)."""
        return None

    # -- the simulator: the control box's timing ------------------------------------------
    def drive_delay_s(self, pose: Pose) -> FloatArray | None:
        """Dead time between the interpolator's reference and the moving joint's drive, s
        (n,). The stepped controller asks once per joint at its start pose."""
        return None

    def response_delay_s(self, period_s: float) -> float:
        """Time every state package waits beyond the base timing's packing phase, s."""
        return 0.0

    # -- the discrepancy workflow -----------------------------------------------------------
    @classmethod
    def signature_effect(cls, sweep_span_s: float) -> Effect:
        """The effect at the magnitude its candidate signature is simulated with (the
        vocabulary's defaults), for a sweep ``sweep_span_s`` long."""
        return cls()

    @classmethod
    def from_amplitude(
        cls, amplitude: FloatArray, joints: tuple[int, ...], sweep_span_s: float
    ) -> Effect:
        """The effect at the magnitude its fitted signature amplitude suggests (one per
        signature column; the start of the nonlinear calibration)."""
        return cls.signature_effect(sweep_span_s)

    def scaled(self, f: float) -> Effect:
        """The effect with its magnitude scaled by ``f`` (0 < f < 1): a weaker start for
        the calibration."""
        return self

    @classmethod
    def n_parameters(cls, n_joints: int) -> int:
        """Parameters it adds to the workflow's model when ``n_joints`` joints are measured."""
        return sum(n_joints if p.per_joint else 1 for p in cls.fit_params)

    @classmethod
    def fit_closed_form(
        cls, y_s: FloatArray, pose: Pose, period_s: float, bounds_s: tuple[float, float]
    ) -> tuple[Effect, float]:
        """A closed-form effect fitted to ``y_s`` (measured minus simulated condition
        means of its delay at the conditions ``pose``, s): the effect and the delay's
        constant (within ``bounds_s``). Only closed-form effects implement it."""
        raise NotImplementedError(f"effect {cls.name!r} is not a closed-form effect")

    @classmethod
    def term_families(cls, x: TermInputs) -> list[TermSpec]:
        """The term families of its shape over the conditions ``x``, in order."""
        return []

    @classmethod
    def own_variable(cls, pose: Pose) -> Variable | None:
        """A condition variable of its own (when :attr:`variable_key` is none of the
        workflow's), at the conditions' poses."""
        return None

    def describe(self, joints: tuple[int, ...], period_s: float) -> dict[str, Any]:
        """Its fitted parameters in physical units (for the report)."""
        return self.to_dict()

    def explain(
        self, x: TermInputs, contrib_ms: FloatArray, *, shaped: bool
    ) -> tuple[dict[str, Any], str] | None:
        """What it does to the delays, in observable units, and a sentence, given its
        contribution to every condition mean (ms; ``shaped``: a measured shape beyond the
        simulator's form is part of it). None: the generic explanation (slopes per unit
        of its variable, per joint)."""
        return None
