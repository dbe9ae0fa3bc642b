"""The HDF5 side of a recording: layout, opening with clear errors, root metadata, statics.

Layout (``docs/recording-format.md``): root attributes (``format``, ``format_version``,
``package_version``, ``header``, ``created_utc``, ``fields``, ``recording_id``,
``journal_seq``, ``compression``, ``trials_per_chunk``, ``sessions``), one dataset per
per-trial field under ``/trials`` (chunked, byte shuffle + compression) and once-only
arrays under ``/static``. Objects are created with library-version bounds ``v108``.

Files the writer changes (a new recording, ``P.partial`` during a checkpoint) are opened by
:func:`writable_h5`, through a file object that cannot leave HDF5 with a half-closed file:
HDF5 2.0 cannot recover from a write that fails while it closes a file (a full disk, an I/O
error). ``H5Fclose`` then fails half-way, the file's id stays valid, and the next close of
it -- at the latest when Python frees the object at exit -- crashes the interpreter
(segmentation fault in ``H5D__flush_all_cb``). Such a file is always discarded, so after
its first failed write every further write of it is dropped, and the close completes.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import re
import signal
import sys
import threading
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import h5py
from numpy.typing import NDArray

from timedexec._version import __version__
from timedexec.errors import ConfigError, RecordingError
from timedexec.recording._fields import Field
from timedexec.recording._protocol import FORMAT_NAME, FORMAT_VERSION

if TYPE_CHECKING:
    from _typeshed import ReadableBuffer, WriteableBuffer

__all__ = [
    "LIBVER",
    "READ_CACHE_BYTES",
    "WRITE_CACHE_BYTES",
    "Compression",
    "Meta",
    "WritableH5",
    "create_recording_file",
    "create_static",
    "open_h5",
    "parse_compression",
    "read_meta",
    "sigint_deferred",
    "writable_h5",
    "write_progress",
]

# HDF5 file-format bounds: objects readable by HDF5 >= 1.8 (dense attribute storage, so a
# large JSON header fits), nothing that needs a newer library.
LIBVER = ("v108", "v108")
READ_CACHE_BYTES = 32 * 2**20  # raw-chunk cache of readers: a gyro chunk is ~1.8 MB
WRITE_CACHE_BYTES = 16 * 2**20
_STATIC_COMPRESS_BYTES = 64 * 2**10  # statics at least this large are chunked + compressed

#: ``(h5py filter, filter level, canonical name)``, e.g. ``("gzip", 4, "gzip-4")``.
Compression = tuple[str | None, int | None, str]


def parse_compression(compression: str | None) -> Compression:
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


class Meta(NamedTuple):
    """The root metadata of a recording file, validated by :func:`read_meta`."""

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
    """An HDF5 string attribute as str (h5py returns bytes for some encodings)."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    return str(value)


def open_h5(path: str, mode: str, **kwargs: Any) -> h5py.File:
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


class _GuardedFile(io.RawIOBase):
    """The file behind a :func:`writable_h5` HDF5 file: positional I/O on one descriptor.

    A failed write is never raised into HDF5: HDF5 cannot recover from one, neither while it
    closes the file nor while it closes a dataset (which flushes its chunk cache), and
    Python closes datasets whenever their last reference goes. The first failure is kept in
    :attr:`error` and every later write (and truncation) is dropped and reported done; the
    writer asks :meth:`WritableH5.check` after each step and abandons the file, which it
    deletes. HDF5 thus always finishes its work, on a file nobody will read.
    """

    def __init__(self, path: str, *, create: bool) -> None:
        super().__init__()
        flags = os.O_RDWR | (os.O_CREAT | os.O_TRUNC if create else 0)
        self.fd = os.open(path, flags, 0o644)
        self.pos = 0
        self.error: OSError | None = None
        try:
            _lock(self.fd)
        except OSError:
            os.close(self.fd)
            raise

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        if whence == os.SEEK_SET:
            self.pos = offset
        elif whence == os.SEEK_CUR:
            self.pos += offset
        else:
            self.pos = os.fstat(self.fd).st_size + offset
        return self.pos

    def tell(self) -> int:
        return self.pos

    def readinto(self, buffer: WriteableBuffer) -> int:
        view = memoryview(buffer).cast("B")
        got = 0
        while got < len(view):
            data = os.pread(self.fd, len(view) - got, self.pos + got)
            if not data:
                break
            view[got : got + len(data)] = data
            got += len(data)
        self.pos += got
        return got

    def write(self, buffer: ReadableBuffer) -> int:
        view = memoryview(buffer).cast("B")
        if self.error is None:
            try:
                done = 0
                while done < len(view):
                    done += os.pwrite(self.fd, view[done:], self.pos + done)
            except OSError as exc:
                self.error = exc
        self.pos += len(view)
        return len(view)

    def truncate(self, size: int | None = None) -> int:
        size = self.pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self.fd, size)
            except OSError as exc:
                self.error = exc
        return size

    def flush(self) -> None:
        """Nothing to flush: every write went to the descriptor (fsync comes later)."""

    def close(self) -> None:
        if not self.closed:
            os.close(self.fd)
        super().close()


