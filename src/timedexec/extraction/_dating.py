"""When each reported package was sampled, by the controller's own clock.

The response fit aligns the reported positions with the gyro angle at the instant each
package describes. Dated by its *arrival* (the host's receive time), a package carries the
network's and both hosts' scheduling jitter into the fit as if the state had been sampled
then, and where packages were held up for a stretch of the motion (a controller or host
thread that stalled and then sent or read the backlog) the single shift τ the fit finds is
neither the held-up packages' age nor the others': through the UR5e twin a 19 ms stall in
the middle of a trial moved the fitted age 1.6 ms off the trial's mean package age (1.0 ms
off its motion-weighted age) with a standard error of 0.07 ms.

Every driver records the controller's time stamp of each package (RTDE ``timestamp``,
RSI ``IPOC``, ``docs/architecture.md``: controller time is mapped to host time by a fitted
clock model, never by per-read host stamps alone). Within one trial (under a second) the
two clocks differ by an offset (drift: 150 ppm is 0.1 ms over a trial, spread evenly
about its middle), so each package is dated ``controller time + the trial's median of
arrival - controller time``; the fit then finds the pipeline's age on that timeline and the
trial's response delay — the mean age of its packages at arrival, what back-dating a
received state needs — is that fitted age plus the mean of ``arrival - dated`` over the
trial's packages. The offset cancels, so no clock fit is needed.

A recording without controller time stamps, or whose stamps do not advance by about one
controller period per package (a driver that leaves them empty, a unit other than
seconds), keeps the arrival times.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray

__all__ = ["dated_by_controller", "sampling_offsets"]

#: Packages with a stamp a trial needs before its stamps are trusted.
_MIN_STAMPED = 8
#: How far the stamps' median step per package may be from the controller period.
_PERIOD_TOLERANCE = 0.1


def dated_by_controller(
    host: FloatArray,
    controller: FloatArray | None,
    present: NDArray[np.bool_],
    period_s: float,
) -> tuple[FloatArray, FloatArray]:
    """Each package's sampling instant on the host's trial clock, and each trial's mean
    package lateness against it.

    Parameters
    ----------
    host : ndarray, shape (n, p)
        Package arrival times, s (trial time).
    controller : ndarray, shape (n, p), optional
        The packages' controller time stamps, s (any origin); ``None`` where the recording
        has none.
    present : ndarray of bool, shape (n, p)
        Packages that arrived.
    period_s : float
        Controller period, s.

    Returns
    -------
    dated : ndarray, shape (n, p)
        Arrival times where a trial's stamps cannot be used, else the stamps moved by the
        trial's median of arrival - stamp, s; NaN where no package arrived.
    lateness : ndarray, shape (n,)
        Mean of ``host - dated`` over each trial's packages, s (0 where the arrival times
        are kept): add it to the age fitted on ``dated`` to get the mean age at arrival.
    """
    n = host.shape[0]
    dated = np.where(present, host, np.nan)
    lateness = np.zeros(n)
    if controller is None:
        return dated, lateness
    stamp = np.where(present & np.isfinite(controller), controller, np.nan)
    rows = _stamped_rows(stamp, period_s)
    row = stamp[rows] + np.nanmedian(host[rows] - stamp[rows], axis=1)[:, None]
    dated[rows] = row
    lateness[rows] = np.nanmean(host[rows] - row, axis=1)
    return dated, lateness


def _stamped_rows(stamp: FloatArray, period_s: float) -> NDArray[np.int64]:
    """The trials whose stamps (NaN where no package) can be used: enough of them, each
    advancing, by about one controller period per package."""
    steps = np.diff(stamp, axis=1)  # NaN across a lost package: its neighbours' steps count
    has_step = np.isfinite(steps)
    rows = np.flatnonzero(
        (np.sum(np.isfinite(stamp), axis=1) >= _MIN_STAMPED)
        & has_step.any(axis=1)
        & ~np.any(has_step & ~(steps > 0), axis=1)  # stamps that advance
    )
    typical = np.nanmedian(np.where(has_step[rows], steps[rows], np.nan), axis=1)
    return rows[np.abs(typical / period_s - 1.0) < _PERIOD_TOLERANCE]


def sampling_offsets(
    host: FloatArray, controller: FloatArray, response: FloatArray, period_s: float
) -> FloatArray:
    """Each trial's host time of sampling minus the controller stamp, s, shape (n,).

    A trial dated by its stamps (:func:`dated_by_controller`) has as response delay the
    mean age of its packages at arrival, so its packages' mean of arrival - stamp less that
    is where, on the host's clock, the stamps' instants lie: the gyro's dating of the
    state, which the publisher's phase does not move (it moves arrival - stamp and the
    response alike). ``host`` and ``controller`` as in :func:`dated_by_controller` (NaN
    where no package arrived), ``response`` (n,); NaN where either is missing or the trial
    kept its arrival times (its response then says nothing about the stamps). On the
    trial's clock (add its start for the host's)."""
    d = host - controller
    seen = np.isfinite(d)
    n = seen.sum(axis=1)
    mean = np.where(n > 0, np.where(seen, d, 0.0).sum(axis=1) / np.maximum(n, 1), np.nan)
    out = np.full(len(mean), np.nan)
    rows = _stamped_rows(np.where(seen, controller, np.nan), period_s)
    out[rows] = mean[rows] - response[rows]
    return out
