"""The shared result-file helpers: atomic writes and output folders."""

from __future__ import annotations

import os

import pytest

from timedexec._files import make_dir, write_atomic
from timedexec.errors import RecordingError


def test_write_atomic_replaces_whole_files_with_the_usual_mode(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Text and bytes land whole, an existing file is replaced, no temporary file stays,
    and the mode is 0o666 less the umask (not mkstemp's 0600)."""
    target = tmp_path / "r.json"
    write_atomic(target, "first\n")
    write_atomic(target, b"second\n")
    assert target.read_bytes() == b"second\n"
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_write_atomic_and_make_dir_name_the_path_on_failure(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A missing folder is a RecordingError naming it (nothing created); a folder that
    cannot be made (a file is in the way) names the path."""
    with pytest.raises(RecordingError, match="does not exist"):
        write_atomic(tmp_path / "missing" / "r.csv", "x")
    assert not (tmp_path / "missing").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(RecordingError, match=r"cannot create the report folder .*file"):
        make_dir(tmp_path / "file" / "sub", "report folder")
    assert make_dir(tmp_path / "a" / "b").is_dir()
