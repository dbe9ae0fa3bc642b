"""RecordingReader: read a recording, including trials still in the journal of a writer.

The reader opens ``P`` and adds the journal records that ``P`` does not hold yet, so it sees
exactly the batches whose :meth:`~timedexec.recording.RecordingWriter.append` returned, at
any instant, without modifying anything. Plain h5py sees ``P`` as of the last checkpoint
(everything after :meth:`~timedexec.recording.RecordingWriter.close`).
"""

from __future__ import annotations

import contextlib
import io
import os
import time
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from timedexec.errors import ConfigError, RecordingError
from timedexec.recording._fields import Field
from timedexec.recording._h5 import READ_CACHE_BYTES, Meta, open_h5, read_meta
from timedexec.recording._journal import (
    KIND_BATCH,
    ForeignJournalError,
    Layout,
    Record,
    pending_records,
    read_into,
    scan_journal,
)
from timedexec.recording._protocol import JOURNAL

__all__ = ["DamagedChunkError", "RecordingReader", "damage_note"]


class DamagedChunkError(RecordingError):
    """Rows of a per-trial field cannot be read: a chunk fails its checksum or does not
    decompress (the file changed after it was written). :meth:`RecordingReader.damaged_rows`
    finds every such row."""


def damage_note(path: str | os.PathLike[str], damaged: int, total: int) -> str:
    """The one sentence every command says of a recording with damaged chunks.

    The policy (docs/recording-format.md, "Damaged chunks"): a damaged chunk costs only the
    trials in it. The commands that use the trials (``extract``, ``report``, ``fleet``) go
    on without them, flag them ``damaged`` and say this sentence (exit 0); ``check``, whose
    job is to say whether a file is whole, says it as a problem (exit 2).
    """
    return (
        f"{damaged} of {total} trials of {os.fspath(path)} lie in damaged chunks (they fail "
        "their checksum): flagged 'damaged' and left out, the others used; restore the file "
        "from its source or record those trials again"
    )


def _inode(path: str) -> tuple[int, int]:
    """(device, inode) of ``path``; (-1, -1) if it cannot be stat'ed."""
    try:
        st = os.stat(path)
    except OSError:
        return (-1, -1)
    return (st.st_dev, st.st_ino)


