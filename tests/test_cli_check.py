"""`timedexec check` (the recording contract on the command line) and the `extract` options
of issue 14 (`--clock-window`, `--max-se`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import pytest

from test_recording_contract import _write_minimal
from timedexec.cli import main
from timedexec.errors import ConfigError


@pytest.fixture(scope="module")
def valid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A minimal recording written with plain h5py from docs/recording-format.md."""
    return Path(_write_minimal(tmp_path_factory.mktemp("check") / "ok.h5", n=6))


def test_valid_recording_exits_0_with_one_line(
    valid: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A valid recording: exit 0 and exactly `REC.h5: a valid timedexec recording`."""
    assert main(["check", str(valid)]) == 0
    assert capsys.readouterr().out == f"{valid}: a valid timedexec recording\n"


def test_every_problem_on_its_own_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A wrong unit, a missing field, a missing static and a missing sensor constant: exit
    2, one line per problem on stdout, each naming what is wrong; no traceback."""
    path = _write_minimal(tmp_path / "bad.h5", n=4, drop_key="transport_latency_s")
    with h5py.File(path, "r+") as f:
        fields = json.loads(f.attrs["fields"])
        for fld in fields:
            if fld["name"] == "state_q_rad":
                fld["unit"] = "furlong"
        f.attrs["fields"] = json.dumps([x for x in fields if x["name"] != "cmd_send_time_s"])
        del f["trials/cmd_send_time_s"]
        del f["static/plan_joint"]
    assert main(["check", str(path)]) == 2
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert len(lines) == 4
    for name in ("transport_latency_s", "furlong", "cmd_send_time_s", "plan_joint"):
        assert sum(name in line for line in lines) == 1, name
    assert "Traceback" not in captured.err


@pytest.mark.parametrize("spelling", [["--json"], ["--json", "-"], ["--json=-"]])
def test_json_verdict_on_stdout(
    valid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], spelling: list[str]
) -> None:
    """--json prints {recording, valid, problems} instead of the text, for a valid and for
    an unreadable file (exit codes unchanged)."""
    assert main(["check", str(valid), *spelling]) == 0
    assert json.loads(capsys.readouterr().out) == {
        "recording": str(valid), "valid": True, "problems": [],
    }  # fmt: skip
    garbage = tmp_path / "g.h5"
    garbage.write_bytes(b"not hdf5")
    assert main(["check", str(garbage), *spelling]) == 2
    doc = json.loads(capsys.readouterr().out)
    assert doc["valid"] is False
    assert len(doc["problems"]) == 1
    assert "g.h5" in doc["problems"][0]


def test_json_path_keeps_the_text(
    valid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--json PATH writes the verdict there and still prints the text."""
    dest = tmp_path / "verdict.json"
    assert main(["check", str(valid), "--json", str(dest)]) == 0
    assert "a valid timedexec recording" in capsys.readouterr().out
    assert json.loads(dest.read_text())["valid"] is True


def test_json_path_that_is_the_recording_is_refused(
    valid: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The output-path policy: --json onto the recording itself is refused (exit 2) and the
    recording is left as it was."""
    before = valid.read_bytes()
    assert main(["check", str(valid), "--json", str(valid)]) == 2
    assert "same file" in capsys.readouterr().err
    assert valid.read_bytes() == before


def test_missing_file_is_a_problem_not_a_crash(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A path that does not exist: exit 2, the path named."""
    assert main(["check", str(tmp_path / "nope.h5")]) == 2
    assert "nope.h5" in capsys.readouterr().out


def test_shallow_does_not_read_the_data(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A problem only the data shows (a trial index outside the plan) is found by default
    and not with --shallow, which says on stderr what it skipped."""
    path = _write_minimal(tmp_path / "t.h5", n=4)
    with h5py.File(path, "r+") as f:
        f["trials/trial"][:] = [0, 1, 2, 9]
    assert main(["check", str(path)]) == 2
    assert "plan" in capsys.readouterr().out
    assert main(["check", str(path), "--shallow"]) == 0
    captured = capsys.readouterr()
    assert captured.out == f"{path}: a valid timedexec recording\n"
    assert "--shallow" in captured.err


class _Called(ConfigError):
    """Raised by the fake extraction to stop the command after it was called."""


def test_extract_passes_clock_window_and_max_se(
    valid: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`extract --clock-window 30 --max-se 1.5` calls the extraction with clock_window_s=30
    and max_se_s=0.0015 (ms on the command line, s in the library); without them, None (the
    window chosen from the data) and MAX_SE_S."""
    import timedexec.extraction as extraction

    calls: list[dict[str, Any]] = []

    def fake(path: Any, **kw: Any) -> None:
        calls.append(kw)
        raise _Called("stop")

    monkeypatch.setattr(extraction, "extract_recording", fake)
    out = str(tmp_path / "d.csv")
    argv = ["extract", str(valid), "--out", out, "--quiet"]
    assert main([*argv, "--clock-window", "30", "--max-se", "1.5"]) == 2
    assert calls[-1]["clock_window_s"] == 30.0
    assert calls[-1]["max_se_s"] == pytest.approx(0.0015)
    assert main(argv) == 2
    assert calls[-1]["clock_window_s"] is None
    assert calls[-1]["max_se_s"] == extraction.MAX_SE_S


@pytest.mark.parametrize(
    ("option", "value"),
    [("--clock-window", "0"), ("--clock-window", "-5"), ("--clock-window", "nan"),
     ("--max-se", "0"), ("--max-se", "inf"), ("--max-se", "x")],
)  # fmt: skip
def test_extract_refuses_bad_option_values(
    valid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str
) -> None:
    """Non-positive, non-finite or non-numeric values: exit 2 naming the option, before any
    work."""
    argv = ["extract", str(valid), "--out", str(tmp_path / "d.csv"), f"{option}={value}"]
    assert main(argv) == 2
    assert option in capsys.readouterr().err
    assert not (tmp_path / "d.csv").exists()


def test_extract_help_states_the_max_se_default(capsys: pytest.CaptureFixture[str]) -> None:
    """The help's default of --max-se is the library's MAX_SE_S (in ms)."""
    from timedexec.extraction import MAX_SE_S

    assert main(["extract", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert f"if not given, {MAX_SE_S * 1e3:g} ms" in text


def test_extract_with_options_on_a_real_recording(
    valid: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """End to end: a tiny --max-se flags every trial 'uncertain'; --clock-window is used."""
    out = tmp_path / "d.csv"
    argv = ["extract", str(valid), "--out", str(out), "--quiet", "--json"]
    assert main([*argv, "--clock-window", "3", "--max-se", "1e-6"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["flags"] == {"uncertain": info["trials"]}
    assert info["gyro_clock"]["0"]["window_s"] == pytest.approx(3.0, rel=0.01)
