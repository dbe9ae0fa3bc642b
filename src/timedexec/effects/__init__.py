"""timedexec.effects: the effect vocabulary, one class per effect, one registry.

Each effect is a frozen, keyword-only dataclass with physical parameters that says
everything about itself (:class:`Effect`): what the simulator applies (:mod:`timedexec.sim`
asks every effect of an :class:`EffectSet` for its physics and timing through the hooks of
:class:`Effect`), what the discrepancy workflow locates, fits and explains (the delay it acts
on, the variable it follows, its free parameters, its term families, its sentence). The
registry :data:`EFFECTS` holds the classes by name, in the vocabulary's order; every
consumer iterates it (the simulator never names an effect, the discrepancy workflow scores
every registered one, the command line lists them). The names are part of the public
interface (DESIGN.md, "Effect vocabulary").

Adding an effect: one module in this package that defines the class and registers it
(``@register_effect``), and its import below (docs/discrepancy.md, "Adding an effect"). An
effect built at run time (e.g. from a term the discrepancy workflow fitted) registers the
same way and is then simulated, scored and explained like the others.

The vocabulary (how each acts in the simulator is in its class's docstring):

``gravity_load``
    Load-dependent friction of the gear: breakaway torque grows with the holding torque.
``gravity_direction``
    Lifting against gravity needs more breakaway torque than lowering with it.
``direction``
    Pose-independent asymmetry of the drive: breakaway torque scales by ``1 + asymmetry_j · d``.
``inertia``
    The joint's true, pose-dependent reflected inertia acts (instead of the nominal one).
``thermal_drift``
    Cold grease: friction starts high and relaxes over the sweep.
``joint_offset``
    Each joint's drive applies the setpoint ``offsets_s[j]`` later.
``response_extra_cycle``
    State sampling and transmission fall in separate controller cycles.

After DESIGN.md's table:

``payload``
    A tool on the flange the robot model lacks: its gravity torque and inertia load the
    joints that carry it.

Outside the vocabulary, terms found in data (:class:`DataTerm`, ``_term``): a closed-form
dead time of the drive, ``coef · basis(inputs)`` per joint (linear, hinge, harmonic, product or bump
in a joint angle or another joint's gravity torque), each registered at run time as a
class of its own (:func:`register_term`) and then simulated like any effect; never named
as vocabulary (``EFFECTS.vocabulary``).
"""

from __future__ import annotations

from timedexec.effects._base import (
    ClosedForm,
    Effect,
    FitParam,
    MassChange,
    Pose,
    TermInputs,
    TermSpec,
    Variable,
)
from timedexec.effects._defaults import default_effects, parse_effects
from timedexec.effects._direction import Direction
from timedexec.effects._gravity_direction import GravityDirection
from timedexec.effects._gravity_load import GravityLoad
from timedexec.effects._inertia import Inertia
from timedexec.effects._joint_offset import JointOffset
from timedexec.effects._payload import Payload as Payload  # registers "payload"
from timedexec.effects._registry import (
    EFFECTS,
    EffectRegistry,
    EffectSet,
    effect_type,
    make_effect,
    register_effect,
)
from timedexec.effects._response_extra_cycle import ResponseExtraCycle
from timedexec.effects._term import TERM_FORMS, DataTerm, register_term, term_columns
from timedexec.effects._thermal_drift import ThermalDrift

#: The names of the effects registered when the package was imported (the built-in
#: vocabulary), in order. Effects registered later are in :data:`EFFECTS`.
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)

__all__ = [
    "EFFECTS",
    "EFFECT_NAMES",
    "TERM_FORMS",
    "ClosedForm",
    "DataTerm",
    "Direction",
    "Effect",
    "EffectRegistry",
    "EffectSet",
    "FitParam",
    "GravityDirection",
    "GravityLoad",
    "Inertia",
    "JointOffset",
    "MassChange",
    "Pose",
    "ResponseExtraCycle",
    "TermInputs",
    "TermSpec",
    "ThermalDrift",
    "Variable",
    "default_effects",
    "effect_type",
    "make_effect",
    "parse_effects",
    "register_effect",
    "register_term",
    "term_columns",
]
