"""Where the RSI controller takes an answer, found by asking it: the RSI intake probe.

RSI is lock-step: the controller sends frame ``k`` (state sampled at the cycle boundary its
IPOC stamps), the PC answers it, and the correction is taken at a controller cycle boundary.
The host sees the frames' arrivals, which carry the time from sampling to sending (a twin's
packing phase wanders through 0.5-9.5 ms of the KR 5's 12 ms cycle over 47 s): dated by
arrival, or by the lower envelope of arrival minus IPOC time over a weld's few seconds, a
state's sampling instant and a command's action move with that phase from run to run.

The boundary itself does not move with it. :func:`~timedexec.drivers.find_latency_step` (the
UR probe's step search too, a delayed answer weighed as such) reads it from answers
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
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from timedexec._realtime import wait_until
from timedexec._types import FloatArray
from timedexec.drivers._step import LatencyStep, find_latency_step
from timedexec.errors import DriverError

__all__ = [
    "PLACE_MARGIN_S",
    "PLACE_NOMINAL_PERIODS",
    "PROBE_LATE_WINDOW_S",
    "AnswerShaping",
    "RSIIntake",
    "probe_intake",
]

#: The probe counts a frame late against the fastest frame of this window, s (a phase
#: drifts, ~0.4 ms/s on the twin).
PROBE_LATE_WINDOW_S = 0.5

#: An answer sent less than this before the probed deadline counts as taken at the next
#: boundary, s. The probed deadline lay 0.07-0.84 ms after the RSI twin's boundary with an
#: equal-weight step fit (the most where the packing phase is smallest: the step then lies
#: at the end of the holds tried; -0.18 to +0.48 ms over seeds 1-4 with the weighted fit of
#: :func:`~timedexec.drivers.find_latency_step`), and answers sent at once to frames that leave just after a boundary (phase
#: 0.5-1 ms) fall right there; a wrong call moves that command's speed change by a whole
#: period. With 1 ms, a host 2 ms late on frames that leave 9 ms into the cycle was
#: miscounted the other way (8 ms too little lag on joints 1, 4, 6 in one weld).
PLACE_MARGIN_S = 0.0005

#: Nominal time from a ``speedj`` call to the boundary its answer is taken at, in periods:
#: a command issued right after frame ``k`` arrives leaves with the answer to frame
#: ``k + 1`` and is taken between one and two periods after the call. With the intake
#: probed, the driver places each command as if taken this long after its call
#: (:meth:`RSIIntake.placement_error_s`), whatever the frames' phase.
PLACE_NOMINAL_PERIODS = 1.5


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


class AnswerShaping:
    """What the RSI driver's answer thread adds to the integrated correction: the intake
    probe's held answers and offsets, and, once probed, each command's placement (the
    driver's command lock guards ``request``, ``sent`` and :meth:`use`).

    Attributes
    ----------
    request : (float, ndarray) or None
        For the next frame's answer: hold it this long after the frame's arrival, s, with
        this absolute offset, rad (6,).
    sent : (int, float, float) or None
        The held answer's frame IPOC, its controller time and its send time, s.
    offset_rad : ndarray (6,)
        The probe's offset in force, rad.
    intake : RSIIntake or None
        The probed intake; ``place``: whether commands are placed by it.
    lead_rad : ndarray (6,)
        The sum of the commands' speed changes times their placement errors, rad.
    """

    def __init__(self) -> None:
        self.request: tuple[float, FloatArray] | None = None
        self.sent: tuple[int, float, float] | None = None
        self.reset()

    def reset(self) -> None:
        """A new RSI session: no intake, no lead, no probe offset."""
        self.intake: RSIIntake | None = None
        self.place = False
        self.lead_rad = np.zeros(6)
        self.offset_rad = np.zeros(6)

    def use(self, intake: RSIIntake, place: bool) -> None:
        """Place the commands from now on by ``intake`` (if ``place``)."""
        self.intake, self.place, self.lead_rad = intake, place, np.zeros(6)

    def total(
        self,
        corr: FloatArray,
        lo: FloatArray,
        hi: FloatArray,
        t_rx: float,
        controller_s: float,
        probe: tuple[float, FloatArray] | None,
        cmd: Any,
        target_before: FloatArray,
    ) -> FloatArray:
        """The absolute correction of this answer, rad (6,): ``corr`` (the profile's) plus
        the lead inside [``lo``, ``hi``], plus the probe's offset; holds the answer as the
        probe asked (``probe``: its request for this frame, arrived at ``t_rx``). ``cmd``:
        the command applied at this frame (None: none), ``target_before`` the speeds it
        replaced, rad/s."""
        if probe is not None:
            self.offset_rad = probe[1]
            if probe[0] > 0.0:
                wait_until(t_rx + probe[0], time.monotonic)
        if self.intake is not None and self.place and cmd is not None:
            # The speed change this command makes, placed when its call meant it.
            late_s = self.intake.placement_error_s(controller_s, time.monotonic(), cmd.call_host_s)
            self.lead_rad = self.lead_rad + (np.asarray(cmd.qd) - target_before) * late_s
        return np.asarray(np.clip(corr + self.lead_rad, lo, hi) + self.offset_rad)


def probe_intake(
    drv: Any, *, phases: int = 16, rounds: int = 3, fine: int = 8, offset_rad: float = 1e-4
) -> RSIIntake:
    """Find where the controller takes an answer (module docstring) through a connected
    :class:`~timedexec.drivers.KukaRSIDriver` ``drv``, the arm at rest.

    Each trial holds the answer to one frame back by one of ``phases`` times spread over a
    cycle, with an absolute correction of ``offset_rad`` on every axis (signs alternating;
    zero again at the end), and counts the cycles until ``ASPos`` shows it; the count steps
    up by one where the send time crosses the intake. Another round while the step is not
    clean (``rounds`` at most), then ``fine`` trials within a spacing of it (kept if clean).
    A trial's phase is its send time less its frame's IPOC time, less how late that frame
    came against the fastest of the last :data:`PROBE_LATE_WINDOW_S` (the RSI twin answers
    a frame it sent late as if it had left on time).

    Raises
    ------
    DriverError
        RSI not running, the arm moving, frames without ``ASPos``, or no clean step (the
        message lists the latencies seen: a controller that takes every in-time answer at
        the next frame shows none).
    """
    period = drv.controller_period_s
    timeout = max(0.5, 20 * period)
    leads: list[float] = []
    late: dict[int, float] = {}  # ipoc -> how late the frame came (see below)

    def read() -> Any:
        st = drv.read_state(timeout_s=timeout)
        lead = st.host_time_s - st.controller_time_s
        leads.append(lead)
        # Against the fastest of the last half second (a phase drifts, ~0.4 ms/s on the
        # twin): a frame the controller sent late is answered as if on time there.
        late[st.ipoc] = lead - min(leads[-round(PROBE_LATE_WINDOW_S / period) :])
        return st

    state = read()  # the first frame may take the driver's first-frame wait
    drv._require_active("probe the intake")
    if float(np.max(np.abs(drv._profile.v))) > 0.0 or drv._pending is not None:
        raise DriverError("probe_intake needs the arm at rest with no command pending")
    if state.q_setpoint is None:
        raise DriverError(
            "probe_intake needs the set-point in the frames: add ASPos to the RSI "
            "configuration's SEND list"
        )
    # Per trial: the hold asked for, the send time minus the frame's controller time,
    # the cycles until ASPos showed it.
    trials: list[tuple[float, float, int | None]] = []
    sign = 1.0

    def trial(hold_s: float) -> None:
        nonlocal sign
        offset_s, cycles, ipoc = _trial(drv, read, hold_s, sign * offset_rad)
        trials.append((hold_s, offset_s - late.get(ipoc, 0.0), cycles))
        sign = -sign

    def fit() -> LatencyStep:
        ref = min(leads)
        kept = [(o - ref, lat) for _, o, lat in trials if 0.0 <= o - ref < period]
        return find_latency_step([k[0] for k in kept], [k[1] for k in kept], period)

    clean = False
    try:
        for _round in range(rounds):
            for m in range(phases):
                trial(m * period / phases)
            step = fit()
            clean = step.trials >= len(trials) // 2 and _few_off(step)
            if clean:
                break
        if clean and fine > 0:  # a finer look at the step: holds within a spacing of it
            ref = min(leads)
            lag = float(np.median([o - ref - h for h, o, lat in trials if lat is not None]))
            spacing = period / phases
            for hold in np.linspace(-spacing, spacing, fine) + step.phase_s - lag:
                if 0.0 <= hold < period - spacing:
                    trial(float(hold))
            refined = fit()
            if _few_off(refined):
                step = refined  # else the coarse step stands
    finally:
        _trial(drv, read, 0.0, 0.0)  # the arm back where it was
    if not clean:
        seen = ", ".join("-" if lat is None else str(lat) for _, _, lat in sorted(trials))
        raise DriverError(
            f"RSI intake probe: the set-point latencies over {len(trials)} held answers "
            f"({seen} cycles, by hold) show no single step ({step.trials} echoes, "
            f"{step.mismatches} off "
            "the best step): the controller takes every in-time answer at the same "
            "cycle, or the host jitters by more than a period; commands stay placed by "
            "their calls"
        )
    # Half the bracketing pair's distance, or as far as a rival step the trials hardly tell
    # from it (the UR probe's rule).
    return RSIIntake(
        deadline_offset_s=min(leads) + step.phase_s,
        period_s=period,
        probed_at_s=time.monotonic(),
        resolution_s=0.5 * step.gap_s + step.rival_s,
        arrival_offset_s=min(leads),
        latency_cycles=step.base,
        trials=step.trials,
        mismatches=step.mismatches,
    )


def _few_off(step: LatencyStep) -> bool:
    """Whether a fit is clean: echoes, and at most 2 trials or one in 8 off the step."""
    return step.base >= 0 and step.mismatches <= max(2, step.trials // 8)


def _trial(
    drv: Any, read: Callable[[], Any], hold_s: float, offset_rad: float
) -> tuple[float, int | None, int]:
    """One held answer: (its send time minus its frame's controller time, s; cycles until
    ASPos moved by half the change, or None within 12 frames; its frame's IPOC)."""
    offset = np.full(6, offset_rad)
    change = float(np.max(np.abs(offset - drv._shaping.offset_rad)))
    with drv._cmd_lock:
        drv._shaping.sent = None
        drv._shaping.request = (hold_s, offset)
    baseline = None
    sent: tuple[int, float, float] | None = None
    for _ in range(40):
        st = read()
        if sent is None:
            with drv._cmd_lock:
                sent = drv._shaping.sent
        if sent is None or st.ipoc <= sent[0]:
            baseline = st.q_setpoint
            continue
        if baseline is None or st.q_setpoint is None:
            break
        cycles = round((st.ipoc - sent[0]) * drv._clock.tick_s / drv.controller_period_s)
        if float(np.max(np.abs(st.q_setpoint - baseline))) > 0.5 * change or change == 0:
            return sent[2] - sent[1], cycles, sent[0]
        if cycles > 12:
            break
    return (math.nan, None, -1) if sent is None else (sent[2] - sent[1], None, sent[0])
