"""Writing result files so that nothing half-written is ever left under a result's name."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from timedexec.errors import RecordingError

__all__ = ["make_dir", "write_atomic"]


def make_dir(path: str | os.PathLike[str], what: str = "output folder") -> Path:
    """Create ``path`` (and its parents) if missing; return it.

    Raises
    ------
    RecordingError
        Naming ``what``, the path and the OS's reason.
    """
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecordingError(f"cannot create the {what} {out}: {exc.strerror or exc}") from exc
    return out


def write_atomic(path: str | os.PathLike[str], data: bytes | str) -> Path:
    """Write ``data`` (str: UTF-8) to ``path`` through a temporary file and a rename.

    Readers see the old file or the complete new one, never a partial write; the file
    gets the usual mode (``0o666`` less the umask).

    Raises
    ------
    RecordingError
        If the folder does not exist or the write fails (naming the path).
    """
    out = Path(path)
    directory = out.parent if str(out.parent) else Path(".")
    if not directory.is_dir():
        raise RecordingError(f"cannot write {out}: directory {directory} does not exist")
    raw = data.encode("utf-8") if isinstance(data, str) else data
    tmp = ""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=directory)
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600
        os.replace(tmp, out)
    except OSError as exc:
        if tmp and os.path.exists(tmp):
            os.unlink(tmp)
        raise RecordingError(f"cannot write {out}: {exc.strerror or exc}") from exc
    return out