def _lock(fd: int) -> None:
    """Lock a file being written as HDF5's own driver does: exclusive, without waiting.

    A reader still holding this (older) version of the recording open has it locked shared
    through HDF5, so the writer gets ``BlockingIOError`` and copies ``P`` instead. A file
    system without locks is accepted (HDF5's ``BEST_EFFORT``), and
    ``HDF5_USE_FILE_LOCKING=FALSE`` turns locking off here as it does in HDF5.
    """
    if sys.platform == "win32" or os.environ.get("HDF5_USE_FILE_LOCKING", "").upper() == "FALSE":
        return
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise
    except OSError as exc:
        if exc.errno not in (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL):
            raise


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) until the block ends, then raise the KeyboardInterrupt.

    A KeyboardInterrupt raised inside one of :class:`_GuardedFile`'s methods (Python code
    that HDF5 calls) would abort an HDF5 operation half-way, and one raised between the
    steps of a checkpoint would throw away finished work; a checkpoint is short next to a
    person's reaction time. Only the main thread receives KeyboardInterrupt, and only it
    may change the handler, so elsewhere this does nothing; a handler the program installed
    itself is left alone (and so is a nested block).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is not signal.default_int_handler:  # a handler of the caller's: leave it
        yield
        return
    held: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if held:
        raise KeyboardInterrupt


class WritableH5:
    """An HDF5 file open for writing through :func:`writable_h5`.

    Attributes
    ----------
    file : h5py.File
        The open file.
    """

    def __init__(self, file: h5py.File, raw: _GuardedFile) -> None:
        self.file = file
        self._raw = raw

    def check(self) -> None:
        """Raise the first write of the file that failed (disk full, I/O error), if any."""
        if self._raw.error is not None:
            raise self._raw.error


@contextlib.contextmanager
def writable_h5(path: str, mode: str, **kwargs: Any) -> Iterator[WritableH5]:
    """Open the HDF5 file ``path`` for writing; close it on leaving, whatever happened.

    Call :meth:`WritableH5.check` after each step: a failed write shows there (and at the
    latest when the block ends), never inside HDF5.

    Parameters
    ----------
    path : str
        A file the writer owns and deletes if anything fails (``P.partial``).
    mode : {'w', 'r+'}
        Create (truncate) or update.
    **kwargs
        Passed to :class:`h5py.File` (``libver``, ``rdcc_nbytes``).

    Yields
    ------
    WritableH5
        The open file and its check.

    Raises
    ------
    OSError
        The first write that failed (disk full, I/O error), even one while closing; or
        ``BlockingIOError`` when opening: the file is locked (a reader has it open). The
        HDF5 file is closed in every case, so nothing is left for the interpreter's exit;
        the caller deletes the file.
    """
    with sigint_deferred():
        raw = _GuardedFile(path, create=mode == "w")
        try:
            f = h5py.File(raw, mode, **kwargs)
        except BaseException:
            raw.close()
            raise
        try:
            try:
                yield WritableH5(f, raw)
            except BaseException:
                if raw.error is None:  # abandoned: what HDF5 writes while closing is dropped
                    raw.error = OSError(errno.ECANCELED, "abandoned")
                raise
            finally:
                f.close()
        finally:
            raw.close()
        if raw.error is not None:
            raise raw.error


def read_meta(f: h5py.File, path: str) -> Meta:
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
    return Meta(
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


def create_static(
    group: h5py.Group,
    name: str,
    data: NDArray[Any],
    unit: str,
    doc: str,
    compression: Compression,
) -> None:
    """Write the array ``/static/<name>``; 64 KiB and more are chunked, compressed and
    checksummed (Fletcher-32 per chunk)."""
    kwargs: dict[str, Any] = {}
    if data.ndim >= 1 and data.nbytes >= _STATIC_COMPRESS_BYTES and compression[0]:
        kwargs = {
            "chunks": True,
            "compression": compression[0],
            "compression_opts": compression[1],
            "shuffle": True,
            "fletcher32": True,
        }
    ds = group.create_dataset(name, data=data, **kwargs)
    ds.attrs["unit"] = unit
    ds.attrs["doc"] = doc


def write_progress(f: h5py.File, seq: int, sessions: Sequence[Mapping[str, Any]]) -> None:
    """Set the root attributes that change at every checkpoint: ``journal_seq``, ``sessions``."""
    f.attrs["journal_seq"] = seq
    f.attrs["sessions"] = json.dumps(sessions)


def create_recording_file(
    path: str,
    meta: Meta,
    compression: Compression,
    sessions: Sequence[Mapping[str, Any]],
) -> None:
    """Write a new, empty recording (root attributes, ``/trials``, ``/static``) at ``path``.

    Parameters
    ----------
    path : str
        The file to create (``P.partial``: it becomes ``P`` by rename once fsync'ed).
    meta : Meta
        Header, fields, recording id, creation time, trials per chunk and ``journal_seq``.
    compression : Compression
        Filter of the per-trial datasets (from :func:`parse_compression`).
    sessions : sequence of mapping
        The ``sessions`` attribute (the creating session).
    """
    with writable_h5(path, "w", libver=LIBVER) as h5:
        f = h5.file
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["package_version"] = __version__
        f.attrs["header"] = meta.header_json
        f.attrs["created_utc"] = meta.created_utc
        f.attrs["fields"] = json.dumps([fld.to_dict() for fld in meta.fields])
        f.attrs["recording_id"] = meta.recording_id
        f.attrs["compression"] = compression[2]
        f.attrs["trials_per_chunk"] = meta.trials_per_chunk
        write_progress(f, meta.seq, sessions)
        trials = f.create_group("trials")
        f.create_group("static")
        tpc = meta.trials_per_chunk
        for fld in meta.fields:
            ds = trials.create_dataset(
                fld.name,
                shape=(0, *fld.shape),
                maxshape=(None, *fld.shape),
                dtype=fld.np_dtype,
                chunks=(tpc, *fld.shape),
                compression=compression[0],
                compression_opts=compression[1],
                shuffle=compression[0] is not None,
                # A checksum per chunk, checked before decompression: a chunk damaged
                # after writing (disk, copy) is an error naming its rows, not numbers that
                # are silently wrong or an LZF decoder fed garbage.
                fletcher32=True,
            )
            ds.attrs["unit"] = fld.unit
            ds.attrs["doc"] = fld.doc
        h5.check()
