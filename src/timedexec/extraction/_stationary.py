"""Stationary analysis: zero-rate, noise PSD and the low-pass FIR designed from it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from timedexec._types import FloatArray

__all__ = ["StillAnalysis", "analyse_still", "design_lowpass"]


@dataclass(frozen=True)
class StillAnalysis:
    """What a still recording tells about the gyro.

    Attributes
    ----------
    bias_rad_s : ndarray, shape (3,)
        Zero-rate offset per axis, rad/s.
    noise_std_rad_s : ndarray, shape (3,)
        Sample standard deviation per axis, rad/s.
    noise_density_rad_s_rthz : ndarray, shape (3,)
        Median one-sided noise density per axis, rad/s/√Hz.
    freq_hz, psd : ndarray
        Welch PSD of the still recording (mean of the axes), (rad/s)²/Hz.
    """

    bias_rad_s: FloatArray
    noise_std_rad_s: FloatArray
    noise_density_rad_s_rthz: FloatArray
    freq_hz: FloatArray
    psd: FloatArray


def analyse_still(rate_rad_s: FloatArray, fs_hz: float, *, nperseg: int = 4096) -> StillAnalysis:
    """Zero-rate offset and noise of a still recording (Welch PSD, DESIGN.md §1).

    Parameters
    ----------
    rate_rad_s : ndarray, shape (n, 3)
        Gyro rates while the robot is still, rad/s.
    fs_hz : float
        Sample rate, Hz.
    """
    x = np.asarray(rate_rad_s, dtype=float)
    bias = x.mean(axis=0)
    detrended = x - bias
    freq, pxx = signal.welch(detrended, fs=fs_hz, nperseg=min(nperseg, len(x)), axis=0)
    band = freq > 1.0
    density = np.sqrt(np.median(pxx[band], axis=0))
    return StillAnalysis(
        bias_rad_s=bias,
        noise_std_rad_s=detrended.std(axis=0),
        noise_density_rad_s_rthz=density,
        freq_hz=freq,
        psd=pxx.mean(axis=1),
    )


def design_lowpass(
    still: StillAnalysis,
    motion_rad_s: FloatArray,
    fs_hz: float,
    *,
    numtaps: int = 161,
    margin_db: float = 10.0,
    bounds_hz: tuple[float, float] = (20.0, 400.0),
) -> tuple[FloatArray, float]:
    """Linear-phase low-pass FIR whose cutoff is where the motion's PSD meets the noise floor.

    Parameters
    ----------
    still : StillAnalysis
        The noise PSD.
    motion_rad_s : ndarray, shape (k, m)
        Projected gyro speeds of a few trials during motion.
    fs_hz : float
        Sample rate, Hz.
    numtaps : int
        Filter length (odd; group delay ``(numtaps - 1) / 2`` samples, compensated).
    margin_db : float
        The cutoff is the highest frequency at which the motion PSD exceeds the noise PSD
        by this margin.
    bounds_hz : (float, float)
        Clamp for the cutoff.

    Returns
    -------
    taps : ndarray, shape (numtaps,)
    cutoff_hz : float
    """
    nper = min(1024, motion_rad_s.shape[1])
    freq, p_motion = signal.welch(motion_rad_s, fs=fs_hz, nperseg=nper, axis=1)
    p_motion = p_motion.mean(axis=0)
    noise = np.interp(freq, still.freq_hz, still.psd)
    above = p_motion > noise * 10 ** (margin_db / 10)
    cutoff = float(freq[above].max()) if above.any() else bounds_hz[0]
    cutoff = float(np.clip(cutoff, *bounds_hz))
    taps = signal.firwin(numtaps | 1, cutoff, fs=fs_hz)
    return taps, cutoff
