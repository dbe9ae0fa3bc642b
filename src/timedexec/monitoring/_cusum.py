"""The sequential test: a two-sided CUSUM on standardized residuals and its threshold.

Siegmund's approximation of the average run length of a one-sided CUSUM
``S_n = max(0, S_{n-1} + z_n - k)`` (alarm when ``S_n > h``) with ``z_n ~ N(mu, 1)``:

    ARL(mu) = (exp(-2 D b) + 2 D b - 1) / (2 D^2),   D = mu - k,  b = h + 1.166

(``b^2`` at ``D = 0``). The two-sided test runs the upper and the lower CUSUM; its run length
satisfies ``1/ARL = 1/ARL+ + 1/ARL-``. The warm-up that standardizes the residuals is itself
estimated: its location error makes ``mu`` a random ``N(0, 1/N)`` for a warm-up of ``N``
moves, and :func:`threshold_for_arl` chooses ``h`` so that the *expected* false-alarm rate
over that error meets the target (Gauss-Hermite quadrature).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from timedexec.errors import ConfigError

__all__ = [
    "SIEGMUND_CORRECTION",
    "arl_one_sided",
    "arl_two_sided",
    "check_arl0",
    "false_alarm_rate",
    "run_lengths",
    "threshold_for_arl",
]

_NODES = np.polynomial.hermite_e.hermegauss(40)

#: Siegmund's overshoot correction (2 x 0.583) added to the threshold.
SIEGMUND_CORRECTION = 1.166


def arl_one_sided(h: float, k: float, mu: float | NDArray[np.float64] = 0.0) -> NDArray[np.float64]:
    """Siegmund's ARL of the upper CUSUM with reference ``k`` and threshold ``h`` when the
    standardized residuals are N(``mu``, 1) (moves; array in, array out)."""
    d = np.asarray(mu, dtype=float) - k
    b = h + SIEGMUND_CORRECTION
    x = 2.0 * d * b
    small = np.abs(d) < 1e-9
    safe = np.where(small, 1.0, d)
    with np.errstate(over="ignore"):
        arl = (np.exp(-x) + x - 1.0) / (2.0 * safe * safe)
    return np.where(small, b * b, arl)


def arl_two_sided(h: float, k: float, mu: float | NDArray[np.float64] = 0.0) -> NDArray[np.float64]:
    """ARL of the two-sided CUSUM (upper and lower, same ``h`` and ``k``), moves."""
    up = arl_one_sided(h, k, mu)
    down = arl_one_sided(h, k, -np.asarray(mu, dtype=float))
    return 1.0 / (1.0 / up + 1.0 / down)


def false_alarm_rate(h: float, k: float, warmup_moves: int | None = None) -> float:
    """Expected false alarms per move of the two-sided CUSUM with no change.

    ``warmup_moves=None``: the in-control distribution known exactly (``1/ARL0``); else the
    average of ``1/ARL(mu)`` over the warm-up's location error ``mu ~ N(0, 1/warmup_moves)``.
    """
    if warmup_moves is None:
        return float(1.0 / arl_two_sided(h, k, 0.0))
    x, w = _NODES
    mu = x / math.sqrt(warmup_moves)
    return float(np.sum(w / arl_two_sided(h, k, mu)) / math.sqrt(2.0 * math.pi))


def check_arl0(arl0_moves: float) -> float:
    """``arl0_moves`` if it is a number of moves >= 10, else a ConfigError naming it."""
    if not (isinstance(arl0_moves, int | float) and math.isfinite(arl0_moves) and arl0_moves >= 10):
        raise ConfigError(
            f"arl0_moves={arl0_moves!r} is out of range; use a number of moves >= 10 "
            "(e.g. 10000: one false alarm per 10,000 moves)"
        )
    return float(arl0_moves)


def threshold_for_arl(arl0_moves: float, k: float, warmup_moves: int | None = None) -> float:
    """The threshold ``h`` whose (expected) false-alarm rate is ``1 / arl0_moves`` per move.

    Raises
    ------
    ConfigError
        ``arl0_moves`` below 10 or ``k`` not in (0, 3].
    """
    check_arl0(arl0_moves)
    if not (math.isfinite(k) and 0 < k <= 3):
        raise ConfigError(
            f"reference k={k!r} is out of range; use 0 < k <= 3 (half the standardized "
            "shift to detect fastest; 0.5 for one standard deviation)"
        )
    target = 1.0 / arl0_moves
    lo, hi = 0.0, 200.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if false_alarm_rate(mid, k, warmup_moves) > target:
            lo = mid
        else:
            hi = mid
    return hi


def run_lengths(z: NDArray[np.float64], h: float, k: float) -> NDArray[np.float64]:
    """Moves to the first alarm of the two-sided CUSUM on each row of ``z`` (chains, moves);
    ``inf`` where a chain never alarms. Vectorised over chains (for verification)."""
    z = np.atleast_2d(np.asarray(z, dtype=float))
    n_chains, n_moves = z.shape
    up = np.zeros(n_chains)
    down = np.zeros(n_chains)
    first = np.full(n_chains, np.inf)
    alive = np.ones(n_chains, dtype=bool)
    for i in range(n_moves):
        up = np.maximum(0.0, up + z[:, i] - k)
        down = np.maximum(0.0, down - z[:, i] - k)
        fired = alive & ((up > h) | (down > h))
        if fired.any():
            first[fired] = i + 1
            alive &= ~fired
            up[fired] = 0.0
            down[fired] = 0.0
    return first
