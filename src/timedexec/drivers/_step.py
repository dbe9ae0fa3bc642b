"""The one step search of the intake probes: where a command's echo latency goes up a cycle.

Both intake probes, the UR's (:func:`timedexec.execution.probe_intake`, ``target_qd``
echoes of tiny ``speedj`` commands) and RSI's (:meth:`~timedexec.drivers.KukaRSIDriver.
probe_intake`, ``ASPos`` echoes of held answers), send trials at phases spread over a
controller cycle and count the cycles until the controller shows each: the count steps up
by one where the send time crosses the controller's intake. :func:`find_latency_step` fits
that step, the same way for both.

A command reaches the controller late or on time, never early: host preemption around the
send and a loaded link or receiver delay it (on a loaded two-core host, 0.3-2 ms from the
send to the independent UR peer's register, 0.1 ms idle), so a trial that missed an intake
is often a delayed one; a trial that made an intake past the deadline needs the intake
itself to run late, which is rarer. Equal weights put the step at the first of a run of
delayed trials before the deadline (a whole step early: the UR CI failure of 2026-11-28),
so a trial showing fewer cycles than the step says weighs :data:`EARLY_WEIGHT` times.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["EARLY_WEIGHT", "LatencyStep", "find_latency_step"]

#: Weight of a trial that made an intake the fitted step says it missed, against 1 for one
#: that missed an intake the step says it made (module docstring): the fit calls a hit an
#: outlier only where explaining it as the step would take more than three delayed misses.
EARLY_WEIGHT = 3


@dataclass(frozen=True, kw_only=True)
class LatencyStep:
    """The fitted step of :func:`find_latency_step`.

    Attributes
    ----------
    phase_s : float
        The intake's send phase: the middle of the pair of trials bracketing the step, in
        [0, period), s (NaN without echoes).
    gap_s : float
        The distance between that pair, s (NaN without echoes).
    mismatches : int
        Trials off the fitted step.
    trials : int
        Trials with an echo.
    rival_s : float
        How far from ``phase_s`` the farthest rival step lies that the trials favour less
        than one outlier would (a cost within :data:`EARLY_WEIGHT` of the best), s; 0 where
        none: one clear step.
    base : int
        The latency before the step, cycles (-1 without echoes).
    """

    phase_s: float
    gap_s: float
    mismatches: int
    trials: int
    rival_s: float
    base: int


def find_latency_step(
    phases_s: Sequence[float], latencies: Sequence[int | None], period_s: float
) -> LatencyStep:
    """The send phase where the echo latency steps up by one cycle.

    Parameters
    ----------
    phases_s : sequence of float (n,)
        Each trial's send time after a fixed reference of its cycle, in [0, period), s, any
        order (trials at one phase are not split).
    latencies : sequence of int or None (n,)
        Each trial's echo latency, cycles (None: lost). Over one period the latency is
        ``base`` before the intake and ``base + 1`` after it; the step may also lie between
        the last phase and the period, where every trial shows ``base``.
    period_s : float
        Controller period, s.

    Returns
    -------
    LatencyStep
        The step minimising the trials off it, a trial showing fewer cycles than the step
        says counting :data:`EARLY_WEIGHT` times (the first of equal fits).
    """
    obs = sorted(
        (float(p), int(v)) for p, v in zip(phases_s, latencies, strict=True) if v is not None
    )
    if not obs:
        return LatencyStep(phase_s=math.nan, gap_s=math.nan, mismatches=0, trials=0,
                           rival_s=0.0, base=-1)  # fmt: skip
    ph = [p for p, _ in obs]
    lat = [v for _, v in obs]
    fits: list[tuple[int, int, float, float, int]] = []  # (cost, off, phase, gap, base)
    for base in sorted(set(lat)):
        for j in range(1, len(ph) + 1):  # the step lies after ph[j - 1] (j == len: wrap)
            if j < len(ph) and ph[j] == ph[j - 1]:
                continue  # not between trials sent at one phase
            late = sum(v > base + (i >= j) for i, v in enumerate(lat))
            early = sum(v < base + (i >= j) for i, v in enumerate(lat))
            edge = ph[j] if j < len(ph) else period_s + ph[0]
            phase = 0.5 * (ph[j - 1] + edge) % period_s
            fits.append((late + EARLY_WEIGHT * early, late + early, phase, edge - ph[j - 1], base))
    best = min(fits, key=lambda f: f[0])  # the first of equals
    rival = max(
        abs((f[2] - best[2] + 0.5 * period_s) % period_s - 0.5 * period_s)
        for f in fits
        if f[0] < best[0] + EARLY_WEIGHT
    )
    return LatencyStep(phase_s=best[2], gap_s=best[3], mismatches=best[1], trials=len(ph),
                       rival_s=rival, base=best[4])  # fmt: skip
