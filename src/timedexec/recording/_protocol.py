"""The commit protocol's names and primitives: format id, side files, durable writes, faults.

A recording ``P`` only ever changes by ``os.replace`` of a complete, closed and fsync'ed
file; the side files next to it (``P + suffix``) carry everything in between (see
``docs/recording-format.md``, "Design: shadow copy + write-ahead journal"):

=================  ===================================================================
suffix             what it is
=================  ===================================================================
``.journal``       append-only write-ahead log of batches and statics not yet in ``P``
``.journal.new``   the next, empty journal being prepared (discarded after a crash)
``.shadow``        an older committed version of ``P``, recycled by the next checkpoint
``.partial``       the next version of ``P`` being prepared (discarded after a crash)
``.old``           a second name of ``P`` during the swap (resolved on resume)
``.lock``          single-writer lock (flock; a stale file after a crash is harmless)
=================  ===================================================================

Crash tests kill the writer at named steps of the protocol: the environment variable
``TIMEDEXEC_RECORDING_FAULT`` holds ``point`` or ``point@N`` and :func:`fault` sends the
process SIGKILL the N-th time it reaches that point (``create.partial_written``,
``append.torn``, ``fold.replaced``, ...; ``tests/test_recording.py`` lists them all).
"""

from __future__ import annotations

import contextlib
import os
import signal

__all__ = [
    "FAULT_ENV",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "JOURNAL",
    "JOURNAL_NEW",
    "LOCK",
    "OLD",
    "PARTIAL",
    "SHADOW",
    "fault",
    "fsync_dir",
    "fsync_path",
    "unlink",
    "write_all",
]

#: Root attribute ``format`` of every recording.
FORMAT_NAME = "timedexec-recording"
#: Version of the HDF5 layout and the journal encoding; readers refuse larger numbers.
FORMAT_VERSION = 1

# Side files next to the recording ``P`` (see the module docstring).
JOURNAL = ".journal"
JOURNAL_NEW = ".journal.new"
SHADOW = ".shadow"
PARTIAL = ".partial"
OLD = ".old"
LOCK = ".lock"

#: Environment variable naming the fault point of a crash test (unset in normal use).
FAULT_ENV = "TIMEDEXEC_RECORDING_FAULT"
_fault_counts: dict[str, int] = {}


def fault(point: str) -> None:
    """Kill this process with SIGKILL at a named point (crash tests only).

    The environment variable ``TIMEDEXEC_RECORDING_FAULT`` holds ``point`` or
    ``point@N`` (the N-th time the point is reached). Unset in normal use: one lookup.
    """
    want = os.environ.get(FAULT_ENV)
    if not want:
        return
    name, _, nth = want.partition("@")
    if name != point:
        return
    _fault_counts[point] = _fault_counts.get(point, 0) + 1
    if _fault_counts[point] >= int(nth or 1):
        os.kill(os.getpid(), signal.SIGKILL)


def fsync_path(path: str) -> None:
    """fsync the file at ``path``."""
    fd = os.open(path, os.O_RDWR)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(directory: str) -> None:
    """fsync a directory, so the renames in it are durable (a no-op on Windows)."""
    if os.name == "nt":  # directories cannot be opened for fsync on Windows
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def unlink(path: str) -> None:
    """Remove ``path`` if it exists."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


def write_all(fd: int, data: bytes | memoryview) -> None:
    """Write every byte of ``data`` to the file descriptor ``fd`` (``os.write`` may be short)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]
