"""RecordingWriter: append trials to a recording, crash-safe and resumable.

HDF5 is not crash-safe: a writer killed while the library flushes its metadata cache leaves
a file that no longer opens, or whose chunks fail to decompress. So the recording file
``P`` is never modified in place. It only ever changes by ``os.replace`` of a complete,
closed and fsync'ed file (full description and guarantees in ``docs/recording-format.md``):

* ``P.journal`` — append-only write-ahead log (:mod:`timedexec.recording._journal`).
  :meth:`RecordingWriter.append` and :meth:`RecordingWriter.write_static` append one
  CRC-protected record and fsync it; that is the commit point. A record torn by a kill
  fails its CRC and is ignored.
* ``P.shadow`` — an older committed version of ``P`` (the "last good state" before it).
  A checkpoint renames it to ``P.partial``, brings it up to date by copying the missing
  compressed chunks from ``P`` (no recompression) and applying the journal, closes and
  fsyncs it, then swaps it in: hard link ``P`` -> ``P.old``, ``os.replace(P.partial, P)``,
  ``os.replace(P.old, P.shadow)``, and starts an empty journal. Each checkpoint costs
  O(data since the previous checkpoint), not O(file).

Failed writes (a full disk, an I/O error) end in a :class:`RecordingError` and nothing
worse: a journal record that fails is cut off again; HDF5 writes a file only through
:func:`~timedexec.recording._h5.writable_h5`, which never lets a failed write abort HDF5
half-way (HDF5 cannot close such a file, and the interpreter crashed at exit); a failed
checkpoint deletes ``P.partial`` and keeps ``P`` and the journal. Leaving the writer's
``with`` block on such an error keeps the journal as it is (no checkpoint on a disk that
just failed), so resuming recovers every appended batch. Ctrl-C during a checkpoint is
held until the checkpoint is done.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import sys
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._version import __version__
from timedexec.errors import ConfigError, RecordingError
from timedexec.recording._fields import (
    Field,
    canonical_dtype,
    check_name,
    coerce,
    dtype_name,
    normalise_fields,
)
from timedexec.recording._h5 import (
    LIBVER,
    WRITE_CACHE_BYTES,
    Compression,
    Meta,
    WritableH5,
    create_recording_file,
    create_static,
    open_h5,
    parse_compression,
    read_meta,
    sigint_deferred,
    writable_h5,
    write_progress,
)
from timedexec.recording._journal import (
    KIND_BATCH,
    KIND_STATIC,
    RHEAD_SIZE,
    ForeignJournalError,
    JournalScan,
    Layout,
    Record,
    journal_header,
    pending_records,
    read_into,
    record_header,
    scan_journal,
    static_payload,
)
from timedexec.recording._protocol import (
    FAULT_ENV,
    FORMAT_VERSION,
    JOURNAL,
    JOURNAL_NEW,
    LOCK,
    OLD,
    PARTIAL,
    SHADOW,
    fault,
    fsync_dir,
    fsync_path,
    unlink,
    write_all,
)

if sys.platform != "win32":
    import fcntl

__all__ = ["RecordingWriter"]

_APPLY_GROUP_BYTES = 32 * 2**20  # journal rows written to HDF5 per write call


def _encode_header(header: Mapping[str, Any]) -> str:
    """The header as stored: JSON with sorted keys."""
    if not isinstance(header, Mapping):
        raise ConfigError(f"header must be a mapping (dict), got {type(header).__name__}")
    try:
        return json.dumps(dict(header), sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ConfigError(
            f"header is not JSON-serialisable ({exc}); convert specs and settings with "
            "their to_dict() and arrays with .tolist() (or store arrays with write_static)"
        ) from exc


def _utc_now() -> str:
    """Now, UTC, ISO 8601 to the second (``2026-11-22T04:52:05Z``)."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