class RecordingReader:
    """Read a recording, including trials still in the journal of a running or killed writer.

    Parameters
    ----------
    path : str or os.PathLike
        The recording file.

    Attributes
    ----------
    header : dict
        The sweep description given to the writer.
    fields : dict of str to Field
        Per-trial fields in their stored order (``trial`` first).
    n_trials : int
        Number of recorded trials (rows), in the order they were appended.
    package_version, created_utc : str
        The timedexec version that created the file and when (UTC, ISO 8601).
    format_version : int

    Raises
    ------
    RecordingError
        The file is missing, not HDF5, truncated or damaged, not a timedexec recording,
        or written by a newer timedexec (format version); the message names the file and
        what to do.

    Notes
    -----
    The reader shows a snapshot taken when it was opened: every batch whose ``append``
    had returned. Reopen it to see later batches.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.path.abspath(os.fspath(path))
        self._h5: h5py.File | None = None
        self._jf: io.FileIO | None = None
        for attempt in range(50):
            inode = _inode(self.path)
            f = open_h5(self.path, "r", rdcc_nbytes=READ_CACHE_BYTES)
            try:
                meta = read_meta(f, self.path)
                loaded = self._load_journal(meta)
            except BaseException:
                f.close()
                raise
            if loaded is not None and _inode(self.path) == inode:
                break
            # A writer swapped in a checkpoint while we opened the file and the journal:
            # the two may not match. Retry with the new pair.
            if loaded is not None and loaded[0] is not None:
                loaded[0].close()
            f.close()
            time.sleep(0.002 * (attempt + 1))
        else:
            warnings.warn(
                f"journal {self.path}{JOURNAL} does not continue {self.path}; ignoring it "
                "(only the trials in the HDF5 file are shown)",
                stacklevel=2,
            )
            f = open_h5(self.path, "r", rdcc_nbytes=READ_CACHE_BYTES)
            meta = read_meta(f, self.path)
            loaded = (None, [])
        assert loaded is not None
        self._h5 = f
        self._jf, records = loaded
        self._meta = meta
        self._layout = Layout(meta.fields)
        self.header: dict[str, Any] = meta.header
        self.fields: dict[str, Field] = {fld.name: fld for fld in meta.fields}
        self.package_version: str = meta.package_version
        self.created_utc: str = meta.created_utc
        self.format_version: int = meta.format_version
        self._h5_rows = meta.rows
        self._batches = [r for r in records if r.kind == KIND_BATCH]
        self._batch_starts = np.array([r.row_start for r in self._batches], dtype=np.int64)
        self._statics = {r.static["name"]: r for r in records if r.static is not None}
        self.n_trials: int = meta.rows + sum(r.n_rows for r in self._batches)

    def _load_journal(self, meta: Meta) -> tuple[io.FileIO | None, list[Record]] | None:
        jpath = self.path + JOURNAL
        try:
            jf: io.FileIO = open(jpath, "rb", buffering=0)  # noqa: SIM115 (kept open)
        except FileNotFoundError:
            return None, []
        try:
            scan = scan_journal(jf, meta.recording_id)
        except ForeignJournalError as exc:
            jf.close()
            warnings.warn(
                f"journal {jpath} belongs to another recording (id {exc.recording_id}); "
                "ignoring it",
                stacklevel=3,
            )
            return None, []
        except BaseException:
            jf.close()
            raise
        if scan is None:
            jf.close()
            return None, []
        pending = pending_records(scan, meta.seq, meta.rows)
        if pending is None:
            jf.close()
            return None
        if not pending:
            jf.close()
            return None, []
        return jf, pending

    # ------------------------------------------------------------------ public API

    @property
    def completed_trials(self) -> NDArray[np.int64]:
        """Sorted plan indices of the recorded trials."""
        return np.sort(self.read("trial")).astype(np.int64, copy=False)

    @property
    def static_names(self) -> list[str]:
        """Names of the static arrays."""
        return sorted({*self._meta.statics, *self._statics})

    def has_static(self, name: str) -> bool:
        """Whether the static array ``name`` exists."""
        return name in self._statics or name in self._meta.statics

    def static(self, name: str) -> NDArray[Any]:
        """The static array ``name`` (as written, any shape)."""
        f = self._open()
        rec = self._statics.get(name)
        if rec is not None:
            assert rec.static is not None
            assert self._jf is not None
            meta = rec.static
            arr = np.empty(tuple(meta["shape"]), dtype=np.dtype(meta["dtype"]).newbyteorder("<"))
            if arr.nbytes:
                read_into(self._jf, meta["data_offset"], arr)
            return arr.astype(np.dtype(meta["dtype"]), copy=False)
        if name not in self._meta.statics:
            raise ConfigError(
                f"recording {self.path} has no static array {name!r}; it has {self.static_names}"
            )
        try:
            return np.asarray(f["static"][name][()])
        except OSError as exc:
            raise RecordingError(
                f"cannot read /static/{name} of {self.path} ({exc}); the file is damaged"
            ) from exc

    def read(self, name: str, rows: slice | NDArray[Any] | None = None) -> NDArray[Any]:
        """Read a per-trial field.

        Parameters
        ----------
        name : str
            Field name.
        rows : slice or array of int or bool, optional
            Rows by position (append order), not by plan index; all rows if None.

        Returns
        -------
        ndarray, shape (len(rows), *field.shape)
        """
        f = self._open()
        fld = self.fields.get(name)
        if fld is None:
            raise ConfigError(
                f"recording {self.path} has no per-trial field {name!r}; fields: "
                f"{list(self.fields)}"
            )
        n = self.n_trials
        if rows is None:
            rows = slice(0, n)
        if isinstance(rows, slice):
            start, stop, step = rows.indices(n)
            if step == 1:
                return self._read_range(f, fld, start, max(start, stop))
            idx = np.arange(start, stop, step, dtype=np.int64)
        else:
            idx = np.asarray(rows)
            if idx.dtype == bool:
                if idx.shape != (n,):
                    raise ConfigError(
                        f"boolean rows must have shape ({n},) (one per trial), got {idx.shape}"
                    )
                idx = np.flatnonzero(idx)
            elif idx.dtype.kind not in "iu" or idx.ndim != 1:
                raise ConfigError(
                    f"rows must be a slice or a 1-D array of int or bool, got {idx.dtype} "
                    f"with shape {idx.shape}"
                )
            idx = idx.astype(np.int64)
            idx = np.where(idx < 0, idx + n, idx)
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ConfigError(
                    f"row index out of range: got {rows!r}, the recording has {n} rows"
                )
        return self._read_index(f, fld, idx)

    def damaged_rows(self, names: Sequence[str] | None = None) -> NDArray[np.bool_]:
        """Which rows cannot be read: a chunk of one of ``names`` (all per-trial fields if
        None) fails its checksum or does not decompress. Reads every such chunk once.

        Returns
        -------
        ndarray of bool, shape (n_trials,)
            True for the rows (append order) of the damaged chunks.
        """
        f = self._open()
        names = list(self.fields) if names is None else list(names)
        out = np.zeros(self.n_trials, dtype=bool)
        for nm in names:
            if nm not in self.fields:
                raise ConfigError(f"no per-trial field {nm!r}; fields: {list(self.fields)}")
            ds = f["trials"][nm]
            for a, b in self._damaged_rows(ds, slice(0, self._h5_rows)):
                out[a:b] = True
        return out

    def iter_chunks(
        self, chunk_trials: int = 1024, names: Sequence[str] | None = None
    ) -> Iterator[dict[str, NDArray[Any]]]:
        """Iterate over consecutive blocks of rows.

        Parameters
        ----------
        chunk_trials : int, default 1024
            Rows per block (a multiple of the file's trials_per_chunk reads each HDF5 chunk
            once).
        names : sequence of str, optional
            Fields to read; all if None.

        Yields
        ------
        dict of str to ndarray
            ``{name: array of shape (rows, *field.shape)}``.
        """
        if chunk_trials < 1:
            raise ConfigError(f"chunk_trials must be >= 1, got {chunk_trials}")
        names = list(self.fields) if names is None else list(names)
        for nm in names:
            if nm not in self.fields:
                raise ConfigError(f"no per-trial field {nm!r}; fields: {list(self.fields)}")
        for start in range(0, self.n_trials, chunk_trials):
            sl = slice(start, min(self.n_trials, start + chunk_trials))
            yield {nm: self.read(nm, sl) for nm in names}

    def close(self) -> None:
        """Close the HDF5 file and the journal."""
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None
        if self._jf is not None:
            self._jf.close()
            self._jf = None

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RecordingReader({self.path!r}, {self.n_trials} trials)"

    # ------------------------------------------------------------------ internals

    def _open(self) -> h5py.File:
        if self._h5 is None:
            raise RecordingError(f"recording reader of {self.path} is closed")
        return self._h5

    def _read_h5(self, f: h5py.File, fld: Field, sel: slice | NDArray[np.int64]) -> NDArray[Any]:
        ds = f["trials"][fld.name]
        try:
            return np.asarray(ds[sel])
        except OSError as exc:
            bad = self._damaged_rows(ds, sel)
            where = (
                f"rows {', '.join(f'{a}-{b - 1}' for a, b in bad)} (append order) fail "
                "their checksum or do not decompress"
                if bad
                else "it cannot be read"
            )
            raise (DamagedChunkError if bad else RecordingError)(
                f"cannot read /trials/{fld.name} of {self.path}: {where} ({exc}). The file "
                "was damaged after it was written (disk, copy, transfer): restore it from "
                "its source, or record the sweep again (`timedexec check` reports it "
                "too)"
            ) from exc

    @staticmethod
    def _damaged_rows(ds: h5py.Dataset, sel: slice | NDArray[np.int64]) -> list[tuple[int, int]]:
        """The chunks (row ranges) of ``ds`` under ``sel`` that cannot be read, one by one."""
        if isinstance(sel, slice):
            lo, hi = sel.start or 0, sel.stop if sel.stop is not None else ds.shape[0]
        else:
            lo, hi = int(np.min(sel)), int(np.max(sel)) + 1
        tpc = ds.chunks[0] if ds.chunks else max(hi - lo, 1)
        bad: list[tuple[int, int]] = []
        for a in range(lo // tpc * tpc, hi, tpc):
            b = min(a + tpc, ds.shape[0])
            try:
                ds[a:b]
            except OSError:
                if bad and bad[-1][1] == a:
                    bad[-1] = (bad[-1][0], b)
                else:
                    bad.append((a, b))
        return bad

    def _read_range(self, f: h5py.File, fld: Field, start: int, stop: int) -> NDArray[Any]:
        parts: list[NDArray[Any]] = []
        if start < self._h5_rows:
            parts.append(self._read_h5(f, fld, slice(start, min(stop, self._h5_rows))))
        if stop > self._h5_rows and self._jf is not None:
            i = self._layout.index[fld.name]
            first = max(0, int(np.searchsorted(self._batch_starts, start, side="right")) - 1)
            for rec in self._batches[first:]:
                lo = max(start, rec.row_start)
                hi = min(stop, rec.row_start + rec.n_rows)
                if rec.row_start >= stop:
                    break
                if hi > lo:
                    parts.append(
                        self._layout.read_rows(
                            self._jf, rec, i, lo - rec.row_start, hi - rec.row_start
                        )
                    )
        if not parts:
            return np.empty((0, *fld.shape), dtype=fld.np_dtype)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _read_index(self, f: h5py.File, fld: Field, idx: NDArray[np.int64]) -> NDArray[Any]:
        out = np.empty((idx.size, *fld.shape), dtype=fld.np_dtype)
        if idx.size == 0:
            return out
        in_h5 = idx < self._h5_rows
        if in_h5.any():
            uniq = np.unique(idx[in_h5])
            lo, hi = int(uniq[0]), int(uniq[-1]) + 1
            data = None
            if uniq.size * 4 >= hi - lo:  # dense: one contiguous read is faster
                with contextlib.suppress(RecordingError):  # unless it spans a damaged chunk
                    data = self._read_h5(f, fld, slice(lo, hi))[uniq - lo]
            if data is None:
                data = self._read_h5(f, fld, uniq)
            out[in_h5] = data[np.searchsorted(uniq, idx[in_h5])]
        rest = np.flatnonzero(~in_h5)
        if rest.size:
            assert self._jf is not None
            i = self._layout.index[fld.name]
            which = np.searchsorted(self._batch_starts, idx[rest], side="right") - 1
            for b in np.unique(which):
                rec = self._batches[int(b)]
                pos = rest[which == b]
                rel = idx[pos] - rec.row_start
                lo, hi = int(rel.min()), int(rel.max()) + 1
                block = self._layout.read_rows(self._jf, rec, i, lo, hi)
                out[pos] = block[rel - lo]
        return out
