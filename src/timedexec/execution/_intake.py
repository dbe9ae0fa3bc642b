"""The controller's intake, found by asking the controller: when a command must leave.

A controller takes its command register once per cycle. Where that intake lies against
the state packages the host sees depends on when the controller's publisher sends them
within the cycle, which the host cannot see. The envelope lock (:mod:`._cycle`) assumes a
package leaves right after the boundary; a host that answers each package at once assumes
the same. Where a package leaves late in the cycle (the twin's publisher wanders through
2-97 % of the period; a UR10 weld with the package 7.4 ms into an 8 ms cycle put every
command 0.03-0.6 ms before the intake), the commands reach the controller right at the
boundary, one cycle gets two and the next none, and a velocity stream integrates the
difference: the tracking lag of that weld changed by up to 15 ms on some joints.

The UR's state carries ``target_qd``, the speed the controller is commanding, so the
controller tells which cycle took a command. :func:`probe_intake`, with the arm at rest,
sends one tiny ``speedj`` (1e-4 rad/s, signs alternating: the arm moves by microradians) at
each of ``phases`` send times spread over a cycle after a package and counts the cycles
until ``target_qd`` shows it (another round of ``phases``, up to three, while the answer
is not clean). The count steps up by one where the send time crosses the intake: that is
the deadline of each cycle on the host clock, independent of when the packages leave. The
lock then aims half a period before it (:class:`IntakeFix`), and a clock line keeps it on
the host clock as the clocks drift (:class:`~._cycle.BoundaryLine`).

A loaded host or link only ever delays a command (on a two-core host beside two busy
loops, 0.3-2.4 ms from the send to the independent peer's register, against 0.1 ms idle),
so a trial right before the deadline can miss its intake, and one round cannot tell that
from a deadline a step earlier: the CI run of 2026-11-28 dated the samples 0.50 ms early
that way. The fit (:func:`timedexec.drivers.find_latency_step`, the RSI probe's too)
therefore weighs a trial that made an intake the step says it missed three times one that
missed, and the probe re-tests the two send phases that bracket the step until it stays
put (:data:`CONFIRM_STABLE`); how far it still moved widens ``resolution_s``. What no probe can see is a link slow on every send (the
deadline it finds is then the one this host can make, earlier by the extra delay; beside
the busy loops the dating came out -0.38 to +0.26 ms off the peer's truth).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from timedexec._realtime import wait_until
from timedexec.drivers import RobotState, find_latency_step
from timedexec.errors import DriverError
from timedexec.execution._cycle import IntakeFix

__all__ = ["PROBE_PHASES", "PROBE_SPEED_RAD_S", "probe_intake"]

#: Speed of each probe command, rad/s (every joint; 1e-4 rad/s for a few cycles moves a
#: joint by microradians, and signs alternate so the arm ends where it started).
PROBE_SPEED_RAD_S = 1e-4
#: Send times tried over one cycle: the deadline is known to half of period / phases.
PROBE_PHASES = 16
#: Packages to wait for a probe's echo before the trial counts as lost.
ECHO_PACKAGES = 12
#: Controller time after which a probe command still without its echo is sent again, s
#: (half the 100 ms the controller's watchdog allows between commands).
FEED_S = 0.05
#: Trials off the fitted step that a clean coarse round may hold, or one in four where
#: more (a link too loaded to trust, or a target that does not follow the commands):
#: then another round of ``phases``.
MAX_MISMATCHES = 2
#: Coarse rounds of ``phases`` trials at most (another while the round is not clean).
PROBE_ROUNDS = 3
#: Re-tests of the two send phases that bracket the step (alternately the one before and
#: the one after), until the step has stayed within a quarter step over this many in a
#: row: 4 where every trial so far fits the step, 8 where any was off it (a loaded host:
#: each trial is weaker evidence). How far it moved over the last of them widens
#: ``resolution_s``.
CONFIRM_STABLE = 4
CONFIRM_STABLE_LOADED = 8
#: Re-tests at most (~3 cycles each).
CONFIRM_TRIALS = 16


def probe_intake(
    read: Callable[[], RobotState],
    send: Callable[[np.ndarray], None],
    clock: Callable[[], float],
    period_s: float,
    reference_offset_s: float,
    *,
    phases: int = PROBE_PHASES,
    speed_rad_s: float = PROBE_SPEED_RAD_S,
    wait: Callable[[float], object] | None = None,
) -> IntakeFix:
    """Find the controller's command deadline (see the module docstring). The arm must be at
    rest and the state must carry ``target_qd``.

    Parameters
    ----------
    read : callable
        The next state package (the caller's clock model ingests it).
    send : callable
        Sends a joint speed (6,), rad/s, as a ``speedj`` that ramps within one cycle.
    clock : callable
        Host time, s.
    period_s : float
        Controller period, s.
    reference_offset_s : float
        The earliest package arrival minus controller time at the start (the clock model's
        envelope), s: the send times are ``controller_time + reference_offset_s + phase``.
    wait : callable, optional
        Lets the host clock reach a time (default: sleep and spin on ``clock``; a virtual
        clock needs its driver's).

    Raises
    ------
    DriverError
        The state has no ``target_qd``, the echoes do not show one clean step after
        :data:`PROBE_ROUNDS` rounds (a target that does not show the commands, or a host,
        link or controller that jitters by cycles), or the stream stalls.
    """
    step = period_s / phases
    if wait is None:

        def wait(t_s: float) -> object:
            return wait_until(t_s, clock)

    # (phase sent at, latency) per trial: the phase is read before the send, so a send the
    # host made late (preempted in the call) is a delay like any other, which the fit
    # weighs as such.
    observed: list[tuple[float, int | None]] = []
    leads: list[float] = []
    sign = 1.0

    def trial(phase_s: float) -> tuple[float, float, int, int, float]:
        nonlocal sign
        if phase_s < 0.5 * step:  # at the earliest arrival the package is rarely read yet:
            phase_s += period_s  # a period later (the same phase of the intake)
        sent, lat = _trial(read, send, clock, wait, base_s=reference_offset_s, phase_s=phase_s,
                           speed=sign * speed_rad_s, period_s=period_s, leads=leads)  # fmt: skip
        # On the grid, down: repeated phases fall together (the fit cannot split a phase's
        # trials by their µs of jitter), and a send the host made late by a fraction of a
        # step is placed earlier, which like any delay can make it miss, never make it.
        observed.append((math.floor(sent / step + 1e-6) * step % period_s, lat))
        sign = -sign
        fit = find_latency_step([p for p, _ in observed], [v for _, v in observed], period_s)
        return fit.phase_s, fit.gap_s, fit.mismatches, fit.trials, fit.rival_s

    positions: list[float] = []  # the step's phase after each re-test

    def last_positions() -> list[float]:
        return positions[-(CONFIRM_STABLE_LOADED if miss else CONFIRM_STABLE) :]

    def settled() -> bool:
        window = last_positions()
        return len(window) == (CONFIRM_STABLE_LOADED if miss else CONFIRM_STABLE) and (
            _span(window, period_s) < 0.25 * step
        )

    try:
        for _round in range(PROBE_ROUNDS):
            for m in range(phases):
                phase, gap, miss, trials, rival = trial(m * step)
            clean = trials >= len(observed) // 2 and miss <= max(MAX_MISMATCHES, trials // 4)
            if clean:
                break
        # Re-test the send phases either side of the step (alternately) until the step
        # stays put: a run of delayed trials right before the deadline moves it back up,
        # an intake that ran late once moves it back down.
        for k in range(CONFIRM_TRIALS if clean else 0):
            if settled():
                break
            side = 0.5 * gap if k % 2 else -0.5 * gap  # the pair of phases bracketing it
            phase, gap, miss, trials, rival = trial((phase + side) % period_s)
            positions.append(phase)
    finally:
        send(np.zeros(6))
    _settle(read, speed_rad_s)
    if not clean:
        seen_text = ", ".join("-" if v is None else str(v) for _, v in observed)
        raise DriverError(
            f"intake probe: the echo latencies over {len(observed)} sends ({seen_text} "
            f"cycles, in send order) show no single step ({trials} echoes, {miss} off "
            "the step): the controller's target_qd does not follow the commands cycle by "
            "cycle, or the link jitters by more than a period; the cycle lock aims by the "
            "package arrivals instead"
        )
    # Half a step at best (repeated phases bracket the step no closer than the grid), and
    # half of how far the step still moved over the last re-tests, or as far as a rival
    # step the trials hardly tell from it (a link that delays most sends near the
    # deadline; the probe's benchmark once settled 0.88 ms early with 11 of 31 trials off).
    resolution = 0.5 * max(gap, step) + max(0.5 * _span(last_positions(), period_s), rival)
    deadline = reference_offset_s + phase
    # The echo of a command that made this deadline, in packages after the one it answered:
    # each trial's latency, one less where it was sent after the step (the fitted step may
    # lie past the last phase tried, reported wrapped to the period's start: then every
    # trial was sent "after" it and the deadline is the previous cycle's).
    echo = round(float(np.median([v - (p >= phase) for p, v in observed if v is not None])))
    lead = (min(leads) - deadline) % period_s
    return IntakeFix(
        deadline_offset_s=deadline,
        period_s=period_s,
        probed_at_s=clock(),
        resolution_s=resolution,
        package_lead_s=lead,
        trials=trials,
        mismatches=miss,
        arrival_offset_s=min(leads),
        echo_cycles=echo,
    )


def _span(phases_s: Sequence[float], period_s: float) -> float:
    """The range of phases that may wrap around the period (all within half of one), s (0
    for none)."""
    if not phases_s:
        return 0.0
    rel = [(p - phases_s[-1] + 0.5 * period_s) % period_s for p in phases_s]
    return max(rel) - min(rel)


def _trial(
    read: Callable[[], RobotState],
    send: Callable[[np.ndarray], None],
    clock: Callable[[], float],
    wait: Callable[[float], object],
    *,
    base_s: float,
    phase_s: float,
    speed: float,
    period_s: float,
    leads: list[float],
) -> tuple[float, int | None]:
    """One probe command ``phase_s`` after a package's earliest arrival (``controller time
    + base_s``): (the phase it was actually sent at, in [0, period), the echo's latency in
    cycles or None). A package that comes after the send time: the next one (3 tries)."""
    for _attempt in range(3):
        ref = read()
        if ref.target_qd is None:
            raise DriverError(
                "the controller's state has no target_qd: the intake cannot be probed "
                "(the cycle lock aims by the package arrivals instead)"
            )
        leads.append(ref.host_time_s - ref.controller_time_s)
        base = ref.controller_time_s + base_s
        if clock() >= base + phase_s:
            continue
        wait(base + phase_s)
        sent = clock() - base
        send(np.full(6, speed))
        lat = _echo_latency(read, send, ref.controller_time_s, speed, period_s)
        wraps = math.floor(sent / period_s)
        return sent - wraps * period_s, None if lat is None else lat - wraps
    return phase_s, None


def _echo_latency(
    read: Callable[[], RobotState],
    send: Callable[[np.ndarray], None],
    ref_controller_s: float,
    speed: float,
    period_s: float,
) -> int | None:
    """Cycles from the reference package to the first whose ``target_qd`` shows ``speed``.

    While the echo is missing the command is sent again every :data:`FEED_S` of controller
    time: the controller's watchdog wants a command every 100 ms (10 Hz) and 12 packages of
    a CB3 are 96 ms, so a lost or late echo on a loaded host let it stop the program
    mid-probe. A repeat leaves the host after the first send, so the controller takes it in
    the same cycle or a later one: it cannot make the echo earlier. Where the first send
    was lost, the repeat's echo comes cycles later than any other trial's and the fit
    counts it off the step (a long pipeline's echo, the simulated KR 5's ~6 cycles, comes
    before any repeat could show)."""
    command = np.full(6, speed)
    fed_s = ref_controller_s
    for _ in range(ECHO_PACKAGES):
        state = read()
        tqd = state.target_qd
        if tqd is not None and float(np.mean(tqd)) * math.copysign(1.0, speed) > 0.5 * abs(speed):
            return round((state.controller_time_s - ref_controller_s) / period_s)
        if state.controller_time_s - fed_s >= FEED_S:
            send(command)
            fed_s = state.controller_time_s
    return None


def _settle(read: Callable[[], RobotState], speed: float) -> None:
    """Read until the target speed is back at zero (the last probe's ramp down)."""
    for _ in range(ECHO_PACKAGES):
        tqd = read().target_qd
        if tqd is None or float(np.max(np.abs(tqd))) < 0.5 * abs(speed):
            return
