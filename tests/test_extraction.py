"""Delay extraction against the simulator's ground truth; flags; bad input."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from timedexec.cli import main
from timedexec.errors import ConfigError, RecordingError
from timedexec.extraction import extract_recording, sampling_offsets
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


def test_unmeasurable_trials_are_flagged_not_guessed(recordings, tmp_path):
    """Clipping, a gap in the gyro stream over the motion, no motion and a long silence of
    the state stream during the motion each give NaN delays and a named flag; the other
    trials are untouched, and a single lost package is not a reason to flag (a few lost
    gyro samples are not either: tests/test_extraction_robustness.py)."""
    import shutil

    path = tmp_path / "damaged.h5"
    shutil.copy(recordings["ur10"], path)
    # Rows 1-5: clean trials that the sweep-wide steps do not depend on (the filter design
    # samples 32 rows spread over the sweep, row 0 among them; the clock fits use only the
    # first counter and the block arrival times, which stay as recorded).
    rows = np.arange(1, 6)
    with h5py.File(path, "r+") as f:  # plain h5py: the documented layout, /trials/<field>
        trials = f["trials"]
        raw = trials["gyro_raw"][1:4]
        raw[0, 1000:1010, 0] = 32767  # clipped
        raw[2] = raw[2, :10].mean(axis=0).astype(np.int16)  # still
        trials["gyro_raw"][1:4] = raw
        counter = trials["gyro_counter"][2]
        counter[1000:] += 800  # 0.1 s lost while the joint moves
        trials["gyro_counter"][2] = counter
        # A 40 ms silence in the stream while the joint starts (one lost package is harmless).
        host = trials["state_host_time_s"][4:6]
        send = trials["cmd_send_time_s"][4]
        host[0, (host[0] > send + 0.03) & (host[0] < send + 0.07)] = np.nan
        host[1, 20] = np.nan  # one lost package
        trials["state_host_time_s"][4:6] = host
    clean = extract_recording(recordings["ur10"], progress=False)
    damaged = extract_recording(path, progress=False)
    # The sweep-wide facts are the same: the filter exactly; the clock fit may lose the
    # damaged trial's arrivals (its counter no longer matches its arrival times, so it is
    # left out as an outlier), which moves the rate by far less than 1 ppm.
    assert damaged.cutoff_hz == clean.cutoff_hz
    assert damaged.clock_rate_hz == pytest.approx(clean.clock_rate_hz, rel=1e-6)
    with RecordingReader(path) as reader:
        trial = reader.read("trial", rows=rows)
    pos = np.searchsorted(clean.table["trial"], trial)  # the tables are sorted by trial
    np.testing.assert_array_equal(clean.table["trial"][pos], trial)
    np.testing.assert_array_equal(damaged.table["trial"], clean.table["trial"])
    assert all(f == "" for f in clean.table["flag"][pos])
    res = {k: damaged.table[k][pos] for k in ("flag", "actuation_delay", "response_delay")}
    assert list(res["flag"]) == ["clipped", "gyro_gap", "no_motion", "package_gap", ""]
    assert np.all(np.isnan(res["actuation_delay"][:4]))
    # 1 µs: the clock fit without the damaged trial moves sample times by a few 0.1 µs
    assert res["actuation_delay"][4] == pytest.approx(clean.table["actuation_delay"][pos[4]], abs=1e-6)
    # The lost package costs the response fit one sample: within 0.1 ms of the clean fit.
    assert abs(res["response_delay"][4] - clean.table["response_delay"][pos[4]]) < 1e-4
    untouched = np.ones(len(clean.table), dtype=bool)
    untouched[pos] = False
    np.testing.assert_array_equal(damaged.table["flag"][untouched], clean.table["flag"][untouched])
    np.testing.assert_allclose(  # 1 µs, as above
        damaged.table["actuation_delay"][untouched],
        clean.table["actuation_delay"][untouched],
        rtol=0,
        atol=1e-6,
    )
    # The response fit iterates a chunk until every trial's step is below 1 ns, so the
    # damaged trials' extra iterations may move a converged one by less than that.
    np.testing.assert_allclose(
        damaged.table["response_delay"][untouched],
        clean.table["response_delay"][untouched],
        rtol=0,
        atol=1e-6,
    )


def _hold_up_packages(src, dst, rows, *, stamps_scale=1.0):
    """Copy ``src`` with the state packages of ``rows`` that arrived 60-76 ms after the
    command held up and delivered in a burst just before the next one (a controller or
    host thread that stalled during the motion; the gap stays under the 25 ms that flags
    ``package_gap``); the controller stamps multiplied by ``stamps_scale`` (NaN: none).
    Returns each row's mean package lateness added, s."""
    import shutil

    shutil.copy(src, dst)
    sl = slice(int(rows[0]), int(rows[-1]) + 1)
    with h5py.File(dst, "r+") as f:
        trials = f["trials"]
        host, send = trials["state_host_time_s"][sl], trials["cmd_send_time_s"][sl]
        added = np.zeros_like(host)
        for i in range(len(host)):
            held = np.flatnonzero((host[i] > send[i] + 0.06) & (host[i] < send[i] + 0.076))
            burst = host[i, held[-1] + 1] - 20e-6 * (len(held) - np.arange(len(held)))
            added[i, held] = burst - host[i, held]
            host[i, held] = burst
        trials["state_host_time_s"][sl] = host
        stamps = trials["state_controller_time_s"]
        stamps[...] = stamps[...] * stamps_scale
    return added.mean(axis=1)


