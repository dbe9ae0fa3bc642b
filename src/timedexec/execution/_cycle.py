"""The cycle-locked sender: each command leaves at a fixed phase of the controller's cycle.

The controller samples its command register once per cycle, at the cycle boundary. A
command that reaches it right at a boundary makes that cycle or the next by chance (host
jitter of a few hundred µs decides): one cycle then gets two commands (the first never
acts) and the next none. Sending as soon as the state package arrives puts the commands
exactly there, because the package leaves the controller right after a boundary and the
command needs about the same round trip back.

The host sees the controller's cycle boundaries through the state stream: the lower
envelope of arrival minus controller time (:class:`~timedexec.execution._state.StateTracker`,
the same clock model as the gyro's clock fit) gives the earliest arrival of each cycle's
package, i.e. the boundary plus the shortest publish-and-wire time. :class:`SendPhase` aims
every command at the middle of the intake window: it leaves at that earliest arrival plus
half a period minus the round trip the command and the package need together (the
shortest publish + wire time up, wire time down; ``round_trip_s``, default
:data:`DEFAULT_ROUND_TRIP_S` as measured on the loopback twin). The command's content is
computed for the instant it leaves; :func:`timedexec._realtime.wait_until` sleeps to just
before the target and spins the rest (``time.sleep`` alone overshoots by 50-100 µs).

Where the controller has told where its intake is (:class:`IntakeFix`, found by
:func:`~timedexec.execution._intake.probe_intake`), :meth:`SendPhase.aim_s` aims by that
deadline instead of by the arrivals.
"""

from __future__ import annotations

import math
import warnings
from collections import deque
from dataclasses import dataclass, replace

from timedexec.errors import ConfigError, DatingWarning

__all__ = [
    "COMMAND_UPLINK_S",
    "DEFAULT_ROUND_TRIP_S",
    "LINE_MIN_SPAN_S",
    "LINE_WINDOW_S",
    "BoundaryLine",
    "IntakeFix",
    "SendPhase",
]

#: Shortest publish + wire-up + wire-down time of the loopback UR twin, s: the earliest
#: package arrival lies this much after the cycle boundary a command sent at once would
#: reach. Measure it for a real cell (the twin's truth gives it; see docs/execution.md).
DEFAULT_ROUND_TRIP_S = 4e-4
#: Time from a command leaving the host to the controller's register, s: half the
#: loopback twin's shortest round trip (a host cannot split a round trip; a wrong split
#: moves every sampling instant found by :meth:`IntakeFix.sampled_s` by the same amount).
COMMAND_UPLINK_S = 0.5 * DEFAULT_ROUND_TRIP_S
#: :meth:`IntakeFix.dated` warns where the mean response chose the sampling cycle with the
#: probe's response within this fraction of a period of flipping it (1 ms on a CB3: a
#: loaded two-core host delays every package by that much; the CI run of 2026-11-29 dated
#: a weld's states a period off at a margin of this order).
DATING_MARGIN_PERIODS = 0.125
#: A choice of whole periods this fraction of a period or more from flipping is firm:
#: :meth:`IntakeFix.echo_depth_at` names a depth only from such a sampling instant, and a
#: mean response that firmly contradicts an echo depth is reported (a quarter: the uplink
#: split, the deadline's resolution and the sampling instant's own error together stay
#: well inside it).
ECHO_DEPTH_MARGIN_PERIODS = 0.25
#: Window of the long-term clock line (:class:`BoundaryLine`), s: over two drift periods of
#: a publisher whose phase wanders like the twin's (47 s).
LINE_WINDOW_S = 120.0
#: Span of arrivals the line needs before it is used, s: until then the short envelope.
LINE_MIN_SPAN_S = 100.0
#: The line keeps the earliest arrival of each bucket this long, s.
LINE_BUCKET_S = 0.5
#: The line is refitted every this many buckets (5 s): a refit (the hull of up to 240
#: points) takes ~0.35 ms, so it falls in 1 of 2,500 cycles at 500 Hz.
LINE_REFIT_BUCKETS = 10
#: A bucket whose earliest arrival lies this far from the line (either way) is a new
#: clock (the controller restarted, the link changed): the line starts over, s. A
#: wandering phase stays within one period (2-12 ms); a stall delays single packages (the
#: twin's reach 90 ms), not a whole bucket's earliest.
LINE_JUMP_S = 0.05
#: Largest rate between the host and controller clocks the line believes (500 ppm, the
#: most NTP slews a host clock); a steeper fit is no line.
LINE_MAX_RATE = 5e-4


