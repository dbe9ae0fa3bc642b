"""A disk that fills during a sweep: a clean exit 2, the journal intact, the resume command
printed, no crash at interpreter exit, and ``--resume`` on a disk with room recovers every
trial.

The disk is a small tmpfs mounted for the test (root only; skipped with the reason when the
OS refuses to mount). Each command runs in a subprocess, so its exit code and everything it
printed, including what the interpreter prints while it shuts down, are seen: before the
store wrote HDF5 through a guarded file, a disk that filled during a checkpoint ended in a
segmentation fault (exit 139) after the right message.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from timedexec.recording import RecordingReader

#: What must never appear on stderr: a traceback (also one h5py prints while freeing an
#: object and ignores), a fatal error of the interpreter.
BROKEN = ("Traceback", "Exception ignored", "Fatal Python error", "Segmentation fault")


class SmallDisk:
    """A tmpfs of a given size at ``path``; :meth:`resize` gives it more room."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def mount(self, size: str) -> None:
        self.path.mkdir(exist_ok=True)
        if os.geteuid() != 0:
            pytest.skip("mounting a tmpfs needs root")
        if shutil.which("mount") is None:
            pytest.skip("no mount command on this system")
        run = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(self.path)],
            capture_output=True,
            text=True,
            check=False,
        )
        if run.returncode != 0:
            pytest.skip(f"the OS refused to mount a tmpfs: {run.stderr.strip()}")

    def resize(self, size: str) -> None:
        subprocess.run(
            ["mount", "-o", f"remount,size={size}", str(self.path)],
            check=True,
            capture_output=True,
        )

    def unmount(self) -> None:
        if os.path.ismount(self.path):
            done = subprocess.run(["umount", str(self.path)], capture_output=True, check=False)
            if done.returncode != 0:  # still busy: detach now, freed when closed
                subprocess.run(["umount", "-l", str(self.path)], capture_output=True, check=False)


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[SmallDisk]:
    d = SmallDisk(tmp_path / "disk")
    try:
        yield d
    finally:
        d.unmount()


