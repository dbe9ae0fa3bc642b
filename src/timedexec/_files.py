"""Result files a user can trust: one output-path policy and one atomic writer.

Every command and every writer of timedexec follows the same policy:

* **an output is never an input**: before any work, :func:`check_paths` refuses an output
  that is the same file as an input or as another output (compared by resolved path and,
  for files that exist, by device and inode, so hard links and symlinks are caught);
* **only regular files are replaced**: results are written to a temporary file that is then
  renamed over the output (:func:`write_atomic`); a rename replaces whatever sits at the
  path, so an existing symlink, directory, device node, FIFO or socket there is refused
  with a :class:`~timedexec.errors.ConfigError` naming the path (never followed, never
  replaced);
* **the folder must exist** (output folders a command creates itself are named as such);
* **an existing regular output is replaced**, and :func:`check_paths` says so (the notes a
  command prints on stderr).
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path

from timedexec.errors import ConfigError, RecordingError

__all__ = ["check_output_file", "check_paths", "make_dir", "write_atomic"]

PathArg = str | os.PathLike[str]

_KINDS = (
    (stat.S_ISLNK, "symbolic link"),
    (stat.S_ISDIR, "directory"),
    (stat.S_ISCHR, "character device"),
    (stat.S_ISBLK, "block device"),
    (stat.S_ISFIFO, "named pipe (FIFO)"),
    (stat.S_ISSOCK, "socket"),
)


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "special file"


def _lstat(path: Path) -> os.stat_result | None:
    try:
        return os.lstat(path)
    except FileNotFoundError:
        return None
    except OSError:  # e.g. a parent that is a file (ENOTDIR): nothing is there
        return None


def check_output_file(path: PathArg, label: str = "output") -> None:
    """Refuse to replace anything at ``path`` that is not a regular file.

    Raises
    ------
    ConfigError
        If ``path`` is a symbolic link (even to a regular file: the rename would replace
        the link, not its target), a directory, a device node, a FIFO or a socket; the
        message names ``label``, the path, what is there and the fix.
    """
    st = _lstat(Path(path))
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise ConfigError(
            f"{label} {os.fspath(path)} is a {_kind(st.st_mode)}, not a regular file; "
            "timedexec writes results by renaming a new file into place and never replaces "
            "anything but a regular file: give the path of a new or regular file"
        )


def _identity(path: Path) -> tuple[Path, tuple[int, int] | None]:
    """(resolved path, (device, inode) if the file exists)."""
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError):  # a symlink loop
        resolved = Path(os.path.abspath(path))
    try:
        st = os.stat(path)
    except OSError:
        return resolved, None
    return resolved, (st.st_dev, st.st_ino)


def _same(a: tuple[Path, tuple[int, int] | None], b: tuple[Path, tuple[int, int] | None]) -> bool:
    return a[0] == b[0] or (a[1] is not None and a[1] == b[1])


def check_paths(
    *,
    inputs: Mapping[str, PathArg | None] | None = None,
    outputs: Mapping[str, PathArg | None] | None = None,
    folders: Mapping[str, PathArg | None] | None = None,
    what: Mapping[str, str] | None = None,
) -> list[str]:
    """Apply the output-path policy to a command's files before it does any work.

    Parameters
    ----------
    inputs : mapping of label to path
        Files (or folders) the command reads, labelled as the user named them
        (``"RECORDING"``, ``"--plan"``); None values are skipped, missing files too (the
        reader reports them).
    outputs : mapping of label to path
        Files the command writes (``"--out"``, ``"--json"``); None values are skipped.
    folders : mapping of label to path
        Output folders the command creates if missing (``train --out DIR``); an output
        file inside one of them needs no existing parent.
    what : mapping of label to str
        What each output will hold (``"the delay table"``); an existing regular file at an
        output with a description gives a note saying it will be replaced by it.

    Returns
    -------
    list of str
        Notes for the user (one per existing output that will be replaced).

    Raises
    ------
    ConfigError
        An output that is the same file as an input or another output, that is not a
        regular file (symlink, directory, device, FIFO, socket), or whose folder does not
        exist; an output folder that exists and is not a folder. The message names the
        labels, the paths and the fix.
    """
    ins = {k: Path(v) for k, v in (inputs or {}).items() if v is not None}
    outs = {k: Path(v) for k, v in (outputs or {}).items() if v is not None}
    dirs = {k: Path(v) for k, v in (folders or {}).items() if v is not None}
    describe = what or {}
    for label, folder in dirs.items():
        if folder.exists() and not folder.is_dir():
            raise ConfigError(
                f"{label} {folder} exists and is not a folder; give a new or existing folder"
            )
    in_ids = {label: _identity(p) for label, p in ins.items()}
    created = [_identity(d)[0] for d in dirs.values()]
    seen: dict[str, tuple[Path, tuple[int, int] | None]] = {}
    notes: list[str] = []
    for label, path in outs.items():
        check_output_file(path, label)
        ident = _identity(path)
        for in_label, in_id in in_ids.items():
            if _same(ident, in_id):
                raise ConfigError(
                    f"{label} {path} is the same file as {in_label} {ins[in_label]}: writing "
                    f"{describe.get(label, 'the result')} there would destroy the input; "
                    f"choose another path for {label}"
                )
        for other, other_id in seen.items():
            if _same(ident, other_id):
                raise ConfigError(
                    f"{label} {path} is the same file as {other} {outs[other]}: one would "
                    f"overwrite the other; give {label} and {other} different paths"
                )
        seen[label] = ident
        parent = ident[0].parent
        if not parent.is_dir() and not any(parent == d or d in parent.parents for d in created):
            shown = path.parent if str(path.parent) else Path(".")
            raise ConfigError(f"{label} {path}: the folder {shown} does not exist; create it first")
        if ident[1] is not None and label in describe:
            notes.append(f"{label} {path} exists; it will be replaced by {describe[label]}")
    return notes


def make_dir(path: PathArg, what: str = "output folder") -> Path:
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


def write_atomic(path: PathArg, data: bytes | str) -> Path:
    """Write ``data`` (str: UTF-8) to ``path`` through a temporary file and a rename.

    Readers see the old file or the complete new one, never a partial write; the file
    gets the usual mode (``0o666`` less the umask). Only a regular file is ever replaced
    (checked before writing and again just before the rename).

    Raises
    ------
    ConfigError
        If something other than a regular file is at ``path`` (:func:`check_output_file`).
    RecordingError
        If the folder does not exist or the write fails (naming the path).
    """
    out = Path(path)
    check_output_file(out)
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
        check_output_file(out)  # nothing but a regular file appeared meanwhile
        os.replace(tmp, out)
        tmp = ""
    except OSError as exc:
        raise RecordingError(f"cannot write {out}: {exc.strerror or exc}") from exc
    finally:
        if tmp and os.path.exists(tmp):
            os.unlink(tmp)
    return out
