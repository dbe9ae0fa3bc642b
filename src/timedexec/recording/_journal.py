"""The write-ahead journal ``P.journal``: encoding, scanning, and the batch payload layout.

All integers little-endian (``docs/recording-format.md``, "Journal encoding"):

* file header (48 bytes): ``b"TXJRNL01"``, u32 format version, 16-byte recording id (the
  ``recording_id`` attribute as UUID bytes), u64 base sequence, u64 base rows, u32 CRC-32
  of the preceding 44 bytes;
* record header (48 bytes): ``b"TXR1"``, u8 kind (1 batch, 2 static), 3 pad bytes, u64
  sequence number, u64 first row, u64 rows, u64 payload length, u32 CRC-32 of the payload,
  u32 CRC-32 of the preceding 44 bytes; then the payload;
* batch payload (:class:`Layout`): for each field in stored order, ``rows x row bytes`` in
  C order;
* static payload (:func:`static_payload`): u32 length of a JSON object ``{name, dtype,
  shape, unit, doc}``, the JSON, then the array bytes in C order.

The journal is append-only and fsync'ed record by record, so only its last record can be
torn: :func:`scan_journal` stops at the first record that is short or fails a CRC.
"""

from __future__ import annotations

import io
import json
import os
import struct
import uuid
import zlib
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from timedexec.errors import RecordingError
from timedexec.recording._fields import Field
from timedexec.recording._protocol import FORMAT_VERSION

__all__ = [
    "KIND_BATCH",
    "KIND_STATIC",
    "RHEAD_SIZE",
    "ForeignJournalError",
    "JournalScan",
    "Layout",
    "Record",
    "journal_header",
    "pending_records",
    "read_exact",
    "read_into",
    "record_header",
    "scan_journal",
    "static_payload",
]

# Journal layout: a file header, then records (header, payload). All integers little-endian.
_JOURNAL_MAGIC = b"TXJRNL01"
_JHEAD = struct.Struct("<8sI16sQQ")  # magic, format version, recording id, base seq, base rows
_JHEAD_SIZE = _JHEAD.size + 4  # + crc32 of the above
_RECORD_MAGIC = b"TXR1"
_RHEAD = struct.Struct("<4sB3xQQQQI")  # magic, kind, seq, row start, rows, payload len, crc
#: Bytes of a record header (the payload follows it).
RHEAD_SIZE = _RHEAD.size + 4  # + crc32 of the above
#: Record kinds.
KIND_BATCH = 1
KIND_STATIC = 2
_U32 = struct.Struct("<I")


class Record(NamedTuple):
    """One valid journal record: where its payload is and what it holds."""

    kind: int
    seq: int
    row_start: int
    n_rows: int
    offset: int  # payload offset in the journal file
    length: int  # payload bytes
    static: dict[str, Any] | None  # static records: name, dtype, shape, unit, doc, data_offset


class JournalScan(NamedTuple):
    """A journal's header fields and its valid records, as :func:`scan_journal` found them."""

    recording_id: str
    base_seq: int
    base_rows: int
    records: list[Record]
    end: int  # byte after the last valid record


class ForeignJournalError(Exception):
    """The journal belongs to another recording (its ``recording_id`` differs)."""

    def __init__(self, recording_id: str) -> None:
        super().__init__(recording_id)
        self.recording_id = recording_id


# --------------------------------------------------------------------------- encoding


def journal_header(recording_id: str, base_seq: int, base_rows: int) -> bytes:
    """File header of a journal that continues a file holding ``(base_seq, base_rows)``."""
    head = _JHEAD.pack(
        _JOURNAL_MAGIC, FORMAT_VERSION, uuid.UUID(hex=recording_id).bytes, base_seq, base_rows
    )
    return head + _U32.pack(zlib.crc32(head))


def record_header(kind: int, seq: int, row_start: int, n_rows: int, payload: bytes) -> bytes:
    """Header of the record ``seq`` (kind, first row, rows) carrying ``payload``."""
    head = _RHEAD.pack(
        _RECORD_MAGIC, kind, seq, row_start, n_rows, len(payload), zlib.crc32(payload)
    )
    return head + _U32.pack(zlib.crc32(head))


def static_payload(info: Mapping[str, Any], data: NDArray[Any]) -> tuple[bytes, int]:
    """Payload of a static record and the offset of the array bytes in it.

    Parameters
    ----------
    info : mapping
        ``{name, dtype, shape, unit, doc}``, stored as JSON in this key order.
    data : ndarray
        The array, C-contiguous and little-endian.
    """
    meta = json.dumps(dict(info)).encode("utf-8")
    return _U32.pack(len(meta)) + meta + data.tobytes(), 4 + len(meta)


