"""HDF5 recording store: one crash-safe, resumable file per calibration sweep.

A recording is one HDF5 file, readable with plain h5py: per-trial fields under
``/trials/<name>`` (shape ``(n, *shape)``, chunked ``trials_per_chunk`` rows per chunk,
compressed), once-only arrays under ``/static/<name>``, and root attributes that make it
self-describing (``format``, ``format_version``, ``package_version``, ``header``,
``created_utc``, ...). Both the batch simulator and the live trial runner write it.

Crash safety (full description and guarantees in ``docs/recording-format.md``)
-------------------------------------------------------------------------------
HDF5 is not crash-safe: a writer killed while the library flushes its metadata cache leaves
a file that no longer opens, or whose chunks fail to decompress. So the recording file
``P`` is never modified in place. It only ever changes by ``os.replace`` of a complete,
closed and fsync'ed file:

* ``P.journal`` — append-only write-ahead log. :meth:`RecordingWriter.append` and
  :meth:`RecordingWriter.write_static` append one CRC-protected record and fsync it; that
  is the commit point. A record torn by a kill fails its CRC and is ignored.
* ``P.shadow`` — an older committed version of ``P`` (the "last good state" before it).
  A checkpoint renames it to ``P.partial``, brings it up to date by copying the missing
  compressed chunks from ``P`` (no recompression) and applying the journal, closes and
  fsyncs it, then swaps it in: hard link ``P`` -> ``P.old``, ``os.replace(P.partial, P)``,
  ``os.replace(P.old, P.shadow)``, and starts an empty journal. Each checkpoint costs
  O(data since the previous checkpoint), not O(file).
* :class:`RecordingReader` opens ``P`` and adds the journal records that ``P`` does not
  hold yet, so it sees exactly the batches whose :meth:`~RecordingWriter.append` returned,
  at any instant. Plain h5py sees ``P`` as of the last checkpoint (everything after
  :meth:`RecordingWriter.close`).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import shutil
import signal
import struct
import sys
import time
import uuid
import warnings
import zlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, NamedTuple

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._version import __version__
from timedexec.errors import ConfigError, RecordingError

if sys.platform != "win32":
    import fcntl

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Field",
    "RecordingReader",
    "RecordingWriter",
]

FORMAT_NAME = "timedexec-recording"
FORMAT_VERSION = 1

# HDF5 file-format bounds: objects readable by HDF5 >= 1.8 (dense attribute storage, so a
# large JSON header fits), nothing that needs a newer library.
_LIBVER = ("v108", "v108")
_READ_CACHE_BYTES = 32 * 2**20  # raw-chunk cache of readers: a gyro chunk is ~1.8 MB
_WRITE_CACHE_BYTES = 16 * 2**20
_APPLY_GROUP_BYTES = 32 * 2**20  # journal rows written to HDF5 per write call
_STATIC_COMPRESS_BYTES = 64 * 2**10  # statics at least this large are chunked + compressed

# Side files next to the recording ``P`` (see the module docstring).
_JOURNAL = ".journal"
_JOURNAL_NEW = ".journal.new"
_SHADOW = ".shadow"
_PARTIAL = ".partial"
_OLD = ".old"
_LOCK = ".lock"

# Journal layout: a file header, then records (header, payload). All integers little-endian.
_JOURNAL_MAGIC = b"TXJRNL01"
_JHEAD = struct.Struct("<8sI16sQQ")  # magic, format version, recording id, base seq, base rows
_JHEAD_SIZE = _JHEAD.size + 4  # + crc32 of the above
_RECORD_MAGIC = b"TXR1"
_RHEAD = struct.Struct("<4sB3xQQQQI")  # magic, kind, seq, row start, rows, payload len, crc
_RHEAD_SIZE = _RHEAD.size + 4  # + crc32 of the above
_KIND_BATCH = 1
_KIND_STATIC = 2
_U32 = struct.Struct("<I")

_FAULT_ENV = "TIMEDEXEC_RECORDING_FAULT"
_fault_counts: dict[str, int] = {}


def _fault(point: str) -> None:
    """Kill this process with SIGKILL at a named point (crash tests only).

    The environment variable ``TIMEDEXEC_RECORDING_FAULT`` holds ``point`` or
    ``point@N`` (the N-th time the point is reached). Unset in normal use: one lookup.
    """
    want = os.environ.get(_FAULT_ENV)
    if not want:
        return
    name, _, nth = want.partition("@")
    if name != point:
        return
    _fault_counts[point] = _fault_counts.get(point, 0) + 1
    if _fault_counts[point] >= int(nth or 1):
        os.kill(os.getpid(), signal.SIGKILL)


# --------------------------------------------------------------------------- fields


_DTYPE_KINDS = "biufcS"  # bool, signed, unsigned, float, complex, fixed-length bytes


def _canonical_dtype(dtype: Any, what: str) -> np.dtype[Any]:
    """Validate a dtype for storage and return it in native byte order."""
    try:
        dt = np.dtype(dtype)
    except TypeError as exc:
        raise ConfigError(f"{what}: {dtype!r} is not a numpy dtype; use e.g. 'int16'") from exc
    if dt.kind not in _DTYPE_KINDS or dt.fields is not None or dt.subdtype is not None:
        raise ConfigError(
            f"{what}: dtype {dt} cannot be stored; use a numeric, bool or fixed-length bytes "
            "dtype ('int16', 'float64', 'bool', 'S16'); put text into the header instead"
        )
    native: np.dtype[Any] = dt.newbyteorder("=")
    return native


def _dtype_name(dt: np.dtype[Any]) -> str:
    return f"S{dt.itemsize}" if dt.kind == "S" else dt.name


def _check_name(name: Any, what: str) -> str:
    if not isinstance(name, str) or not name or "/" in name or name in (".", ".."):
        raise ConfigError(f"{what} name {name!r} is invalid; use a non-empty name without '/'")
    return name


@dataclass(frozen=True)
class Field:
    """One per-trial dataset of a recording.

    Parameters
    ----------
    name : str
        Dataset name, stored as ``/trials/<name>``, e.g. ``"gyro"``, ``"state_host_time_s"``.
    shape : tuple of int
        Shape of one trial's value, e.g. ``(4800, 3)``; ``()`` for a scalar per trial.
    dtype : str
        numpy dtype of the stored values, e.g. ``"int16"``, ``"float64"``; normalised to
        its canonical name.
    unit : str, optional
        Unit of the values (SI), stored as the dataset attribute ``unit``.
    doc : str, optional
        One-line description, stored as the dataset attribute ``doc``.
    """

    name: str
    shape: tuple[int, ...]
    dtype: str
    unit: str = ""
    doc: str = ""

    def __post_init__(self) -> None:
        _check_name(self.name, "field")
        try:
            shape = tuple(int(s) for s in self.shape)
        except (TypeError, ValueError) as exc:
            raise ConfigError(
                f"field {self.name!r}: shape {self.shape!r} must be a tuple of ints"
            ) from exc
        if any(s < 1 for s in shape):
            raise ConfigError(
                f"field {self.name!r}: shape {shape} has a dimension < 1; every per-trial "
                "dimension must be at least 1"
            )
        dt = _canonical_dtype(self.dtype, f"field {self.name!r}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "dtype", _dtype_name(dt))
        object.__setattr__(self, "unit", str(self.unit))
        object.__setattr__(self, "doc", str(self.doc))

    @property
    def np_dtype(self) -> np.dtype[Any]:
        """The numpy dtype (native byte order)."""
        return np.dtype(self.dtype)

    @property
    def row_nbytes(self) -> int:
        """Bytes of one trial's value."""
        return self.np_dtype.itemsize * math.prod(self.shape)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (``shape`` as a list)."""
        return {
            "name": self.name,
            "shape": list(self.shape),
            "dtype": self.dtype,
            "unit": self.unit,
            "doc": self.doc,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Field:
        """Inverse of :meth:`to_dict`."""
        unknown = set(data) - {"name", "shape", "dtype", "unit", "doc"}
        if unknown:
            raise ConfigError(f"Field.from_dict: unknown keys {sorted(unknown)}")
        return cls(
            name=data["name"],
            shape=tuple(data["shape"]),
            dtype=data["dtype"],
            unit=data.get("unit", ""),
            doc=data.get("doc", ""),
        )


_TRIAL_FIELD = Field("trial", (), "int64", doc="sweep plan index of the trial")


def _normalise_fields(fields: Sequence[Field]) -> list[Field]:
    out: list[Field] = []
    seen: set[str] = set()
    for f in fields:
        if not isinstance(f, Field):
            raise ConfigError(f"fields must be Field objects, got {type(f).__name__}")
        if f.name in seen:
            raise ConfigError(f"field {f.name!r} is listed twice; field names must be unique")
        seen.add(f.name)
        out.append(f)
    if "trial" in seen:
        trial = next(f for f in out if f.name == "trial")
        if trial.shape != () or trial.dtype != "int64":
            raise ConfigError(
                f"field 'trial' must have shape () and dtype int64 (the plan index), got "
                f"shape {trial.shape} and dtype {trial.dtype}; drop it to get the default"
            )
    else:
        out.insert(0, _TRIAL_FIELD)
    return out


def _parse_compression(compression: str | None) -> tuple[str | None, int | None, str]:
    """Return (h5py filter, filter level, canonical name); shuffle is on when compressing."""
    if compression is None or compression == "none":
        return None, None, "none"
    if compression == "lzf":
        return "lzf", None, "lzf"
    if compression == "gzip":
        return "gzip", 4, "gzip-4"
    m = re.fullmatch(r"gzip-([1-9])", str(compression))
    if m:
        return "gzip", int(m.group(1)), f"gzip-{m.group(1)}"
    raise ConfigError(
        f"compression {compression!r} is not supported; use 'lzf' (default, fast), 'gzip' "
        "(level 4), 'gzip-1' ... 'gzip-9' (smaller, slower) or 'none'"
    )


def _encode_header(header: Mapping[str, Any]) -> str:
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
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


# --------------------------------------------------------------------------- file helpers


def _fsync_path(path: str) -> None:
    fd = os.open(path, os.O_RDWR)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(directory: str) -> None:
    if os.name == "nt":  # directories cannot be opened for fsync on Windows
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _unlink(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def _write_all(fd: int, data: bytes | memoryview) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _read_exact(f: io.FileIO, offset: int, n: int) -> bytes:
    f.seek(offset)
    parts = []
    while n > 0:
        b = f.read(n)
        if not b:
            break
        parts.append(b)
        n -= len(b)
    return b"".join(parts)


def _read_into(f: io.FileIO, offset: int, out: NDArray[Any]) -> None:
    """Fill the C-contiguous array ``out`` with bytes from ``offset``."""
    view = memoryview(out).cast("B")  # type: ignore[arg-type]
    f.seek(offset)
    while view:
        n = f.readinto(view)
        if not n:
            raise RecordingError(f"journal {f.name} ends early at byte {f.tell()}")
        view = view[n:]


# --------------------------------------------------------------------------- journal


class _Record(NamedTuple):
    kind: int
    seq: int
    row_start: int
    n_rows: int
    offset: int  # payload offset in the journal file
    length: int  # payload bytes
    static: dict[str, Any] | None  # static records: name, dtype, shape, unit, doc, data_offset


class _JournalScan(NamedTuple):
    recording_id: str
    base_seq: int
    base_rows: int
    records: list[_Record]
    end: int  # byte after the last valid record


class _ForeignJournalError(Exception):
    def __init__(self, recording_id: str) -> None:
        super().__init__(recording_id)
        self.recording_id = recording_id


def _journal_header(recording_id: str, base_seq: int, base_rows: int) -> bytes:
    head = _JHEAD.pack(
        _JOURNAL_MAGIC, FORMAT_VERSION, uuid.UUID(hex=recording_id).bytes, base_seq, base_rows
    )
    return head + _U32.pack(zlib.crc32(head))


def _scan_journal(f: io.FileIO, expected_id: str | None) -> _JournalScan | None:
    """Index the valid records of a journal; None if its header is missing or torn.

    Stops at the first record that is short or fails a CRC: with an append-only file that
    is fsync'ed after every record, only the last record can be torn.
    """
    size = os.fstat(f.fileno()).st_size
    head = _read_exact(f, 0, _JHEAD_SIZE)
    if len(head) < _JHEAD_SIZE or zlib.crc32(head[:-4]) != _U32.unpack(head[-4:])[0]:
        return None
    magic, version, rid_bytes, base_seq, base_rows = _JHEAD.unpack(head[:-4])
    if magic != _JOURNAL_MAGIC:
        return None
    rid = uuid.UUID(bytes=rid_bytes).hex
    if expected_id is not None and rid != expected_id:
        raise _ForeignJournalError(rid)
    if version > FORMAT_VERSION:
        raise RecordingError(
            f"journal {f.name} was written by a newer timedexec (format {version}); upgrade "
            "timedexec to read or resume this recording"
        )
    records: list[_Record] = []
    pos = _JHEAD_SIZE
    while pos + _RHEAD_SIZE <= size:
        raw = _read_exact(f, pos, _RHEAD_SIZE)
        if len(raw) < _RHEAD_SIZE or zlib.crc32(raw[:-4]) != _U32.unpack(raw[-4:])[0]:
            break
        magic, kind, seq, row_start, n_rows, length, crc = _RHEAD.unpack(raw[:-4])
        offset = pos + _RHEAD_SIZE
        if magic != _RECORD_MAGIC or kind not in (_KIND_BATCH, _KIND_STATIC):
            break
        if offset + length > size:
            break
        got = 0
        first = b""
        f.seek(offset)
        remaining = length
        while remaining > 0:
            piece = f.read(min(remaining, 8 * 2**20))
            if not piece:
                break
            if not first:
                first = piece
            got = zlib.crc32(piece, got)
            remaining -= len(piece)
        if remaining or got != crc:
            break
        static: dict[str, Any] | None = None
        if kind == _KIND_STATIC:
            (meta_len,) = _U32.unpack(first[:4])
            meta_raw = first[4 : 4 + meta_len]
            if len(meta_raw) < meta_len:  # a meta block larger than one read piece
                meta_raw = _read_exact(f, offset + 4, meta_len)
            static = json.loads(meta_raw.decode("utf-8"))
            static["data_offset"] = offset + 4 + meta_len
        records.append(_Record(kind, seq, row_start, n_rows, offset, length, static))
        pos = offset + length
    return _JournalScan(rid, base_seq, base_rows, records, pos)


def _pending(scan: _JournalScan, seq: int, rows: int) -> list[_Record] | None:
    """Records after (seq, rows) if they continue it without a gap, else None."""
    if scan.base_seq > seq:
        return None
    out = [r for r in scan.records if r.seq > seq]
    want_seq, want_row = seq + 1, rows
    for r in out:
        if r.seq != want_seq or r.row_start != want_row:
            return None
        want_seq += 1
        want_row += r.n_rows
    return out


class _Layout:
    """Byte layout of batch payloads: fields one after another, k rows each, little-endian."""

    def __init__(self, fields: Sequence[Field]) -> None:
        self.fields = list(fields)
        self.index = {f.name: i for i, f in enumerate(self.fields)}
        self.disk_dtypes = [f.np_dtype.newbyteorder("<") for f in self.fields]
        self.row_nbytes = [f.row_nbytes for f in self.fields]
        self.total_row_nbytes = sum(self.row_nbytes)

    def field_offset(self, rec: _Record, i: int) -> int:
        return rec.offset + rec.n_rows * sum(self.row_nbytes[:i])

    def read_rows(self, f: io.FileIO, rec: _Record, i: int, lo: int, hi: int) -> NDArray[Any]:
        """Rows ``lo:hi`` (record-relative) of field ``i`` of a batch record."""
        fld = self.fields[i]
        out = np.empty((hi - lo, *fld.shape), dtype=self.disk_dtypes[i])
        if hi > lo:
            _read_into(f, self.field_offset(rec, i) + lo * self.row_nbytes[i], out)
        return out.astype(fld.np_dtype, copy=False)


# --------------------------------------------------------------------------- HDF5 side


class _Meta(NamedTuple):
    header_json: str
    header: dict[str, Any]
    fields: list[Field]
    recording_id: str
    seq: int
    rows: int
    statics: list[str]
    package_version: str
    created_utc: str
    format_version: int
    compression: str
    trials_per_chunk: int
    sessions: list[dict[str, Any]]


def _attr_str(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8")
    return str(value)


def _inode(path: str) -> tuple[int, int]:
    try:
        st = os.stat(path)
    except OSError:
        return (-1, -1)
    return (st.st_dev, st.st_ino)


def _open_h5(path: str, mode: str, **kwargs: Any) -> h5py.File:
    """Open with h5py, turning its OSError into a RecordingError that says what to do."""
    if not os.path.exists(path):
        raise RecordingError(f"recording {path} does not exist; check the path")
    if os.path.isdir(path):
        raise RecordingError(f"recording {path} is a directory, not a recording file")
    try:
        return h5py.File(path, mode, **kwargs)
    except OSError as exc:
        text = str(exc)
        if "unable to lock file" in text:
            raise RecordingError(
                f"recording {path} is locked by another process ({text}); wait for it to "
                "finish or stop it"
            ) from exc
        try:
            is_hdf5 = h5py.is_hdf5(path)
        except OSError:
            is_hdf5 = False
        if not is_hdf5 and "truncated" not in text:
            raise RecordingError(
                f"{path} is not a timedexec recording: it is not an HDF5 file (empty, cut "
                "short, or another format); pass a file written by RecordingWriter"
            ) from exc
        raise RecordingError(
            f"recording {path} is damaged and cannot be opened ({text}). timedexec never "
            "leaves it like this, even when a sweep is killed: it was probably truncated by "
            "a copy, a download or a full disk. Restore it from its source or record the "
            "sweep again"
        ) from exc


def _read_meta(f: h5py.File, path: str) -> _Meta:
    """Validate the root attributes and datasets of an open recording."""
    attrs = f.attrs
    fmt = attrs.get("format")
    if fmt is None or _attr_str(fmt) != FORMAT_NAME:
        found = "missing" if fmt is None else repr(_attr_str(fmt))
        raise RecordingError(
            f"{path} is an HDF5 file but not a timedexec recording (root attribute 'format' "
            f"is {found}, expected {FORMAT_NAME!r}); pass a file written by RecordingWriter"
        )
    try:
        version = int(attrs["format_version"])
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(
            f"recording {path} has no valid 'format_version' attribute; the file is damaged"
        ) from exc
    if version > FORMAT_VERSION:
        raise RecordingError(
            f"recording {path} was written by a newer timedexec (format {version}; this "
            f"timedexec {__version__} reads format {FORMAT_VERSION}); upgrade timedexec "
            "(pip install -U timedexec) to read it"
        )
    if version < 1:
        raise RecordingError(f"recording {path} has format_version {version}; it is damaged")
    try:
        header_json = _attr_str(attrs["header"])
        header = json.loads(header_json)
        fields = [Field.from_dict(d) for d in json.loads(_attr_str(attrs["fields"]))]
        rid = _attr_str(attrs["recording_id"])
        seq = int(attrs["journal_seq"])
        compression = _attr_str(attrs["compression"])
        tpc = int(attrs["trials_per_chunk"])
        sessions = json.loads(_attr_str(attrs.get("sessions", "[]")))
        trials_group = f["trials"]
        static_group = f["static"]
    except (KeyError, ValueError, TypeError, ConfigError) as exc:
        raise RecordingError(
            f"recording {path} lacks or has a malformed root attribute or group ({exc}); "
            "the file is damaged"
        ) from exc
    rows = -1
    for fld in fields:
        ds = trials_group.get(fld.name)
        if not isinstance(ds, h5py.Dataset):
            raise RecordingError(f"recording {path} has no dataset /trials/{fld.name}; damaged")
        if ds.shape[1:] != fld.shape or ds.dtype != fld.np_dtype:
            raise RecordingError(
                f"recording {path}: /trials/{fld.name} has shape {ds.shape} and dtype "
                f"{ds.dtype}, but its field says (n, *{fld.shape}) {fld.dtype}; damaged"
            )
        if rows not in (-1, ds.shape[0]):
            raise RecordingError(
                f"recording {path}: /trials/{fld.name} has {ds.shape[0]} rows, other fields "
                f"{rows}; the file is damaged"
            )
        rows = ds.shape[0]
    return _Meta(
        header_json=header_json,
        header=header,
        fields=fields,
        recording_id=rid,
        seq=seq,
        rows=max(rows, 0),
        statics=list(static_group.keys()),
        package_version=_attr_str(attrs.get("package_version", "")),
        created_utc=_attr_str(attrs.get("created_utc", "")),
        format_version=version,
        compression=compression,
        trials_per_chunk=tpc,
        sessions=sessions,
    )


def _create_static(
    group: h5py.Group,
    name: str,
    data: NDArray[Any],
    unit: str,
    doc: str,
    compression: tuple[str | None, int | None, str],
) -> None:
    kwargs: dict[str, Any] = {}
    if data.ndim >= 1 and data.nbytes >= _STATIC_COMPRESS_BYTES and compression[0]:
        kwargs = {
            "chunks": True,
            "compression": compression[0],
            "compression_opts": compression[1],
            "shuffle": True,
        }
    ds = group.create_dataset(name, data=data, **kwargs)
    ds.attrs["unit"] = unit
    ds.attrs["doc"] = doc


# --------------------------------------------------------------------------- writer


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
        comp = _parse_compression(compression)
        header_json = None if header is None else _encode_header(header)
        norm_fields = None if fields is None else _normalise_fields(fields)

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
        except BaseException:
            self._release()
            raise
        self._closed = False

    # ------------------------------------------------------------------ paths and lock

    def _side(self, suffix: str) -> str:
        return self._path + suffix

    def _acquire_lock(self) -> None:
        lock_path = self._side(_LOCK)
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
            _unlink(self._side(_LOCK))
            os.close(self._lock_fd)
            self._lock_fd = None

    def _sync_file(self, path: str) -> None:
        if self._fsync:
            _fsync_path(path)

    def _sync_dir(self) -> None:
        if self._fsync:
            _fsync_dir(self._dir)

    # ------------------------------------------------------------------ open / create

    def _init_state(self, meta: _Meta, comp: tuple[str | None, int | None, str]) -> None:
        self._header_json = meta.header_json
        self._fields = meta.fields
        self._layout = _Layout(meta.fields)
        self._id = meta.recording_id
        self._comp = comp
        self._tpc = meta.trials_per_chunk
        self._p_seq = meta.seq  # what the HDF5 file P holds
        self._p_rows = meta.rows
        self._seq = meta.seq  # what P + journal hold
        self._rows = meta.rows
        self._statics: dict[str, _Record | None] = dict.fromkeys(meta.statics)
        self._records: list[_Record] = []
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
        comp: tuple[str | None, int | None, str],
        tpc: int,
    ) -> None:
        for suffix in (_JOURNAL, _JOURNAL_NEW, _SHADOW, _PARTIAL, _OLD):
            _unlink(self._side(suffix))  # left by a sweep that never committed its file
        partial = self._side(_PARTIAL)
        created = _utc_now()
        meta = _Meta(
            header_json=header_json,
            header=json.loads(header_json),
            fields=fields,
            recording_id=uuid.uuid4().hex,
            seq=0,
            rows=0,
            statics=[],
            package_version=__version__,
            created_utc=created,
            format_version=FORMAT_VERSION,
            compression=comp[2],
            trials_per_chunk=tpc,
            sessions=[],
        )
        self._init_state(meta, comp)
        try:
            with h5py.File(partial, "w", libver=_LIBVER) as f:
                f.attrs["format"] = FORMAT_NAME
                f.attrs["format_version"] = FORMAT_VERSION
                f.attrs["package_version"] = __version__
                f.attrs["header"] = header_json
                f.attrs["created_utc"] = created
                f.attrs["fields"] = json.dumps([fld.to_dict() for fld in fields])
                f.attrs["recording_id"] = self._id
                f.attrs["compression"] = comp[2]
                f.attrs["trials_per_chunk"] = tpc
                self._set_progress_attrs(f)
                trials = f.create_group("trials")
                f.create_group("static")
                for fld in fields:
                    ds = trials.create_dataset(
                        fld.name,
                        shape=(0, *fld.shape),
                        maxshape=(None, *fld.shape),
                        dtype=fld.np_dtype,
                        chunks=(tpc, *fld.shape),
                        compression=comp[0],
                        compression_opts=comp[1],
                        shuffle=comp[0] is not None,
                    )
                    ds.attrs["unit"] = fld.unit
                    ds.attrs["doc"] = fld.doc
            self._sync_file(partial)
            _fault("create.partial_written")
            os.replace(partial, self._path)
            self._sync_dir()
        except OSError as exc:
            _unlink(partial)
            raise RecordingError(f"cannot create recording {self._path}: {exc}") from exc
        _fault("create.committed")
        try:
            self._new_journal()
        except OSError as exc:
            raise RecordingError(f"cannot create the journal of {self._path}: {exc}") from exc

    def _open_existing(self, header_json: str | None, fields: list[Field] | None) -> None:
        # Leftovers of a checkpoint that was interrupted: P itself is always complete.
        _unlink(self._side(_PARTIAL))
        _unlink(self._side(_JOURNAL_NEW))
        old, shadow = self._side(_OLD), self._side(_SHADOW)
        if os.path.exists(old):
            if os.path.samefile(old, self._path) or os.path.exists(shadow):
                _unlink(old)  # a second name of P itself, never to be modified
            else:
                os.replace(old, shadow)  # the previous P: a clean shadow
        with _open_h5(self._path, "r") as f:
            meta = _read_meta(f, self._path)
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
        self._init_state(meta, _parse_compression(meta.compression))
        self._trial_set = set(trials.tolist())

        jpath = self._side(_JOURNAL)
        scan: _JournalScan | None = None
        if os.path.exists(jpath):
            with open(jpath, "rb", buffering=0) as jf:
                try:
                    scan = _scan_journal(jf, self._id)
                except _ForeignJournalError as exc:
                    raise RecordingError(
                        f"cannot resume {self._path}: journal {jpath} belongs to another "
                        f"recording (id {exc.recording_id}, expected {self._id}); move it "
                        "away to resume from the HDF5 file alone"
                    ) from exc
        pending = None if scan is None else _pending(scan, meta.seq, meta.rows)
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
                if rec.kind == _KIND_BATCH:
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
        new, jpath = self._side(_JOURNAL_NEW), self._side(_JOURNAL)
        fd = os.open(new, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, _journal_header(self._id, self._p_seq, self._p_rows))
            if self._fsync:
                os.fsync(fd)
        finally:
            os.close(fd)
        _fault("fold.journal_new")
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
        _check_name(name, "static")
        if name in self._statics:
            raise ConfigError(
                f"static {name!r} is already in {self._path}; statics are written once "
                "(check has_static() before writing on resume)"
            )
        arr = np.asarray(data)
        dt = _canonical_dtype(arr.dtype, f"static {name!r}")
        arr = np.ascontiguousarray(arr, dtype=dt.newbyteorder("<"))
        meta = json.dumps(
            {
                "name": name,
                "dtype": _dtype_name(dt),
                "shape": list(arr.shape),
                "unit": str(unit),
                "doc": str(doc),
            }
        ).encode("utf-8")
        payload = _U32.pack(len(meta)) + meta + arr.tobytes()
        rec = self._write_record(_KIND_STATIC, 0, payload)
        info = json.loads(meta)
        info["data_offset"] = rec.offset + 4 + len(meta)
        rec = rec._replace(static=info)
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
            The journal cannot be written (disk full, I/O error); nothing of the batch is
            recorded then.
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
            _coerce(f.name, batch[f.name], f.np_dtype, (k, *f.shape), k, f.shape)
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
        payload = b"".join(
            np.ascontiguousarray(a, dtype=d).tobytes()
            for a, d in zip(arrays, self._layout.disk_dtypes, strict=True)
        )
        self._write_record(_KIND_BATCH, k, payload)
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
                _fault("close.folded")
                for suffix in (_SHADOW, _JOURNAL):
                    _unlink(self._side(suffix))
                self._sync_dir()
        finally:
            self._closed = True
            self._release()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"{self._rows} trials"
        return f"RecordingWriter({self._path!r}, {state})"

    # ------------------------------------------------------------------ journal writes

    def _write_record(self, kind: int, n_rows: int, payload: bytes) -> _Record:
        assert self._journal_fd is not None
        seq = self._seq + 1
        head = _RHEAD.pack(
            _RECORD_MAGIC, kind, seq, self._rows, n_rows, len(payload), zlib.crc32(payload)
        )
        head += _U32.pack(zlib.crc32(head))
        fd = self._journal_fd
        start = os.fstat(fd).st_size
        try:
            _write_all(fd, head)
            if os.environ.get(_FAULT_ENV, "").startswith("append.torn"):
                _write_all(fd, payload[: len(payload) // 2])
                _fault("append.torn")
                _write_all(fd, payload[len(payload) // 2 :])
            else:
                _write_all(fd, payload)
            _fault("append.written")
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
        rec = _Record(kind, seq, self._rows, n_rows, start + _RHEAD_SIZE, len(payload), None)
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
        """Bring P up to date with the journal by swapping in an updated copy."""
        if not self._records:
            return
        partial = self._side(_PARTIAL)
        try:
            w = self._open_partial()
            try:
                self._catch_up(w)
                _fault("fold.caught_up")
                self._apply_journal(w)
                self._set_progress_attrs(w)
                _fault("fold.applied")
            finally:
                w.close()
            self._sync_file(partial)
            _fault("fold.synced")
            old = self._side(_OLD)
            _unlink(old)
            try:
                os.link(self._path, old)  # keep the current P: it becomes the next shadow
                linked = True
            except OSError:  # no hard links on this file system: copy P at the next fold
                linked = False
            _fault("fold.linked")
            os.replace(partial, self._path)  # the commit point of the checkpoint
            self._sync_dir()
            self._p_seq, self._p_rows = self._seq, self._rows
            _fault("fold.replaced")
            if linked:
                os.replace(old, self._side(_SHADOW))
                self._sync_dir()
            _fault("fold.shadowed")
            self._new_journal()
        except BaseException as exc:  # P is intact; the journal keeps every batch
            with contextlib.suppress(OSError):
                _unlink(partial)
            self._broken = repr(exc)
            if isinstance(exc, RecordingError) or not isinstance(exc, OSError):
                raise
            raise RecordingError(
                f"checkpoint of {self._path} failed ({exc}); every appended batch is kept in "
                f"{self._side(_JOURNAL)}. Fix the cause (disk space?) and resume"
            ) from exc

    def _open_partial(self) -> h5py.File:
        """P.partial opened for writing: the shadow if usable, else a fresh copy of P."""
        partial, shadow = self._side(_PARTIAL), self._side(_SHADOW)
        _unlink(partial)
        if os.path.exists(shadow):
            if os.path.samefile(shadow, self._path):
                _unlink(shadow)
            else:
                os.replace(shadow, partial)
                _fault("fold.partial_opened")
                try:
                    w = h5py.File(partial, "r+", libver=_LIBVER, rdcc_nbytes=_WRITE_CACHE_BYTES)
                except OSError:  # e.g. a reader still has this old version open (lock)
                    w = None
                if w is not None:
                    ok = False
                    with contextlib.suppress(RecordingError, KeyError, ValueError):
                        m = _read_meta(w, partial)
                        ok = (
                            m.recording_id == self._id
                            and m.seq <= self._p_seq
                            and m.rows <= self._p_rows
                        )
                    if ok:
                        return w
                    w.close()
                _unlink(partial)
        shutil.copyfile(self._path, partial)
        _fault("fold.copied")
        return h5py.File(partial, "r+", libver=_LIBVER, rdcc_nbytes=_WRITE_CACHE_BYTES)

    def _catch_up(self, w: h5py.File) -> None:
        """Copy what P has and the shadow lacks: whole compressed chunks, no recompression."""
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
            for name in missing_statics:
                src.copy(src["static"][name], w["static"], name=name)

    def _p_statics(self) -> list[str]:
        pending = {r.static["name"] for r in self._records if r.static is not None}
        return [s for s in self._statics if s not in pending]

    def _apply_journal(self, w: h5py.File) -> None:
        recs = [r for r in self._records if r.seq > self._p_seq]
        with open(self._side(_JOURNAL), "rb", buffering=0) as jf:
            group: list[_Record] = []
            group_bytes = 0
            for rec in recs:
                if rec.kind == _KIND_STATIC:
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

    def _write_rows(self, w: h5py.File, jf: io.FileIO, group: list[_Record]) -> None:
        if not group:
            return
        start = group[0].row_start
        end = group[-1].row_start + group[-1].n_rows
        for i, fld in enumerate(self._fields):
            arr = np.empty((end - start, *fld.shape), dtype=self._layout.disk_dtypes[i])
            for rec in group:
                lo = rec.row_start - start
                _read_into(jf, self._layout.field_offset(rec, i), arr[lo : lo + rec.n_rows])
            ds = w["trials"][fld.name]
            ds.resize(end, axis=0)
            ds[start:end] = arr

    def _apply_static(self, w: h5py.File, jf: io.FileIO, rec: _Record) -> None:
        meta = rec.static
        assert meta is not None
        if meta["name"] in w["static"]:
            return
        arr = np.empty(tuple(meta["shape"]), dtype=np.dtype(meta["dtype"]).newbyteorder("<"))
        if arr.nbytes:
            _read_into(jf, meta["data_offset"], arr)
        _create_static(
            w["static"],
            meta["name"],
            arr.astype(np.dtype(meta["dtype"]), copy=False),
            meta["unit"],
            meta["doc"],
            self._comp,
        )

    def _set_progress_attrs(self, f: h5py.File) -> None:
        f.attrs["journal_seq"] = self._seq
        f.attrs["sessions"] = json.dumps(self._sessions)


def _coerce(
    name: str,
    value: ArrayLike,
    dt: np.dtype[Any],
    expected: tuple[int, ...],
    k: int,
    per_trial: tuple[int, ...],
) -> NDArray[Any]:
    """Check one batch field's shape and convert it to the field dtype if lossless."""
    arr = np.asarray(value)
    if arr.shape != expected:
        raise ConfigError(
            f"batch field {name!r}: expected shape {expected} ({k} trials x per-trial shape "
            f"{per_trial}), got {arr.shape}"
        )
    if arr.dtype == dt:
        return arr
    if np.can_cast(arr.dtype, dt, "safe"):
        return arr.astype(dt)
    if arr.dtype.kind in "iu" and dt.kind in "iu":
        info = np.iinfo(dt)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            raise ConfigError(
                f"batch field {name!r}: values {arr.min()}..{arr.max()} do not fit dtype "
                f"{_dtype_name(dt)} (range {info.min}..{info.max}); check the scaling"
            )
        return arr.astype(dt)
    if arr.dtype.kind == "f" and dt.kind == "f":
        return arr.astype(dt)
    raise ConfigError(
        f"batch field {name!r}: expected dtype {_dtype_name(dt)} (or one that converts to it "
        f"without loss), got {arr.dtype}; convert it explicitly"
    )


