"""Sample-counter unwrapping and gap accounting.

The gyro's uint16 counter wraps every 65536 samples (8.192 s at 8 kHz). The unwrapped index
starts at the first counter seen (so ``index % 65536 == counter`` holds until a sensor reset)
and advances by
the modular step between accepted frames. A step larger than one is a gap: the missing
samples are counted and logged with their position. Frames whose counter does not fit the
sequence (a chance CRC match on corrupted bytes, a duplicate) are dropped and counted unless
the next frame confirms the new sequence (a real jump or a sensor reset). When arrival times
are given, a silence longer than half a wrap period is bridged by choosing the number of
wraps that agrees with the elapsed host time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError

__all__ = ["CounterUnwrapper", "UnwrapResult", "relative_counter_rows", "unwrap_counter"]

_WRAP = 65536
_EMPTY = np.zeros(0, dtype=np.int64)
_EMPTY.flags.writeable = False


def unwrap_counter(counter: ArrayLike, *, start: int | None = None) -> NDArray[np.int64]:
    """Unwrap a recorded uint16 counter sequence (offline, no gap rejection).

    Parameters
    ----------
    counter : array_like of int, shape (n,)
        Counters in 0..65535, in stream order, consecutive frames at most 32767 apart.
    start : int, optional
        Unwrapped index of the first sample; defaults to ``counter[0]``. Must be congruent
        to ``counter[0]`` modulo 65536.

    Returns
    -------
    ndarray of int64, shape (n,)
        Unwrapped sample indices.
    """
    c = np.asarray(counter, dtype=np.int64)
    if c.ndim != 1:
        raise ConfigError(f"counter must have shape (n,), got {c.shape}")
    if c.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    first = int(c[0]) if start is None else int(start)
    if (first - int(c[0])) % _WRAP:
        raise ConfigError(
            f"start={start} is not congruent to counter[0]={int(c[0])} modulo 65536; "
            "pick start = counter[0] + k * 65536"
        )
    steps = np.diff(c) % _WRAP
    out = np.empty_like(c)
    out[0] = first
    np.cumsum(steps, out=out[1:])
    out[1:] += first
    return out


@dataclass(frozen=True, kw_only=True, eq=False)
class UnwrapResult:
    """Result of one :meth:`CounterUnwrapper.update` call.

    Attributes
    ----------
    index : ndarray of int64, shape (m,)
        Unwrapped sample index of each accepted frame.
    keep : ndarray of bool, shape (n,)
        Which of the input frames were accepted (m of them).
    gap_start : ndarray of int64, shape (g,)
        Unwrapped index of the first missing sample of each new gap.
    gap_missing : ndarray of int64, shape (g,)
        Number of missing samples of each new gap.
    discontinuity : bool
        The counter sequence restarted (sensor reset) in this call; indices after it are
        re-anchored and a clock model must be refitted from scratch.
    """

    index: NDArray[np.int64]
    keep: NDArray[np.bool_]
    gap_start: NDArray[np.int64]
    gap_missing: NDArray[np.int64]
    discontinuity: bool = False


class CounterUnwrapper:
    """Unwrap the counter across calls and account for gaps.

    Parameters
    ----------
    nominal_rate_hz : float
        Sample rate used to bridge long silences with arrival times, Hz.
    max_step : int
        Largest counter step accepted without confirmation by the next frame, samples.
        Default 4096 (0.5 s at 8 kHz).
    """

    def __init__(self, *, nominal_rate_hz: float = 8000.0, max_step: int = 4096) -> None:
        if not nominal_rate_hz > 0:
            raise ConfigError(f"nominal_rate_hz={nominal_rate_hz!r} must be positive, Hz")
        if not 1 <= max_step < _WRAP // 2:
            raise ConfigError(f"max_step={max_step!r} must be in 1..32767 samples")
        self.nominal_rate_hz = float(nominal_rate_hz)
        self.max_step = int(max_step)
        self._last_counter: int | None = None
        self._last_index = 0
        self._last_arrival: float | None = None
        self._gap_start: list[NDArray[np.int64]] = []
        self._gap_missing: list[NDArray[np.int64]] = []
        self.missing_samples = 0
        """Samples missing from the sequence (sum of gap lengths)."""
        self.dropped_frames = 0
        """Valid-CRC frames dropped because their counter did not fit the sequence."""
        self.discontinuities = 0
        """Counter restarts (sensor resets) confirmed by the following frame."""

    @property
    def last_index(self) -> int | None:
        """Unwrapped index of the last accepted frame (None before the first)."""
        return None if self._last_counter is None else self._last_index

    @property
    def gaps(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """All gaps so far: (first missing index, number missing), each shape (g,)."""
        if not self._gap_start:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.concatenate(self._gap_start), np.concatenate(self._gap_missing)

    @property
    def gap_count(self) -> int:
        """Number of gaps so far."""
        return sum(int(g.shape[0]) for g in self._gap_start)

    def update(
        self, counter: ArrayLike, arrival_s: float | ArrayLike | None = None
    ) -> UnwrapResult:
        """Unwrap the next frames.

        Parameters
        ----------
        counter : array_like of int, shape (n,)
            Wrapped counters (0..65535) in stream order.
        arrival_s : float or array_like of float, shape (n,), optional
            Host arrival time of each frame (or one time for all), s; bridges silences
            longer than 4.096 s.

        Returns
        -------
        UnwrapResult
        """
        arrival = None if arrival_s is None else np.atleast_1d(np.asarray(arrival_s, np.float64))
        if self._last_counter is not None:
            fast = self._fast_path(counter, arrival)
            if fast is not None:
                return fast
        c = np.asarray(counter, dtype=np.int64)
        n = int(c.shape[0])
        if n == 0:
            return UnwrapResult(
                index=np.zeros(0, dtype=np.int64),
                keep=np.zeros(0, dtype=bool),
                gap_start=np.zeros(0, dtype=np.int64),
                gap_missing=np.zeros(0, dtype=np.int64),
            )
        first_ever = self._last_counter is None
        prev_counter = int(c[0]) - 1 if self._last_counter is None else self._last_counter
        prev_index = int(c[0]) - 1 if first_ever else self._last_index
        steps = np.empty(n, dtype=np.int64)
        steps[0] = (int(c[0]) - prev_counter) % _WRAP
        steps[1:] = np.diff(c) % _WRAP
        bridged = False
        if not first_ever and arrival is not None and self._last_arrival is not None:
            silence_s = float(arrival[0]) - self._last_arrival
            if silence_s * self.nominal_rate_hz > _WRAP // 2:
                expected = silence_s * self.nominal_rate_hz
                wraps = max(round((expected - int(steps[0])) / _WRAP), 0)
                steps[0] += wraps * _WRAP
                bridged = True
        ok = (steps >= 1) & (steps <= self.max_step)
        if bridged:
            ok[0] = bool(steps[0] >= 1)
        if ok.all():
            index = prev_index + np.cumsum(steps)
            keep = np.ones(n, dtype=bool)
            gap_mask = steps > 1
            gap_start = index[gap_mask] - steps[gap_mask] + 1
            gap_missing = steps[gap_mask] - 1
            discontinuity = False
        else:
            index, keep, gap_start, gap_missing, discontinuity = self._slow_path(
                c, steps, ok, prev_counter, prev_index
            )
        if index.shape[0]:
            self._last_index = int(index[-1])
            last_kept = int(np.flatnonzero(keep)[-1])
            self._last_counter = int(c[last_kept])
            if arrival is not None:
                self._last_arrival = float(arrival[last_kept if arrival.shape[0] > 1 else 0])
        if gap_start.shape[0]:
            self._gap_start.append(gap_start)
            self._gap_missing.append(gap_missing)
            self.missing_samples += int(gap_missing.sum())
        return UnwrapResult(
            index=index,
            keep=keep,
            gap_start=gap_start,
            gap_missing=gap_missing,
            discontinuity=discontinuity,
        )

    def _fast_path(
        self, counter: ArrayLike, arrival: NDArray[np.float64] | None
    ) -> UnwrapResult | None:
        """Healthy stream: each counter is the previous one plus one (uint16 arithmetic
        wraps by itself). Returns None when the general path is needed."""
        assert self._last_counter is not None
        c16 = np.asarray(counter)
        if c16.dtype != np.uint16 or c16.ndim != 1 or c16.shape[0] == 0:
            return None
        n = int(c16.shape[0])
        if int(c16[0]) != (self._last_counter + 1) % _WRAP:
            return None
        if n > 1 and not np.all(np.diff(c16) == 1):
            return None
        if (
            arrival is not None
            and self._last_arrival is not None
            and ((float(arrival[0]) - self._last_arrival) * self.nominal_rate_hz > _WRAP // 2)
        ):
            return None  # a long silence: let the general path count the wraps
        first = self._last_index + 1
        self._last_index += n
        self._last_counter = int(c16[-1])
        if arrival is not None:
            self._last_arrival = float(arrival[-1])
        return UnwrapResult(
            index=np.arange(first, first + n, dtype=np.int64),
            keep=np.ones(n, dtype=bool),
            gap_start=_EMPTY,
            gap_missing=_EMPTY,
        )

    def _slow_path(
        self,
        c: NDArray[np.int64],
        steps: NDArray[np.int64],
        ok: NDArray[np.bool_],
        prev_counter: int,
        prev_index: int,
    ) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.int64], NDArray[np.int64], bool]:
        """Frame-by-frame path for batches with suspicious steps."""
        n = int(c.shape[0])
        counters = c.tolist()
        keep = np.zeros(n, dtype=bool)
        index: list[int] = []
        gap_start: list[int] = []
        gap_missing: list[int] = []
        discontinuity = False
        last_c, last_i = prev_counter, prev_index
        for j in range(n):
            step = int(steps[0]) if j == 0 else (counters[j] - last_c) % _WRAP
            if (j == 0 and ok[0]) or 1 <= step <= self.max_step:
                accepted = step
            else:
                confirmed = (
                    j + 1 < n
                    and (counters[j + 1] - counters[j]) % _WRAP == 1
                    and not 1 <= (counters[j + 1] - last_c) % _WRAP <= self.max_step
                )
                if not confirmed:
                    self.dropped_frames += 1
                    continue
                if self.max_step < step < _WRAP // 2:
                    accepted = step  # a long but real gap
                else:
                    # Sensor reset or backwards jump: re-anchor, the gap length is unknown.
                    accepted = 1
                    discontinuity = True
                    self.discontinuities += 1
            if accepted > 1:
                gap_start.append(last_i + 1)
                gap_missing.append(accepted - 1)
            last_i += accepted
            last_c = counters[j]
            keep[j] = True
            index.append(last_i)
        return (
            np.asarray(index, dtype=np.int64),
            keep,
            np.asarray(gap_start, dtype=np.int64),
            np.asarray(gap_missing, dtype=np.int64),
            discontinuity,
        )


def relative_counter_rows(
    counter: ArrayLike,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Sample positions of recorded counter rows relative to each row's first sample.

    A row is one trial's recorded window, in arrival order, as a lossy USB stream delivers
    it: blocks may be lost (the counter jumps ahead), delivered twice (the counter repeats)
    or out of order (it steps back). Each frame's position is its counter minus the
    row's first counter, modulo 65536 and taken in -32768..32767 (a window is far shorter
    than a wrap). A frame is kept when its position is ahead of every frame before it
    (duplicates and backward steps are dropped) and it is not a lone corrupted counter (one
    frame off the sequence whose neighbours agree with each other).

    Parameters
    ----------
    counter : array_like of int, shape (n, g)
        Recorded uint16 counters, one row per trial window.

    Returns
    -------
    position : ndarray of int64, shape (n, g)
        Sample position of each frame relative to the row's first frame (samples).
    keep : ndarray of bool, shape (n, g)
        Frames to use; positions of kept frames increase strictly along each row, and
        position jumps larger than one are gaps (samples lost).
    """
    arr = np.asarray(counter)
    if arr.ndim != 2:
        raise ConfigError(f"counter must have shape (n, g), got {arr.shape}")
    n, g = arr.shape
    if g < 2 or g > _WRAP // 2 or arr.dtype.kind not in "iu":
        c = arr.astype(np.int64)
        pos = (c - c[:, :1] + _WRAP // 2) % _WRAP - _WRAP // 2
        if g < 2:
            return pos, np.ones(c.shape, dtype=bool)
        clean = np.all(np.diff(pos, axis=1) == 1, axis=1)
    else:
        # Fast path: a clean row counts up by one (uint16 arithmetic wraps by itself), so
        # its positions are 0..g-1; only the other rows need the full treatment.
        c16 = arr if arr.dtype == np.uint16 else (arr.astype(np.int64) % _WRAP).astype(np.uint16)
        clean = np.all(np.diff(c16, axis=1) == 1, axis=1)
        pos = np.empty((n, g), dtype=np.int64)
        pos[:] = np.arange(g)
        dirty = np.flatnonzero(~clean)
        if dirty.size:
            c = c16[dirty].astype(np.int64)
            pos[dirty] = (c - c[:, :1] + _WRAP // 2) % _WRAP - _WRAP // 2
    keep = np.ones((n, g), dtype=bool)
    bad = np.flatnonzero(~clean)
    if bad.size:
        p = pos[bad]
        lone = np.zeros(p.shape, dtype=bool)
        if p.shape[1] > 2:
            lone[:, 1:-1] = (p[:, 2:] - p[:, :-2] == 2) & (p[:, 1:-1] - p[:, :-2] != 1)
        q = np.where(lone, np.iinfo(np.int64).min, p)
        prev_max = np.maximum.accumulate(q, axis=1)
        ahead = np.ones(p.shape, dtype=bool)
        ahead[:, 1:] = q[:, 1:] > prev_max[:, :-1]
        keep[bad] = ahead & ~lone & (p >= 0)
    return pos, keep