class BoundaryLine:
    """Long-term lower envelope of arrival minus controller time: a line, offset + drift.

    The short envelope (:class:`~timedexec.execution._state.StateTracker`, 0.5 s) is the
    cycle boundary plus the shortest sampling-to-arrival time *now*; where the controller's
    publisher lets its phase wander against the cycle (the twin's drifts through 2-97 % of
    the period in 47 s), that follows the phase, and the lock aims anywhere in the cycle.
    Over a window of several wander periods the phase comes back to its least value again
    and again, while the host/controller clock drift (tens of ppm) is a straight line: the
    lower convex hull of the window's earliest arrivals (one per :data:`LINE_BUCKET_S`)
    touches those returns, and its edge at the window's mean time is the line that lies
    below every arrival and highest under their mass (the L1 supporting line), refitted
    every :data:`LINE_REFIT_BUCKETS` buckets. Used once the window spans
    :data:`LINE_MIN_SPAN_S`; a fit steeper than :data:`LINE_MAX_RATE` is
    refused (the clocks cannot drift so fast: the arrivals do not fit a line), and a
    bucket :data:`LINE_JUMP_S` off the line starts it over (a new controller clock).

    Parameters
    ----------
    window_s, min_span_s, bucket_s : float
        See the module constants, s.
    """

    def __init__(
        self,
        window_s: float = LINE_WINDOW_S,
        min_span_s: float = LINE_MIN_SPAN_S,
        bucket_s: float = LINE_BUCKET_S,
    ) -> None:
        if not 0 < bucket_s <= min_span_s <= window_s < math.inf:
            raise ConfigError(
                f"BoundaryLine: need 0 < bucket_s ({bucket_s!r}) <= min_span_s "
                f"({min_span_s!r}) <= window_s ({window_s!r}) s, finite"
            )
        self.window_s, self.min_span_s, self.bucket_s = window_s, min_span_s, bucket_s
        self._points: deque[tuple[float, float]] = deque()  # closed buckets' earliest
        self._bucket_end = -math.inf
        self._best = (math.nan, math.inf)
        self._closed = 0
        #: ``(t_ref, offset_ref, rate)``: the line through (t_ref, offset_ref) with this
        #: slope (s per s), or None while the window is too short or the fit refused.
        self.line: tuple[float, float, float] | None = None

    def add(self, t_s: float, offset_s: float) -> None:
        """One package: host arrival time ``t_s`` and arrival minus controller time, s."""
        if t_s >= self._bucket_end:
            if math.isfinite(self._best[1]):
                t_best, off_best = self._best
                if abs(off_best - self.offset_s(t_best)) > LINE_JUMP_S:  # (False if NaN)
                    self._points.clear()
                    self.line = None
                self._points.append(self._best)
                self._closed += 1
                if self._closed % LINE_REFIT_BUCKETS == 0:
                    self._refit(t_s)
            self._bucket_end = t_s + self.bucket_s
            self._best = (t_s, offset_s)
        elif offset_s < self._best[1]:
            self._best = (t_s, offset_s)

    def offset_s(self, t_s: float) -> float:
        """The line at host time ``t_s``, s (NaN without a line)."""
        line = self.line
        if line is None:
            return math.nan
        t0, o0, rate = line
        return o0 + rate * (t_s - t0)

    def _refit(self, now_s: float) -> None:
        pts = self._points
        while pts and pts[0][0] < now_s - self.window_s:
            pts.popleft()
        if len(pts) < 2 or pts[-1][0] - pts[0][0] < self.min_span_s:
            self.line = None
            return
        # Lower convex hull (Andrew's monotone chain; the points come in time order).
        hull: list[tuple[float, float]] = []
        for p in pts:
            while len(hull) >= 2:
                (t1, o1), (t2, o2) = hull[-2], hull[-1]
                if (t2 - t1) * (p[1] - o1) - (o2 - o1) * (p[0] - t1) <= 0.0:
                    hull.pop()
                else:
                    break
            hull.append(p)
        t_mean = sum(p[0] for p in pts) / len(pts)
        k = 1
        while k < len(hull) - 1 and hull[k][0] < t_mean:
            k += 1
        (ta, oa), (tb, ob) = hull[k - 1], hull[k]  # the edge spanning the mean time
        rate = (ob - oa) / (tb - ta)
        self.line = (ta, oa, rate) if abs(rate) <= LINE_MAX_RATE else None


