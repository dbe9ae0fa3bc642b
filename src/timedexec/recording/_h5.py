"""The HDF5 side of a recording: layout, opening with clear errors, root metadata, statics.

Layout (``docs/recording-format.md``): root attributes (``format``, ``format_version``,
``package_version``, ``header``, ``created_utc``, ``fields``, ``recording_id``,
``journal_seq``, ``compression``, ``trials_per_chunk``, ``sessions``), one dataset per
per-trial field under ``/trials`` (chunked, byte shuffle + compression) and once-only
arrays under ``/static``. Objects are created with library-version bounds ``v108``.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import h5py
from numpy.typing import NDArray

from timedexec._version import __version__
from timedexec.errors import ConfigError, RecordingError
from timedexec.recording._fields import Field
from timedexec.recording._protocol import FORMAT_NAME, FORMAT_VERSION

__all__ = [
    "LIBVER",
    "READ_CACHE_BYTES",
    "WRITE_CACHE_BYTES",
    "Compression",
    "Meta",
    "create_recording_file",
    "create_static",
    "open_h5",
    "parse_compression",
    "read_meta",
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
    """Write the array ``/static/<name>``; 64 KiB and more are chunked and compressed."""
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
    with h5py.File(path, "w", libver=LIBVER) as f:
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
            )
            ds.attrs["unit"] = fld.unit
            ds.attrs["doc"] = fld.doc
