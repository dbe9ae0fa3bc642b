"""Result files a user can trust: one output-path policy and one atomic writer.

Every command and every writer of timedexec follows the same policy:

* **an output is never an input**: before any work, :func:`check_paths` refuses an output
  that is the same file as an input or as another output (compared by resolved path and,
  for files that exist, by device and inode, so hard links and symlinks are caught); an
  input that is a folder (a model bundle) counts every file inside it as an input;
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
from collections.abc import Collection, Mapping
from pathlib import Path

from timedexec.errors import ConfigError, RecordingError

__all__ = [
    "check_folder_takes_files",
    "check_input_kind",
    "check_output_file",
    "check_path_length",
    "check_paths",
    "make_dir",
    "write_atomic",
]

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


#: Bytes a file name needs beyond the name given: the temporary file of an atomic write
#: (``.NAME.XXXXXXXX.tmp``) and a recording's side files (``NAME.journal.new``).
_NAME_MARGIN = 16


#: Bytes kept free in an output folder's path for the files written inside it.
_FOLDER_MARGIN = 64


def _limit(path: Path, name: str, fallback: int) -> int:
    """``os.pathconf`` of the nearest existing folder of ``path`` (``fallback`` if none)."""
    for folder in (path, *path.parents):
        if folder.is_dir():
            try:
                return int(os.pathconf(folder, name))
            except (OSError, ValueError):
                return fallback
    return fallback


def check_path_length(path: PathArg, label: str = "output", *, inside: int = 0) -> None:
    """Refuse an output path the file system cannot hold: a name longer than the folder's
    ``NAME_MAX`` (less what a temporary or side file adds to it) or a whole path longer
    than ``PATH_MAX``, before any work rather than when the result is written.

    Raises
    ------
    ConfigError
        Naming ``label``, the part that is too long, its length and the limit.
    """
    absolute = Path(os.path.abspath(path))
    name_max = _limit(absolute.parent, "PC_NAME_MAX", 255)
    path_max = _limit(absolute.parent, "PC_PATH_MAX", 4096)
    for part in absolute.parts[1:]:
        size = len(os.fsencode(part))
        room = name_max - (_NAME_MARGIN if part == absolute.name else 0)
        if size > room:
            raise ConfigError(
                f"{label}: the name {part[:40]}... is {size} bytes long; this file system "
                f"takes names of up to {name_max} bytes ({room} for a result, which is "
                "written through a temporary file beside it): give a shorter name"
            )
    reserve = _NAME_MARGIN + inside
    size = len(os.fsencode(str(absolute)))
    if size + reserve >= path_max:
        raise ConfigError(
            f"{label}: the path is {size} bytes long (absolute); this system "
            f"takes paths of up to {path_max - 1 - reserve} bytes here: choose "
            "a shorter path (or work from a folder nearer the root)"
        )


def check_input_kind(path: PathArg, label: str = "input", *, device: bool = False) -> None:
    """Refuse an input that is neither a regular file nor a folder (a FIFO, a device, a
    socket): reading one blocks forever or never ends. Symlinks are followed; a missing
    path passes (the reader reports it). ``device``: a character device is what this input
    must be (a serial port), and is accepted.

    Raises
    ------
    ConfigError
        Naming ``label``, the path and what is there.
    """
    try:
        st = os.stat(path)
    except OSError:
        return
    if device and stat.S_ISCHR(st.st_mode):
        return
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        raise ConfigError(
            f"{label} {os.fspath(path)} is a {_kind(st.st_mode)}, not a regular file; "
            "timedexec reads its inputs from files: give the path of a file"
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


# Files looked at inside one input folder: a model bundle holds two; a folder with more
# than this many is not what any command reads, and its outputs are still checked against
# the folder itself and the files seen.
_MAX_FOLDER_FILES = 10_000


def _folder_files(label: str, folder: Path) -> dict[str, tuple[Path, tuple[int, int] | None]]:
    """The identities of the files inside an input folder, labelled ``LABEL/NAME``."""
    out: dict[str, tuple[Path, tuple[int, int] | None]] = {}
    try:
        for root, _dirs, files in os.walk(folder):
            for name in files:
                path = Path(root) / name
                out[f"{label} file {path}"] = _identity(path)
                if len(out) >= _MAX_FOLDER_FILES:
                    return out
    except OSError:  # unreadable: the reader reports it
        pass
    return out


def check_paths(
    *,
    inputs: Mapping[str, PathArg | None] | None = None,
    outputs: Mapping[str, PathArg | None] | None = None,
    folders: Mapping[str, PathArg | None] | None = None,
    what: Mapping[str, str] | None = None,
    devices: Collection[str] = (),
) -> list[str]:
    """Apply the output-path policy to a command's files before it does any work.

    Parameters
    ----------
    inputs : mapping of label to path
        Files (or folders) the command reads, labelled as the user named them
        (``"RECORDING"``, ``"--plan"``); None values are skipped, missing files too (the
        reader reports them). Every file inside an input folder (``--model DIR``) is an
        input too.
    outputs : mapping of label to path
        Files the command writes (``"--out"``, ``"--json"``); None values are skipped.
    folders : mapping of label to path
        Output folders the command creates if missing (``train --out DIR``); an output
        file inside one of them needs no existing parent.
    what : mapping of label to str
        What each output will hold (``"the delay table"``); an existing regular file at an
        output with a description gives a note saying it will be replaced by it.
    devices : collection of str
        Labels of inputs that are serial ports (character devices are accepted there).

    Returns
    -------
    list of str
        Notes for the user (one per existing output that will be replaced).

    Raises
    ------
    ConfigError
        An input that is a FIFO, device or socket (:func:`check_input_kind`); an output
        that is the same file as an input or another output, that is not a regular file
        (symlink, directory, device, FIFO, socket), or whose folder does not exist or takes
        no new file; an output folder that exists and is not a folder. The message names
        the labels, the paths and the fix.
    """
    ins = {k: Path(v) for k, v in (inputs or {}).items() if v is not None}
    outs = {k: Path(v) for k, v in (outputs or {}).items() if v is not None}
    dirs = {k: Path(v) for k, v in (folders or {}).items() if v is not None}
    describe = what or {}
    for label, folder in dirs.items():
        check_path_length(folder, label, inside=_FOLDER_MARGIN)
        if folder.exists() and not folder.is_dir():
            raise ConfigError(
                f"{label} {folder} exists and is not a folder; give a new or existing folder"
            )
    for label, p in ins.items():
        check_input_kind(p, label, device=label in devices)
    in_ids = {label: _identity(p) for label, p in ins.items()}
    shown_in = {label: str(p) for label, p in ins.items()}
    for label, p in ins.items():
        if p.is_dir():
            inside = _folder_files(label, p)
            in_ids.update(inside)
            shown_in.update(dict.fromkeys(inside, ""))
    created = [_identity(d)[0] for d in dirs.values()]
    seen: dict[str, tuple[Path, tuple[int, int] | None]] = {}
    notes: list[str] = []
    for label, path in outs.items():
        check_path_length(path, label)
        check_output_file(path, label)
        ident = _identity(path)
        for in_label, in_id in in_ids.items():
            if _same(ident, in_id):
                named = f"{in_label} {shown_in[in_label]}".rstrip()
                raise ConfigError(
                    f"{label} {path} is the same file as {named}: writing "
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
        shown = path.parent if str(path.parent) else Path(".")
        if not parent.is_dir():
            if not any(parent == d or d in parent.parents for d in created):
                raise ConfigError(
                    f"{label} {path}: the folder {shown} does not exist; create it first"
                )
        else:
            check_folder_takes_files(shown, label, path)
        if ident[1] is not None and label in describe:
            notes.append(f"{label} {path} exists; it will be replaced by {describe[label]}")
    return notes


def check_folder_takes_files(folder: PathArg, label: str, path: PathArg) -> None:
    """Refuse a folder in which no new file can be made now (read-only mount, no
    permission, a pseudo-file system), before any work rather than after it.

    The one reliable test is to make a file: root ignores mode bits, a read-only mount
    does not. The probe file is removed at once.

    Raises
    ------
    ConfigError
        Naming ``label``, ``path``, the folder and the reason.
    """
    try:
        fd, probe = tempfile.mkstemp(prefix=".timedexec-probe.", dir=folder)
    except OSError as exc:
        raise ConfigError(
            f"{label} {os.fspath(path)}: cannot create files in the folder {os.fspath(folder)} "
            f"({exc.strerror or exc}); choose a writable folder"
        ) from None
    os.close(fd)
    os.unlink(probe)


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
