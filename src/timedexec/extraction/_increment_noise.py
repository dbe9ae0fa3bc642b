"""The covariance of the response fit's increment errors under its noise model: the
middle of the standard error's sandwich in ``_response.response_increments``."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray

__all__ = ["NoiseModel"]


#: Lags (packages) of the residuals' own covariance in the misfit variance.
_HAC_LAGS = 3


class NoiseModel:
    """The covariance of the increments' errors under the noise model, for the sandwich.

    Two errors reach the increments. The gyro angle's random walk: increments of variance
    ∝ their span (the weights), correlated over the moving average's width. And each
    package's *timing*: its latency jitter ε shifts its level by v·ε, which enters two
    neighbouring increments with opposite signs (E[e_j e_j+1] = -v_j²·σ_ε²). Counted as
    independent noise, the second made the standard error 2-9x the error (clean: 99-100 %
    coverage on the independent recordings and our simulator). The first is measured where
    the joint rests (no level error there: its lag-0..L covariances γ_l), σ_ε² from the
    lag-1 covariance in motion beyond γ_1, and the error of τ is the sandwich A⁻¹ Q A⁻¹
    (A = JᵀWJ) of the covariance they give, positive by construction. (σ_r² as the
    residual variance beyond the level part took up the level estimate's error: a 10 %
    low σ_ε made it 7x the rest increments' variance.)
    """

    def __init__(
        self,
        res: FloatArray,
        use: NDArray[np.bool_],
        wgt: FloatArray,
        speed: FloatArray,
        pj: NDArray[np.int64],
        dt: FloatArray,
        smooth_samples: int,
        typical: FloatArray,
        n_params: int,
    ) -> None:
        n = res.shape[0]
        n_use = np.maximum(np.sum(use, axis=1), 1)
        dof = n_use / np.maximum(n_use - n_params, 1)
        v2 = np.where(use, speed, 0.0) ** 2
        v2_prev = np.where(use, np.take_along_axis(v2, pj, axis=1), 0.0)
        rest = use & (v2 + v2_prev <= (0.05 * np.max(np.abs(speed), axis=1, keepdims=True)) ** 2)
        has_rest = np.sum(rest, axis=1) >= 8
        typical_s = float(np.nanmedian(typical)) if np.isfinite(typical).any() else 1.0
        lags = int(min(max(math.ceil(smooth_samples * float(np.median(dt)) / typical_s), 1), 16))
        gamma = np.zeros((n, lags + 1))
        for lag in range(lags + 1):
            pair = rest[:, lag:] & rest[:, : rest.shape[1] - lag]
            prod = np.where(pair, res[:, lag:] * res[:, : res.shape[1] - lag], 0.0)
            gamma[:, lag] = np.sum(prod, axis=1) / np.maximum(np.sum(pair, axis=1), 1) * dof
        both = use[:, 1:] & use[:, :-1]
        lag1 = np.sum(np.where(both, res[:, 1:] * res[:, :-1], 0.0), axis=1)
        lag1 -= np.where(has_rest, gamma[:, 1], 0.0) * np.sum(both, axis=1)
        s_e2 = np.maximum(
            -lag1 / np.maximum(np.sum(np.where(both, v2[:, :-1], 0.0), axis=1), 1e-30), 0.0
        )
        # Without 8 increments at rest: σ_r² as the variance beyond the level part, no lags.
        gamma[~has_rest] = 0.0
        gamma[~has_rest, 0] = np.maximum(
            np.sum(wgt * (res * res * dof[:, None] - s_e2[:, None] * (v2 + v2_prev)), axis=1)
            / n_use,
            0.0,
        )[~has_rest]
        # Both are properties of the sensor and of the network, not of a trial: estimated
        # per trial from ~35 increments each, they scattered the standard error enough to
        # give the errors heavy tails (99th percentile of |error / se| 3.0-4.4 instead of
        # 2.6: 88-93 % coverage); the chunk's median is used, and a trial's own estimate
        # where it exceeds three times that (a disturbance of that trial: the ratio of two
        # variance estimates from ~35 increments stays below 2 on 99.9 % of trials).
        own_g, own_e = gamma[:, 0].copy(), s_e2.copy()
        if has_rest.any():
            pooled = np.median(gamma[has_rest], axis=0)
            gamma = np.where((has_rest & (own_g <= 3.0 * pooled[0]))[:, None], pooled, gamma)
        self.gamma = gamma
        self.lags = lags
        self.s_e2 = np.where(own_e > 3.0 * np.median(own_e), own_e, np.median(own_e))
        self.v2 = v2
        self.v2_prev = v2_prev
        self.wgt = wgt
        self.span_rel = np.where(use, 1.0 / np.where(wgt > 0, wgt, 1.0), 0.0)  # span / typical

    def cov(self, ci: FloatArray, cj: FloatArray) -> FloatArray:
        """Covariance of Σ w·cᵢ·e and Σ w·cⱼ·e per row."""
        a_, b_ = self.wgt * ci, self.wgt * cj
        out: FloatArray = self.gamma[:, 0] * np.sum(a_ * b_ * self.span_rel, axis=1)
        for lag in range(1, self.lags + 1):
            out = out + self.gamma[:, lag] * np.sum(
                a_[:, lag:] * b_[:, :-lag] + a_[:, :-lag] * b_[:, lag:], axis=1
            )
        # Level k is the end of increment k and the start of the next: its error enters the
        # weighted scores as v_k·ε_k·(g_k - g_k+1), g = w·J.
        da = np.diff(np.pad(a_, ((0, 0), (0, 1))), axis=1)
        db = np.diff(np.pad(b_, ((0, 0), (0, 1))), axis=1)
        total: FloatArray = out + self.s_e2 * np.sum(self.v2 * da * db, axis=1)
        return total

    def misfit_variance(
        self, infl: FloatArray, res: FloatArray, use: NDArray[np.bool_], rows: NDArray[np.bool_]
    ) -> FloatArray:
        """Variance of τ = Σ ψ_j e_j from the residuals' lag covariances beyond the noise
        model's (Bartlett weights 1 - l/(L+1), L = ``_HAC_LAGS``), for ``rows``: what a
        misfit adds to the standard error (negative: none seen)."""
        gamma = self.gamma[rows]
        e2 = self.s_e2[rows, None]
        z = np.where(use, infl, 0.0)
        expect0 = gamma[:, :1] * self.span_rel[rows] + e2 * (self.v2[rows] + self.v2_prev[rows])
        var = np.sum(z * z * (res * res - expect0), axis=1)
        for lag in range(1, _HAC_LAGS + 1):
            # The noise model's lag covariance: γ_l, and at lag 1 the shared level's -v²σ_ε².
            expect = gamma[:, lag, None] if lag < gamma.shape[1] else np.zeros((z.shape[0], 1))
            if lag == 1:
                expect = expect - e2 * self.v2[rows][:, :-1]
            prod = res[:, lag:] * res[:, :-lag] - expect
            w_l = 2 * (1 - lag / (_HAC_LAGS + 1))
            var = var + w_l * np.sum(z[:, lag:] * z[:, :-lag] * prod, axis=1)
        out: FloatArray = var
        return out

    def cov_matrix(self, cols: list[FloatArray]) -> FloatArray:
        """(n, p, p) covariance of the weighted scores of the columns."""
        p = len(cols)
        q = np.empty((cols[0].shape[0], p, p))
        for i in range(p):
            for j in range(i, p):
                q[:, i, j] = q[:, j, i] = self.cov(cols[i], cols[j])
        return q
