"""Gyro serial frame format: vectorised encoder and a resynchronising parser.

Frame layout (11 bytes, little-endian; see ``docs/gyro-protocol.md``)::

    offset  size  field
    0       1     sync byte 0: 0xA5
    1       1     sync byte 1: 0x5A
    2       2     uint16 sample counter (wraps at 65536, i.e. every 8.192 s at 8 kHz)
    4       2     int16 rate x, raw LSB
    6       2     int16 rate y, raw LSB
    8       2     int16 rate z, raw LSB
    10      1     CRC-8 over bytes 2..9

Checksum: CRC-8 with polynomial 0x07 (x^8 + x^2 + x + 1), initial value 0x00, no bit
reflection, no final XOR ("CRC-8/SMBUS"; check value of ``b"123456789"`` is 0xF4), computed
over the 8 bytes after the sync bytes. It detects every single-byte error (every burst of at
most 8 bits), every error with an odd number of flipped bits, and every 2-bit error in the
9 checked bytes; it also catches swapped bytes, which a sum checksum misses, and two flips of
the same bit in different bytes, which an XOR checksum misses. The test suite verifies these
claims exhaustively.

Parsing is vectorised with numpy: candidate frame starts are found with one comparison over
the whole buffer, checksums are computed for all candidates at once (CRC-8 is linear over
GF(2), so the CRC of a frame is the XOR of nine per-position table lookups), and frames are
decoded with a single gather. Overlapping candidates (a chance CRC match across a truncated
frame, a sync pattern inside a payload) are rare; only they fall back to a small Python
resolution step. The parser holds back the last 21 bytes of each buffer so that every decision
sees both neighbours of a candidate: the frames it returns do not depend on how the stream is
cut into ``feed`` calls.
"""

from __future__ import annotations

import bisect
import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError

__all__ = [
    "CRC8_POLY",
    "FRAME_SIZE",
    "SYNC",
    "FrameParser",
    "ParsedFrames",
    "crc8",
    "encode_frames",
]

#: Frame length, bytes.
FRAME_SIZE = 11
#: The two sync bytes that start every frame.
SYNC = b"\xa5\x5a"
#: CRC-8 generator polynomial (x^8 + x^2 + x + 1, implicit x^8).
CRC8_POLY = 0x07

_SYNC0 = np.uint8(SYNC[0])
_SYNC1 = np.uint8(SYNC[1])
_SYNC_PAIR = np.frombuffer(SYNC, dtype=np.uint8)
_PAYLOAD = 8  # counter + 3 rates
_HOLD_BACK = 2 * FRAME_SIZE - 1  # bytes that must follow a start before it is decided


def _crc_table() -> NDArray[np.uint8]:
    table = np.zeros(256, dtype=np.uint8)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table[byte] = crc
    return table


_TABLE = _crc_table()


def _position_tables(length: int) -> NDArray[np.uint8]:
    """Per-position CRC contributions, shape (length, 256).

    With initial value 0 and no final XOR the CRC is linear: the CRC of a message is the XOR
    of the CRCs of the messages holding one of its bytes each. The byte at position k is
    followed by ``length - 1 - k`` zero bytes; each zero byte maps a CRC c to ``_TABLE[c]``.
    """
    tables = np.empty((length, 256), dtype=np.uint8)
    contribution = _TABLE.copy()  # byte in the last position
    for k in range(length - 1, -1, -1):
        tables[k] = contribution
        contribution = _TABLE[contribution]
    return tables


_POS_TABLES = _position_tables(_PAYLOAD)
_POS_INDEX = np.arange(_PAYLOAD)
_PAYLOAD_OFFSETS = np.arange(2, 2 + _PAYLOAD)
_FRAME_OFFSETS = np.arange(FRAME_SIZE)


def crc8(data: bytes | bytearray | memoryview) -> int:
    """CRC-8 of the frame format (poly 0x07, init 0, no reflection, no final XOR).

    Parameters
    ----------
    data : bytes-like
        Message bytes.

    Returns
    -------
    int
        The CRC, 0..255. ``crc8(b"123456789") == 0xF4``.
    """
    crc = 0
    for byte in bytes(data):
        crc = int(_TABLE[crc ^ byte])
    return crc