@dataclass(frozen=True)
class IntakeFix:
    """The controller's command deadline on the host clock, from :func:`probe_intake`.

    A command sent before ``controller_time + deadline_offset_s`` (host time; the
    controller time of any cycle's package) makes that cycle's intake, one sent after makes
    the next.

    Attributes
    ----------
    deadline_offset_s : float
        Host send deadline minus the cycle's controller time stamp, s (at ``probed_at_s``).
    period_s : float
        Controller period, s.
    probed_at_s : float
        Host time of the probe, s.
    resolution_s : float
        The deadline's uncertainty, s: half the spacing of the send times tried, plus half
        of how far the probe's last re-tests still moved it (a loaded host).
    package_lead_s : float
        Where the packages arrive in the intake cycle: the earliest arrival minus the
        preceding deadline, s, in [0, period) (small: packages arrive just after a deadline,
        so answering at once straddles it).
    trials : int
        Probe commands whose echo was seen.
    mismatches : int
        Trials on the other side of the fitted step.
    arrival_offset_s : float
        The earliest package arrival minus its controller time stamp during the probe, s.
    sample_offset_s : float
        Host time a package was sampled at minus its controller time stamp, s (NaN until
        :meth:`dated`): its cycle boundary, which does not move with the publisher's phase.
    sample_margin_s : float
        How far the probe's earliest response was from flipping the boundary chosen by a
        whole period (half a period minus its distance from the mean response), s; half a
        period where the echo chose it (``dated_by`` ``"echo"``). Never negative: a
        response past half a period from the mean is measured from the flipped boundary.
    echo_cycles : int
        Cycles from the package a probe command answered to the first package whose
        ``target_qd`` showed it, for a command that made the deadline (-1: unknown).
    echo_depth_cycles : int or None
        The controller's pipeline from the intake that takes a command to the package that
        shows it, cycles (``ExecutorSettings.echo_depth_cycles``; None: unknown): with
        ``echo_cycles`` it names the cycle a package was sampled in, whatever the
        publisher's phase.
    dated_by : str
        What chose the whole periods of ``sample_offset_s``: ``"echo"``, ``"response"``
        (the mean response delay), or ``""`` before :meth:`dated`.
    """

    deadline_offset_s: float
    period_s: float
    probed_at_s: float
    resolution_s: float
    package_lead_s: float
    trials: int
    mismatches: int
    arrival_offset_s: float = math.nan
    sample_offset_s: float = math.nan
    sample_margin_s: float = math.nan
    echo_cycles: int = -1
    echo_depth_cycles: int | None = None
    dated_by: str = ""

    def deadline_s(self, controller_time_s: float, rate: float = 0.0) -> float:
        """Host send deadline of the cycle whose package is stamped ``controller_time_s``, s
        (``rate``: host/controller clock drift since the probe, s per s; the elapsed time is
        taken in host time, the difference being second order)."""
        elapsed = controller_time_s + self.deadline_offset_s - self.probed_at_s
        return controller_time_s + self.deadline_offset_s + rate * elapsed

    def dated(self, response_s: float, uplink_s: float = COMMAND_UPLINK_S) -> IntakeFix:
        """This fix with the packages' sampling instant (``sample_offset_s``).

        The controller samples its state at the cycle boundary, which a command leaving at
        the deadline reaches ``uplink_s`` later: a deadline plus ``uplink_s``, some whole
        periods back from the probe's earliest arrival. Chosen once: the boundary's place
        on the controller clock does not move as the publisher's phase wanders, so a
        package stamped ``t`` is dated ``t + sample_offset_s`` from then on.

        The whole periods: where the controller's echo depth is known
        (``echo_depth_cycles``) and the probe saw its echoes (``echo_cycles``), the command
        that made the deadline showed in the package ``echo_cycles`` after the reference,
        so the deadline's cycle is ``echo_cycles - echo_depth_cycles`` packages after it:
        a count, which no publisher phase moves. Otherwise, the number that leaves the
        probe's response nearest ``response_s`` (the model's mean response delay), wrong
        by a whole period where the probe saw a response more than half a period from the
        mean (``sample_margin_s`` then measures from the wrong boundary, so a small margin
        warns and none proves): a publisher whose phase wanders over most of the
        period, as the UR twins' (2-97 %), is that near its extremes (the CI run of
        2026-11-29: a weld's positions dated a period late, the next weld 4 mm off).
        The echo decides where both can: a loaded host delays the packages the probe sees,
        which moves the response, not the count (on the simulated e-Series, every package
        0.5 ms late dated 24 % of probes a period off by the response, none by the echo;
        ``benchmarks/bench_intake_dating.py``). Where they disagree with the response a
        quarter period or more from flipping, a warning says that the depth given may not
        fit this controller.
        """
        boundary = self.deadline_offset_s + uplink_s
        whole, margin = self._by_response(response_s, uplink_s)
        by = "response"
        if self.echo_depth_cycles is not None and self.echo_cycles >= 0:
            # The reference package's cycle lies ``echo - depth`` periods before the
            # deadline's; the probe's earliest arrival is of packages like it.
            echo_whole = self.echo_depth_cycles - self.echo_cycles
            if echo_whole != whole and margin >= ECHO_DEPTH_MARGIN_PERIODS * self.period_s:
                warnings.warn(
                    f"intake probe: an echo depth of {self.echo_depth_cycles} cycles dates "
                    f"the state {echo_whole - whole:+d} period(s) from the mean response "
                    f"delay ({response_s * 1e3:.2f} ms, {margin * 1e3:.2f} ms from "
                    "flipping): the echo decides; check that "
                    "ExecutorSettings.echo_depth_cycles fits this controller (or that the "
                    "host was not delaying every package during the probe)",
                    DatingWarning,
                    stacklevel=2,
                )
            whole, margin, by = echo_whole, 0.5 * self.period_s, "echo"
        if by == "response" and margin < DATING_MARGIN_PERIODS * self.period_s:
            warnings.warn(
                f"intake probe: the mean response delay ({response_s * 1e3:.2f} ms) chose "
                f"the cycle the state is sampled in with {margin * 1e3:.2f} ms to spare "
                f"(period {self.period_s * 1e3:g} ms): packages that much later would date "
                "every state a whole period off (a publisher phase at the end of a wide "
                "range); a tracking model from calibrate's tracking phases carries this "
                "controller's echo depth (or give ExecutorSettings.echo_depth_cycles), or "
                "probe again when the phase has moved",
                DatingWarning,
                stacklevel=2,
            )
        return replace(
            self,
            sample_offset_s=boundary + whole * self.period_s,
            sample_margin_s=margin,
            dated_by=by,
        )

    def echo_depth_at(
        self,
        sample_offset_s: float,
        response_s: float | None = None,
        uplink_s: float = COMMAND_UPLINK_S,
    ) -> tuple[int | None, float, str]:
        """The controller's echo depth, given when its packages are sampled.

        ``sample_offset_s`` is host time of sampling minus the package's controller stamp
        near the probe, measured by other means (``calibrate``: the sweep's gyro, which
        dates the states whatever the publisher's phase). It lies some whole periods from
        the probe's boundary (deadline + ``uplink_s``); those plus the probe's echo count
        are the depth (:meth:`dated` the other way round). ``response_s``, the mean
        response delay, is a second witness: where it chooses the whole periods with as
        much to spare and chooses others, no depth.

        Returns
        -------
        depth : int or None
            Cycles; None where the probe saw no echo count, the offset lies less than
            ``ECHO_DEPTH_MARGIN_PERIODS`` of a period from flipping the whole periods, or
            the witness contradicts it.
        margin_s : float
            How far the offset lay from flipping, s (half a period at best).
        why : str
            How the depth was found, or why none was.
        """
        period, need = self.period_s, ECHO_DEPTH_MARGIN_PERIODS * self.period_s
        boundary = self.deadline_offset_s + uplink_s
        frac = (sample_offset_s - boundary) / period
        whole = round(frac)
        margin = (0.5 - abs(frac - whole)) * period
        if self.echo_cycles < 0:
            return None, margin, "the probe saw no echo count"
        if margin < need:
            return None, margin, (
                f"the sampling instant {margin * 1e3:.2f} ms from flipping the probe's "
                f"whole periods ({need * 1e3:.2f} ms needed)"
            )
        if response_s is not None:
            by_response, firm = self._by_response(response_s, uplink_s)
            if firm >= need and by_response != whole:
                return None, margin, (
                    f"the sampling instant implies {whole + self.echo_cycles} cycles, the "
                    f"mean response delay {by_response - whole:+d} period(s) from it with "
                    f"{need * 1e3:.2f} ms or more to spare"
                )
        return whole + self.echo_cycles, margin, "the sampling instant and the probe's echo"

    def _by_response(self, response_s: float, uplink_s: float) -> tuple[int, float]:
        """The whole periods from the boundary to the sampling instant that leave the
        probe's earliest response nearest ``response_s``, and how far that choice was from
        flipping, s."""
        response = self.arrival_offset_s - (self.deadline_offset_s + uplink_s)
        whole = round((response - response_s) / self.period_s)
        off = response - whole * self.period_s - response_s
        return whole, 0.5 * self.period_s - abs(off)

    def sampled_s(self, controller_time_s: float, rate: float = 0.0) -> float:
        """Host time the package stamped ``controller_time_s`` was sampled at, s (NaN
        before :meth:`dated`; ``rate`` as in :meth:`deadline_s`)."""
        t = controller_time_s + self.sample_offset_s
        return t + rate * (t - self.probed_at_s)

    def summary(self) -> dict[str, float | int | str]:
        """JSON-safe description (times in ms)."""
        return {
            "deadline_offset_ms": self.deadline_offset_s * 1e3,
            "resolution_ms": self.resolution_s * 1e3,
            "package_lead_ms": self.package_lead_s * 1e3,
            "trials": self.trials,
            "mismatches": self.mismatches,
            "sample_offset_ms": self.sample_offset_s * 1e3,
            "sample_margin_ms": self.sample_margin_s * 1e3,
            "echo_cycles": self.echo_cycles,
            "dated_by": self.dated_by,
        }