def timedexec(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the ``timedexec`` command in a fresh interpreter (exit and shutdown included)."""
    return subprocess.run(
        [sys.executable, "-m", "timedexec.cli", *args],
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )


def assert_clean_exit_2(run: subprocess.CompletedProcess[str], command: str) -> list[str]:
    """Exit 2, nothing on stdout, one line on stderr naming the full disk and ending with the
    command that resumes; returns that command, split into arguments."""
    assert run.returncode == 2, run.stderr
    assert run.stdout == ""
    assert not any(word in run.stderr for word in BROKEN), run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    assert lines[0].startswith(f"timedexec {command}: error: "), lines[0]
    assert "No space left on device" in lines[0]
    _, sep, resume = lines[0].partition("resume with: ")
    assert sep, lines[0]
    words = shlex.split(resume)
    assert words[:2] == ["timedexec", command]
    assert words[-1] == "--resume"
    return words[2:]


def fill_then_resume(disk: SmallDisk, n: int, *extra: str) -> Path:
    """`simulate` of ``n`` trials on a 30 MiB disk (the journal takes the simulator's
    512-trial blocks raw, 27.1 MB each: the first block fits, the rest of a 600-trial
    sweep, 4.7 MB, does not): exit 2 with the message and the resume command, the journal
    next to the recording; the printed command on a disk with room then ends with exit 0
    and no side file. Returns the recording."""
    disk.mount("30m")
    out = disk.path / "sweep.h5"
    args = ["--robot", "ur10", "--trials", str(n), "--seed", "5", "--out", str(out), "--quiet"]
    resume = assert_clean_exit_2(timedexec("simulate", *args, *extra), "simulate")
    assert Path(str(out) + ".journal").exists()  # P + journal hold what was recorded
    with RecordingReader(out) as r:
        assert r.n_trials == 512
    disk.resize("128m")
    second = timedexec("simulate", *resume)
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in disk.path.iterdir()) == ["sweep.h5"]  # no side files
    with RecordingReader(out) as r:
        np.testing.assert_array_equal(np.sort(r.read("trial")), np.arange(n))
    return out


def test_simulate_on_a_full_disk_exits_2_then_resumes(disk: SmallDisk) -> None:
    """`simulate` on a disk that fills: a clean exit 2 with the resume command (see
    fill_then_resume); that command records every trial."""
    fill_then_resume(disk, 600)


@pytest.mark.slow
def test_simulate_with_workers_on_a_full_disk_resumes_to_the_same_recording(
    disk: SmallDisk, tmp_path: Path
) -> None:
    """`simulate --jobs -1` (worker processes, blocks computed ahead and dropped quietly)
    on a disk that fills, resumed by the printed command: the recording equals an
    uninterrupted run with one worker (same seed, same output). Slow: three runs, one with
    worker start-up (about 20 s on the development VM)."""
    out = fill_then_resume(disk, 600, "--jobs", "-1")
    reference = tmp_path / "reference.h5"
    args = ["--robot", "ur10", "--trials", "600", "--seed", "5", "--out", str(reference)]
    assert timedexec("simulate", *args, "--quiet").returncode == 0
    with RecordingReader(out) as got, RecordingReader(reference) as want:
        order_got, order_want = np.argsort(got.read("trial")), np.argsort(want.read("trial"))
        for name in ("gyro_raw", "state_q_rad", "true_actuation_delay_s"):
            np.testing.assert_array_equal(
                got.read(name)[order_got], want.read(name)[order_want], err_msg=name
            )
        np.testing.assert_array_equal(got.static("still_gyro_raw"), want.static("still_gyro_raw"))


@pytest.mark.slow
def test_calibrate_on_a_full_disk_exits_2_then_resumes(disk: SmallDisk, tmp_path: Path) -> None:
    """`calibrate --robot-url sim://ur10` on a 1 MiB disk (the still recording and a few
    trials fit): exit 2 with the message and the resume command; on a disk with room the
    printed command records every planned trial exactly once, in a second session. Slow:
    two runs of the simulated robot (start-up, the move to the start configuration and the
    pre-flight each, about 5 s on the development VM).

    6 planned trials (it was 12): the disk takes the still recording and 4 trials
    (fixed-size records: the same 4 on every run), which leaves 2 for the resume instead of
    8. The plan, that of ``--trials 6 --seed 2``, is a ``--plan`` file (off the small disk):
    drawing it imports scipy.stats, ~1.5 s of each run's start-up."""
    from timedexec.recording import SweepPlan

    disk.mount("1m")
    out = disk.path / "cal.h5"
    n = 6
    plan = tmp_path / "plan.npz"
    np.savez(plan, **SweepPlan.generate("ur10", n, seed=2).to_arrays())
    args = ["--robot-url", "sim://ur10", "--plan", str(plan), "--seed", "2", "--out", str(out),
            "--no-tracking-phases"]
    resume = assert_clean_exit_2(timedexec("calibrate", *args, "--quiet"), "calibrate")
    assert Path(str(out) + ".journal").exists()
    with RecordingReader(out) as r:
        assert r.has_static("still_gyro_raw")
        first = r.n_trials
    assert 0 < first < n
    disk.resize("32m")
    second = timedexec("calibrate", *resume)
    assert second.returncode == 0, second.stderr
    assert f"recorded {n - first} trials ({n} planned)" in second.stdout
    with RecordingReader(out) as r:
        np.testing.assert_array_equal(np.sort(r.read("trial")), np.arange(n))
        assert set(r.read("session").tolist()) == {0, 1}


_WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from timedexec.errors import RecordingError
    from timedexec.recording import Field, RecordingWriter

    fields = [Field("gyro", (4800, 3), "int16"), Field("t_s", (), "float64", unit="s")]
    rng = np.random.default_rng(1)
    w = RecordingWriter(sys.argv[1], header={"test": 1}, fields=fields,
                        checkpoint_bytes=int(sys.argv[2]), trials_per_chunk=4)
    appended = 0
    try:
        for start in range(0, 100_000, 4):
            trials = np.arange(start, start + 4)
            gyro = rng.integers(-2000, 2000, (4, 4800, 3)).astype(np.int16)
            w.append({"trial": trials, "gyro": gyro, "t_s": trials * 1.0})
            appended += 4
    except RecordingError as exc:
        kind = "checkpoint" if "checkpoint" in str(exc) else "append"
        print(kind, appended, flush=True)
    try:
        w.close()  # folds the journal if there is room, else fails as cleanly
    except RecordingError:
        pass
    """
)


@pytest.mark.parametrize(
    ("checkpoint_bytes", "kinds"),
    [
        # never a checkpoint: the journal fills the disk
        (10**9, {"append"}),
        # a checkpoint every two batches: P, its shadow and the checkpoint's copy fill it
        (200_000, {"checkpoint"}),
    ],
)
def test_writer_on_a_full_disk_fails_cleanly_in_append_and_checkpoint(
    disk: SmallDisk, checkpoint_bytes: int, kinds: set[str]
) -> None:
    """RecordingWriter filling disks with different room left, the disk full in a journal
    append or while HDF5 writes a checkpoint: every time the error is a RecordingError,
    close() after it fails as cleanly (the disk is still full), the interpreter exits 0
    with nothing on stderr, and the recording (with its journal) holds every recorded
    trial."""
    disk.mount("4m")
    seen = set()
    # Filler sizes that leave the writer different room (seeded data: the same failure
    # points on every run).
    for k, filler_kb in enumerate((3000, 2500, 2000)):
        filler = disk.path / "filler"
        filler.write_bytes(b"\0" * filler_kb * 1024)
        path = disk.path / f"w{k}.h5"
        run = subprocess.run(
            [sys.executable, "-c", _WRITER, str(path), str(checkpoint_bytes)],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert run.returncode == 0, run.stderr
        assert run.stderr == "", run.stderr
        kind, appended = run.stdout.split()
        seen.add(kind)
        filler.unlink()
        # P + journal: every batch whose append returned; after a failed checkpoint also the
        # batch that append committed to the journal before checkpointing
        recorded = int(appended) + (4 if kind == "checkpoint" else 0)
        with RecordingReader(path) as r:
            np.testing.assert_array_equal(np.sort(r.read("trial")), np.arange(recorded))
        for side in disk.path.iterdir():
            side.unlink()
    assert seen == kinds
