"""What RSI can reach: the pose where RSI started, within the correction limits.

In ``RSI_ON(#ABSOLUTE)`` every correction is an offset from the pose where RSI started,
and the configuration's AXISCORR limits bound it (the driver's ``max_correction_deg``): a
sweep planned elsewhere can never be reached, and a move towards it saturates. These
helpers say so before anything moves (:func:`check_reach`) and after a move stopped
converging (:func:`diagnose`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.drivers._rsi_profile import SpeedProfile
from timedexec.errors import ConfigError, DriverError
from timedexec.robots import RobotSpec

__all__ = ["check_reach", "diagnose"]


def check_reach(
    q_rad: ArrayLike,
    lo: FloatArray,
    hi: FloatArray,
    q_start: FloatArray,
    max_correction_rad: FloatArray,
    spec: RobotSpec,
    *,
    margin_rad: ArrayLike = 0.0,
    what: str = "configuration",
) -> None:
    """Raise :class:`ConfigError` for the first of ``q_rad`` (n, 6), widened by
    ``margin_rad``, outside ``[lo, hi]`` (rad): naming the axis, the angle, the correction
    it needs from ``q_start``, the limit that binds and how many configurations leave."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    margin = np.broadcast_to(np.asarray(margin_rad, dtype=float), (6,))
    below, above = q - margin < lo - 1e-9, q + margin > hi + 1e-9
    bad = below | above
    if not bad.any():
        return
    rows = np.flatnonzero(bad.any(axis=1))
    i = int(rows[0])
    j = int(np.flatnonzero(bad[i])[0])
    edge = q[i, j] + (margin[j] if above[i, j] else -margin[j])
    need = math.degrees(edge - q_start[j])
    limit = math.degrees(max_correction_rad[j])
    if abs(need) > limit:
        why = (f"beyond the correction limit of {limit:.1f}° (max_correction_deg, the RSI "
               "configuration's AXISCORR limit)")  # fmt: skip
    else:
        bound = spec.q_max_rad[j] if above[i, j] else spec.q_min_rad[j]
        why = f"beyond A{j + 1}'s joint limit of {math.degrees(bound):.1f}° (less 0.5°)"
    span = ", ".join(
        f"A{k + 1} {math.degrees(lo[k]):.1f}..{math.degrees(hi[k]):.1f}°" for k in range(6)
    )
    raise ConfigError(
        f"{what} {i} is out of RSI's reach: axis A{j + 1} needs {math.degrees(edge):.1f}°, "
        f"a correction of {need:+.1f}° from the pose where RSI started "
        f"({math.degrees(q_start[j]):.1f}°), {why}; {len(rows)} of {len(q)} configurations "
        f"leave the limits (reachable: {span}). Plan the sweep around the start pose "
        "(calibrate --trials N does), start RSI nearer the sweep, or raise "
        "max_correction_deg (rsi://PORT?max_correction_deg=D, --max-correction-deg) "
        "up to the configuration's limit"
    )


def diagnose(
    prof: SpeedProfile,
    *,
    fault: DriverError | None,
    silent_s: float,
    stopped: bool,
    late_count: int,
) -> str | None:
    """What keeps a motion from converging, for a message (None if nothing): a fault,
    axes whose correction is held at its limit, RSI stopped, the robot's late counter."""
    seen: list[str] = []
    if fault is not None:
        seen.append(f"a fault: {fault}")
    corr = prof.corr
    at = np.flatnonzero((corr >= prof.hi - 1e-6) | (corr <= prof.lo + 1e-6))
    if at.size:
        axes = ", ".join(
            f"A{k + 1} at {math.degrees(corr[k]):+.1f}° (limit "
            f"{math.degrees(prof.lo[k] if corr[k] < 0 else prof.hi[k]):+.1f}°)"
            for k in at
        )
        seen.append(f"the correction is saturated: {axes} from the pose where RSI started")
    if stopped:
        seen.append(f"no RSI frame for {silent_s:.1f} s: the robot stopped RSI")
    if late_count > 0:
        seen.append(f"the robot counts {late_count} late answers (<Delay>)")
    return "; ".join(seen) or None
