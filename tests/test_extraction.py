"""Delay extraction against the simulator's ground truth; flags; bad input."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from timedexec.cli import main
from timedexec.errors import ConfigError, RecordingError
from timedexec.extraction import REQUIRED_FIELDS, extract_recording
from timedexec.extraction._extract import _context, _extract_chunk
from timedexec.recording import RecordingReader
from timedexec.sim import simulate_sweep


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    out = {}
    for robot, seed in (("ur10", 4), ("kr5", 5)):
        path = tmp_path_factory.mktemp(robot) / f"{robot}.h5"
        simulate_sweep(robot, 640, path, seed=seed, progress=False)
        out[robot] = path
    return out


def rmse_ms(table, name):
    ok = np.array([not f for f in table["flag"]], dtype=bool)
    err = (table[name] - table[f"true_{name}"])[ok]
    return float(np.sqrt(np.mean(err**2)) * 1e3), ok.mean()


@pytest.mark.parametrize("robot", ["ur10", "kr5"])
def test_fit_method_meets_the_accuracy_targets(recordings, robot):
    """Default method against ground truth: actuation RMSE <= 0.2 ms, response <= 0.5 ms,
    under 2 % flagged (the issue's targets; measured 0.10-0.15 ms and 0.12 ms on 1,200
    trials, so 640 trials keep a margin for their sampling error of about 3 %)."""
    table = extract_recording(recordings[robot], progress=False).table
    act, kept = rmse_ms(table, "actuation_delay")
    resp, _ = rmse_ms(table, "response_delay")
    assert act <= 0.2
    assert resp <= 0.5
    assert kept > 0.98


def test_extrema_method_is_worse_than_fit(recordings):
    """The published extrema method, applied to the same trials, errs by milliseconds."""
    fit = extract_recording(recordings["kr5"], progress=False).table
    ext = extract_recording(recordings["kr5"], method="extrema", progress=False).table
    assert rmse_ms(ext, "actuation_delay")[0] > 10 * rmse_ms(fit, "actuation_delay")[0]
    assert np.isfinite(ext["actuation_delay"]).mean() > 0.98


def test_parallel_jobs_give_the_same_table(recordings):
    """joblib workers process chunks independently: same numbers as one process."""
    one = extract_recording(recordings["ur10"], progress=False, chunk_trials=200).table
    two = extract_recording(recordings["ur10"], progress=False, chunk_trials=200, jobs=2).table
    np.testing.assert_array_equal(one["actuation_delay"], two["actuation_delay"])
    np.testing.assert_array_equal(one["response_delay"], two["response_delay"])


def test_unmeasurable_trials_are_flagged_not_guessed(recordings):
    """Clipping, a gap in the gyro stream, no motion and a long silence of the state stream
    during the motion each give NaN delays and a named flag; the other trials are
    untouched, and a single lost package is not a reason to flag."""
    path = recordings["ur10"]
    with RecordingReader(path) as reader:
        ctx, *_ = _context(reader, clock_window_s=120.0, numtaps=161)
        rows = np.arange(8)
        chunk = {name: reader.read(name, rows=rows) for name in REQUIRED_FIELDS}
    clean = _extract_chunk(ctx, {k: v.copy() for k, v in chunk.items()}, rows, "fit")
    assert all(f == "" for f in clean["flag"])
    chunk["gyro_raw"][0, 1000:1010, 0] = 32767
    chunk["gyro_counter"][1, 2000:] += 3  # three samples lost
    chunk["gyro_raw"][2] = chunk["gyro_raw"][2, :10].mean(axis=0).astype(np.int16)  # still
    # A 40 ms silence in the stream while the joint starts (one lost package is harmless).
    send = chunk["cmd_send_time_s"][3]
    host = chunk["state_host_time_s"][3]
    chunk["state_host_time_s"][3, (host > send + 0.03) & (host < send + 0.07)] = np.nan
    chunk["state_host_time_s"][4, 20] = np.nan  # one lost package
    res = _extract_chunk(ctx, chunk, rows, "fit")
    assert list(res["flag"][:5]) == ["clipped", "gyro_gap", "no_motion", "package_gap", ""]
    assert np.all(np.isnan(res["actuation_delay"][:4]))
    np.testing.assert_array_equal(res["actuation_delay"][4:], clean["actuation_delay"][4:])
    # The lost package costs the response fit one sample: within 0.1 ms of the clean fit.
    assert abs(res["response_delay"][4] - clean["response_delay"][4]) < 1e-4


def test_cli_extract_writes_the_delay_table(recordings, tmp_path, capsys):
    """`timedexec extract` writes the CSV of the delay-table contract and reports the error
    against ground truth in --json."""
    out = tmp_path / "delays.csv"
    code = main(["extract", str(recordings["kr5"]), "--out", str(out), "--json", "--quiet"])
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert info["trials"] == 640
    assert info["actuation_delay_rmse_ms"] <= 0.2
    header = out.read_text().splitlines()[0].split(",")
    assert header[:15] == [
        "trial", "robot", "joint", "direction", "q1", "q2", "q3", "q4", "q5", "q6",
        "t_start", "actuation_delay", "response_delay", "true_actuation_delay",
        "true_response_delay",
    ]  # fmt: skip
    assert "flag" in header


def test_bad_recordings_exit_2_with_a_clear_message(tmp_path, capsys):
    """Truncated, foreign and newer-version recordings and an empty sweep: exit code 2 and
    a message naming the file and what to do."""
    out = str(tmp_path / "x.csv")
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    assert main(["extract", str(garbage), "--out", out]) == 2
    assert "garbage.h5" in capsys.readouterr().err
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = np.arange(3)
    assert main(["extract", str(foreign), "--out", out]) == 2
    assert "not a timedexec recording" in capsys.readouterr().err
    assert main(["extract", str(tmp_path / "missing.h5"), "--out", out]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_newer_format_and_empty_sweep_are_refused(recordings, tmp_path):
    """A recording from a newer format version and one with no trials raise errors that
    say what to do."""
    import shutil

    newer = tmp_path / "newer.h5"
    shutil.copy(recordings["ur10"], newer)
    with h5py.File(newer, "r+") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(RecordingError, match="newer"):
        extract_recording(newer, progress=False)
    with pytest.raises(ConfigError, match="unknown extraction method"):
        extract_recording(recordings["ur10"], method="peak", progress=False)


def test_empty_sweep_is_refused(tmp_path):
    """A recording whose sweep holds no trial yet cannot be extracted: ConfigError."""
    from timedexec.recording import RecordingWriter, trial_fields
    from timedexec.sim import default_settings

    settings = default_settings("ur10")
    path = tmp_path / "empty.h5"
    header = {
        "robot": settings.spec.to_dict(),
        "profile": settings.profile.to_dict(),
        "gyro": settings.gyro.header().to_dict(),
        "controller_period_s": settings.controller_period_s,
    }
    with RecordingWriter(path, header=header, fields=trial_fields(settings.protocol, truth=False)) as w:
        w.write_static("still_gyro_raw", np.zeros((800, 3), np.int16))
    with pytest.raises(ConfigError, match="no trials"):
        extract_recording(path, progress=False)
