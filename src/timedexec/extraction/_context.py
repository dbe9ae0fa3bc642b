"""The sweep-wide context of an extraction: what every chunk of trials needs from the
whole recording (the contract, the low-pass filter, the sensor clock per session, each
row's unwrapped first sample, time order and sessions), and the reader that shows only the
readable rows of a recording with damaged chunks.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.extraction._check import Contract, read_contract
from timedexec.extraction._stationary import StillAnalysis, analyse_still, design_lowpass
from timedexec.recording import RecordingReader
from timedexec.sensors import (
    DriftingClockFit,
    fit_clock_drifting,
    fit_clock_lower_envelope,
    relative_counter_rows,
)

__all__ = ["RowsView", "SweepContext", "open_rows", "sweep_context"]


#: Segments per trial whose lowest block arrival enters the clock fits: at least this many,
#: more for short sweeps (about _ENVELOPE_POINTS points in all).
_ENVELOPE_SEGMENTS = 8
_ENVELOPE_POINTS = 200_000
#: Rows per read of the sweep-wide scan (counters and pre-command samples).
_SCAN_ROWS = 2048


@dataclass(frozen=True)
class SweepContext:
    """Sweep-wide facts every chunk needs."""

    contract: Contract
    taps: FloatArray
    clocks: dict[int, DriftingClockFit]  # per session
    n_first: FloatArray  # unwrapped index of each recorded row's first sample
    time_order: NDArray[np.int64]  # rows sorted by session, then by t0
    time_rank: NDArray[np.int64]  # (n_rows,) each row's position in time_order
    session_span: NDArray[np.int64]  # (n_rows, 2) its session's [start, stop) in time_order
    keep: NDArray[np.int64] | None = None  # the readable rows, when chunks are damaged

    @property
    def robot(self) -> str:
        return self.contract.robot

    @property
    def period_s(self) -> float:
        return self.contract.period_s

    @property
    def profile(self) -> dict[str, float]:
        return self.contract.profile

    @property
    def fs_hz(self) -> float:
        return self.contract.fs_hz


def _unwrap_rows(
    first_counter: NDArray[np.int64],
    first_time: FloatArray,
    start_index: int,
    start_time: float,
    rate_hz: float,
) -> NDArray[np.int64]:
    """Unwrapped index of each row's first sample: rows are in time order; the host time
    elapsed since the previous row decides how many 65536 wraps lie in between."""
    prev_c = np.r_[start_index % 65536, first_counter[:-1]]
    prev_t = np.r_[start_time, first_time[:-1]]
    dc = (first_counter - prev_c) % 65536
    expected = (first_time - prev_t) * rate_hz
    wraps = np.round((expected - dc) / 65536.0)
    return start_index + np.cumsum(dc + 65536 * wraps).astype(np.int64)


_Scan = tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]


class RowsView:
    """A reader that shows only the rows ``keep`` (append order) of a recording: what
    extraction sees of one whose damaged chunks are left out. Row positions given to
    :meth:`read` are positions among ``keep``; everything else is the reader's."""

    def __init__(self, reader: RecordingReader, keep: NDArray[np.int64]) -> None:
        self._reader = reader
        self._keep = keep

    @property
    def n_trials(self) -> int:
        return int(self._keep.size)

    @property
    def whole(self) -> RecordingReader:
        """The reader of every row."""
        return self._reader

    def read(self, name: str, rows: slice | NDArray[Any] | None = None) -> NDArray[Any]:
        return self._reader.read(name, self._keep if rows is None else self._keep[rows])

    def __getattr__(self, name: str) -> Any:
        return getattr(self._reader, name)

    def __enter__(self) -> RowsView:
        return self

    def __exit__(self, *exc: object) -> None:
        self._reader.close()


def open_rows(path: str, keep: NDArray[np.int64] | None) -> Any:
    """The recording at ``path``, as extraction reads it (only ``keep`` when given)."""
    reader = RecordingReader(path)
    return reader if keep is None else RowsView(reader, keep)


