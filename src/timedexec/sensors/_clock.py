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
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError, SensorError

__all__ = [
    "ClockFit",
    "SensorClock",
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