class SendPhase:
    """When, in host time, the command of a controller cycle leaves.

    Parameters
    ----------
    period_s : float
        Controller period, s.
    round_trip_s : float
        Shortest time from a cycle boundary, through the package's arrival, back to the
        controller for a command sent at that arrival, s (>= 0, below one period).
    fraction : float
        Where in the intake window to land, as a fraction of the period (0.5: middle).

    Attributes
    ----------
    offset_s : float
        The send time after the cycle's earliest package arrival, s (without ``intake``).
    intake : IntakeFix or None
        The controller's command deadline found by probing it
        (:func:`~timedexec.execution._intake.probe_intake`): when set, commands are aimed
        half a period before a deadline instead (:meth:`aim_s`).
    """

    def __init__(
        self, period_s: float, round_trip_s: float = DEFAULT_ROUND_TRIP_S, fraction: float = 0.5
    ) -> None:
        if not 0 <= round_trip_s < period_s:
            raise ConfigError(
                f"round_trip_s={round_trip_s!r} outside [0, {period_s:g}) s (one controller "
                "period); measure it against the controller or keep the default"
            )
        if not 0 < fraction < 1:
            raise ConfigError(f"fraction={fraction!r} outside (0, 1); 0.5 is mid-cycle")
        self.period_s = float(period_s)
        self.round_trip_s = float(round_trip_s)
        self.fraction = float(fraction)
        self.offset_s = (fraction * period_s - round_trip_s) % period_s
        self.intake: IntakeFix | None = None
        self._lead: int | None = None
        self._work_peak_s = 0.0

    def target_s(self, earliest_arrival_s: float) -> float:
        """Host send time of the command answering the package whose earliest possible
        arrival is ``earliest_arrival_s``, s (by the arrivals alone)."""
        return earliest_arrival_s + self.offset_s

    def note_work(self, work_s: float) -> None:
        """The time a command took to compute, s: a decaying peak of it (halves in ~140
        cycles) is how early a coasting loop gives up waiting for the package."""
        self._work_peak_s = max(float(work_s), 0.995 * self._work_peak_s)

    @property
    def coast_lead_s(self) -> float:
        """How long before the send time a coasting loop stops waiting for the package and
        computes the command from the estimate, s: the recent peak work (a quarter period
        at most), so the command is ready when it is due rather than late by its work."""
        return min(self._work_peak_s, 0.25 * self.period_s)

    def aim_s(
        self, controller_time_s: float, earliest_arrival_s: float, rate: float = 0.0
    ) -> float:
        """Host send time of the command answering the package stamped ``controller_time_s``
        whose earliest possible arrival is ``earliest_arrival_s``, s.

        With an ``intake`` fix: ``fraction`` of a period into the intake window (the period
        before a deadline), at the first deadline whose aim is not before that arrival
        (``rate``: the clock line's drift, s per s). The deadline chosen stays the same
        one cycle after cycle while its aim lies within [arrival - period/4, arrival +
        period): as the packages' phase wanders past it, one cycle gets no command or two,
        once, instead of every cycle by chance.
        """
        fix = self.intake
        if fix is None:
            return earliest_arrival_s + self.offset_s
        period = self.period_s
        base = fix.deadline_s(controller_time_s, rate) - (1.0 - self.fraction) * period
        lead = self._lead
        if lead is None or not (
            earliest_arrival_s - 0.25 * period <= base + lead * period < earliest_arrival_s + period
        ):
            lead = self._lead = math.ceil((earliest_arrival_s - base) / period)
        return base + lead * period
