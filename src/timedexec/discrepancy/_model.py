"""The simulator as the model: condition means of the delays for an effect set, and the
calibration of the effects' physical parameters to measured condition means.

The model of a condition's mean delay is the batch simulator (``simulate_delays``) run once
per condition with the base timing's randomness replaced by its mean:

* the packing phase is fixed so that the command reaches the controller half a cycle before
  the next cycle boundary (the mean wait for intake is half a period, as for a random phase);
* cycle, network and host jitter are off.

The joint physics is time-invariant, so every trial of a condition has the same onset
relative to the reference start; the random timing only adds a scatter whose mean is a
constant. Two constants the base timing of a real robot does not reveal are calibrated:
``act_offset_s`` (pipeline, latencies) and ``resp_offset_s`` (packing phase, latency). The
latter is bounded: without ``response_extra_cycle`` the packing phase lies within one
controller period (``TimingSettings``), so the base timing cannot produce a mean response
delay above one period plus the wire latency.

Effects that are exact additive shifts of the simulator's output (``Effect.closed_form``:
``joint_offset``, each joint's drive takes the reference later, so the onset moves by the
offset; ``response_extra_cycle``, every package leaves ``cycles`` periods later) are applied
here in closed form, through the effect's own timing hooks, instead of by simulation
(``test_linear_effects_are_additive`` checks it), and fitted by the effect's
``fit_closed_form``. Everything else about an effect (its free parameters, the magnitude its
signature is simulated with) is declared by its class (:mod:`timedexec.effects`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._conditions import Conditions
from timedexec.effects import DataTerm, Effect, EffectSet, Pose, effect_type
from timedexec.robots import RobotSpec
from timedexec.sim import SimSettings, default_settings, simulate_delays

__all__ = [
    "FittedModel",
    "Param",
    "SimModel",
    "actuation_columns",
    "calibrate",
    "closed_form_shift_s",
    "data_terms",
    "default_effect",
    "joint_levels",
    "model_params",
]


#: Window after the trigger in which the model looks for the onset, s (delays up to 0.12 s
#: and friction far beyond the vocabulary's defaults fit; a joint that does not break
#: away inside it counts as starting at its end).
RECORD_S = 0.3


def deterministic_settings(settings: SimSettings) -> tuple[SimSettings, float]:
    """``settings`` with the base timing's randomness replaced by its mean.

    Returns the settings and the fixed packing phase, s.
    """
    tm = settings.timing
    period = settings.protocol.controller_period_s
    # Time from the trigger package's sampling boundary to the command's arrival at the
    # controller, minus the phase: host processing (+ its 20 µs mean excess) and the two
    # wire latencies. Put the arrival half a period before the next boundary.
    lead = tm.host_processing_s + 20e-6 + tm.to_controller_latency_s + tm.to_host_latency_s
    phase = (0.5 * period - lead) % period
    timing = dataclasses.replace(
        tm,
        packing_phase_s=(phase, phase),
        cycle_jitter_s=0.0,
        to_host_jitter_s=0.0,
        to_controller_jitter_s=0.0,
    )
    # Only the onset matters here: a shorter recording window integrates 2.5x less.
    protocol = settings.protocol
    profile = dataclasses.replace(
        protocol.profile, record_s=min(protocol.profile.record_s, RECORD_S)
    )
    protocol = dataclasses.replace(protocol, profile=profile)
    return settings.replace(timing=timing, protocol=protocol), phase


class SimModel:
    """Condition means of the simulated delays for effect sets, with a cache.

    Parameters
    ----------
    spec : RobotSpec
        The robot (its controller period included).
    cond : Conditions
        The measured conditions to simulate.
    settings : SimSettings, optional
        Simulator settings (default: the robot's calibrated defaults).
    seed : int
        Seed of the (small) remaining randomness.
    """

    def __init__(
        self,
        spec: RobotSpec,
        cond: Conditions,
        *,
        settings: SimSettings | None = None,
        seed: int = 0,
    ) -> None:
        self.spec = spec
        self.cond = cond
        self.settings = settings or default_settings(spec)
        self.det_settings, self.phase_s = deterministic_settings(self.settings)
        self.period_s = self.settings.protocol.controller_period_s
        self.seed = seed
        self.n_simulations = 0
        self.simulated_conditions = 0
        self.sim_time_s = 0.0
        self._cache: dict[str, dict[str, FloatArray]] = {}
        m = len(cond)
        #: The conditions as poses (what the effects' hooks are asked at).
        self.pose = Pose(
            spec=spec,
            q_start_rad=cond.q_rad,
            joint=cond.joint,
            t_start_s=cond.t_start_s,
            direction=cond.direction.astype(float),
        )
        self.true_inertia_kgm2 = self.pose.inertia_kgm2
        self.joint_rows = {j: cond.joint == j for j in cond.joints}
        self._rows = np.arange(m)
        t = cond.t_start_s
        #: Length of the sweep the conditions span, s.
        self.sweep_span_s = float(t.max() - t.min()) if len(t) else 0.0

    @property
    def response_offset_bounds_s(self) -> tuple[float, float]:
        """Allowed range of ``resp_offset_s``: the mean packing phase within one period."""
        return -self.phase_s, self.period_s - self.phase_s

    def simulate(
        self,
        effects: EffectSet,
        rows: NDArray[np.bool_] | None = None,
        *,
        closed_form: bool = False,
    ) -> dict[str, FloatArray]:
        """Simulated condition means for the simulated part of ``effects`` (closed-form
        effects are ignored here; ``closed_form``: the simulator runs them too, as it does
        for a sweep — the check that the closed form is what the simulator applies). With
        ``rows``, only those conditions are simulated (the others are NaN). Returns
        ``actuation_delay``, ``response_delay`` (s) and ``gravity_torque_nm`` of every
        condition, arrays (m,)."""
        physical = effects if closed_form else EffectSet(tuple(e for e in effects if e.simulated))
        key = json.dumps(physical.to_dict(), sort_keys=True)
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        c = self.cond
        idx = self._rows if rows is None or rows.all() else self._rows[rows]
        t0 = time.perf_counter()
        table = simulate_delays(
            self.spec,
            c.q_rad[idx],
            c.joint[idx],
            c.direction[idx],
            c.t_start_s[idx],
            effects=physical,
            settings=self.det_settings,
            seed=self.seed,
        )
        self.sim_time_s += time.perf_counter() - t0
        self.n_simulations += 1
        self.simulated_conditions += len(idx)
        out: dict[str, FloatArray] = {}
        for name in (*DELAY_COLUMNS, "gravity_torque_nm"):
            full = np.full(len(c), np.nan)
            # A joint that never breaks away in the window: its onset is the window's end.
            full[idx] = np.nan_to_num(table[name], nan=self.det_settings.protocol.profile.record_s)
            out[name] = full
        if len(idx) == len(c):
            if len(self._cache) > 256:
                self._cache.clear()
            self._cache[key] = out
        return out


# ---------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class Param:
    """One free physical parameter of a simulated effect.

    ``value`` is in internal coordinates (``log`` for scale parameters); ``rows`` marks the
    conditions it can change (parameters of one ``group`` change disjoint rows and are
    perturbed together in finite differences).
    """

    effect: str
    field: str
    index: int | None
    log: bool
    lower: float
    upper: float
    step: float
    group: str
    rows: NDArray[np.bool_] | None = None

    @property
    def label(self) -> str:
        """``effect.field[joint]``."""
        if self.index is None:
            return f"{self.effect}.{self.field}"
        return f"{self.effect}.{self.field}[joint {self.index + 1}]"


def model_params(effects: EffectSet, model: SimModel) -> list[Param]:
    """The free parameters of the simulated effects in ``effects`` (each effect's
    ``fit_params``; a per-joint one once per measured joint)."""
    out: list[Param] = []
    for e in effects:
        for fp in e.fit_params:
            lower, upper = (
                (math.log(fp.lower), math.log(fp.upper)) if fp.log else (fp.lower, fp.upper)
            )
            group = e.name + fp.group
            if fp.per_joint:
                out += [
                    Param(e.name, fp.field, j - 1, fp.log, lower, upper, fp.step, group, rows)
                    for j, rows in model.joint_rows.items()
                ]
            else:
                out.append(Param(e.name, fp.field, None, fp.log, lower, upper, fp.step, group))
    return out


def get_values(effects: EffectSet, params: list[Param]) -> FloatArray:
    """Internal values of ``params`` in ``effects``."""
    x = np.empty(len(params))
    for k, p in enumerate(params):
        value = getattr(effects.get(p.effect), p.field)
        v = float(value[p.index] if p.index is not None else value)
        x[k] = math.log(max(v, 1e-300)) if p.log else v
    return np.clip(x, [p.lower for p in params], [p.upper for p in params])


def set_values(effects: EffectSet, params: list[Param], x: FloatArray) -> EffectSet:
    """A copy of ``effects`` with ``params`` set to internal values ``x``."""
    changes: dict[str, dict[str, Any]] = {}
    for p, v in zip(params, x, strict=True):
        value = math.exp(v) if p.log else float(v)
        eff = effects.get(p.effect)
        ch = changes.setdefault(p.effect, {})
        if p.index is not None:
            current = list(ch.get(p.field, getattr(eff, p.field)))
            current[p.index] = value
            ch[p.field] = tuple(current)
        else:
            ch[p.field] = value
    out = effects
    for name, ch in changes.items():
        eff = out.get(name)
        assert eff is not None
        out = out.with_effect(dataclasses.replace(eff, **ch))
    return out


def default_effect(name: str, model: SimModel) -> Effect:
    """The effect ``name`` at the magnitude its candidate signature is simulated with
    (``Effect.signature_effect`` for the sweep the conditions span)."""
    return effect_type(name).signature_effect(model.sweep_span_s)


def joint_levels(effects: EffectSet) -> bool:
    """The model's actuation constant is one per joint (an effect of per-joint levels,
    ``joint_offset``, is present)."""
    return any(e.closed_form == "joint_levels" for e in effects)


def data_terms(effects: EffectSet) -> list[DataTerm]:
    """The data-driven terms of ``effects`` (closed form ``"term"``), in order."""
    return [e for e in effects if isinstance(e, DataTerm)]


def actuation_columns(model: SimModel, effects: EffectSet) -> FloatArray:
    """The linear part of the actuation model, (m, k): its constant (one, or one per joint
    with per-joint levels) and the basis of each data-driven term (each column scaled to
    unit RMS; the terms' coefficients are fitted with the constants)."""
    m = len(model.cond)
    if joint_levels(effects):
        cols = [mk.astype(float) for mk in model.joint_rows.values()]
    else:
        cols = [np.ones(m)]
    for term in data_terms(effects):
        for c in term.basis(model.pose).T:
            rms = float(np.sqrt(np.mean(c**2)))
            if rms > 0:
                cols.append(c / rms)
    return np.column_stack(cols)


def closed_form_shift_s(effect: Effect, model: SimModel) -> FloatArray:
    """What a closed-form effect adds to its delay in every condition, s (m,): its timing
    hooks, exactly as the simulator applies them."""
    m = len(model.cond)
    if effect.acts_on == "actuation_delay":
        delay = effect.drive_delay_s(model.pose)
        return np.zeros(m) if delay is None else np.zeros(m) + delay
    return np.full(m, effect.response_delay_s(model.period_s))


# ---------------------------------------------------------------------------- fitting
@dataclass(eq=False)
class FittedModel:
    """An effect set calibrated to the measured condition means.

    Attributes
    ----------
    effects : EffectSet
        The effects with their fitted parameters.
    act_offset_s, resp_offset_s : float
        Calibrated constants added to the simulated actuation and response delays, s.
    pred_s, resid_s : dict delay -> ndarray (m,)
        Predicted condition means and measured minus predicted, s.
    sim : dict
        The simulator's output for the simulated effects (``gravity_torque_nm`` too).
    params : list of Param
        Free parameters of the simulated effects.
    jac : ndarray (m, p)
        Sensitivity of the simulated actuation delay to ``params`` (s per internal unit).
    n_fitted : dict delay -> int
        Parameters fitted to each delay (for the degrees of freedom of the tests).
    """

    effects: EffectSet
    act_offset_s: float
    resp_offset_s: float
    pred_s: dict[str, FloatArray]
    resid_s: dict[str, FloatArray]
    sim: dict[str, FloatArray]
    params: list[Param]
    jac: FloatArray
    n_fitted: dict[str, int]
    nfev: int = 0
    info: dict[str, Any] = field(default_factory=dict)

    def gap_s(self, delay: str) -> float:
        """RMS over conditions of measured minus simulated mean, s."""
        return float(np.sqrt(np.mean(self.resid_s[delay] ** 2)))

    def parameters(self) -> dict[str, Any]:
        """Calibrated parameters, physical units, JSON-safe."""
        return {
            "effects": self.effects.to_dict(),
            "actuation_offset_ms": self.act_offset_s * 1e3,
            "response_offset_ms": self.resp_offset_s * 1e3,
        }


def _act_centre(model: SimModel, effects: EffectSet) -> Callable[[FloatArray], FloatArray]:
    """The projection that removes the linear actuation parameters from residuals: the
    mean (one constant) or the per-joint means (with per-joint levels), and the
    data-driven terms' bases (:func:`actuation_columns`)."""
    if data_terms(effects):
        q, _ = np.linalg.qr(actuation_columns(model, effects))

        def project(r: FloatArray) -> FloatArray:
            out: FloatArray = r - q @ (q.T @ r)
            return out

        return project
    if not joint_levels(effects):
        return lambda r: r - r.mean(axis=0)
    masks = list(model.joint_rows.values())

    def centre(r: FloatArray) -> FloatArray:
        out = np.array(r, dtype=float, copy=True)
        for mk in masks:
            out[mk] -= out[mk].mean(axis=0)
        return out

    return centre


def _linear_fit(
    model: SimModel, effects: EffectSet, sim: dict[str, FloatArray]
) -> tuple[EffectSet, float, float, dict[str, FloatArray]]:
    """Closed-form fit of the constants and the closed-form effects (per-joint levels,
    whole periods), each by its effect's ``fit_closed_form``."""
    cond = model.cond
    # The response constant is the packing phase: within one period (module docstring).
    bounds = {
        "actuation_delay": (-np.inf, np.inf),
        "response_delay": model.response_offset_bounds_s,
    }
    pred: dict[str, FloatArray] = {}
    offsets: dict[str, float] = {}
    for delay in DELAY_COLUMNS:
        y = cond.mean_s[delay] - sim[delay]
        term_shift = np.zeros(len(cond))
        terms = [t for t in data_terms(effects) if t.acts_on == delay]
        if terms:
            # The terms' coefficients with the actuation constants (one, or per joint):
            # least squares; what they leave goes to the other closed forms below.
            others = EffectSet(tuple(e for e in effects if not isinstance(e, DataTerm)))
            consts = actuation_columns(model, others)
            bases = [t.basis(model.pose) for t in terms]
            coef, *_ = np.linalg.lstsq(np.column_stack([consts, *bases]), y, rcond=None)
            col = consts.shape[1]
            for t, b in zip(terms, bases, strict=True):
                fitted_t = t.with_coefficients(
                    np.asarray(coef[col : col + b.shape[1]], dtype=np.float64)
                )
                effects = effects.with_effect(fitted_t)
                term_shift = term_shift + closed_form_shift_s(fitted_t, model)
                col += b.shape[1]
            y = y - term_shift
        shift: FloatArray | None = None
        for e in effects:
            if e.closed_form is not None and e.closed_form != "term" and e.acts_on == delay:
                fitted, offsets[delay] = type(e).fit_closed_form(
                    y, model.pose, model.period_s, bounds[delay]
                )
                effects = effects.with_effect(fitted)
                shift = closed_form_shift_s(fitted, model)
        if delay not in offsets:
            offsets[delay] = float(np.clip(y.mean(), *bounds[delay]))
        if shift is None:
            shift = np.zeros(len(cond))
        pred[delay] = sim[delay] + offsets[delay] + shift + term_shift
    return effects, offsets["actuation_delay"], offsets["response_delay"], pred


def _finite_jacobian(
    model: SimModel,
    effects: EffectSet,
    params: list[Param],
    x: FloatArray,
    s0: FloatArray,
) -> FloatArray:
    """Forward-difference sensitivity of the simulated actuation delay, (m, p); the
    parameters of one group (disjoint rows) are perturbed in one simulation."""
    m = len(model.cond)
    jac = np.zeros((m, len(params)))
    groups: dict[str, list[int]] = {}
    for k, p in enumerate(params):
        groups.setdefault(p.group, []).append(k)
    for members in groups.values():
        xs = x.copy()
        steps = {}
        for k in members:
            p = params[k]
            h = p.step if x[k] + p.step <= p.upper else -p.step
            xs[k] = x[k] + h
            steps[k] = h
        s1 = model.simulate(set_values(effects, params, xs))["actuation_delay"]
        for k in members:
            rows = params[k].rows
            diff = (s1 - s0) / steps[k]
            jac[:, k] = diff if rows is None else np.where(rows, diff, 0.0)
    return jac


def calibrate(
    model: SimModel,
    effects: EffectSet,
    *,
    max_nfev: int = 12,
    fit_simulated: bool = True,
) -> FittedModel:
    """Calibrate ``effects`` to the measured condition means.

    The simulated effects' parameters are fitted by bounded nonlinear least squares on the
    actuation condition means (scipy's trust-region reflective method) with the simulator
    in the loop and finite-difference sensitivities; the constants, joint offsets and extra
    cycles are projected out in closed form at every step (variable projection).

    Parameters
    ----------
    model : SimModel
    effects : EffectSet
        Effects and starting values.
    max_nfev : int
        Most simulator evaluations of the residual (each Jacobian costs one simulation per
        parameter group on top).
    fit_simulated : bool
        False: keep the simulated effects' parameters, fit only the linear part.
    """
    from scipy.optimize import least_squares

    params = model_params(effects, model)
    ya = model.cond.mean_s["actuation_delay"]
    centre = _act_centre(model, effects)
    nfev = 0
    info: dict[str, Any] = {}
    last: dict[str, Any] = {}
    if params and fit_simulated:
        x0 = get_values(effects, params)
        lower = np.array([p.lower for p in params])
        upper = np.array([p.upper for p in params])

        def sim_at(x: FloatArray) -> FloatArray:
            key = x.tobytes()
            if last.get("key") != key:
                last["key"] = key
                last["s"] = model.simulate(set_values(effects, params, x))["actuation_delay"]
            s: FloatArray = last["s"]
            return s

        def fun(x: FloatArray) -> FloatArray:
            # Residuals in ms keep the solver's tolerances meaningful.
            r: FloatArray = centre(ya - sim_at(x)) * 1e3
            return r

        def jac(x: FloatArray) -> FloatArray:
            j = _finite_jacobian(model, effects, params, x, sim_at(x))
            last["jac"] = j
            out: FloatArray = -centre(j) * 1e3
            return out

        res = least_squares(
            fun,
            x0,
            jac=jac,
            bounds=(lower, upper),
            method="trf",
            x_scale=np.array([p.step for p in params]) * 5.0,
            max_nfev=max_nfev,
            # Steps that change the sum of squares by < 0.1 % are far below the noise.
            xtol=1e-2,
            ftol=1e-3,
        )
        nfev = int(res.nfev)
        effects = set_values(effects, params, res.x)
        info = {"status": int(res.status), "message": str(res.message), "cost": float(res.cost)}
    sim = model.simulate(effects)
    x = get_values(effects, params)
    if not params:
        jac_final = np.zeros((len(model.cond), 0))
    elif "jac" in last:
        # The sensitivities of the last iteration: close enough to serve as nuisance columns.
        jac_final = last["jac"]
    else:
        jac_final = _finite_jacobian(model, effects, params, x, sim["actuation_delay"])
    effects, act_offset, resp_offset, pred = _linear_fit(model, effects, sim)
    resid = {d: model.cond.mean_s[d] - pred[d] for d in DELAY_COLUMNS}
    n_act = len(params) + (len(model.cond.joints) if joint_levels(effects) else 1)
    n_act += sum(t.n_columns for t in data_terms(effects))
    n_resp = 1 + sum(1 for e in effects if e.closed_form == "response_periods")
    return FittedModel(
        effects=effects,
        act_offset_s=act_offset,
        resp_offset_s=resp_offset,
        pred_s=pred,
        resid_s=resid,
        sim=sim,
        params=params,
        jac=jac_final,
        n_fitted={"actuation_delay": n_act, "response_delay": n_resp},
        nfev=nfev,
        info=info,
    )