class RecordingWriter:
    """Append trials to a recording; crash-safe and resumable.

    Parameters
    ----------
    path : str or os.PathLike
        The recording file (``.h5``). Side files ``path + '.journal'``, ``'.shadow'`` and
        ``'.lock'`` live next to it while writing and are removed by :meth:`close`.
    header : mapping, optional
        JSON-serialisable description of the sweep (robot spec, plan, settings, ...),
        stored as the root attribute ``header``. Required for a new file; on resume it must
        equal the stored header if given.
    fields : sequence of Field, optional
        The per-trial datasets. A field ``trial`` (int64 plan index, shape ``()``) is added
        first if absent. Required for a new file; on resume it must match if given.
    resume : bool, default False
        Continue an existing recording (recovering from a crash). Without it an existing
        file is never overwritten. If ``path`` does not exist and header and fields are
        given, a new recording is started.
    compression : {'lzf', 'gzip', 'gzip-1', ..., 'gzip-9', 'none'}, default 'lzf'
        HDF5 filter of the per-trial datasets (with byte shuffle). On resume the file's
        own setting is kept.
    trials_per_chunk : int, default 64
        Rows per HDF5 chunk. On resume the file's own setting is kept.
    checkpoint_bytes : int, default 64 MiB
        Journal size after which the journal is folded into the HDF5 file. Smaller values
        make plain-h5py views fresher at the cost of more checkpoints.
    fsync : bool, default True
        fsync every journal record and every checkpoint. Without it a SIGKILL is still
        survived (the OS holds the written pages) but a power loss is not.

    Raises
    ------
    RecordingError
        The path exists (without ``resume``), its directory is missing or not writable,
        another process is writing it, or the existing file cannot be resumed.
    ConfigError
        Invalid arguments, or a header/field mismatch on resume.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        header: Mapping[str, Any] | None = None,
        fields: Sequence[Field] | None = None,
        resume: bool = False,
        compression: str = "lzf",
        trials_per_chunk: int = 64,
        checkpoint_bytes: int = 64 * 2**20,
        fsync: bool = True,
    ) -> None:
        self._path = os.path.abspath(os.fspath(path))
        self._dir = os.path.dirname(self._path)
        self._fsync = bool(fsync)
        self._closed = True
        self._broken: str | None = None
        self._lock_fd: int | None = None
        self._journal_fd: int | None = None
        if isinstance(trials_per_chunk, bool) or not isinstance(trials_per_chunk, int):
            raise ConfigError(f"trials_per_chunk must be an int >= 1, got {trials_per_chunk!r}")
        if trials_per_chunk < 1:
            raise ConfigError(f"trials_per_chunk must be >= 1, got {trials_per_chunk}")
        if checkpoint_bytes < 0:
            raise ConfigError(f"checkpoint_bytes must be >= 0, got {checkpoint_bytes}")
        self._checkpoint_bytes = int(checkpoint_bytes)
        comp = parse_compression(compression)
        header_json = None if header is None else _encode_header(header)
        norm_fields = None if fields is None else normalise_fields(fields)

        if not os.path.isdir(self._dir):
            raise RecordingError(
                f"cannot write recording {self._path}: directory {self._dir} does not exist; "
                "create it or choose another output path"
            )
        if not os.access(self._dir, os.W_OK | os.X_OK):
            raise RecordingError(
                f"cannot write recording {self._path}: directory {self._dir} is not writable; "
                "choose another output path or fix its permissions"
            )
        if os.path.isdir(self._path):
            raise RecordingError(f"cannot write recording {self._path}: it is a directory")
        exists = os.path.exists(self._path)
        if exists and not resume:
            raise RecordingError(
                f"recording {self._path} already exists; refusing to overwrite it. To continue "
                "an interrupted sweep use --resume (resume=True); to start over delete it"
            )
        if not exists and (header_json is None or norm_fields is None):
            if resume:
                raise RecordingError(
                    f"cannot resume {self._path}: it does not exist; pass header and fields "
                    "to start a new recording"
                )
            raise ConfigError("a new recording needs both header and fields")

        self._acquire_lock()
        try:
            if os.path.exists(self._path):
                self._open_existing(header_json, norm_fields)
            else:
                assert header_json is not None
                assert norm_fields is not None
                self._create(header_json, norm_fields, comp, trials_per_chunk)
        except BaseException as exc:
            self._release()
            if isinstance(exc, OSError) and not isinstance(exc, RecordingError):
                raise RecordingError(
                    f"cannot open recording {self._path} for writing ({exc}); nothing "
                    "recorded so far is lost: fix the cause (disk space?) and resume"
                ) from exc
            raise
        self._closed = False

    # ------------------------------------------------------------------ paths and lock

    def _side(self, suffix: str) -> str:
        return self._path + suffix

    def _acquire_lock(self) -> None:
        lock_path = self._side(LOCK)
        for _ in range(10):
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise RecordingError(
                    f"cannot write recording {self._path}: cannot create files in {self._dir} "
                    f"({exc.strerror}); choose another output path or fix its permissions"
                ) from exc
            if sys.platform == "win32":
                self._lock_fd = fd
                return
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                raise RecordingError(
                    f"recording {self._path} is being written by another process (lock "
                    f"{lock_path} is held); wait for it to finish or stop it"
                ) from exc
            try:  # the previous owner may have unlinked the lock file while we waited
                same = os.fstat(fd).st_ino == os.stat(lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self._lock_fd = fd
                return
            os.close(fd)
        raise RecordingError(f"cannot lock {lock_path}: it keeps being replaced")

    def _release(self) -> None:
        if self._journal_fd is not None:
            os.close(self._journal_fd)
            self._journal_fd = None
        if self._lock_fd is not None:
            unlink(self._side(LOCK))
            os.close(self._lock_fd)
            self._lock_fd = None

    def _sync_file(self, path: str) -> None:
        if self._fsync:
            fsync_path(path)

    def _sync_dir(self) -> None:
        if self._fsync:
            fsync_dir(self._dir)

    # ------------------------------------------------------------------ open / create

    def _init_state(self, meta: Meta, comp: Compression) -> None:
        self._header_json = meta.header_json
        self._fields = meta.fields
        self._layout = Layout(meta.fields)
        self._id = meta.recording_id
        self._comp = comp
        self._tpc = meta.trials_per_chunk
        self._p_seq = meta.seq  # what the HDF5 file P holds
        self._p_rows = meta.rows
        self._seq = meta.seq  # what P + journal hold
        self._rows = meta.rows
        self._statics: dict[str, Record | None] = dict.fromkeys(meta.statics)
        self._records: list[Record] = []
        self._journal_bytes = 0
        self._sessions = [
            *meta.sessions,
            {"package_version": __version__, "opened_utc": _utc_now()},
        ]
        self._trial_set: set[int] = set()
        self._completed_cache: NDArray[np.int64] | None = None

    def _create(
        self,
        header_json: str,
        fields: list[Field],
        comp: Compression,
        tpc: int,
    ) -> None:
        for suffix in (JOURNAL, JOURNAL_NEW, SHADOW, PARTIAL, OLD):
            unlink(self._side(suffix))  # left by a sweep that never committed its file
        partial = self._side(PARTIAL)
        meta = Meta(
            header_json=header_json,
            header=json.loads(header_json),
            fields=fields,
            recording_id=uuid.uuid4().hex,
            seq=0,
            rows=0,
            statics=[],
            package_version=__version__,
            created_utc=_utc_now(),
            format_version=FORMAT_VERSION,
            compression=comp[2],
            trials_per_chunk=tpc,
            sessions=[],
        )
        self._init_state(meta, comp)
        try:
            create_recording_file(partial, meta, comp, self._sessions)
            self._sync_file(partial)
            fault("create.partial_written")
            os.replace(partial, self._path)
            self._sync_dir()
        except OSError as exc:
            unlink(partial)
            raise RecordingError(f"cannot create recording {self._path}: {exc}") from exc
        fault("create.committed")
        try:
            self._new_journal()
        except OSError as exc:
            raise RecordingError(f"cannot create the journal of {self._path}: {exc}") from exc

    def _open_existing(self, header_json: str | None, fields: list[Field] | None) -> None:
        # Leftovers of a checkpoint that was interrupted: P itself is always complete.
        unlink(self._side(PARTIAL))
        unlink(self._side(JOURNAL_NEW))
        old, shadow = self._side(OLD), self._side(SHADOW)
        if os.path.exists(old):
            if os.path.samefile(old, self._path) or os.path.exists(shadow):
                unlink(old)  # a second name of P itself, never to be modified
            else:
                os.replace(old, shadow)  # the previous P: a clean shadow
        with open_h5(self._path, "r") as f:
            meta = read_meta(f, self._path)
            trials = np.asarray(f["trials/trial"][:], dtype=np.int64)
        if header_json is not None and header_json != meta.header_json:
            stored = meta.header
            given = json.loads(header_json)
            keys = sorted(k for k in set(stored) | set(given) if stored.get(k) != given.get(k))
            raise ConfigError(
                f"cannot resume {self._path}: its header differs from the given one in "
                f"{keys}; resume with the settings that started the sweep, or write a new file"
            )
        if fields is not None:
            stored_f = {f.name: (f.shape, f.dtype, f.unit) for f in meta.fields}
            given_f = {f.name: (f.shape, f.dtype, f.unit) for f in fields}
            if stored_f != given_f:
                diff = sorted(
                    n for n in set(stored_f) | set(given_f) if stored_f.get(n) != given_f.get(n)
                )
                raise ConfigError(
                    f"cannot resume {self._path}: fields {diff} differ from the recording's "
                    f"(stored: {[(n, *stored_f[n]) for n in diff if n in stored_f]}); resume "
                    "with the fields that started the sweep, or write a new file"
                )
        self._init_state(meta, parse_compression(meta.compression))
        self._trial_set = set(trials.tolist())

        jpath = self._side(JOURNAL)
        scan: JournalScan | None = None
        if os.path.exists(jpath):
            with open(jpath, "rb", buffering=0) as jf:
                try:
                    scan = scan_journal(jf, self._id)
                except ForeignJournalError as exc:
                    raise RecordingError(
                        f"cannot resume {self._path}: journal {jpath} belongs to another "
                        f"recording (id {exc.recording_id}, expected {self._id}); move it "
                        "away to resume from the HDF5 file alone"
                    ) from exc
        pending = None if scan is None else pending_records(scan, meta.seq, meta.rows)
        if scan is not None and pending is None:
            raise RecordingError(
                f"cannot resume {self._path}: journal {jpath} does not continue it (the "
                "recording was replaced by an older copy?); move the journal away to resume "
                "from the HDF5 file alone (the trials only it holds are then lost)"
            )
        if scan is None or not pending:
            self._new_journal()
            return
        # Keep the valid records, cut a torn tail, and continue appending after them.
        fd = os.open(jpath, os.O_RDWR)
        try:
            if os.fstat(fd).st_size > scan.end:
                os.ftruncate(fd, scan.end)
                if self._fsync:
                    os.fsync(fd)
        finally:
            os.close(fd)
        self._journal_fd = os.open(jpath, os.O_WRONLY | os.O_APPEND)
        with open(jpath, "rb", buffering=0) as jf:
            ti = self._layout.index["trial"]
            for rec in pending:
                self._records.append(rec)
                self._journal_bytes += rec.length
                self._seq = rec.seq
                if rec.kind == KIND_BATCH:
                    t = self._layout.read_rows(jf, rec, ti, 0, rec.n_rows)
                    self._trial_set.update(t.tolist())
                    self._rows += rec.n_rows
                else:
                    assert rec.static is not None
                    self._statics[rec.static["name"]] = rec

    def _new_journal(self) -> None:
        """Atomically start an empty journal continuing P (seq, rows)."""
        if self._journal_fd is not None:
            os.close(self._journal_fd)
            self._journal_fd = None
        new, jpath = self._side(JOURNAL_NEW), self._side(JOURNAL)
        fd = os.open(new, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            write_all(fd, journal_header(self._id, self._p_seq, self._p_rows))
            if self._fsync:
                os.fsync(fd)
        finally:
            os.close(fd)
        fault("fold.journal_new")
        os.replace(new, jpath)
        self._sync_dir()
        self._journal_fd = os.open(jpath, os.O_WRONLY | os.O_APPEND)
        self._records = []
        self._journal_bytes = 0

    # ------------------------------------------------------------------ public API

    @property
    def path(self) -> str:
        """Absolute path of the recording file."""
        return self._path

    @property
    def fields(self) -> list[Field]:
        """The per-trial fields, ``trial`` first."""
        return list(self._fields)

    @property
    def header(self) -> dict[str, Any]:
        """The header as stored (a fresh dict)."""
        return dict(json.loads(self._header_json))

    @property
    def completed_trials(self) -> NDArray[np.int64]:
        """Sorted plan indices of every trial recorded so far (including earlier sessions)."""
        if self._completed_cache is None:
            self._completed_cache = np.array(sorted(self._trial_set), dtype=np.int64)
        return self._completed_cache

    @property
    def n_trials(self) -> int:
        """Number of trials recorded so far."""
        return self._rows

    def has_static(self, name: str) -> bool:
        """Whether the static array ``name`` has been written (in any session)."""
        return name in self._statics

    def _check_usable(self) -> None:
        if self._closed:
            raise RecordingError(f"recording writer of {self._path} is closed")
        if self._broken is not None:
            raise RecordingError(
                f"recording writer of {self._path} failed earlier ({self._broken}); close it "
                "and reopen the recording with resume=True"
            )

    def write_static(self, name: str, data: ArrayLike, *, unit: str = "", doc: str = "") -> None:
        """Store a once-only array under ``/static/<name>`` (crash-safe like append).

        Parameters
        ----------
        name : str
            Dataset name, e.g. ``"plan_q_rad"`` or ``"still_gyro"``.
        data : array_like
            Any shape; numeric, bool or fixed-length bytes.
        unit, doc : str, optional
            Stored as dataset attributes.

        Raises
        ------
        ConfigError
            The name is invalid or already written (check :meth:`has_static` on resume),
            or the dtype cannot be stored.
        """
        self._check_usable()
        check_name(name, "static")
        if name in self._statics:
            raise ConfigError(
                f"static {name!r} is already in {self._path}; statics are written once "
                "(check has_static() before writing on resume)"
            )
        arr = np.asarray(data)
        dt = canonical_dtype(arr.dtype, f"static {name!r}")
        arr = np.ascontiguousarray(arr, dtype=dt.newbyteorder("<"))
        info: dict[str, Any] = {
            "name": name,
            "dtype": dtype_name(dt),
            "shape": list(arr.shape),
            "unit": str(unit),
            "doc": str(doc),
        }
        payload, data_start = static_payload(info, arr)
        with sigint_deferred():  # see append
            rec = self._write_record(KIND_STATIC, 0, payload)
            rec = rec._replace(static={**info, "data_offset": rec.offset + data_start})
            self._records[-1] = rec
            self._statics[name] = rec
        self._maybe_checkpoint()

    def append(self, batch: Mapping[str, ArrayLike]) -> None:
        """Record a batch of k trials atomically.

        Parameters
        ----------
        batch : mapping of str to array_like
            Every field, each with shape ``(k, *field.shape)``, including ``trial`` (plan
            indices, int). Values are converted to the field dtype when that is lossless
            (integers are range-checked; float64 -> float32 is accepted).

        Raises
        ------
        ConfigError
            A field is missing or unknown, a shape or dtype does not fit (the message names
            the field, the expected and the given shape), or a trial index is negative,
            repeated in the batch or already recorded.
        RecordingError
            The journal cannot be written (disk full, I/O error): nothing of the batch is
            recorded, and the writer stays usable. Or the batch was recorded and the
            checkpoint that followed failed (the message says "checkpoint"): the journal
            keeps every batch; close the writer and resume.
        """
        self._check_usable()
        if not isinstance(batch, Mapping):
            raise ConfigError(f"batch must be a mapping of field name to array, got {batch!r}")
        names = [f.name for f in self._fields]
        missing = [n for n in names if n not in batch]
        if missing:
            raise ConfigError(
                f"batch is missing field(s) {missing}; every field is required: {names}"
            )
        unknown = sorted(set(batch) - set(names))
        if unknown:
            raise ConfigError(f"batch has unknown field(s) {unknown}; known fields: {names}")
        trial = np.asarray(batch["trial"])
        if trial.ndim != 1:
            raise ConfigError(
                f"batch field 'trial': expected shape (k,) (one plan index per trial), got "
                f"{trial.shape}"
            )
        k = trial.shape[0]
        arrays = [
            coerce(f.name, batch[f.name], f.np_dtype, (k, *f.shape), k, f.shape)
            for f in self._fields
        ]
        trials = arrays[self._layout.index["trial"]]
        if k == 0:
            return
        if trials.min() < 0:
            raise ConfigError(f"batch field 'trial': plan indices must be >= 0, got {trials.min()}")
        tl = trials.tolist()
        if len(set(tl)) != k:
            dups = sorted({t for t in tl if tl.count(t) > 1})[:5]
            raise ConfigError(f"batch repeats trial indices {dups}; each trial is recorded once")
        done = [t for t in tl if t in self._trial_set]
        if done:
            raise ConfigError(
                f"trial indices {done[:5]}{' ...' if len(done) > 5 else ''} are already "
                f"recorded in {self._path}; skip completed_trials when resuming a sweep"
            )
        payload = self._layout.encode(arrays)
        # Ctrl-C is held while the record is written and counted: a reader sees a record as
        # soon as its bytes are in the journal, and a KeyboardInterrupt during its fsync cut
        # it off again (a reader had seen trials the file then lacked), or after it, before
        # the count, left a record the next checkpoint would not fold.
        with sigint_deferred():
            self._write_record(KIND_BATCH, k, payload)
            self._rows += k
            self._trial_set.update(tl)
            self._completed_cache = None
        self._maybe_checkpoint()

    def checkpoint(self) -> None:
        """Fold the journal into the HDF5 file now (plain h5py then sees every trial)."""
        self._check_usable()
        self._fold()

    def close(self) -> None:
        """Fold the journal into the HDF5 file and remove the side files."""
        if self._closed:
            return
        try:
            if self._broken is None:
                self._fold()
                fault("close.folded")
                for suffix in (SHADOW, JOURNAL):
                    unlink(self._side(suffix))
                self._sync_dir()
        finally:
            self._closed = True
            self._release()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> None:
        """Close; after a failed write (disk full, I/O error) keep the journal as it is.

        On a disk that just failed a write, a checkpoint (a second copy of the file) would
        fail too or fill the disk for others: the recording and its journal stay as they
        are, every appended batch is in them and resuming folds them. When another exception
        leaves the block (Ctrl-C, a bad batch) the writer closes as usual; if closing fails
        as well, that exception still leaves, with a note.
        """
        if exc is None:
            self.close()
            return
        if isinstance(exc, OSError) and self._records and self._broken is None:
            self._broken = repr(exc)  # close() then only releases the files
        try:
            self.close()
        except OSError as err:
            exc.add_note(
                f"closing {self._path} failed too ({err}); {self._side(JOURNAL)} keeps every "
                "appended batch: resume"
            )

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"{self._rows} trials"
        return f"RecordingWriter({self._path!r}, {state})"

    # ------------------------------------------------------------------ journal writes

    def _write_record(self, kind: int, n_rows: int, payload: bytes) -> Record:
        assert self._journal_fd is not None
        seq = self._seq + 1
        head = record_header(kind, seq, self._rows, n_rows, payload)
        fd = self._journal_fd
        start = os.fstat(fd).st_size
        try:
            write_all(fd, head)
            if os.environ.get(FAULT_ENV, "").startswith("append.torn"):
                write_all(fd, payload[: len(payload) // 2])
                fault("append.torn")
                write_all(fd, payload[len(payload) // 2 :])
            else:
                write_all(fd, payload)
            fault("append.written")
            if self._fsync:
                os.fsync(fd)
        except BaseException as exc:  # also KeyboardInterrupt: no torn record may stay
            with contextlib.suppress(OSError):
                os.ftruncate(fd, start)
            if isinstance(exc, OSError):
                raise RecordingError(
                    f"cannot append to the journal of {self._path} ({exc}); nothing of this "
                    "batch was recorded. Free disk space, then resume"
                ) from exc
            raise
        rec = Record(kind, seq, self._rows, n_rows, start + RHEAD_SIZE, len(payload), None)
        self._records.append(rec)
        self._seq = seq
        self._journal_bytes += len(payload)
        return rec

    def _maybe_checkpoint(self) -> None:
        if self._journal_bytes < self._checkpoint_bytes:
            return
        # Prefer chunk-aligned checkpoints: then no chunk is ever rewritten in HDF5.
        if self._rows % self._tpc == 0 or self._journal_bytes >= 2 * self._checkpoint_bytes:
            self._fold()

    # ------------------------------------------------------------------ checkpoint

    def _fold(self) -> None:
        """Bring P up to date with the journal by swapping in an updated copy.

        Ctrl-C is held until the checkpoint is complete (or has failed): a checkpoint takes
        about a second per 64 MiB of journal, and an interrupted one would only be redone.
        """
        if not self._records:
            return
        partial = self._side(PARTIAL)
        with sigint_deferred():
            try:
                self._write_partial(partial)
                self._sync_file(partial)
                fault("fold.synced")
                old = self._side(OLD)
                unlink(old)
                try:
                    os.link(self._path, old)  # keep the current P: it becomes the next shadow
                    linked = True
                except OSError:  # no hard links on this file system: copy P at the next fold
                    linked = False
                fault("fold.linked")
                os.replace(partial, self._path)  # the commit point of the checkpoint
                self._sync_dir()
                self._p_seq, self._p_rows = self._seq, self._rows
                fault("fold.replaced")
                if linked:
                    os.replace(old, self._side(SHADOW))
                    self._sync_dir()
                fault("fold.shadowed")
                self._new_journal()
            except BaseException as exc:  # P is intact; the journal keeps every batch
                with contextlib.suppress(OSError):
                    unlink(partial)
                self._broken = repr(exc)
                if isinstance(exc, RecordingError) or not isinstance(exc, OSError):
                    raise
                raise RecordingError(
                    f"checkpoint of {self._path} failed ({exc}); every appended batch is kept "
                    f"in {self._side(JOURNAL)}. Fix the cause (disk space?) and resume"
                ) from exc

    def _write_partial(self, partial: str) -> None:
        """Write P.partial: the next P, from the shadow if usable, else from a copy of P."""
        if self._take_shadow(partial):
            try:
                self._update_partial(partial)
                return
            except BlockingIOError:  # a reader still has this old version open (lock)
                unlink(partial)
        unlink(partial)
        shutil.copyfile(self._path, partial)
        fault("fold.copied")
        self._update_partial(partial)

    def _take_shadow(self, partial: str) -> bool:
        """Rename the shadow to P.partial if it is an older version of P; else drop it."""
        shadow = self._side(SHADOW)
        if not os.path.exists(shadow):
            return False
        if os.path.samefile(shadow, self._path):
            unlink(shadow)
            return False
        unlink(partial)
        os.replace(shadow, partial)
        fault("fold.partial_opened")
        ok = False
        with contextlib.suppress(RecordingError, KeyError, ValueError):
            with open_h5(partial, "r") as f:  # read only: nothing to go wrong on closing
                m = read_meta(f, partial)
            ok = m.recording_id == self._id and m.seq <= self._p_seq and m.rows <= self._p_rows
        if not ok:
            unlink(partial)
        return ok

    def _update_partial(self, partial: str) -> None:
        """Bring P.partial (an older version of P) up to P plus the journal, and close it."""
        with writable_h5(partial, "r+", libver=LIBVER, rdcc_nbytes=WRITE_CACHE_BYTES) as h5:
            self._catch_up(h5)
            fault("fold.caught_up")
            self._apply_journal(h5)
            self._set_progress_attrs(h5.file)
            h5.check()
            fault("fold.applied")

    def _catch_up(self, h5: WritableH5) -> None:
        """Copy what P has and the shadow lacks: whole compressed chunks, no recompression."""
        w = h5.file
        n_w = int(w["trials/trial"].shape[0])
        missing_statics = [s for s in self._p_statics() if s not in w["static"]]
        if n_w == self._p_rows and not missing_statics:
            return
        with h5py.File(self._path, "r") as src:
            for fld in self._fields:
                s_ds, w_ds = src["trials"][fld.name], w["trials"][fld.name]
                w_ds.resize(self._p_rows, axis=0)
                tpc = s_ds.chunks[0]
                zeros = (0,) * len(fld.shape)
                for c in range(n_w // tpc, -(-self._p_rows // tpc)):
                    mask, data = s_ds.id.read_direct_chunk((c * tpc, *zeros))
                    w_ds.id.write_direct_chunk((c * tpc, *zeros), data, mask)
                    h5.check()
            for name in missing_statics:
                src.copy(src["static"][name], w["static"], name=name)
                h5.check()

    def _p_statics(self) -> list[str]:
        pending = {r.static["name"] for r in self._records if r.static is not None}
        return [s for s in self._statics if s not in pending]

    def _apply_journal(self, w: WritableH5) -> None:
        recs = [r for r in self._records if r.seq > self._p_seq]
        with open(self._side(JOURNAL), "rb", buffering=0) as jf:
            group: list[Record] = []
            group_bytes = 0
            for rec in recs:
                if rec.kind == KIND_STATIC:
                    self._write_rows(w, jf, group)
                    group, group_bytes = [], 0
                    self._apply_static(w, jf, rec)
                    continue
                group.append(rec)
                group_bytes += rec.length
                if group_bytes >= _APPLY_GROUP_BYTES:
                    self._write_rows(w, jf, group)
                    group, group_bytes = [], 0
            self._write_rows(w, jf, group)

    def _write_rows(self, h5: WritableH5, jf: io.FileIO, group: list[Record]) -> None:
        if not group:
            return
        start = group[0].row_start
        end = group[-1].row_start + group[-1].n_rows
        for i, fld in enumerate(self._fields):
            arr = np.empty((end - start, *fld.shape), dtype=self._layout.disk_dtypes[i])
            for rec in group:
                lo = rec.row_start - start
                read_into(jf, self._layout.field_offset(rec, i), arr[lo : lo + rec.n_rows])
            ds = h5.file["trials"][fld.name]
            ds.resize(end, axis=0)
            ds[start:end] = arr
            h5.check()

    def _apply_static(self, h5: WritableH5, jf: io.FileIO, rec: Record) -> None:
        w = h5.file
        meta = rec.static
        assert meta is not None
        if meta["name"] in w["static"]:
            return
        arr = np.empty(tuple(meta["shape"]), dtype=np.dtype(meta["dtype"]).newbyteorder("<"))
        if arr.nbytes:
            read_into(jf, meta["data_offset"], arr)
        create_static(
            w["static"],
            meta["name"],
            arr.astype(np.dtype(meta["dtype"]), copy=False),
            meta["unit"],
            meta["doc"],
            self._comp,
        )
        h5.check()

    def _set_progress_attrs(self, f: h5py.File) -> None:
        write_progress(f, self._seq, self._sessions)
