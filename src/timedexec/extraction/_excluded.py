"""Trials extraction leaves out of the sweep and lists flagged: rows with a time value that
is not finite (``bad_time``) and rows in damaged chunks (``damaged``)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.errors import RecordingError
from timedexec.recording import DamagedChunkError, RecordingReader

__all__ = ["bad_time_rows", "lost_trials"]


#: Per-trial scalar times extraction cannot do without; a trial where one is not finite is
#: left out of the sweep's statistics and flagged ``bad_time``.
_TIME_FIELDS = ("t0_s", "cmd_send_time_s")


def bad_time_rows(path: str) -> tuple[NDArray[np.int64], dict[int, str]] | None:
    """Rows whose ``t0_s`` or ``cmd_send_time_s`` is not finite (a corrupt value, a
    recorder's bug) with their flag, or None. One such value used to spoil every trial of
    the sweep (NaN in a sweep-wide statistic) or end in a traceback.

    Raises
    ------
    RecordingError
        When no trial has finite times: nothing can be extracted (the message names the
        field).
    """
    with RecordingReader(path) as reader:
        n = reader.n_trials
        bad = np.zeros(n, dtype=bool)
        for name in _TIME_FIELDS:
            if name not in reader.fields:
                continue
            try:
                values = np.asarray(reader.read(name), dtype=np.float64)
            except DamagedChunkError:
                continue  # the damaged-chunk path deals with it
            wrong = ~np.isfinite(values)
            if n and wrong.all():
                raise RecordingError(
                    f"{path}: field {name!r} is not finite in any of its {n} trials; no "
                    "trial can be timed: the recorder wrote no usable times (record the "
                    "sweep again)"
                )
            bad |= wrong
    if not bad.any():
        return None
    rows = np.flatnonzero(bad)
    return rows, {int(r): "bad_time" for r in rows}


def lost_trials(
    reader: RecordingReader, rows: NDArray[np.int64], t0_scale: float
) -> tuple[NDArray[np.int64], FloatArray, NDArray[np.int64]]:
    """Plan index, start time (s; NaN if unreadable) and row of the left-out ``rows`` whose
    plan index can still be read; rows whose ``trial`` chunk is damaged too are left out."""
    trials: list[int] = []
    starts: list[float] = []
    kept: list[int] = []
    for r in rows.tolist():
        try:
            trials.append(int(reader.read("trial", np.array([r]))[0]))
        except RecordingError:
            continue
        kept.append(r)
        try:
            starts.append(float(reader.read("t0_s", np.array([r]))[0]) * t0_scale)
        except RecordingError:
            starts.append(math.nan)
    return (
        np.array(trials, dtype=np.int64),
        np.array(starts, dtype=np.float64),
        np.array(kept, dtype=np.int64),
    )
