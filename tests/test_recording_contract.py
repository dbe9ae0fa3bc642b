"""The recording format as a contract: a file written with plain h5py from
docs/recording-format.md alone is extracted; every departure is named by check_recording."""

from __future__ import annotations

import json
import math
import uuid
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from numpy.typing import NDArray

from timedexec.errors import ConfigError, RecordingError
from timedexec.extraction import check_recording, extract_recording
from timedexec.recording import GyroHeader

FS = 8000.0
B = 8
PERIOD = 0.008
FloatArray = NDArray[np.float64]


def _write_minimal(
    path: Path, *, n: int = 24, gyro_unit: str = "LSB", drop_key: str | None = None, seed: int = 0
) -> Path:
    """A minimal recording, following the document's tables: root attributes, the required
    per-trial datasets (with their unit attributes) and statics. Physics: the joint speed
    follows the commanded ramp 20 ms late (first order, 5 ms); the state is 3 ms old."""
    rng = np.random.default_rng(seed)
    lsb = 65.536
    g = 5600
    p = 81
    t_pre = 0.05
    k = np.arange(g)
    fields, data = [], {}

    def add(name: str, arr: Any, unit: str, doc: str = "") -> None:
        arr = np.asarray(arr)
        fields.append({"name": name, "shape": list(arr.shape[1:]), "dtype": arr.dtype.name,
                       "unit": unit, "doc": doc})  # fmt: skip
        data[name] = arr

    t0 = 10.0 + 1.2 * np.arange(n)
    t_send = np.full(n, 2e-4)
    joint = np.full(n, 2)
    direction = np.where(np.arange(n) % 2 == 0, 1, -1)
    speed, accel, hold, pause = 0.4, 8.0, 0.05, 0.15
    onset_lag = 0.02

    def v_phys(t: FloatArray) -> FloatArray:  # out pulse only, first-order lag of a delayed trapezoid
        x = t - onset_lag
        ramp = speed / accel
        pulse = 2 * ramp + hold
        up = np.clip(x, 0, ramp) * accel
        down = np.clip(pulse - x, 0, ramp) * accel
        v = np.where((x > 0) & (x < pulse), np.minimum(up, down), 0.0)
        out = np.zeros_like(v)
        a = 1 - math.exp(-1.25e-4 / 0.005)
        for i in range(1, v.shape[-1]):
            out[..., i] = out[..., i - 1] + a * (v[..., i] - out[..., i - 1])
        return out

    t_g = -t_pre + k / FS  # sensor on time (exact 8 kHz, latency 0.5 ms + no filter)
    v = v_phys(np.broadcast_to(t_g, (n, g)).copy()) * direction[:, None]
    rate_dps = np.degrees(v)[:, :, None] * np.array([0.0, 0.0, 1.0])
    rate_dps = rate_dps + 0.5 + rng.normal(0, 0.3, (n, g, 3))
    counter0 = (t0 - t_pre) * FS
    counters = ((counter0[:, None] + k) % 65536).astype(np.uint16)
    blocks = (t_g[B - 1 :: B] + 5e-4)[None, :] + rng.gamma(2, 1e-4, (n, g // B))
    blocks = np.maximum.accumulate(blocks, axis=1)
    host = 3e-3 + np.arange(p) * PERIOD + rng.normal(0, 2e-5, (n, p))
    host[:, 0] = 0.0
    samp = host - 3e-3
    angle = np.cumsum(v, axis=1) / FS
    q_j = np.stack([np.interp(samp[i], t_g, angle[i]) for i in range(n)])
    q = np.zeros((n, p, 6))
    q[:, :, 1] = 0.3 + q_j
    qd = np.zeros((n, p, 6))
    qd[:, :, 1] = np.stack([np.interp(samp[i], t_g, v[i]) for i in range(n)])
    raw = np.rint(rate_dps * lsb).astype(np.int16) if gyro_unit == "LSB" else rate_dps.astype(
        np.float32
    )
    add("trial", np.arange(n, dtype=np.int64), "")
    add("t0_s", t0, "s")
    add("cmd_send_time_s", t_send, "s")
    add("cmd_qd_rad_s", np.where(np.arange(6) == 1, direction[:, None] * speed, 0.0), "rad/s")
    add("state_host_time_s", host, "s")
    add("state_q_rad", q.astype(np.float32), "rad")
    add("state_qd_rad_s", qd.astype(np.float32), "rad/s")
    add("gyro_raw", raw, gyro_unit)
    add("gyro_counter", counters, "")
    add("gyro_block_host_time_s", blocks.astype(np.float32) * 1.0, "s")
    add("true_actuation_delay_s", np.full(n, np.nan), "s")
    gyro = {"full_scale_dps": 500, "nominal_rate_hz": FS, "block_samples": B,
            "lsb_per_dps": lsb, "group_delay_s": 0.0, "transport_latency_s": 5e-4}  # fmt: skip
    if drop_key:
        gyro.pop(drop_key)
    header = {"robot": {"name": "ur10", "vendor": "universal_robots"},
              "controller_period_s": PERIOD,
              "profile": {"speed_rad_s": speed, "acceleration_rad_s2": accel, "hold_s": hold,
                          "pause_s": pause},
              "gyro": gyro}  # fmt: skip
    m_still = 8000
    t_s = np.arange(m_still) / FS
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "timedexec-recording"
        f.attrs["format_version"] = 1
        f.attrs["header"] = json.dumps(header)
        f.attrs["fields"] = json.dumps(fields)
        f.attrs["recording_id"] = uuid.uuid4().hex
        f.attrs["journal_seq"] = 0
        f.attrs["compression"] = "none"
        f.attrs["trials_per_chunk"] = 64
        for name, arr in data.items():
            ds = f.create_dataset(f"trials/{name}", data=arr, maxshape=(None, *arr.shape[1:]))
            ds.attrs["unit"] = next(x["unit"] for x in fields if x["name"] == name)
        f["static/plan_q_start_rad"] = np.tile([0.0, 0.3, 0.0, 0.0, 0.0, 0.0], (n, 1))
        f["static/plan_joint"] = joint
        f["static/plan_direction"] = direction
        still = np.rint((0.5 + rng.normal(0, 0.3, (m_still, 3))) * lsb).astype(np.int16)
        f["static/still_gyro_raw"] = still if gyro_unit == "LSB" else (still / lsb).astype(
            np.float32
        )
        f["static/still_gyro_counter"] = ((1000 + np.arange(m_still)) % 65536).astype(np.uint16)
        f["static/still_gyro_block_host_time_s"] = t_s[B - 1 :: B] + 2.0 + 5e-4
    return path


def test_minimal_h5py_recording_is_extracted(tmp_path: Path) -> None:
    """Written from the document alone: check_recording finds nothing, the extraction
    recovers the 20 ms + ramp onset and the 3 ms state age (tolerances: 0.3 ms, several
    times the standard error of these 24 short, noisy trials)."""
    path = _write_minimal(tmp_path / "min.h5")
    assert check_recording(path) == []
    table = extract_recording(path, progress=False).table
    ok = np.array([not f for f in table["flag"]])
    assert ok.mean() > 0.9
    # The first-order lag of 5 ms reaches 10 % of the ramp later than the ramp itself:
    # onset of v = level is the delayed ramp's crossing + ~tau (5 ms) for a ramp input.
    act = table["actuation_delay"][ok]
    assert np.all(np.isfinite(act))
    assert 0.015 < np.median(act) < 0.035
    np.testing.assert_allclose(np.median(table["response_delay"][ok]), 3e-3, atol=3e-4)
    assert np.all(table["actuation_delay_se"][ok] > 0)


def test_gyro_rates_in_deg_per_s_are_converted(tmp_path: Path) -> None:
    """The same recording with the gyro stored in °/s (float) gives the same delays
    (0.05 ms: the counts' quantisation differs)."""
    a = extract_recording(_write_minimal(tmp_path / "a.h5"), progress=False).table
    b = extract_recording(_write_minimal(tmp_path / "b.h5", gyro_unit="deg/s"), progress=False)
    np.testing.assert_allclose(
        np.nanmedian(b.table["actuation_delay"]), np.nanmedian(a["actuation_delay"]), atol=5e-5
    )


@pytest.mark.parametrize("key", ["group_delay_s", "transport_latency_s"])
def test_missing_sensor_constant_is_an_error_not_zero(tmp_path: Path, key: str) -> None:
    """A header without the group delay or the transport latency is refused, naming it."""
    path = _write_minimal(tmp_path / "x.h5", n=4, drop_key=key)
    problems = check_recording(path)
    assert any(key in p for p in problems)
    with pytest.raises(RecordingError, match=key):
        extract_recording(path, progress=False)


def test_check_names_every_problem(tmp_path: Path) -> None:
    """A wrong unit, a missing field and a missing static are all listed, each named."""
    path = _write_minimal(tmp_path / "bad.h5", n=4)
    with h5py.File(path, "r+") as f:
        fields = json.loads(f.attrs["fields"])
        for fld in fields:
            if fld["name"] == "state_q_rad":
                fld["unit"] = "furlong"
        fields = [x for x in fields if x["name"] != "cmd_send_time_s"]
        f.attrs["fields"] = json.dumps(fields)
        del f["trials/cmd_send_time_s"]
        del f["static/plan_joint"]
    problems = check_recording(path)
    text = "\n".join(problems)
    assert "state_q_rad" in text
    assert "furlong" in text
    assert "cmd_send_time_s" in text
    assert "plan_joint" in text
    with pytest.raises(RecordingError, match="furlong"):
        extract_recording(path, progress=False)


def test_check_never_raises_on_garbage(tmp_path: Path) -> None:
    """Not a file, not HDF5: one problem each, no exception."""
    bad = tmp_path / "g.h5"
    bad.write_bytes(b"nope")
    assert len(check_recording(bad)) == 1
    assert len(check_recording(tmp_path / "missing.h5")) == 1


def test_sensor_profile_round_trip(tmp_path: Path) -> None:
    """A sensor profile JSON loads into the header; missing constants are refused."""
    p = tmp_path / "mpu.json"
    p.write_text(json.dumps({"group_delay_s": 0.00098, "transport_latency_s": 0.00072}))
    h = GyroHeader.from_json(p)
    assert h.group_delay_s == 0.00098
    assert h.transport_latency_s == 0.00072
    p.write_text(json.dumps({"group_delay_s": 0.00098}))
    with pytest.raises(ConfigError, match="transport_latency_s"):
        GyroHeader.from_json(p)


def _doc_section(title: str) -> str:
    """The text of one ### section of docs/recording-format.md."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "recording-format.md").read_text()
    start = text.index(f"### {title}")
    end = text.find("\n#", start + 4)
    return text[start : end if end > 0 else None]


def _table_rows(section: str) -> list[list[str]]:
    rows = [ln for ln in section.splitlines() if ln.startswith("| ")]
    return [[c.strip() for c in ln.strip("|").split(" | ")] for ln in rows[1:]]  # no header


def _ticked(cell: str) -> list[str]:
    import re

    return re.findall(r"`([^`]*)`", cell)


def test_document_and_code_state_the_same_contract() -> None:
    """docs/recording-format.md ("What extraction needs") lists exactly the fields (with
    their kinds), statics and header keys the extraction requires, and the units table
    accepts exactly the spellings the code converts: the document is the contract."""
    from timedexec.extraction import REQUIRED_FIELDS, REQUIRED_HEADER, REQUIRED_STATICS, UNITS

    fields = {_ticked(r[0])[0]: r[2] for r in _table_rows(_doc_section("Per-trial fields"))}
    assert fields == {name: kind for name, (kind, _) in REQUIRED_FIELDS.items()}
    statics = [_ticked(r[0])[0] for r in _table_rows(_doc_section("Static arrays"))]
    assert statics == list(REQUIRED_STATICS)
    header = [_ticked(r[0])[0] for r in _table_rows(_doc_section("Header keys"))]
    assert header[: len(REQUIRED_HEADER)] == list(REQUIRED_HEADER)
    # the rest are conditional: the sensitivity, needed only for counts
    assert header[len(REQUIRED_HEADER) :] == ["gyro.lsb_per_dps"]
    units = {r[0]: set(_ticked(r[1])) for r in _table_rows(_doc_section("Units"))}
    assert set(units) == set(UNITS)
    for kind, table in UNITS.items():
        assert units[kind] == set(table), kind


def test_deep_check_names_trials_outside_the_plan(tmp_path: Path) -> None:
    """A trial index beyond the plan arrays and a repeated one are named (deep check only:
    --shallow does not read the data)."""
    path = _write_minimal(tmp_path / "t.h5", n=4)
    with h5py.File(path, "r+") as f:
        f["trials/trial"][:] = [0, 1, 1, 7]
    problems = check_recording(path)
    assert any("index no row of the plan" in p for p in problems)
    assert any("more than once" in p for p in problems)
    assert check_recording(path, deep=False) == []
