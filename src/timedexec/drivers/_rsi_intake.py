"""Where the RSI controller takes an answer, found by asking it: the RSI intake probe.

RSI is lock-step: the controller sends frame ``k`` (state sampled at the cycle boundary its
IPOC stamps), the PC answers it, and the correction is taken at a controller cycle boundary.
The host sees the frames' arrivals, which carry the time from sampling to sending (a twin's
packing phase wanders through 0.5-9.5 ms of the KR 5's 12 ms cycle over 47 s): dated by
arrival, or by the lower envelope of arrival minus IPOC time over a weld's few seconds, a
state's sampling instant and a command's action move with that phase from run to run.

The boundary itself does not move with it. :func:`find_answer_step` reads it from answers
the driver holds back on purpose (:meth:`~timedexec.drivers.KukaRSIDriver.probe_intake`,
the arm at rest): each trial answers one frame a chosen time after its arrival with a tiny
absolute correction (1e-4 rad, signs alternating) and counts the cycles until the
controller's set-point (``ASPos``) shows it. An answer sent after the boundary is taken one
cycle later, so the count steps up by one where the send time crosses the controller's
intake: that send time minus the frame's IPOC time is :attr:`RSIIntake.deadline_offset_s`,
the RSI counterpart of the UR's :class:`~timedexec.execution.IntakeFix` (whose
``dated`` gives the sampling boundary). A controller that takes every in-time answer at
the next frame (no step within the cycle) leaves no step: the probe says so.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["PLACE_MARGIN_S", "PLACE_NOMINAL_PERIODS", "RSIIntake", "find_answer_step"]

#: An answer sent less than this before the probed deadline counts as taken at the next
#: boundary, s. The probed deadline lay 0.07-0.84 ms after the RSI twin's boundary (the
#: largest where the packing phase is smallest: the step then lies at the end of the holds
#: tried), and answers sent at once to frames that leave just after a boundary (phase
#: 0.5-1 ms) fall right there; a wrong call moves that command's speed change by a whole
#: period. Sending less than 1 ms before a real deadline takes a host 2.5 ms or more late.
PLACE_MARGIN_S = 0.001

#: Nominal time from a ``speedj`` call to the boundary its answer is taken at, in periods:
#: a command issued right after frame ``k`` arrives leaves with the answer to frame
#: ``k + 1`` and is taken between one and two periods after the call. With the intake
#: probed, the driver places each command as if taken this long after its call
#: (:meth:`RSIIntake.placement_error_s`), whatever the frames' phase.
PLACE_NOMINAL_PERIODS = 1.5


def find_answer_step(
    phases_s: Sequence[float], latencies: Sequence[int | None], period_s: float
) -> tuple[float, int, int, int]:
    """The send phase where the answers' latency steps up by one cycle.

    ``latencies[m]`` (cycles until the set-point showed the answer, None if never) of an
    answer sent ``phases_s[m]`` (in [0, period)) after a fixed reference of its frame's
    cycle. Over one period the latency is ``base`` before the intake and ``base + 1`` after
    it; the step may also lie between the last phase and the period, where every trial
    shows ``base``. (The same search as the UR probe's, which lives in a layer above.)

    Returns
    -------
    (phase_s, mismatches, trials, base) : the step's phase (the middle of the bracketing
        pair, in [0, period)), the trials off the fitted step, the trials with an echo, the
        latency before the step (-1 without echoes; the phase is then NaN).
    """
    pairs = sorted(
        (float(p), int(v)) for p, v in zip(phases_s, latencies, strict=True) if v is not None
    )
    if not pairs:
        return math.nan, 0, 0, -1
    ph = [p[0] for p in pairs]
    lat = [p[1] for p in pairs]
    best: tuple[int, float, int] | None = None
    for base in sorted(set(lat)):
        for j in range(1, len(ph) + 1):  # the step lies after ph[j - 1] (j == len: wrap)
            miss = sum(v != base + (i >= j) for i, v in enumerate(lat))
            edge = ph[j] if j < len(ph) else period_s + ph[0]
            if best is None or miss < best[0]:
                best = (miss, 0.5 * (ph[j - 1] + edge) % period_s, base)
    assert best is not None
    return best[1], best[0], len(ph), best[2]


@dataclass(frozen=True)
class RSIIntake:
    """The RSI controller's intake on the host clock, from
    :meth:`~timedexec.drivers.KukaRSIDriver.probe_intake`.

    An answer sent before ``controller_time + deadline_offset_s + n * period_s`` (host time;
    ``controller_time`` any frame's IPOC time, ``n`` whole) is taken at that boundary, one
    sent after at the next.

    Attributes
    ----------
    deadline_offset_s : float
        Host send deadline minus the controller time of the frame answered, s.
    period_s : float
        RSI cycle, s.
    probed_at_s : float
        Host time of the probe, s.
    resolution_s : float
        Half the spacing of the send offsets tried around the step, s.
    arrival_offset_s : float
        Earliest frame arrival minus its controller time during the probe, s.
    latency_cycles : int
        Cycles from the frame answered to the first frame whose ``ASPos`` shows an answer
        taken before the step.
    trials, mismatches : int
        Answers whose echo was seen; those off the fitted step.
    """

    deadline_offset_s: float
    period_s: float
    probed_at_s: float
    resolution_s: float
    arrival_offset_s: float
    latency_cycles: int
    trials: int
    mismatches: int

    def deadline_after_s(self, controller_time_s: float, send_s: float) -> float:
        """The host deadline an answer sent at ``send_s`` makes (the first at or after it),
        for any frame of controller time ``controller_time_s``, s."""
        first = controller_time_s + self.deadline_offset_s
        return first + math.ceil((send_s - first) / self.period_s) * self.period_s

    def placement_error_s(self, controller_time_s: float, send_s: float, call_s: float) -> float:
        """How much later than :data:`PLACE_NOMINAL_PERIODS` after its call (``call_s``) a
        command leaving at ``send_s`` in the answer to a frame of ``controller_time_s`` is
        taken (within :data:`PLACE_MARGIN_S` of a deadline: at the next), s; the driver
        leads the command's speed change by this."""
        taken = self.deadline_after_s(controller_time_s, send_s + PLACE_MARGIN_S)
        return taken - call_s - PLACE_NOMINAL_PERIODS * self.period_s

    def summary(self) -> dict[str, float | int]:
        """JSON-safe description (times in ms)."""
        return {
            "deadline_offset_ms": self.deadline_offset_s * 1e3,
            "resolution_ms": self.resolution_s * 1e3,
            "arrival_offset_ms": self.arrival_offset_s * 1e3,
            "latency_cycles": self.latency_cycles,
            "trials": self.trials,
            "mismatches": self.mismatches,
        }
