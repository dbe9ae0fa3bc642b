"""The shared result-file helpers: atomic writes, output folders and the output-path policy."""

from __future__ import annotations

import os

import pytest

from timedexec._files import check_paths, make_dir, write_atomic
from timedexec.errors import ConfigError, RecordingError


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


def test_write_atomic_never_replaces_anything_but_a_regular_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A symlink (even to a regular file), a folder or a FIFO at the output is a ConfigError
    naming the path and what is there; the link, its target and the folder stay as they
    were, and no temporary file is left."""
    target = tmp_path / "target.txt"
    target.write_text("keep\n")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    folder = tmp_path / "folder"
    folder.mkdir()
    for path, kind in ((link, "symbolic link"), (fifo, "named pipe"), (folder, "directory")):
        with pytest.raises(ConfigError, match=rf"{path} is a {kind}"):
            write_atomic(path, "new\n")
    assert link.is_symlink()
    assert target.read_text() == "keep\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "fifo",
        "folder",
        "link.txt",
        "target.txt",
    ]


def test_check_paths_refuses_an_output_that_is_an_input(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The same file by name, through `..`, through a symlink or a hard link is refused
    naming both labels; two outputs on one file are refused; a missing folder is named."""
    rec = tmp_path / "rec.h5"
    rec.write_bytes(b"data")
    (tmp_path / "sub").mkdir()
    os.link(rec, tmp_path / "hard.h5")
    (tmp_path / "soft.h5").symlink_to(rec)
    for alias in (rec, tmp_path / "sub" / ".." / "rec.h5", tmp_path / "hard.h5"):
        with pytest.raises(ConfigError, match=r"--out .* is the same file as RECORDING"):
            check_paths(inputs={"RECORDING": alias}, outputs={"--out": rec})
    with pytest.raises(ConfigError, match="is the same file as RECORDING"):
        check_paths(inputs={"RECORDING": tmp_path / "soft.h5"}, outputs={"--out": rec})
    with pytest.raises(ConfigError, match=r"--truth .* is the same file as --out"):
        check_paths(outputs={"--out": tmp_path / "x.h5", "--truth": tmp_path / "x.h5"})
    with pytest.raises(ConfigError, match=r"the folder .*missing does not exist"):
        check_paths(outputs={"--out": tmp_path / "missing" / "x.csv"})
    assert rec.read_bytes() == b"data"


def test_check_paths_notes_replacements_and_allows_new_folders(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """An existing regular output gets a note saying what replaces it (only when the caller
    describes it); outputs inside an output folder the command creates need no existing
    parent; an output folder that is a file is refused; missing inputs are left to the
    reader."""
    old = tmp_path / "d.csv"
    old.write_text("old")
    notes = check_paths(
        inputs={"RECORDING": tmp_path / "absent.h5"},
        outputs={"--out": old, "--json": tmp_path / "new.json"},
        what={"--out": "the delay table", "--json": "the JSON result"},
    )
    assert notes == [f"--out {old} exists; it will be replaced by the delay table"]
    bundle = tmp_path / "new" / "bundle"
    assert (
        check_paths(outputs={"manifest": bundle / "manifest.json"}, folders={"--out": bundle}) == []
    )
    with pytest.raises(ConfigError, match="exists and is not a folder"):
        check_paths(folders={"--out": old})