def test_packages_held_up_in_the_motion_are_dated_by_the_controller_clock(recordings, tmp_path):
    """A stretch of state packages held up during the motion and delivered in a burst:
    dated by their arrival, the response fit read the trials' age up to 3.4 ms off with
    standard errors of 0.3 ms (16 UR10 trials: a confident wrong number); dated by the
    controller's stamps (every driver records them) the mean package age is met as on the
    clean recording. Stamps that do not advance by a controller period per package (here
    in ms) are not trusted: the arrival times are used, as without stamps, and no sampling
    instant is read from them (``sampling_offsets``)."""
    rows = np.arange(1, 17)
    results, offsets = {}, {}
    for name, scale in (("stamped", 1.0), ("unstamped", np.nan), ("ms", 1e3)):
        path = tmp_path / f"{name}.h5"
        added = _hold_up_packages(recordings["ur10"], path, rows, stamps_scale=scale)
        table = extract_recording(path, progress=False).table
        with RecordingReader(path) as reader:
            pos = np.searchsorted(table["trial"], reader.read("trial", rows=rows))
        assert all(f == "" for f in table["flag"][pos])
        truth = table["true_response_delay"][pos] + added
        results[name] = (table["response_delay"][pos] - truth, table["response_delay_se"][pos])
        with RecordingReader(path) as reader:
            host = reader.read("state_host_time_s", rows=rows)
            stamp = reader.read("state_controller_time_s", rows=rows)
        # where the gyro puts the stamps' instants (calibrate's echo depth)
        offsets[name] = sampling_offsets(host, stamp, table["response_delay"][pos], 0.008)
    err, _ = results["stamped"]
    # 0.1 ms: 5x the clean fit's standard error here (0.02 ms; measured |error| <= 0.045 ms).
    assert np.max(np.abs(err)) < 1e-4
    # stamps the extraction trusts give where their instants lie; those it does not (ms)
    # give none, so calibrate reads no echo depth from them
    assert np.isfinite(offsets["stamped"]).all()
    assert np.isnan(offsets["ms"]).all()
    bad, bad_se = results["unstamped"]
    assert np.max(np.abs(bad)) > 1e-3  # what dating by arrival gave (up to 3.4 ms)
    assert np.max(np.abs(bad) / bad_se) > 5  # ... with a standard error that hid it
    np.testing.assert_array_equal(results["ms"][0], bad)


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
    from timedexec.recording import RecordingWriter, SweepProtocol, trial_fields

    protocol = SweepProtocol.for_robot("ur10")
    path = tmp_path / "empty.h5"
    header = {
        "robot": protocol.spec.to_dict(),
        "profile": protocol.profile.to_dict(),
        "gyro": protocol.gyro.to_dict(),
        "controller_period_s": protocol.controller_period_s,
    }
    with RecordingWriter(path, header=header, fields=trial_fields(protocol, truth=False)) as w:
        w.write_static("still_gyro_raw", np.zeros((800, 3), np.int16))
    with pytest.raises(ConfigError, match="no trials"):
        extract_recording(path, progress=False)


@pytest.mark.parametrize("jobs", [1, 2])
def test_damaged_chunk_flags_its_trials_and_extracts_the_rest(recordings, tmp_path, jobs):
    """Bytes overwritten in one gyro chunk (64 trials) of a 640-trial recording: those
    trials are in the table flagged ``damaged`` with NaN delays, the other 576 are extracted
    (in worker processes too) and are as accurate as the undamaged file's extraction (they
    lose the damaged trials as neighbours of the zero-rate pooling and the clock fit, which
    moves a few of them within the estimator's own error); before, the whole extraction
    stopped at the damaged chunk."""
    path = tmp_path / "damaged.h5"
    path.write_bytes(recordings["ur10"].read_bytes())
    with h5py.File(path, "r") as f:
        ds = f["trials/gyro_raw"]
        tpc = ds.chunks[0]
        info = ds.id.get_chunk_info(3)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(np.random.default_rng(5).bytes(256))
    with RecordingReader(path) as r:
        rows = np.flatnonzero(r.damaged_rows())
        lost = np.sort(r.read("trial", rows))
    assert rows.tolist() == list(range(3 * tpc, 4 * tpc))
    whole = extract_recording(recordings["ur10"], progress=False).table
    res = extract_recording(path, progress=False, jobs=jobs)
    t = res.table
    assert res.damaged_rows == tpc
    assert len(t) == len(whole)
    flag = np.asarray(t["flag"])
    assert np.array_equal(np.flatnonzero(flag == "damaged"), np.searchsorted(t["trial"], lost))
    assert np.all(np.isnan(t["actuation_delay"][flag == "damaged"]))
    ok = flag != "damaged"
    for name in ("actuation_delay", "response_delay"):
        a, b, truth = t[name][ok], whole[name][ok], t[f"true_{name}"][ok]
        both = np.isfinite(a) & np.isfinite(b)
        d = np.abs(a[both] - b[both])
        e_a, e_b = (np.sqrt(np.mean((x[both] - truth[both]) ** 2)) for x in (a, b))
        assert np.array_equal(np.isfinite(a), np.isfinite(b)), name
        # as accurate as from the whole file (measured 0.1011 vs 0.1018 ms actuation,
        # 0.0248 vs 0.0248 response): 0.005 ms is 5 % of the actuation RMSE
        assert abs(e_a - e_b) < 5e-6, name
        # trial by trial: most barely move (median 0.9 us actuation), some move within the
        # estimator's own error (max 0.12 ms actuation, 0.1 us response): bound 0.25 ms
        assert np.median(d) < 5e-6, name
        assert np.max(d) < 2.5e-4, name