# --------------------------------------------------------------------------- reader


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
            f = _open_h5(self.path, "r", rdcc_nbytes=_READ_CACHE_BYTES)
            try:
                meta = _read_meta(f, self.path)
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
                f"journal {self.path}{_JOURNAL} does not continue {self.path}; ignoring it "
                "(only the trials in the HDF5 file are shown)",
                stacklevel=2,
            )
            f = _open_h5(self.path, "r", rdcc_nbytes=_READ_CACHE_BYTES)
            meta = _read_meta(f, self.path)
            loaded = (None, [])
        assert loaded is not None
        self._h5 = f
        self._jf, records = loaded
        self._meta = meta
        self._layout = _Layout(meta.fields)
        self.header: dict[str, Any] = meta.header
        self.fields: dict[str, Field] = {fld.name: fld for fld in meta.fields}
        self.package_version: str = meta.package_version
        self.created_utc: str = meta.created_utc
        self.format_version: int = meta.format_version
        self._h5_rows = meta.rows
        self._batches = [r for r in records if r.kind == _KIND_BATCH]
        self._batch_starts = np.array([r.row_start for r in self._batches], dtype=np.int64)
        self._statics = {r.static["name"]: r for r in records if r.static is not None}
        self.n_trials: int = meta.rows + sum(r.n_rows for r in self._batches)

    def _load_journal(self, meta: _Meta) -> tuple[io.FileIO | None, list[_Record]] | None:
        jpath = self.path + _JOURNAL
        try:
            jf: io.FileIO = open(jpath, "rb", buffering=0)  # noqa: SIM115 (kept open)
        except FileNotFoundError:
            return None, []
        try:
            scan = _scan_journal(jf, meta.recording_id)
        except _ForeignJournalError as exc:
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
        pending = _pending(scan, meta.seq, meta.rows)
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
                _read_into(self._jf, meta["data_offset"], arr)
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
        try:
            return np.asarray(f["trials"][fld.name][sel])
        except OSError as exc:
            raise RecordingError(
                f"cannot read /trials/{fld.name} of {self.path} ({exc}); the file is damaged"
            ) from exc

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
            if uniq.size * 4 >= hi - lo:  # dense: one contiguous read is faster
                data = self._read_h5(f, fld, slice(lo, hi))[uniq - lo]
            else:
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