def _crc_rows(payload: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """CRC-8 of each row of an (m, 8) uint8 array, shape (m,)."""
    looked_up: NDArray[np.uint8] = _POS_TABLES[_POS_INDEX, payload]
    crc: NDArray[np.uint8] = np.bitwise_xor.reduce(looked_up, axis=1)
    return crc


def encode_frames(counter: ArrayLike, raw: ArrayLike) -> bytes:
    """Encode samples as consecutive 11-byte frames.

    Parameters
    ----------
    counter : array_like of int, shape (n,)
        Sample counters, 0..65535 (wrap them yourself: ``k % 65536``).
    raw : array_like of int, shape (n, 3)
        Raw rates x, y, z in sensor LSB, -32768..32767.

    Returns
    -------
    bytes
        ``11 * n`` bytes.

    Raises
    ------
    ConfigError
        If the shapes disagree or a value does not fit its field.
    """
    counter_arr = np.asarray(counter)
    raw_arr = np.asarray(raw)
    if counter_arr.ndim != 1:
        raise ConfigError(
            f"counter must have shape (n,), got {counter_arr.shape}; pass a 1-D array"
        )
    n = counter_arr.shape[0]
    if raw_arr.shape != (n, 3):
        raise ConfigError(
            f"raw must have shape (n, 3) = ({n}, 3) to match counter, got {raw_arr.shape}"
        )
    if n and not (
        np.issubdtype(counter_arr.dtype, np.integer)
        and int(counter_arr.min()) >= 0
        and int(counter_arr.max()) <= 0xFFFF
    ):
        raise ConfigError(
            "counter values must be integers in 0..65535 "
            f"(got dtype {counter_arr.dtype}, range "
            f"{counter_arr.min()!r}..{counter_arr.max()!r}); wrap with k % 65536"
        )
    if n and not (
        np.issubdtype(raw_arr.dtype, np.integer)
        and int(raw_arr.min()) >= -32768
        and int(raw_arr.max()) <= 32767
    ):
        raise ConfigError(
            "raw rates must be integers in -32768..32767 "
            f"(got dtype {raw_arr.dtype}, range {raw_arr.min()!r}..{raw_arr.max()!r}); "
            "clip to the int16 range"
        )
    words = np.empty((n, 4), dtype="<u2")
    words[:, 0] = counter_arr
    words[:, 1:] = raw_arr.astype("<i2").view("<u2")
    frames = np.empty((n, FRAME_SIZE), dtype=np.uint8)
    frames[:, 0] = _SYNC0
    frames[:, 1] = _SYNC1
    frames[:, 2:10] = words.view(np.uint8).reshape(n, _PAYLOAD)
    frames[:, 10] = _crc_rows(frames[:, 2:10])
    return frames.tobytes()


@dataclass(frozen=True, kw_only=True, eq=False)
class ParsedFrames:
    """Frames decoded by one :meth:`FrameParser.feed` call, plus running totals.

    Attributes
    ----------
    counter : ndarray of uint16, shape (n,)
        Sample counters as sent (wrapped).
    raw : ndarray of int16, shape (n, 3)
        Raw rates x, y, z, sensor LSB.
    end_offset : ndarray of int64, shape (n,)
        Stream offset (bytes since the parser started) just past each frame's last byte;
        maps a frame to the read that delivered it.
    frames_ok : int
        Valid frames decoded since the parser started.
    checksum_errors : int
        Sync patterns outside valid frames whose CRC failed, since the parser started.
    resync_bytes_skipped : int
        Bytes that belonged to no valid frame, since the parser started.
    """

    counter: NDArray[np.uint16]
    raw: NDArray[np.int16]
    end_offset: NDArray[np.int64]
    frames_ok: int
    checksum_errors: int
    resync_bytes_skipped: int

    def __len__(self) -> int:
        return int(self.counter.shape[0])


_EMPTY_U16 = np.zeros(0, dtype=np.uint16)
_EMPTY_I16 = np.zeros((0, 3), dtype=np.int16)
_EMPTY_I64 = np.zeros(0, dtype=np.int64)


class FrameParser:
    """Incremental, resynchronising parser of the 11-byte gyro frames.

    Feed it bytes in chunks of any size; it keeps partial frames (and the 21 bytes it needs
    to decide the last candidates) across calls. It never raises on bad input: garbage,
    truncated frames and corrupted checksums are skipped and counted.

    Examples
    --------
    >>> parser = FrameParser()
    >>> data = encode_frames([7, 8], [[1, 2, 3], [4, 5, 6]])
    >>> len(parser.feed(data[:15])), len(parser.feed(data[15:])), len(parser.flush())
    (0, 1, 1)
    >>> parser.flush().counter.tolist(), parser.frames_ok
    ([], 2)
    """

    def __init__(self) -> None:
        self._buf: NDArray[np.uint8] = np.zeros(0, dtype=np.uint8)
        self._base = 0  # stream offset of _buf[0]
        self._start = 0  # index in _buf where undecided bytes begin (bytes before: context)
        self._frames_ok = 0
        self._checksum_errors = 0
        self._skipped = 0

    @property
    def frames_ok(self) -> int:
        """Valid frames decoded so far."""
        return self._frames_ok

    @property
    def checksum_errors(self) -> int:
        """Sync patterns outside valid frames whose CRC failed."""
        return self._checksum_errors

    @property
    def resync_bytes_skipped(self) -> int:
        """Bytes that belonged to no valid frame."""
        return self._skipped

    @property
    def pending_bytes(self) -> int:
        """Bytes received but not decided yet (at most 21 plus an incomplete frame)."""
        return int(self._buf.shape[0]) - self._start

    def feed(self, data: bytes | bytearray | memoryview) -> ParsedFrames:
        """Parse the next chunk of the stream.

        Parameters
        ----------
        data : bytes-like
            The next bytes, any length (empty is fine).

        Returns
        -------
        ParsedFrames
            The frames decided in this call, in stream order. Frames whose last byte is among
            the final 21 bytes received may be returned by a later call (or :meth:`flush`).
        """
        return self._parse(data, final=False)

    def flush(self) -> ParsedFrames:
        """Decide every complete candidate now (call at the end of a stream)."""
        return self._parse(b"", final=True)

    def _parse(self, data: bytes | bytearray | memoryview, *, final: bool) -> ParsedFrames:
        new = np.frombuffer(data, dtype=np.uint8)
        buf = np.concatenate((self._buf, new)) if self._buf.shape[0] else new
        length = int(buf.shape[0])
        start = self._start
        last_complete = length - FRAME_SIZE  # last start with a complete frame
        limit = last_complete if final else length - 2 * FRAME_SIZE
        if limit < start:
            self._buf = buf if buf is not new else new.copy()
            return self._result(_EMPTY_U16, _EMPTY_I16, _EMPTY_I64)

        if not final:
            fast = self._aligned_run(buf, start, limit)
            if fast is not None:
                return fast

        # Candidates from 11 bytes before the undecided region (left neighbours) on.
        lo = max(start - FRAME_SIZE, 0)
        hits = (
            np.flatnonzero(
                (buf[lo : last_complete + 1] == _SYNC0)
                & (buf[lo + 1 : last_complete + 2] == _SYNC1)
            )
            + lo
        )
        block = buf[hits[:, None] + _PAYLOAD_OFFSETS]
        valid = _crc_rows(block) == buf[hits + FRAME_SIZE - 1]
        cand = hits[valid]
        undecided = cand[cand >= start]

        decided_end = limit + 1  # positions below are decided in this call
        if undecided.shape[0] == 0:
            selected = undecided
        else:
            overlap = np.diff(undecided) < FRAME_SIZE
            if not overlap.any():
                selected = undecided[undecided <= limit]
            else:
                selected, decided_end = _resolve_clusters(undecided, overlap, cand, limit)

        n_sel = int(selected.shape[0])
        new_start = start if n_sel == 0 else max(start, int(selected[-1]) + FRAME_SIZE)
        new_start = max(new_start, decided_end)

        # Statistics over the newly decided region [start, new_start).
        self._skipped += new_start - start - FRAME_SIZE * n_sel
        bad = hits[~valid]
        bad = bad[(bad >= start) & (bad < new_start)]
        if bad.shape[0]:
            if n_sel:
                j = np.searchsorted(selected, bad, side="right") - 1
                inside = (j >= 0) & (bad < selected[np.maximum(j, 0)] + FRAME_SIZE)
                self._checksum_errors += int(np.count_nonzero(~inside))
            else:
                self._checksum_errors += int(bad.shape[0])

        if n_sel:
            frames = buf[selected[:, None] + _PAYLOAD_OFFSETS]
            words = frames.view("<u2")  # (n, 4): counter, x, y, z
            counter = words[:, 0].astype(np.uint16)
            raw = words[:, 1:].view("<i2").astype(np.int16)
            end_offset = selected.astype(np.int64) + (self._base + FRAME_SIZE)
            self._frames_ok += n_sel
        else:
            counter, raw, end_offset = _EMPTY_U16, _EMPTY_I16, _EMPTY_I64

        keep_from = max(new_start - FRAME_SIZE, 0)
        self._buf = buf[keep_from:].copy()
        self._base += keep_from
        self._start = new_start - keep_from
        return self._result(counter, raw, end_offset)

    def _aligned_run(self, buf: NDArray[np.uint8], start: int, limit: int) -> ParsedFrames | None:
        """Fast path: the undecided region is a run of valid, back-to-back frames.

        That is what a healthy stream looks like. The run is checked one frame beyond the
        last decidable start (those bytes are always there when ``limit = length - 22``):
        a chance candidate overlapping the run then overlaps two valid frames of the chain,
        and the general search would also select exactly the chain. Returns None (use the
        general path) as soon as one frame is not valid.
        """
        m = (limit - start) // FRAME_SIZE + 1
        frames = buf[start : start + (m + 1) * FRAME_SIZE].reshape(m + 1, FRAME_SIZE)
        if not (frames[:, :2] == _SYNC_PAIR).all():
            return None
        payload = frames[:, 2:10]
        if not np.array_equal(_crc_rows(payload), frames[:, 10]):
            return None
        words = np.ascontiguousarray(payload[:m]).view("<u2")
        counter = words[:, 0].copy()
        raw = words[:, 1:].view("<i2").copy()
        end_offset = np.arange(
            self._base + start + FRAME_SIZE,
            self._base + start + (m + 1) * FRAME_SIZE,
            FRAME_SIZE,
            dtype=np.int64,
        )
        self._frames_ok += m
        new_start = start + m * FRAME_SIZE
        keep_from = new_start - FRAME_SIZE
        self._buf = buf[keep_from:].copy()
        self._base += keep_from
        self._start = new_start - keep_from
        return self._result(counter, raw, end_offset)

    def _result(
        self,
        counter: NDArray[np.uint16],
        raw: NDArray[np.int16],
        end_offset: NDArray[np.int64],
    ) -> ParsedFrames:
        return ParsedFrames(
            counter=counter,
            raw=raw,
            end_offset=end_offset,
            frames_ok=self._frames_ok,
            checksum_errors=self._checksum_errors,
            resync_bytes_skipped=self._skipped,
        )


def _resolve_clusters(
    undecided: NDArray[np.intp],
    overlap: NDArray[np.bool_],
    cand: NDArray[np.intp],
    limit: int,
) -> tuple[NDArray[np.intp], int]:
    """Pick non-overlapping frames where valid candidates overlap.

    A cluster is a maximal run of valid candidates that overlap their successor. Within a
    cluster the choice maximises, in order: the number of frames, the number of valid
    neighbours exactly one frame before or after (genuine frames form an 11-byte chain, a
    chance CRC match across a truncated frame or inside a payload does not), and lateness
    (after a truncation the later candidate is the new, intact data). A cluster that reaches
    beyond ``limit`` is left for the next call.

    Returns
    -------
    selected : ndarray of intp
        Chosen frame starts, sorted.
    decided_end : int
        First position not decided (the start of a deferred cluster, else ``limit + 1``).
    """
    valid_set = set(cand.tolist())
    starts = undecided.tolist()
    breaks = np.flatnonzero(~overlap).tolist()
    bounds = [0, *(b + 1 for b in breaks), len(starts)]
    chosen: list[int] = []
    decided_end = limit + 1
    for a, b in itertools.pairwise(bounds):
        members = starts[a:b]
        if members[-1] > limit:
            if members[0] <= limit:
                decided_end = members[0]
            break
        if len(members) == 1:
            chosen.append(members[0])
            continue
        weights = [
            1.0
            + 0.25 * ((s - FRAME_SIZE in valid_set) + (s + FRAME_SIZE in valid_set))
            + 1e-3 * i / len(members)
            for i, s in enumerate(members)
        ]
        chosen.extend(_max_weight_schedule(members, weights))
    return np.asarray(chosen, dtype=np.intp), decided_end


def _max_weight_schedule(starts: list[int], weights: list[float]) -> list[int]:
    """Weighted interval scheduling over equal-length intervals [s, s + 11), sorted by s."""
    best = [0.0] * (len(starts) + 1)  # best[i]: best total using the first i intervals
    take = [False] * len(starts)
    prev = [0] * len(starts)
    for i, s in enumerate(starts):
        # Intervals before i that end at or before s.
        p = bisect.bisect_right(starts, s - FRAME_SIZE, 0, i)
        prev[i] = p
        with_i = best[p] + weights[i]
        if with_i > best[i]:
            best[i + 1] = with_i
            take[i] = True
        else:
            best[i + 1] = best[i]
    out: list[int] = []
    i = len(starts)
    while i > 0:
        if take[i - 1]:
            out.append(starts[i - 1])
            i = prev[i - 1]
        else:
            i -= 1
    out.reverse()
    return out
