"""Calibration of a Gaussian process's predictive standard deviation from cross-validation.

A GP's single-trial standard deviation ``s = sqrt(latent var + σ_n²)`` is only as good as
its hyperparameters. The trial noise ``σ_n`` is pinned down by the replicates, but the
latent variance comes from length scales and a signal variance fitted on the start
configurations: with 10 configurations (800 trials) the GP misses pose dependence and
warm-up drift and its held-out errors reach ~1.5 s on a UR10 joint; with 100 it is about
right. Cross-validation already predicts every trial from a model that never saw its start
configuration, so its standardised residuals ``z = (y - mean) / s`` measure how far ``s``
is off.

**Rule.** Per delay and model (joint or combined), over all held-out trials of all folds,

    c = max(1, sqrt(mean(z²)))

the single scale of the predictive standard deviations that maximises the Gaussian log
likelihood of the held-out trials (``d/dc Σ [-log(c s_i) - r_i²/(2 c² s_i²)] = 0`` gives
``c² = mean(z²)``): the scale at which the held-out mean squared error equals the
predicted variance. It calibrates a second moment, which is what ``*_std`` means and what
the executor's bounds take as input, without assuming a shape; the shape of the interval
is the executor's business (a uniform wait for the next cycle boundary plus a Gaussian).
Matching a Gaussian 95 % quantile instead (``q95(|z|) / 1.96``) assumes Gaussian tails:
delays quantised by the controller cycle have shorter ones, so it under-inflates, and the
executor's bounds then covered 93.1 % (UR10) and 93.6 % (KR 5) of held-out trials where
this rule gave 94.8 % and 94.6 % (ten simulated 800-trial sweeps each,
benchmarks/bench_learning_calibration.py; docs/models.md).

**Never below 1.** The CV models are fitted on ``(k-1)/k`` of the configurations, so their
latent variance is at least the final model's: a CV ratio below 1 is either noise or a
model that is already conservative, and shrinking the GP's own variance on that evidence
would trade a known-safe bound for an unverified one.

**Bounds with the right shape.** A Gaussian ``mean ± 1.96 std`` at the calibrated std
over-covers short-tailed delays: on the UR10e (2 ms cycle) 97.3-99.5 % of held-out trials
on new configurations, on the KR 5 (12 ms) 99.5-100 % (issue 39). The GP's 95 % *prediction
bounds* (:meth:`~timedexec.learning.DelayModel.predict_bounds`) therefore take their width
from the same held-out residuals, split-conformal over the configuration-grouped folds:
per delay and model, ``q`` is the ``ceil((n + 1) · 0.95)``-th smallest of the ``n``
held-out ``|z| = |y - mean| / (c · std)`` (:func:`bound_quantile`), and the bound is
``mean ± q · c · std``. It assumes no shape, so it holds on new configurations whatever the
cycle makes of the tails (about 1.65 for a uniform scatter, 1.96 for a Gaussian one). It
changes neither ``c`` nor ``*_std``: the executor's timing bounds, which add their own
uniform cycle wait to a Gaussian, keep taking the second moment.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from timedexec.errors import ConfigError, ModelError

__all__ = [
    "BOUND_CONFIDENCE",
    "CALIBRATED_METHOD",
    "DelayBounds",
    "bound_quantile",
    "gaussian_coverage",
    "std_scale_factor",
]

#: The method whose std training calibrates: the GP, whose std the executor's timing bounds
#: use. A bundle's ``std_scale`` holds its factors (``std_calibration.method`` names it);
#: other methods with a variance report their own predictive std.
CALIBRATED_METHOD = "gpr"
#: The rule's name, stored in bundle manifests beside the factors.
STD_SCALE_RULE = "max(1, sqrt(mean(z^2))), z = held-out (y - mean) / std over the CV folds"
#: Confidence of the GP's prediction bounds stored in bundles (``bound_z``).
BOUND_CONFIDENCE = 0.95
#: The bounds' rule, stored in bundle manifests beside the quantiles.
BOUND_RULE = (
    "split-conformal: the ceil((n+1)*0.95)-th smallest |z|, z = held-out (y - mean) / "
    "(c * std) over the configuration-grouped CV folds; bound = mean +- q * c * std"
)


#: The Gaussian two-sided 95 % quantile: the bound of methods and bundles without ``bound_z``.
GAUSSIAN_Z95 = NormalDist().inv_cdf(0.975)
#: The delays a bundle models (its manifest's per-delay entries).
DELAYS = ("actuation_delay", "response_delay")


class DelayBounds(NamedTuple):
    """95 % prediction bounds of single future trials' delays (``DelayModel.predict_bounds``).

    Attributes
    ----------
    actuation_lower_s, actuation_upper_s, response_lower_s, response_upper_s : ndarray
        Shape (n,), s.
    """

    actuation_lower_s: Any
    actuation_upper_s: Any
    response_lower_s: Any
    response_upper_s: Any


def read_per_model(raw: Any, keys: Sequence[str], name: str) -> dict[str, dict[str, float]]:
    """A manifest's ``{delay: {key: positive number}}`` entry ``name`` (``std_scale``: the
    GP std's factors, ``bound_z``: its bounds' half-widths); missing entries mean none."""
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ModelError(f"manifest {name} must map delays to {{model: number}}, got {raw!r}")
    out: dict[str, dict[str, float]] = {}
    for delay, by_key in raw.items():
        if delay not in DELAYS or not isinstance(by_key, dict):
            raise ModelError(
                f"manifest {name}: entry {delay!r}: {by_key!r} must be one of "
                f"{', '.join(DELAYS)} mapping models ({', '.join(keys)}) to numbers"
            )
        out[delay] = {}
        for key, value in by_key.items():
            try:
                c = float(value)
            except (TypeError, ValueError):
                c = float("nan")
            if not (math.isfinite(c) and c > 0):
                raise ModelError(
                    f"manifest {name}[{delay!r}][{key!r}] = {value!r}: it must be a finite "
                    "number > 0 (training writes them); fix or delete the entry"
                )
            out[delay][str(key)] = c
    return out


def _standardised(residual_s: ArrayLike, std_s: ArrayLike) -> np.ndarray:
    r = np.asarray(residual_s, dtype=float).ravel()
    s = np.asarray(std_s, dtype=float).ravel()
    if r.shape != s.shape:
        raise ValueError(f"residuals {r.shape} and stds {s.shape} differ in shape")
    ok = np.isfinite(r) & np.isfinite(s) & (s > 0)
    return np.asarray(r[ok] / s[ok])


def std_scale_factor(residual_s: ArrayLike, std_s: ArrayLike) -> float:
    """Scale for a GP's predictive std from held-out residuals: ``max(1, sqrt(mean(z²)))``.

    Parameters
    ----------
    residual_s : array, shape (n,)
        Held-out ``y - mean``, s.
    std_s : array, shape (n,)
        The GP's predictive single-trial standard deviation at the same trials, s.

    Returns
    -------
    float
        Factor >= 1 to multiply the trial standard deviation by; 1.0 without any usable
        trial (non-finite or non-positive std rows are skipped).
    """
    z = _standardised(residual_s, std_s)
    if len(z) == 0:
        return 1.0
    return max(1.0, math.sqrt(float(np.mean(z * z))))


def gaussian_coverage(
    residual_s: ArrayLike, std_s: ArrayLike, confidence: float = 0.95, scale: float = 1.0
) -> float:
    """Share of trials inside the Gaussian ``confidence`` interval ``mean ± q · scale · std``.

    ``q`` is the two-sided standard normal quantile (1.96 at 0.95). NaN without trials.
    """
    z = _standardised(residual_s, std_s)
    if len(z) == 0:
        return float("nan")
    q = NormalDist().inv_cdf(0.5 + 0.5 * float(confidence))
    return float(np.mean(np.abs(z) <= q * float(scale)))


def bound_quantile(
    residual_s: ArrayLike, std_s: ArrayLike, confidence: float = BOUND_CONFIDENCE
) -> float:
    """Split-conformal half-width of a ``confidence`` bound, in units of ``std_s``.

    The ``ceil((n + 1) · confidence)``-th smallest of the ``n`` held-out ``|residual / std|``:
    a new trial exchangeable with the held-out ones lies within ``mean ± q · std`` with
    probability at least ``confidence``.

    Parameters
    ----------
    residual_s : array, shape (n,)
        Held-out ``y - mean``, s.
    std_s : array, shape (n,)
        The standard deviation the bound will multiply (the calibrated trial std), s.
    confidence : float
        In (0, 1).

    Returns
    -------
    float
        ``q > 0``; NaN when ``n`` is too small for the rank (``(n + 1) · confidence > n``),
        the caller then keeps a Gaussian bound.
    """
    if not 0.0 < float(confidence) < 1.0:
        raise ConfigError(f"confidence={confidence!r} must lie in (0, 1), e.g. 0.95")
    z = np.sort(np.abs(_standardised(residual_s, std_s)))
    rank = math.ceil((len(z) + 1) * float(confidence))
    if rank > len(z):
        return float("nan")
    return float(z[rank - 1])
