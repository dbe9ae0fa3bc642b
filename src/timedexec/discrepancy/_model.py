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

Two effects are exact additive shifts of the simulator's output and are applied here in
closed form instead of by simulation (``test_linear_effects_are_additive`` checks it):
``joint_offset`` (each joint's drive takes the reference later: the onset moves by the
offset) and ``response_extra_cycle`` (every package leaves ``cycles`` periods later).
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

from timedexec.delays import DELAY_COLUMNS
from timedexec.discrepancy._conditions import Conditions
from timedexec.effects import (
    Direction,
    Effect,
    EffectSet,
    GravityDirection,
    GravityLoad,
    Inertia,
    JointOffset,
    ResponseExtraCycle,
    ThermalDrift,
)
from timedexec.robots import RobotSpec, joint_inertia
from timedexec.sim import SimSettings, default_settings, simulate_delays

__all__ = [
    "LINEAR_EFFECTS",
    "SIMULATED_EFFECTS",
    "FittedModel",
    "Param",
    "SimModel",
    "calibrate",
    "model_params",
]

FloatArray = NDArray[np.float64]

#: Effects that change the joint physics: the simulator runs them.
SIMULATED_EFFECTS = ("gravity_load", "gravity_direction", "direction", "inertia", "thermal_drift")
#: Effects that shift the simulator's output by a constant per joint or per package.
LINEAR_EFFECTS = ("joint_offset", "response_extra_cycle")
#: Largest ``response_extra_cycle.cycles`` the calibration tries.
MAX_EXTRA_CYCLES = 4
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
        self.true_inertia_kgm2 = joint_inertia(spec, cond.q_rad)[np.arange(m), cond.joint - 1]
        self.joint_rows = {j: cond.joint == j for j in cond.joints}
        self._rows = np.arange(m)

    @property
    def response_offset_bounds_s(self) -> tuple[float, float]:
        """Allowed range of ``resp_offset_s``: the mean packing phase within one period."""
        return -self.phase_s, self.period_s - self.phase_s

    def simulate(
        self, effects: EffectSet, rows: NDArray[np.bool_] | None = None
    ) -> dict[str, FloatArray]:
        """Simulated condition means for the simulated part of ``effects`` (linear effects
        are ignored here). With ``rows``, only those conditions are simulated (the others
        are NaN). Returns ``actuation_delay``, ``response_delay`` (s) and
        ``gravity_torque_nm`` of every condition, arrays (m,)."""
        physical = EffectSet(tuple(e for e in effects if e.name in SIMULATED_EFFECTS))
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
    """The free parameters of the simulated effects in ``effects``."""
    out: list[Param] = []
    for e in effects:
        if e.name in ("gravity_load", "gravity_direction"):
            out.append(Param(e.name, "friction_per_load", None, False, 0.0, 3.0, 0.03, e.name))
        elif e.name == "direction":
            for j in model.cond.joints:
                out.append(
                    Param(
                        e.name,
                        "asymmetry",
                        j - 1,
                        False,
                        -0.85,
                        0.85,
                        0.04,
                        e.name,
                        model.joint_rows[j],
                    )
                )
        elif e.name == "inertia":
            out.append(
                Param(e.name, "scale", None, True, math.log(0.05), math.log(20.0), 0.1, e.name)
            )
        elif e.name == "thermal_drift":
            out.append(Param(e.name, "cold_excess", None, False, 0.0, 5.0, 0.04, e.name + ".c"))
            out.append(
                Param(
                    e.name,
                    "time_constant_s",
                    None,
                    True,
                    math.log(60.0),
                    math.log(1e6),
                    0.1,
                    e.name + ".t",
                )
            )
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
    """The effect ``name`` at the magnitude its candidate signature is simulated with.

    Vocabulary defaults, except that ``direction`` uses one asymmetry (0.2) on every joint
    and ``thermal_drift`` a time constant of the sweep's length (at least 10 min), so that
    its signature has the shape of a warm-up seen within the sweep.
    """
    if name == "gravity_load":
        return GravityLoad()
    if name == "gravity_direction":
        return GravityDirection()
    if name == "direction":
        return Direction(asymmetry=(0.2,) * 6)
    if name == "inertia":
        return Inertia()
    if name == "thermal_drift":
        t = model.cond.t_start_s
        span = float(t.max() - t.min()) if len(t) else 0.0
        return ThermalDrift(cold_excess=0.6, time_constant_s=max(600.0, span))
    if name == "joint_offset":
        return JointOffset(offsets_s=(0.0,) * 6)
    if name == "response_extra_cycle":
        return ResponseExtraCycle()
    raise KeyError(name)


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
    mean (one constant) or the per-joint means (with ``joint_offset``)."""
    if "joint_offset" not in effects:
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
    """Closed-form fit of the constants, the joint offsets and the extra cycles."""
    cond = model.cond
    ya = cond.mean_s["actuation_delay"] - sim["actuation_delay"]
    if "joint_offset" in effects:
        means = {j: float(ya[mk].mean()) for j, mk in model.joint_rows.items()}
        base = min(means.values())
        offsets = [0.0] * 6
        for j, mu in means.items():
            offsets[j - 1] = min(mu - base, 0.05)
        effects = effects.with_effect(JointOffset(offsets_s=tuple(offsets)))
        act_offset = base
        shift = np.asarray(offsets)[cond.joint - 1]
    else:
        act_offset = float(ya.mean())
        shift = np.zeros(len(cond))
    pred_a = sim["actuation_delay"] + act_offset + shift
    yr = cond.mean_s["response_delay"] - sim["response_delay"]
    lo, hi = model.response_offset_bounds_s
    if "response_extra_cycle" in effects:
        best: tuple[float, int, float] | None = None
        for k in range(1, MAX_EXTRA_CYCLES + 1):
            off = float(np.clip(yr.mean() - k * model.period_s, lo, hi))
            ss = float(np.sum((yr - k * model.period_s - off) ** 2))
            if best is None or ss < best[0] - 1e-15:
                best = (ss, k, off)
        assert best is not None
        _, cycles, resp_offset = best
        effects = effects.with_effect(ResponseExtraCycle(cycles=cycles))
        extra = cycles * model.period_s
    else:
        resp_offset = float(np.clip(yr.mean(), lo, hi))
        extra = 0.0
    pred_r = sim["response_delay"] + resp_offset + extra
    pred = {"actuation_delay": pred_a, "response_delay": pred_r}
    return effects, act_offset, resp_offset, pred


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
    n_act = len(params) + (len(model.cond.joints) if "joint_offset" in effects else 1)
    n_resp = 1 + (1 if "response_extra_cycle" in effects else 0)
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
