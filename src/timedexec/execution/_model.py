"""What the executor needs from a delay model, and how it gets one.

The executor talks to any object with the delay-model interface of
:class:`timedexec.learning.DelayModel` (structural typing, :class:`DelayPredictor`):
``robot``, ``controller_period_s`` (or ``period_s``) and ``predict_many(joint, direction, q)`` returning an
object with ``actuation_mean``, ``actuation_std``, ``response_mean``, ``response_std`` (s;
the std is that of a single trial's delay). :class:`FixedDelays` is such an object with
constant delays (MoveIt Servo's single latency, or per-joint medians).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.errors import ConfigError, ModelError
from timedexec.learning import BUNDLED_MODELS, bundled_model_dir
from timedexec.robots import get_robot

__all__ = [
    "DelayPredictions",
    "DelayPredictor",
    "FixedDelays",
    "check_model_robot",
    "load_delay_model",
    "model_echo_depth",
    "model_period_s",
    "predict_delays",
]


@runtime_checkable
class DelayPredictor(Protocol):
    """The delay-model interface the executor uses (see the module docstring)."""

    @property
    def robot(self) -> str:
        """Robot spec name the model was trained for."""

    def predict_many(self, joint: Any, direction: Any, q: Any) -> Any:
        """Vectorised predictions for ``joint`` (n,), ``direction`` (n,), ``q`` (n, 6)."""


@dataclass(frozen=True)
class DelayPredictions:
    """Predicted delays per condition, shapes (n,), s."""

    actuation_mean: FloatArray
    actuation_std: FloatArray
    response_mean: FloatArray
    response_std: FloatArray


def predict_delays(
    model: DelayPredictor,
    joint: ArrayLike,
    direction: ArrayLike,
    q: ArrayLike,
    *,
    t_s: ArrayLike | None = None,
) -> DelayPredictions:
    """Call ``model.predict_many`` and normalise its answer to float arrays of shape (n,).

    ``t_s`` (the time since the robot started working, s) is passed on only when given,
    for models with a time input.

    Raises
    ------
    ModelError
        If the model answers with non-finite values or negative standard deviations.
    """
    j = np.atleast_1d(np.asarray(joint, dtype=np.int64))
    d = np.atleast_1d(np.asarray(direction, dtype=np.int64))
    qq = np.asarray(q, dtype=float).reshape(-1, 6)
    n = max(len(j), len(d), len(qq))
    j, d = np.broadcast_to(j, (n,)).copy(), np.broadcast_to(d, (n,)).copy()
    qq = np.broadcast_to(qq, (n, 6)).copy()
    raw = model.predict_many(j, d, qq) if t_s is None else model.predict_many(j, d, qq, t_s=t_s)  # type: ignore[call-arg]
    out = {}
    for name in ("actuation_mean", "actuation_std", "response_mean", "response_std"):
        value = getattr(raw, name, None)
        if value is None and isinstance(raw, dict):
            value = raw.get(name)
        if value is None:
            raise ModelError(
                f"delay model {type(model).__name__} answered without {name!r}; a delay model "
                "must return actuation_mean, actuation_std, response_mean and response_std"
            )
        arr = np.broadcast_to(np.asarray(value, dtype=float).reshape(-1), (n,)).copy()
        if not np.all(np.isfinite(arr)):
            raise ModelError(
                f"delay model {type(model).__name__} predicted non-finite {name} "
                f"({arr[~np.isfinite(arr)][:3]}) for joints {j[~np.isfinite(arr)][:3]}; check "
                "that the model covers these joints"
            )
        out[name] = arr
    for name in ("actuation_std", "response_std"):
        if np.any(out[name] < 0):
            raise ModelError(f"delay model predicted a negative {name}")
    return DelayPredictions(**out)


@dataclass(frozen=True, kw_only=True)
class FixedDelays:
    """Constant delays: one per joint (or one for all), independent of pose and direction.

    Parameters
    ----------
    robot : str
        Robot the delays belong to.
    actuation_s : float or 6 floats
        Actuation delay per joint (joint 1 first), s.
    response_s : float
        Response delay, s.
    actuation_std_s, response_std_s : float or 6 floats
        Single-trial standard deviations, s (for timing bounds).
    controller_period_s : float, optional
        Default: the robot spec's period.

    Examples
    --------
    MoveIt Servo's single latency setting as a delay model:

    >>> servo_like = FixedDelays(robot="ur10", actuation_s=0.021, response_s=0.004)
    """

    robot: str
    actuation_s: Any = 0.0
    response_s: float = 0.0
    actuation_std_s: Any = 0.0
    response_std_s: float = 0.0
    controller_period_s: float = 0.0

    def __post_init__(self) -> None:
        spec = get_robot(self.robot)
        object.__setattr__(self, "robot", spec.name)
        for name in ("actuation_s", "actuation_std_s"):
            arr = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (6,))
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise ConfigError(f"FixedDelays.{name}={arr.tolist()} must be finite and >= 0 s")
            object.__setattr__(self, name, tuple(float(v) for v in arr))
        for name in ("response_s", "response_std_s"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"FixedDelays.{name}={v!r} must be finite and >= 0 s")
            object.__setattr__(self, name, v)
        if not self.controller_period_s:
            object.__setattr__(self, "controller_period_s", spec.controller_period_s)

    def predict_many(self, joint: Any, direction: Any, q: Any) -> DelayPredictions:
        """Constant predictions for each row."""
        j = np.atleast_1d(np.asarray(joint, dtype=np.int64))
        n = len(j)
        if np.any((j < 1) | (j > 6)):
            raise ConfigError(f"joint numbers must lie in 1..6, got {j[(j < 1) | (j > 6)][:3]}")
        act = np.asarray(self.actuation_s)[j - 1]
        act_std = np.asarray(self.actuation_std_s)[j - 1]
        return DelayPredictions(
            actuation_mean=act,
            actuation_std=act_std,
            response_mean=np.full(n, self.response_s),
            response_std=np.full(n, self.response_std_s),
        )

    def predict(self, *, joint: int, direction: int, q: ArrayLike) -> DelayPredictions:
        """One prediction (arrays of length 1)."""
        return self.predict_many([joint], [direction], np.asarray(q, dtype=float).reshape(1, 6))


def model_period_s(model: Any) -> float:
    """The controller period a model was trained at, s (``controller_period_s``, or the
    ``period_s`` of :class:`timedexec.learning.DelayModel`)."""
    for name in ("controller_period_s", "period_s"):
        value = getattr(model, name, None)
        if value is not None:
            return float(value)
    raise ModelError(
        f"{type(model).__name__} does not say its controller period (controller_period_s)"
    )


def model_echo_depth(model: Any) -> int | None:
    """The controller's echo depth a model carries (``echo_depth_cycles``: what
    ``calibrate`` measured on the robot, :class:`~timedexec.tasks.TrackingDelays`), cycles,
    or None where it carries none."""
    value = getattr(model, "echo_depth_cycles", None)
    return None if value is None else int(value)


def load_delay_model(model: DelayPredictor | str | os.PathLike[str]) -> DelayPredictor:
    """A delay model object: a bundle folder is loaded with ``DelayModel.load``, a bundled
    model's name (one of :data:`BUNDLED_MODELS`, e.g. ``"ur10-sim"``) from the package, and a
    model object is checked for the delay-model interface.

    Raises
    ------
    ModelError
        If the path holds no model bundle or the object lacks the delay-model interface.
    """
    if isinstance(model, str | os.PathLike):
        path = Path(model)
        if not path.exists() and str(model) in BUNDLED_MODELS:
            path = bundled_model_dir(str(model))
        if not path.exists():
            raise ModelError(
                f"no delay-model bundle at {path}; train one (timedexec train) or use a bundled "
                f"model by name: {', '.join(BUNDLED_MODELS)}"
            )
        from timedexec.learning import DelayModel

        loaded: Any = DelayModel.load(path)
        return loaded  # type: ignore[no-any-return]
    missing = [name for name in ("robot", "predict_many") if not hasattr(model, name)]
    if not (hasattr(model, "controller_period_s") or hasattr(model, "period_s")):
        missing.append("controller_period_s")
    if missing:
        raise ModelError(
            f"{type(model).__name__} is not a delay model: it lacks {missing}; pass a "
            "timedexec.learning.DelayModel, a bundle directory or FixedDelays"
        )
    return model


def check_model_robot(
    model: DelayPredictor,
    robot: str,
    period_s: float | None = None,
    *,
    against: str = "the driver talks to",
) -> None:
    """Refuse a model trained for another robot (or controller period).

    ``against`` names where ``robot`` came from in the message (default: the driver).

    Raises
    ------
    ModelError
        Naming the model's robot and the other robot, and how to fix it.
    """
    mine = str(model.robot).lower()
    if mine != robot.lower():
        raise ModelError(
            f"the delay model is for robot {model.robot!r} but {against} {robot!r}; "
            f"load a model for {robot} (e.g. the bundled '{robot}-sim') or train one on {robot} data"
        )
    trained = model_period_s(model)
    if period_s is not None and not np.isclose(trained, float(period_s), rtol=1e-6, atol=1e-9):
        raise ModelError(
            f"the delay model was trained at a controller period of "
            f"{trained * 1e3:g} ms but the {robot} driver runs at "
            f"{period_s * 1e3:g} ms; retrain at this period or change the controller's period"
        )