def _scan_rows(reader: RecordingReader, start: int, stop: int, rows_b: NDArray[np.int64]) -> _Scan:
    """What the sweep-wide clock fit needs of rows ``start:stop``: each row's first counter,
    and the position and kept state of each block's last row."""
    c = reader.read("gyro_counter", slice(start, stop))
    k = len(c)
    c16 = c if c.dtype == np.uint16 else (c.astype(np.int64) % 65536).astype(np.uint16)
    clean = np.all(np.diff(c16, axis=1) == 1, axis=1)
    pos_block = np.broadcast_to(rows_b, (k, rows_b.size)).copy()
    keep_block = np.ones((k, rows_b.size), dtype=bool)
    dirty = np.flatnonzero(~clean)
    if dirty.size:  # lost, duplicated or out-of-order frames: positions from the counter
        pos, keep = relative_counter_rows(c[dirty])
        pos_block[dirty] = pos[:, rows_b]
        keep_block[dirty] = keep[:, rows_b]
    return np.asarray(c[:, 0], dtype=np.int64), pos_block, keep_block


def _scan_path(
    path: str, start: int, stop: int, rows_b: NDArray[np.int64], keep: NDArray[np.int64] | None
) -> _Scan:
    with open_rows(path, keep) as reader:
        return _scan_rows(reader, start, stop, rows_b)


