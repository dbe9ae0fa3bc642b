"""One integration step of one drive, in plain floats (the physics of
:mod:`timedexec.sim._physics`; its own module so that the compiled bank step,
:mod:`timedexec.sim._kernel`, and the Python chain import it without importing each other).
"""

from __future__ import annotations

import math

__all__ = ["_drive_step"]


def _drive_step(  # type: ignore[no-untyped-def]
    grav_a, grav_b, kp, ki, alpha, inv_j, torque_max, breakaway_pos, breakaway_neg,
    kinetic_pos, kinetic_neg, viscous, dt, q, v, tau_m, integ, stuck, v_ref,
):  # fmt: skip
    """One integration step of one drive (see the module docstring), in plain floats: the
    coefficients (the fields of ``_physics._Coefficients``), the step, then the state.
    Returns ``(q, v, tau_m, integ, stuck)`` after the step.

    Written once: :class:`~timedexec.sim._physics.JointChain` runs it as Python,
    :class:`~timedexec.sim._physics.JointBank` compiled by Numba over its elements
    (:mod:`timedexec.sim._kernel`); the same IEEE operations in the same order, so both
    give the same bits (``tests/test_sim.py`` steps them in lockstep)."""
    tau_g = grav_a * math.cos(q) + grav_b * math.sin(q)
    err = v_ref - v
    integ_new = integ + err * dt
    tau_cmd = tau_g + kp * err + ki * integ_new
    limited = min(max(tau_cmd, -torque_max), torque_max)
    # Conditional integration (anti-windup): keep the integrator where the limit binds.
    if limited == tau_cmd:
        integ = integ_new
    tau_m = tau_m + alpha * (limited - tau_m)
    net = tau_m - tau_g
    # Breakaway: a stuck joint starts when the net torque beats static friction.
    moving = (not stuck) or net > breakaway_pos or net < -breakaway_neg
    if v > 0.0:
        direction = 1.0
    elif v < 0.0:
        direction = -1.0
    else:
        direction = 1.0 if net > 0.0 else (-1.0 if net < 0.0 else 0.0)
    friction = (kinetic_pos if direction > 0.0 else -kinetic_neg) + viscous * v
    acc = (net - friction) * inv_j
    v_new = v + acc * dt if moving else 0.0
    # Stick at a velocity reversal: the joint stops and must break away again. Coming to
    # rest without a reversal (the loop settles asymptotically): stick once the speed is
    # negligible and the drive torque cannot break the joint free again.
    reversal = moving and (
        v_new * direction < 0.0
        or (abs(v_new) < 1e-7 and net <= breakaway_pos and net >= -breakaway_neg)
    )
    if reversal:
        v_new = 0.0
    if moving:
        stuck = reversal
    q = q + 0.5 * (v + v_new) * dt
    return q, v_new, tau_m, integ, stuck