# --------------------------------------------------------------------------- reading


def read_exact(f: io.FileIO, offset: int, n: int) -> bytes:
    """Up to ``n`` bytes from ``offset`` (fewer only at the end of the file)."""
    f.seek(offset)
    parts = []
    while n > 0:
        b = f.read(n)
        if not b:
            break
        parts.append(b)
        n -= len(b)
    return b"".join(parts)


def read_into(f: io.FileIO, offset: int, out: NDArray[Any]) -> None:
    """Fill the C-contiguous array ``out`` with bytes from ``offset``."""
    view = memoryview(out).cast("B")  # type: ignore[arg-type]
    f.seek(offset)
    while view:
        n = f.readinto(view)
        if not n:
            raise RecordingError(f"journal {f.name} ends early at byte {f.tell()}")
        view = view[n:]


def scan_journal(f: io.FileIO, expected_id: str | None) -> JournalScan | None:
    """Index the valid records of a journal; None if its header is missing or torn.

    Stops at the first record that is short or fails a CRC: with an append-only file that
    is fsync'ed after every record, only the last record can be torn.
    """
    size = os.fstat(f.fileno()).st_size
    head = read_exact(f, 0, _JHEAD_SIZE)
    if len(head) < _JHEAD_SIZE or zlib.crc32(head[:-4]) != _U32.unpack(head[-4:])[0]:
        return None
    magic, version, rid_bytes, base_seq, base_rows = _JHEAD.unpack(head[:-4])
    if magic != _JOURNAL_MAGIC:
        return None
    rid = uuid.UUID(bytes=rid_bytes).hex
    if expected_id is not None and rid != expected_id:
        raise ForeignJournalError(rid)
    if version > FORMAT_VERSION:
        raise RecordingError(
            f"journal {f.name} was written by a newer timedexec (format {version}); upgrade "
            "timedexec to read or resume this recording"
        )
    records: list[Record] = []
    pos = _JHEAD_SIZE
    while pos + RHEAD_SIZE <= size:
        raw = read_exact(f, pos, RHEAD_SIZE)
        if len(raw) < RHEAD_SIZE or zlib.crc32(raw[:-4]) != _U32.unpack(raw[-4:])[0]:
            break
        magic, kind, seq, row_start, n_rows, length, crc = _RHEAD.unpack(raw[:-4])
        offset = pos + RHEAD_SIZE
        if magic != _RECORD_MAGIC or kind not in (KIND_BATCH, KIND_STATIC):
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
        if kind == KIND_STATIC:
            (meta_len,) = _U32.unpack(first[:4])
            meta_raw = first[4 : 4 + meta_len]
            if len(meta_raw) < meta_len:  # a meta block larger than one read piece
                meta_raw = read_exact(f, offset + 4, meta_len)
            static = json.loads(meta_raw.decode("utf-8"))
            static["data_offset"] = offset + 4 + meta_len
        records.append(Record(kind, seq, row_start, n_rows, offset, length, static))
        pos = offset + length
    return JournalScan(rid, base_seq, base_rows, records, pos)


def pending_records(scan: JournalScan, seq: int, rows: int) -> list[Record] | None:
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


class Layout:
    """Byte layout of batch payloads: fields one after another, k rows each, little-endian."""

    def __init__(self, fields: Sequence[Field]) -> None:
        self.fields = list(fields)
        self.index = {f.name: i for i, f in enumerate(self.fields)}
        self.disk_dtypes = [f.np_dtype.newbyteorder("<") for f in self.fields]
        self.row_nbytes = [f.row_nbytes for f in self.fields]
        self.total_row_nbytes = sum(self.row_nbytes)

    def encode(self, arrays: Sequence[NDArray[Any]]) -> bytes:
        """Payload of a batch: ``arrays[i]`` (k rows of field ``i``) one after another."""
        return b"".join(
            np.ascontiguousarray(a, dtype=d).tobytes()
            for a, d in zip(arrays, self.disk_dtypes, strict=True)
        )

    def field_offset(self, rec: Record, i: int) -> int:
        """Byte offset of field ``i`` in the journal file, for the batch record ``rec``."""
        return rec.offset + rec.n_rows * sum(self.row_nbytes[:i])

    def read_rows(self, f: io.FileIO, rec: Record, i: int, lo: int, hi: int) -> NDArray[Any]:
        """Rows ``lo:hi`` (record-relative) of field ``i`` of a batch record."""
        fld = self.fields[i]
        out = np.empty((hi - lo, *fld.shape), dtype=self.disk_dtypes[i])
        if hi > lo:
            read_into(f, self.field_offset(rec, i) + lo * self.row_nbytes[i], out)
        return out.astype(fld.np_dtype, copy=False)