def sweep_context(
    reader: RecordingReader, *, clock_window_s: float | None, numtaps: int, jobs: int = 1
) -> tuple[SweepContext, StillAnalysis, float, float, dict[str, Any]]:
    con = read_contract(reader)
    fs, block = con.fs_hz, con.block
    rate_scale = con.scale["gyro_raw"]

    # Still recording: zero-rate and noise PSD; its counter anchors the unwrap.
    still_raw = reader.static("still_gyro_raw")
    still = analyse_still(np.asarray(still_raw, dtype=np.float64) * rate_scale, fs)
    still_counter = reader.static("still_gyro_counter")
    still_blocks = reader.static("still_gyro_block_host_time_s").astype(np.float64)
    still_blocks = still_blocks * con.scale["gyro_block_host_time_s"]
    s_pos, s_keep = relative_counter_rows(np.asarray(still_counter)[None, :])
    n_still = int(still_counter[0]) + s_pos[0]
    s_rows = np.arange(block - 1, len(n_still), block)[: len(still_blocks)]
    s_ok = s_keep[0, s_rows] & np.isfinite(still_blocks[: len(s_rows)])
    still_fit = fit_clock_lower_envelope(
        n_still[s_rows][s_ok], still_blocks[: len(s_rows)][s_ok], nominal_rate_hz=fs
    )

    # One pass over the per-trial stream: counters (positions, kept frames) and the
    # pre-command samples (zero-rate).
    t0 = reader.read("t0_s").astype(np.float64) * con.scale["t0_s"]
    n = len(t0)
    session = reader.read("session") if "session" in reader.fields else np.zeros(n, np.int64)
    session = np.asarray(session, dtype=np.int64)
    blocks = reader.read("gyro_block_host_time_s").astype(np.float64)
    blocks *= con.scale["gyro_block_host_time_s"]
    n_blocks = blocks.shape[1]
    rows_b = np.arange(n_blocks) * block + block - 1
    spans = [(a, min(a + _SCAN_ROWS, n)) for a in range(0, n, _SCAN_ROWS)]
    if jobs == 1 or len(spans) == 1:
        parts = [_scan_rows(reader, a, b, rows_b) for a, b in spans]
    else:
        from joblib import Parallel, delayed

        parts = Parallel(n_jobs=jobs)(
            delayed(_scan_path)(reader.path, a, b, rows_b, getattr(reader, "_keep", None))
            for a, b in spans
        )
    first_counter = np.concatenate([p[0] for p in parts])
    pos_block = np.concatenate([p[1] for p in parts])
    keep_block = np.concatenate([p[2] for p in parts]) & np.isfinite(blocks)
    # Time order within each session: the zero-rate of a row pools its neighbours in time.
    time_order = np.lexsort((t0, session)).astype(np.int64)
    time_rank = np.empty(n, dtype=np.int64)
    time_rank[time_order] = np.arange(n)
    sess_sorted = session[time_order]
    bounds = np.searchsorted(sess_sorted, [session, session + 1], side="left").T
    session_span = np.asarray(bounds, dtype=np.int64)

    # Unwrap every row's first sample, per session (a resumed run is a new gyro stream and
    # host clock), in time order; the still recording anchors session 0. The arrival of
    # a row's first kept block dates its first sample.
    b_first = np.argmax(keep_block, axis=1)
    r = np.arange(n)
    first_time = t0 + blocks[r, b_first] - pos_block[r, b_first] / still_fit.rate_hz
    n_first = np.empty(n, dtype=np.int64)
    for sess in np.unique(session):
        rows = np.flatnonzero(session == sess)
        rows = rows[np.argsort(t0[rows])]
        if sess == session.min():
            anchor_n = int(n_still[-1])
            anchor_t = float(still_fit.to_host_time(n_still[-1])[()])
        else:  # a new stream: its first trial anchors it
            anchor_n, anchor_t = int(first_counter[rows[0]]), float(first_time[rows[0]])
        n_first[rows] = _unwrap_rows(
            first_counter[rows], first_time[rows], anchor_n, anchor_t, still_fit.rate_hz
        )

    # Clock points: each trial's lowest block arrival in each of a few segments, relative to
    # the still recording's line (only the lowest can lie on a lower envelope).
    block_n = n_first[:, None] + pos_block
    block_t = t0[:, None] + blocks
    resid = block_t - (still_fit.t_ref_s + (block_n - still_fit.n_ref) * still_fit.period_s)
    resid = np.where(keep_block, resid, np.inf)
    segments = int(np.clip(_ENVELOPE_POINTS // max(n, 1), _ENVELOPE_SEGMENTS, n_blocks))
    edges_b = np.linspace(0, n_blocks, segments + 1).astype(int)
    pick = np.stack(
        [lo + np.argmin(resid[:, lo:hi], axis=1) for lo, hi in itertools.pairwise(edges_b)],
        axis=1,
    )
    ok = np.isfinite(np.take_along_axis(resid, pick, axis=1))
    pn = np.take_along_axis(block_n, pick, axis=1)
    pt = np.take_along_axis(block_t, pick, axis=1)
    pg = np.broadcast_to(r[:, None], pick.shape)
    clocks: dict[int, DriftingClockFit] = {}
    for sess in np.unique(session):
        sel = (session == sess)[:, None] & ok
        cn, ct, cg = pn[sel], pt[sel], pg[sel]
        if sess == session.min():
            cn = np.r_[n_still[s_rows][s_ok], cn]
            ct = np.r_[still_blocks[: len(s_rows)][s_ok], ct]
            cg = np.r_[np.full(int(s_ok.sum()), -1), cg]
        clocks[int(sess)] = fit_clock_drifting(
            cn, ct, cg, nominal_rate_hz=fs, window_s=clock_window_s, transfer_samples=block
        )
    main = clocks[int(session.min())]
    rate = float(np.mean(1.0 / main.period_s))
    clock_info = {str(k): v.to_dict() for k, v in clocks.items()}

    # Filter from the PSDs (a few trials' motion against the still noise).
    sample_rows = np.unique(np.linspace(0, n - 1, min(32, n)).astype(int))
    raw = reader.read("gyro_raw", rows=sample_rows).astype(np.float64) * rate_scale
    motion = np.linalg.norm(raw - still.bias_rad_s, axis=2)
    taps, cutoff = design_lowpass(still, motion, fs, numtaps=numtaps)
    ctx = SweepContext(
        contract=con,
        taps=taps,
        clocks=clocks,
        n_first=n_first.astype(np.float64),
        time_order=time_order,
        time_rank=time_rank,
        session_span=session_span,
    )
    return ctx, still, cutoff, rate, clock_info
