"""Sensor-to-host clock model: host_time = a + b·n for the unwrapped sample index n.

The gyro's MEMS clock is only within about ±1 % of its nominal 8 kHz, so sample times come
from a fitted line, not from per-read host stamps. Each arrival (n, t) satisfies
``t = a + b·n + latency`` with ``latency >= min_latency``; USB delivers samples in bursts and
the host reads them in chunks, so latency is positive, skewed and correlated.

Plain least squares gets the slope but puts the line through the *middle* of the arrivals:
its offset is biased by the mean latency (often milliseconds). The lower-envelope fit used
here instead takes the line that lies below every arrival and is as high as possible at the
mean index — the linear-programming clock-skew estimator of Moon, Skelly and Towsley
("Estimation and removal of clock skew from network delay measurements", INFOCOM 1999):
minimise sum_i (t_i - a - b·n_i) subject to t_i >= a + b·n_i. Its solution is the edge of
the lower convex hull of the points that spans the mean index, so it is computed with
Andrew's monotone chain instead of an LP solver. The line then describes the
*minimum-latency* arrival of each sample; the remaining constant (the minimum transport
latency) cannot be observed from arrival times alone and joins the DLPF group delay as a
fixed offset.

Only the latest sample of each read can lie on the envelope (samples of one read share an
arrival time and the earlier ones waited longer), so arrivals with equal host times are
reduced to the one with the highest index before fitting.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError, SensorError

__all__ = [
    "ClockFit",
    "DriftingClockFit",
    "SensorClock",
    "fit_clock_drifting",
    "fit_clock_least_squares",
    "fit_clock_lower_envelope",
]

FitMethod = Literal["lower_envelope", "least_squares", "nominal"]


@dataclass(frozen=True, kw_only=True)
class ClockFit:
    """A fitted line host_time = t_ref_s + period_s·(n - n_ref).

    Attributes
    ----------
    method : {"lower_envelope", "least_squares", "nominal"}
        How the line was obtained ("nominal": too little data, nominal rate through the
        lowest arrival).
    n_ref : int
        Reference sample index (anchor of the line).
    t_ref_s : float
        Host time of ``n_ref``, s.
    period_s : float
        Fitted sample period, s.
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    n_points : int
        Arrivals used (after reducing equal arrival times).
    span_samples : int
        Index range covered by those arrivals, samples.
    """

    method: FitMethod
    n_ref: int
    t_ref_s: float
    period_s: float
    nominal_rate_hz: float
    n_points: int
    span_samples: int

    @property
    def rate_hz(self) -> float:
        """Fitted sample rate, Hz."""
        return 1.0 / self.period_s

    @property
    def rate_error_ppm(self) -> float:
        """Fitted rate relative to nominal, ppm (+3000 means 0.3 % fast)."""
        return (self.rate_hz / self.nominal_rate_hz - 1.0) * 1e6

    @property
    def offset_s(self) -> float:
        """Host time of sample index 0, s (the line's intercept a)."""
        return self.t_ref_s - self.n_ref * self.period_s

    def to_host_time(self, n: ArrayLike) -> NDArray[np.float64]:
        """Host time of sample index ``n`` (array of any shape), s."""
        x = np.asarray(n, dtype=np.int64) - self.n_ref
        return self.t_ref_s + x.astype(np.float64) * self.period_s

    def to_index(self, host_time_s: ArrayLike) -> NDArray[np.float64]:
        """Fractional sample index at host time ``host_time_s`` (array of any shape)."""
        t = np.asarray(host_time_s, dtype=np.float64)
        return self.n_ref + (t - self.t_ref_s) / self.period_s

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation (round-trips through :meth:`from_dict`)."""
        return {
            "method": self.method,
            "n_ref": self.n_ref,
            "t_ref_s": self.t_ref_s,
            "period_s": self.period_s,
            "nominal_rate_hz": self.nominal_rate_hz,
            "n_points": self.n_points,
            "span_samples": self.span_samples,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ClockFit:
        """Inverse of :meth:`to_dict`."""
        return cls(**data)


def _reduce(
    n: NDArray[np.int64], t: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Keep the highest index of each run of equal arrival times; sort by index."""
    if n.shape[0] == 0:
        return n, t
    starts = np.concatenate(([0], np.flatnonzero(t[1:] != t[:-1]) + 1))
    n_red = np.maximum.reduceat(n, starts)
    t_red = t[starts]
    if n_red.shape[0] > 1 and np.any(np.diff(n_red) <= 0):
        order = np.lexsort((t_red, n_red))
        n_red, t_red = n_red[order], t_red[order]
        first = np.concatenate(([True], np.diff(n_red) > 0))  # lowest t per index
        n_red, t_red = n_red[first], t_red[first]
    return n_red, t_red


def _lower_hull(x: list[float], y: list[float]) -> list[int]:
    """Indices of the lower convex hull of points sorted by strictly increasing x.

    Andrew's monotone chain; a point is popped when the turn it makes is not strictly
    counter-clockwise.
    """
    hull: list[int] = []
    for i, (xi, yi) in enumerate(zip(x, y, strict=True)):
        while len(hull) >= 2:
            o, a = hull[-2], hull[-1]
            if (x[a] - x[o]) * (yi - y[o]) - (y[a] - y[o]) * (xi - x[o]) <= 0.0:
                hull.pop()
            else:
                break
        hull.append(i)
    return hull


#: Points from which the lower hull is computed by Qhull (C) instead of the Python chain.
_QHULL_MIN_POINTS = 256


def _lower_hull_array(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.intp]:
    """:func:`_lower_hull` for arrays; large inputs go through Qhull.

    Qhull's 2-D hull lists its vertices counter-clockwise: from the leftmost point that is
    the lower chain up to the rightmost. The hull is invariant under scaling each axis, so
    the points are mapped to the unit square first (sample indices span millions, arrival
    residuals milliseconds); collinear points are not vertices, as in the chain.
    """
    k = int(x.shape[0])
    if k < _QHULL_MIN_POINTS:
        return np.asarray(_lower_hull(x.tolist(), y.tolist()), dtype=np.intp)
    from scipy.spatial import ConvexHull, QhullError

    y_span = float(y.max() - y.min())
    if not (y_span > 0 and x[-1] > x[0]):
        return np.array([0, k - 1], dtype=np.intp)
    pts = np.column_stack([(x - x[0]) / (x[-1] - x[0]), (y - y.min()) / y_span])
    try:
        vertices = ConvexHull(pts).vertices
    except QhullError:  # degenerate input: the exact chain decides
        return np.asarray(_lower_hull(x.tolist(), y.tolist()), dtype=np.intp)
    start = int(np.flatnonzero(vertices == 0)[0])
    ring = np.roll(vertices, -start)
    end = int(np.flatnonzero(ring == k - 1)[0])
    return np.asarray(ring[: end + 1], dtype=np.intp)


def _check_pairs(n: ArrayLike, t: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    n_arr = np.asarray(n, dtype=np.int64).reshape(-1)
    t_arr = np.asarray(t, dtype=np.float64).reshape(-1)
    if n_arr.shape != t_arr.shape:
        raise ConfigError(
            f"sample indices and arrival times differ in length ({n_arr.shape[0]} vs "
            f"{t_arr.shape[0]}); pass one arrival time per index"
        )
    if not np.all(np.isfinite(t_arr)):
        raise ConfigError("arrival times must be finite; drop NaN/inf before fitting")
    return n_arr, t_arr


def _nominal_fit(n: NDArray[np.int64], t: NDArray[np.float64], nominal_rate_hz: float) -> ClockFit:
    if n.shape[0] == 0:
        raise SensorError(
            "the clock model has no arrivals yet; read samples from the gyro before asking "
            "for host times"
        )
    period = 1.0 / nominal_rate_hz
    resid = t - (n - n[0]).astype(np.float64) * period
    k = int(np.argmin(resid))
    return ClockFit(
        method="nominal",
        n_ref=int(n[k]),
        t_ref_s=float(t[k]),
        period_s=period,
        nominal_rate_hz=nominal_rate_hz,
        n_points=int(n.shape[0]),
        span_samples=int(n[-1] - n[0]),
    )


def _envelope_from_candidates(
    n: NDArray[np.int64],
    t: NDArray[np.float64],
    n_mean: float,
    nominal_rate_hz: float,
    n_points: int,
    span: int,
) -> ClockFit:
    """Lower-envelope line through candidate points (sorted, unique n) at the mean index."""
    period0 = 1.0 / nominal_rate_hz
    x_arr = (n - n[0]).astype(np.float64)
    y_arr = t - t[0] - x_arr * period0  # shear: the hull is unchanged, numbers stay small
    hull = _lower_hull_array(x_arr, y_arr)
    if len(hull) < 2:
        return _nominal_fit(n, t, nominal_rate_hz)
    hx = x_arr[hull]
    x_mean = n_mean - float(n[0])
    e = int(np.clip(np.searchsorted(hx, x_mean, side="right") - 1, 0, len(hull) - 2))
    i, j = hull[e], hull[e + 1]
    slope = (y_arr[j] - y_arr[i]) / (x_arr[j] - x_arr[i])
    return ClockFit(
        method="lower_envelope",
        n_ref=int(n[i]),
        t_ref_s=float(t[i]),
        period_s=period0 + float(slope),
        nominal_rate_hz=nominal_rate_hz,
        n_points=n_points,
        span_samples=span,
    )


def fit_clock_lower_envelope(
    n: ArrayLike, t: ArrayLike, *, nominal_rate_hz: float = 8000.0
) -> ClockFit:
    """Fit the lower envelope of arrivals (linear-programming clock fit).

    Parameters
    ----------
    n : array_like of int, shape (k,)
        Unwrapped sample indices.
    t : array_like of float, shape (k,)
        Host arrival time of each sample, s.
    nominal_rate_hz : float
        Nominal sample rate, Hz.

    Returns
    -------
    ClockFit
        The supporting line of the lower convex hull at the mean index (method
        ``"lower_envelope"``), or the nominal rate through the lowest arrival if fewer than
        two distinct reads are available (method ``"nominal"``).
    """
    n_arr, t_arr = _check_pairs(n, t)
    n_red, t_red = _reduce(n_arr, t_arr)
    if n_red.shape[0] < 2:
        return _nominal_fit(n_red, t_red, nominal_rate_hz)
    return _envelope_from_candidates(
        n_red,
        t_red,
        float(np.mean(n_red)),
        nominal_rate_hz,
        int(n_red.shape[0]),
        int(n_red[-1] - n_red[0]),
    )


def fit_clock_least_squares(
    n: ArrayLike, t: ArrayLike, *, nominal_rate_hz: float = 8000.0
) -> ClockFit:
    """Ordinary least-squares line through all arrivals (the comparison method).

    Its slope is unbiased, but its offset includes the mean transport latency.

    Parameters
    ----------
    n, t, nominal_rate_hz
        As for :func:`fit_clock_lower_envelope`; no reduction is applied.

    Returns
    -------
    ClockFit
        Method ``"least_squares"``, anchored at the mean index.
    """
    n_arr, t_arr = _check_pairs(n, t)
    if n_arr.shape[0] < 2 or n_arr.max() == n_arr.min():
        return _nominal_fit(n_arr, t_arr, nominal_rate_hz)
    period0 = 1.0 / nominal_rate_hz
    x = (n_arr - n_arr[0]).astype(np.float64)
    y = t_arr - t_arr[0] - x * period0
    x_mean, y_mean = float(x.mean()), float(y.mean())
    dx = x - x_mean
    slope = float(np.dot(dx, y - y_mean) / np.dot(dx, dx))
    n_ref = int(n_arr[0]) + round(x_mean)
    x_ref = float(n_ref - n_arr[0])
    return ClockFit(
        method="least_squares",
        n_ref=n_ref,
        t_ref_s=float(t_arr[0] + y_mean + slope * (x_ref - x_mean) + x_ref * period0),
        period_s=period0 + slope,
        nominal_rate_hz=nominal_rate_hz,
        n_points=int(n_arr.shape[0]),
        span_samples=int(n_arr.max() - n_arr.min()),
    )


class SensorClock:
    """Incremental lower-envelope clock model of one sensor stream.

    Arrivals are added as they come (from the reader thread); :meth:`fit` refits from all of
    them, or from the last ``window_s`` seconds if set (for long runs where the sensor clock
    drifts with temperature). Points are kept in blocks of ``block_s`` seconds whose lower
    hulls are cached, so a refit costs a hull over a few vertices per block, not over every
    read.

    Parameters
    ----------
    nominal_rate_hz : float
        Nominal sample rate, Hz (8000 for the MPU-6000 with DLPF off).
    window_s : float, optional
        Fit only the most recent ``window_s`` seconds (whole blocks); None = everything.
    block_s : float
        Block length for hull caching, s.
    """

    def __init__(
        self,
        nominal_rate_hz: float = 8000.0,
        *,
        window_s: float | None = None,
        block_s: float = 1.0,
    ) -> None:
        if not (math.isfinite(nominal_rate_hz) and nominal_rate_hz > 0):
            raise ConfigError(f"nominal_rate_hz={nominal_rate_hz!r} must be positive, Hz")
        if window_s is not None and not window_s > 0:
            raise ConfigError(f"window_s={window_s!r} must be positive (s) or None")
        if not block_s > 0:
            raise ConfigError(f"block_s={block_s!r} must be positive, s")
        self.nominal_rate_hz = float(nominal_rate_hz)
        self.window_s = window_s
        self._block_samples = max(round(block_s * nominal_rate_hz), 1)
        self._lock = threading.Lock()
        self._fit: ClockFit | None = None
        self._fit_wall_s = -math.inf
        self._fit_points = 0
        self.reset()

    def reset(self) -> None:
        """Forget every arrival (after a sensor reset)."""
        with self._lock:
            self._n = np.zeros(1024, dtype=np.int64)
            self._t = np.zeros(1024, dtype=np.float64)
            self._size = 0
            self._hulls: list[NDArray[np.intp]] = []  # vertex indices of finished blocks
            self._block_first: list[int] = []  # first point index of each finished block
            self._fit = None
            self._fit_points = 0
            self.rejected_points = 0

    @property
    def n_points(self) -> int:
        """Arrivals stored (after reduction)."""
        return self._size

    def add(self, n: ArrayLike, t: ArrayLike) -> None:
        """Add arrivals.

        Parameters
        ----------
        n : array_like of int, shape (k,)
            Unwrapped sample indices, nondecreasing across calls.
        t : array_like of float, shape (k,)
            Host arrival times, s.
        """
        n_arr, t_arr = _check_pairs(n, t)
        n_red, t_red = _reduce(n_arr, t_arr)
        if n_red.shape[0] == 0:
            return
        with self._lock:
            size = self._size
            if size and t_red[0] == self._t[size - 1]:
                self._n[size - 1] = max(int(self._n[size - 1]), int(n_red[0]))
                n_red, t_red = n_red[1:], t_red[1:]
            if size:
                fresh = n_red > self._n[size - 1]
                self.rejected_points += int(np.count_nonzero(~fresh))
                n_red, t_red = n_red[fresh], t_red[fresh]
            k = int(n_red.shape[0])
            if size + k > self._n.shape[0]:
                cap = max(2 * self._n.shape[0], size + k)
                self._n = np.concatenate((self._n[:size], np.zeros(cap - size, np.int64)))
                self._t = np.concatenate((self._t[:size], np.zeros(cap - size, np.float64)))
            self._n[size : size + k] = n_red
            self._t[size : size + k] = t_red
            self._size = size + k

    def add_point(self, n: int, t: float) -> None:
        """Add one arrival: the newest sample ``n`` of a read that returned at host time
        ``t`` (s). Cheaper than :meth:`add` for the reader thread."""
        with self._lock:
            size = self._size
            if size:
                if t == self._t[size - 1]:
                    if n > self._n[size - 1]:
                        self._n[size - 1] = n
                    return
                if n <= self._n[size - 1]:
                    self.rejected_points += 1
                    return
            if size == self._n.shape[0]:
                self._n = np.concatenate((self._n, np.zeros(size, np.int64)))
                self._t = np.concatenate((self._t, np.zeros(size, np.float64)))
            self._n[size] = n
            self._t[size] = t
            self._size = size + 1

    def fit(self) -> ClockFit:
        """Refit from the stored arrivals and return the new line.

        Raises
        ------
        SensorError
            If no arrival has been added.
        """
        with self._lock:
            size = self._size
            n_all = self._n[:size]
            t_all = self._t[:size]
            if size < 2:
                fit = _nominal_fit(n_all, t_all, self.nominal_rate_hz)
            else:
                fit = self._fit_blocks(n_all, t_all)
            self._fit = fit
            self._fit_points = size
            self._fit_wall_s = time.monotonic()
            return fit

    def _fit_blocks(self, n_all: NDArray[np.int64], t_all: NDArray[np.float64]) -> ClockFit:
        size = int(n_all.shape[0])
        block_id = (n_all - n_all[0]) // self._block_samples
        current = int(block_id[-1])
        # Cache hulls of finished blocks not seen yet.
        done = len(self._hulls)
        if done < current:
            firsts = np.searchsorted(block_id, np.arange(done, current + 1))
            period0 = 1.0 / self.nominal_rate_hz
            for b in range(done, current):
                i0, i1 = int(firsts[b - done]), int(firsts[b - done + 1])
                if i1 <= i0:
                    self._hulls.append(np.zeros(0, dtype=np.intp))
                else:
                    x = (n_all[i0:i1] - n_all[i0]).astype(np.float64)
                    y = t_all[i0:i1] - t_all[i0] - x * period0
                    hull = _lower_hull(x.tolist(), y.tolist())
                    self._hulls.append(np.asarray(hull, dtype=np.intp) + i0)
                self._block_first.append(i0)
        current_first = int(np.searchsorted(block_id, current)) if current else 0
        first_block = 0
        first_point = 0
        if self.window_s is not None:
            window_samples = self.window_s * self.nominal_rate_hz
            first_block = max(current - math.ceil(window_samples / self._block_samples), 0)
            first_point = (
                self._block_first[first_block] if first_block < current else (current_first)
            )
        parts = [h for h in self._hulls[first_block:current] if h.shape[0]]
        parts.append(np.arange(current_first, size, dtype=np.intp))
        idx = np.concatenate(parts)
        n_win = n_all[first_point:]
        if n_win.shape[0] < 2:
            return _nominal_fit(n_win, t_all[first_point:], self.nominal_rate_hz)
        return _envelope_from_candidates(
            n_all[idx],
            t_all[idx],
            float(np.mean(n_win)),
            self.nominal_rate_hz,
            int(n_win.shape[0]),
            int(n_win[-1] - n_win[0]),
        )

    def least_squares(self) -> ClockFit:
        """Least-squares line through the stored (reduced) arrivals, for comparison."""
        with self._lock:
            return fit_clock_least_squares(
                self._n[: self._size].copy(),
                self._t[: self._size].copy(),
                nominal_rate_hz=self.nominal_rate_hz,
            )

    def fit_if_stale(self, max_age_s: float = 0.2) -> ClockFit:
        """Return the current fit, refitting if arrivals came in and it is older than
        ``max_age_s`` (wall time), or if there is none."""
        if self._fit is None or (
            self._size != self._fit_points and time.monotonic() - self._fit_wall_s > max_age_s
        ):
            return self.fit()
        return self._fit

    @property
    def current(self) -> ClockFit:
        """The last fit (fits now if there is none)."""
        return self._fit if self._fit is not None else self.fit()

    @property
    def rate_hz(self) -> float:
        """Fitted sample rate, Hz."""
        return self.current.rate_hz

    @property
    def rate_error_ppm(self) -> float:
        """Fitted rate relative to nominal, ppm."""
        return self.current.rate_error_ppm

    @property
    def offset_s(self) -> float:
        """Host time of sample index 0, s."""
        return self.current.offset_s

    @property
    def period_s(self) -> float:
        """Fitted sample period, s."""
        return self.current.period_s

    def to_host_time(self, n: ArrayLike) -> NDArray[np.float64]:
        """Host time of unwrapped sample index ``n`` under the current fit, s."""
        return self.current.to_host_time(n)


@dataclass(frozen=True, kw_only=True)
class DriftingClockFit:
    """A sensor clock that drifts: overlapping lower-envelope curves, blended.

    Window ``m`` is centred at ``centres[m]`` (sample index) and spans ``±half_width``
    samples; neighbouring windows overlap by half. Each window's curve is
    ``t = t_ref_s + period_s·(n - n_ref) + curvature_s·(n - n_ref)²`` (a line when the
    curvature is 0). The host time of index n is the average of the two nearest windows'
    curves weighted by a triangle (1 at a window's centre, 0 at its neighbour's), so the
    model is continuous and follows slow drift.

    Attributes
    ----------
    centres : ndarray, shape (w,)
        Window centres, sample index.
    half_width : float
        Window half width, samples (window length ``2·half_width``).
    n_ref, t_ref_s, period_s : ndarray, shape (w,)
        Each window's reference index, its host time (s) and the period there (s per
        sample).
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    curvature_s : ndarray, shape (w,) or (0,)
        Each window's quadratic coefficient, s per sample² (half the period's change per
        sample: a rate drifting by D ppm/s gives -D·1e-6/(2·rate²)); empty: lines.
    spread_s : float
        Structure left in the per-group minimum residuals (5-95 % range of their running
        median), s: what decided the window length.
    outlier_groups : int
        Groups left out because they lay far below their neighbours.
    transfer_phase : int
        Sample index (modulo the transfer length) at which the device's transfers end,
        when the arrivals showed one (see :func:`fit_clock_drifting`); -1: none found or
        not searched.
    """

    centres: NDArray[np.float64]
    half_width: float
    n_ref: NDArray[np.float64]
    t_ref_s: NDArray[np.float64]
    period_s: NDArray[np.float64]
    nominal_rate_hz: float
    spread_s: float = 0.0
    outlier_groups: int = 0
    curvature_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    transfer_phase: int = -1

    @property
    def window_s(self) -> float:
        """Window length, s (nominal)."""
        return 2.0 * self.half_width / self.nominal_rate_hz

    @property
    def rate_error_ppm(self) -> NDArray[np.float64]:
        """Each window's rate relative to nominal, ppm."""
        return (1.0 / (self.period_s * self.nominal_rate_hz) - 1.0) * 1e6

    @property
    def drift_ppm(self) -> float:
        """Range of the windows' rate errors (max - min), ppm."""
        ppm = self.rate_error_ppm
        return float(ppm.max() - ppm.min()) if ppm.size else 0.0

    def to_host_time(self, n: ArrayLike) -> NDArray[np.float64]:
        """Host time of (fractional) sample index ``n`` (any shape), s."""
        x = np.asarray(n, dtype=np.float64)
        w = self.centres.shape[0]
        curv = self.curvature_s if self.curvature_s.size else np.zeros(w)

        def curve(m: NDArray[np.int64] | int) -> NDArray[np.float64]:
            d = x - self.n_ref[m]
            out: NDArray[np.float64] = self.t_ref_s[m] + d * (self.period_s[m] + curv[m] * d)
            return out

        if w == 1:
            return curve(0)
        pos = np.clip((x - self.centres[0]) / self.half_width, 0.0, w - 1.0)
        m = np.minimum(np.floor(pos).astype(np.int64), w - 2)
        frac = pos - m
        lo = curve(m)
        blended: NDArray[np.float64] = lo + frac * (curve(m + 1) - lo)
        return blended

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe summary: window length, mean rate error and drift (ppm)."""
        ppm = self.rate_error_ppm
        return {
            "window_s": self.window_s,
            "windows": int(self.centres.shape[0]),
            "rate_error_ppm": float(np.mean(ppm)),
            "rate_error_ppm_min": float(ppm.min()),
            "rate_error_ppm_max": float(ppm.max()),
            "drift_ppm": self.drift_ppm,
            "residual_structure_s": self.spread_s,
            "outlier_groups": self.outlier_groups,
            "transfer_phase": self.transfer_phase,
            "curved": bool(self.curvature_s.size and np.any(self.curvature_s != 0)),
        }


def _running_median(x: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    if x.shape[0] <= k:
        return np.full_like(x, float(np.median(x)))
    pad = k // 2
    xp = np.pad(x, pad, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(xp, k)
    return np.asarray(np.median(win, axis=1), dtype=np.float64)


def _running_min(x: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    if x.shape[0] <= k:
        return np.full_like(x, float(np.min(x)))
    pad = k // 2
    xp = np.pad(x, pad, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(xp, k)
    return np.asarray(np.min(win, axis=1), dtype=np.float64)


#: Samples per bin whose lowest arrival (relative to a window's line) is a candidate of
#: the window's curved envelope: 0.25 s at 8 kHz, over which a drift of a few ppm/s bends
#: the offset by < 0.1 µs.
_CURVE_BIN = 2000


def _envelope_curved(
    n: NDArray[np.int64], t: NDArray[np.float64], nominal_rate_hz: float
) -> tuple[float, float, float, float]:
    """Lower envelope of arrivals by a quadratic in the sample index, as high as possible
    on average over the arrivals: the linear program of the line envelope (Moon, Skelly
    and Towsley 1999) with a curvature term. Returns (n_ref, t_ref, period, curvature) at
    the arrivals' mean index; the line envelope (curvature 0) when there are too few
    distinct arrivals or the program fails."""
    line = _envelope_from_candidates(
        n, t, float(np.mean(n)), nominal_rate_hz, int(n.shape[0]), int(n[-1] - n[0])
    )
    n_c = float(np.mean(n))
    t_line = line.t_ref_s + (n_c - line.n_ref) * line.period_s
    as_line = (n_c, t_line, line.period_s, 0.0)
    r = t - (line.t_ref_s + (n - line.n_ref).astype(np.float64) * line.period_s)
    bins = (n - n[0]) // _CURVE_BIN
    order = np.lexsort((r, bins))
    first = np.r_[True, np.diff(bins[order]) != 0]
    sel = order[first]
    if sel.size < 8:
        return as_line
    from scipy.optimize import linprog

    half = max(0.5 * float(n[-1] - n[0]), 1.0)
    x = (n[sel] - n_c) / half
    a_ub = np.column_stack([np.ones_like(x), x, x * x])
    res = linprog(
        -a_ub.sum(axis=0), A_ub=a_ub, b_ub=r[sel], bounds=[(None, None)] * 3, method="highs"
    )
    if res.status != 0 or not np.all(np.isfinite(res.x)):
        return as_line
    a, b, c = (float(v) for v in res.x)
    return n_c, t_line + a, line.period_s + b / half, c / half**2


def _windows_fit(
    n: NDArray[np.int64],
    t: NDArray[np.float64],
    half: float,
    nominal_rate_hz: float,
    curved: bool = False,
) -> tuple[NDArray[np.float64], ...]:
    """Centres, and per window n_ref, t_ref, period and curvature of the envelopes of
    half-overlapping windows of ``2·half`` samples (lines unless ``curved``)."""

    def envelope(nw: NDArray[np.int64], tw: NDArray[np.float64]) -> tuple[float, ...]:
        if curved:
            return _envelope_curved(nw, tw, nominal_rate_hz)
        fit = _envelope_from_candidates(
            nw, tw, float(np.mean(nw)), nominal_rate_hz, int(nw.shape[0]), int(nw[-1] - nw[0])
        )
        return float(fit.n_ref), fit.t_ref_s, fit.period_s, 0.0

    lo, hi = float(n[0]), float(n[-1])
    w = max(math.ceil((hi - lo) / half) + 1, 1)
    if w == 1 or hi - lo <= 2 * half:
        if n.shape[0] < 2 or n[-1] == n[0]:
            fit = fit_clock_lower_envelope(n, t, nominal_rate_hz=nominal_rate_hz)
            one: tuple[float, ...] = (float(fit.n_ref), fit.t_ref_s, fit.period_s, 0.0)
        else:
            one = envelope(n, t)
        return (np.array([0.5 * (lo + hi)]), *(np.array([v]) for v in one))
    centres: NDArray[np.float64] = lo + np.arange(w, dtype=np.float64) * half
    par = np.full((4, w), np.nan)
    edges = np.asarray(np.searchsorted(n, np.r_[centres - half, centres + half]), dtype=np.int64)
    for m in range(w):
        a, b = int(edges[m]), int(edges[w + m])
        if b - a < 2 or n[b - 1] == n[a]:  # an empty window (a pause): borrow a neighbour's
            continue
        par[:, m] = envelope(n[a:b], t[a:b])
    good = np.flatnonzero(np.isfinite(par[2]))
    for empty in np.flatnonzero(~np.isfinite(par[2])).tolist():
        j = int(good[np.argmin(np.abs(good - empty))])
        par[:, empty] = par[:, j]
    return centres, par[0], par[1], par[2], par[3]


def fit_clock_drifting(
    n: ArrayLike,
    t: ArrayLike,
    group: ArrayLike,
    *,
    nominal_rate_hz: float = 8000.0,
    window_s: float | None = None,
    min_window_s: float = 4.0,
    max_window_s: float = 240.0,
    tolerance_s: float = 20e-6,
    curved: bool = True,
    transfer_samples: int | None = None,
) -> DriftingClockFit:
    """Lower-envelope clock fit that follows slow oscillator drift (temperature).

    The arrivals are split into half-overlapping windows, each fitted with a lower
    envelope — a quadratic in the sample index (``curved``, default: the linear program
    of :func:`fit_clock_lower_envelope` with a curvature term, so that a rate that keeps
    drifting within a window does not bend the offset) or a line — and blended (see
    :class:`DriftingClockFit`). Unless ``window_s`` is given, the window length is chosen
    from the data: starting from the whole span (at most ``max_window_s``) it is halved
    while the per-group minimum residuals (groups are e.g. trials) still show structure —
    the 5-95 % range of their running minimum over 31 groups above ``tolerance_s`` — and
    the windows stay at least ``min_window_s`` and 31 groups long (a group's lowest
    arrival may sit a few samples above the envelope when its recorded blocks do not end
    where the device's transfers end; one group in 31 touching it is enough). A drift
    of the rate by D ppm/s bends the time offset by D·1e-6·L²/8 within a window of L s,
    which is what the residual structure measures. Groups whose minimum lies more than
    max(10 MAD, 0.5 ms) below their neighbours' (a wrongly indexed stretch) are left out.

    Parameters
    ----------
    n : array_like of int, shape (k,)
        Unwrapped sample indices (any order).
    t : array_like of float, shape (k,)
        Host arrival times, s.
    group : array_like of int, shape (k,)
        Group of each arrival (a trial); used to judge the residual structure.
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    window_s : float, optional
        Fixed window length, s (no search).
    min_window_s, max_window_s : float
        Bounds of the window search, s (the lower one at least 31 groups' span).
    tolerance_s : float
        Residual structure accepted, s (20 µs: a tenth of the 0.2 ms drift target).
    transfer_samples : int, optional
        Samples per device transfer, when transfers are of fixed size (the phase search
        above); None: stamps taken as they are.
    curved : bool
        Quadratic envelopes per window (True) or lines. On the independent recordings of
        ``benchmarks/bench_extract_robustness.py`` (-1500 ppm, 300 ppm exponential
        warm-up over 6 min, 31-trial windows) curves cut the actuation RMSE from 0.33 to
        0.12 ms; a clock without drift loses 5 µs of RMSE to the extra freedom.

    Returns
    -------
    DriftingClockFit
    """
    n_arr, t_arr = _check_pairs(n, t)
    g_arr = np.asarray(group).reshape(-1)
    if g_arr.shape != n_arr.shape:
        raise ConfigError("group must have one entry per arrival")
    opts = {"nominal_rate_hz": nominal_rate_hz, "window_s": window_s,
            "min_window_s": min_window_s, "max_window_s": max_window_s,
            "tolerance_s": tolerance_s, "curved": curved}  # fmt: skip
    fit = _fit_drifting(n_arr, t_arr, g_arr, **opts)
    if transfer_samples is None or transfer_samples < 2 or n_arr.shape[0] < 2:
        return fit
    phase = _transfer_phase(fit, n_arr, t_arr, g_arr, int(transfer_samples))
    if phase < 0:
        return fit
    n_end = n_arr + (phase - n_arr) % transfer_samples  # each stamp's transfer end
    refit = _fit_drifting(n_end, t_arr, g_arr, **opts)
    return DriftingClockFit(**{**refit.__dict__, "transfer_phase": phase})


def _transfer_phase(
    fit: DriftingClockFit,
    n: NDArray[np.int64],
    t: NDArray[np.float64],
    group: NDArray[np.int64],
    b: int,
) -> int:
    """Residue (mod b) of the device's transfer ends, or -1 (see fit_clock_drifting)."""
    resid = t - fit.to_host_time(n)
    uniq, g_idx = np.unique(group, return_inverse=True)
    if uniq.shape[0] < 8:
        return -1
    g_first = np.full(uniq.shape[0], np.iinfo(np.int64).max)
    np.minimum.at(g_first, g_idx, n)
    order = np.argsort(g_first)
    period = float(np.median(fit.period_s))

    def disagreement(extra: NDArray[np.float64]) -> float:
        m = np.full(uniq.shape[0], np.inf)
        np.minimum.at(m, g_idx, resid - extra)
        d = np.diff(m[order])
        return float(np.median(np.abs(d[np.isfinite(d)]))) if np.isfinite(d).any() else math.inf

    none = disagreement(np.zeros_like(resid))
    scores = [disagreement(((p - n) % b) * period) for p in range(b)]
    best = int(np.argmin(scores))
    if scores[best] < 0.5 * none and scores[best] < 0.25 * period:
        return best
    return -1


def _fit_drifting(
    n_arr: NDArray[np.int64],
    t_arr: NDArray[np.float64],
    g_arr: NDArray[np.int64],
    *,
    nominal_rate_hz: float,
    window_s: float | None,
    min_window_s: float,
    max_window_s: float,
    tolerance_s: float,
    curved: bool,
) -> DriftingClockFit:
    """fit_clock_drifting on checked arrays, stamps as they are."""
    if n_arr.shape[0] < 2:
        fit = _nominal_fit(n_arr, t_arr, nominal_rate_hz)
        return DriftingClockFit(
            centres=np.array([float(fit.n_ref)]), half_width=1.0,
            n_ref=np.array([float(fit.n_ref)]), t_ref_s=np.array([fit.t_ref_s]),
            period_s=np.array([fit.period_s]), nominal_rate_hz=nominal_rate_hz,
        )  # fmt: skip
    order = np.lexsort((t_arr, n_arr))
    n_arr, t_arr, g_arr = n_arr[order], t_arr[order], g_arr[order]
    uniq, g_idx = np.unique(g_arr, return_inverse=True)
    n_groups = uniq.shape[0]
    # Groups in time order (by their first index).
    g_first = np.full(n_groups, np.iinfo(np.int64).max)
    np.minimum.at(g_first, g_idx, n_arr)
    g_rank = np.empty(n_groups, dtype=np.int64)
    g_rank[np.argsort(g_first)] = np.arange(n_groups)

    def group_minima(model: DriftingClockFit) -> NDArray[np.float64]:
        resid = t_arr - model.to_host_time(n_arr)
        m = np.full(n_groups, np.inf)
        np.minimum.at(m, g_idx, resid)
        return m[np.argsort(g_rank)]  # in time order

    span_s = float(n_arr[-1] - n_arr[0]) / nominal_rate_hz
    # A group's lowest arrival may sit a few samples above the envelope (its recorded
    # blocks need not end where the device's transfers end), so the structure is judged on
    # the running minimum over group_span groups, and a window spans at least that many.
    group_span = 31
    spacing = float(np.median(np.diff(np.sort(g_first)))) / nominal_rate_hz if n_groups > 1 else 0.0
    min_window_s = max(min_window_s, group_span * spacing)
    length = window_s if window_s is not None else min(max(span_s, min_window_s), max_window_s)
    keep = np.ones(n_arr.shape[0], dtype=bool)
    n_out = 0
    while True:
        half = 0.5 * length * nominal_rate_hz
        centres, n_ref, t_ref, per, curv = _windows_fit(
            n_arr[keep], t_arr[keep], half, nominal_rate_hz, curved
        )
        model = DriftingClockFit(
            centres=centres,
            half_width=half,
            n_ref=n_ref,
            t_ref_s=t_ref,
            period_s=per,
            nominal_rate_hz=nominal_rate_hz,
            outlier_groups=n_out,
            curvature_s=curv,
        )
        mins = group_minima(model)
        centre = _running_median(mins, 7)
        mad = float(np.median(np.abs(mins - centre))) + 1e-9
        low = mins < centre - max(10.0 * mad, 5e-4)
        smooth = _running_min(np.where(low, np.inf, mins), group_span)
        if low.any() and n_out == 0:
            bad_groups = np.argsort(g_rank)[low]
            keep &= ~np.isin(g_idx, bad_groups)
            n_out = int(low.sum())
            continue
        ok = smooth[~low] if (~low).any() else smooth
        spread = float(np.percentile(ok, 95) - np.percentile(ok, 5)) if ok.size > 2 else 0.0
        model = DriftingClockFit(**{**model.__dict__, "spread_s": spread})
        if window_s is not None or spread <= tolerance_s or length / 2 < min_window_s:
            return model
        length /= 2
