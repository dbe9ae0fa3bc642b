"""`timedexec train`: outputs, the CV.json format, and exit code 2 with clear messages on bad input."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from timedexec.cli import main

sys.path.insert(0, str(Path(__file__).parent))
from test_learning import synthetic_table


def run(argv: Sequence[str]) -> int:
    """The `train` subcommand through the real command line."""
    return main(list(argv))


@pytest.fixture(scope="module")
def csv_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cli") / "delays.csv"
    synthetic_table(n_cfg=12, repeats=3).to_csv(path)
    return path


def test_train_writes_bundle_cv_json_and_tables(
    csv_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A run writes the bundle, cv.json (exact format), cv-table.txt and --json; the tables
    go to stdout."""
    out = tmp_path / "bundle"
    cv_path = tmp_path / "cv.json"
    code = run(
        [
            "train",
            str(csv_path),
            "--out",
            str(out),
            "--folds",
            "3",
            "--json",
            str(cv_path),
            "--quiet",
        ]
    )
    assert code == 0
    stdout = capsys.readouterr().out
    assert "Table I: actuation delay" in stdout
    assert "bundle for ur10 at 8 ms" in stdout
    cv = json.loads(cv_path.read_text())
    assert list(cv) == ["actuation_delay", "response_delay"]
    assert list(cv["actuation_delay"]) == ["median", "nn", "rt", "gpr"]
    assert list(cv["response_delay"]["gpr"]) == ["1", "2", "3", "5", "combined", "average"]
    assert all(isinstance(v, float) for v in cv["actuation_delay"]["nn"].values())
    assert json.loads((out / "cv.json").read_text()) == cv
    assert (out / "cv-table.txt").read_text().startswith("Table I")
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["training_data"]["file_sha256"]) == 64
    from timedexec.learning import DelayModel

    p = DelayModel.load(out, robot="ur10").predict(joint=3, direction=-1, q=np.zeros(6))
    assert 0.0 < p.actuation_mean < 0.1  # s


def test_train_json_dash_prints_cv_only(
    csv_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--json - prints the CV scores as JSON to stdout (machine-readable), nothing else."""
    code = run(
        ["train", str(csv_path), "--out", str(tmp_path / "b"), "--folds", "2", "--methods",
         "median,rt", "--json", "-", "--quiet"]
    )  # fmt: skip
    assert code == 0
    cv = json.loads(capsys.readouterr().out)
    assert list(cv["actuation_delay"]) == ["median", "rt"]


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _set(lines: list[str], row: int, col: int, value: str) -> list[str]:
    """Replace field ``col`` of data row ``row`` (0-based, after the header)."""
    out = list(lines)
    fields = out[row + 1].split(",")
    fields[col] = value
    out[row + 1] = ",".join(fields)
    return out


def _drop_column(lines: list[str], col: int) -> list[str]:
    return [",".join(f for i, f in enumerate(r.split(",")) if i != col) for r in lines]


# Columns of the synthetic CSV: trial, robot, joint, direction, q1..q6 (4-9), t_start,
# actuation_delay (11), response_delay (12).
BAD_TABLES = {
    "empty": (lambda lines: lines[:1], "empty"),
    "missing-column": (lambda lines: _drop_column(lines, 12), "missing column(s) response_delay"),
    "nan-delay": (lambda lines: _set(lines, 4, 11, "nan"), "column 'actuation_delay' row 4 is nan"),
    "inf-delay": (lambda lines: _set(lines, 2, 12, "inf"), "column 'response_delay' row 2 is inf"),
    "unknown-joint": (lambda lines: _set(lines, 1, 2, "7"), "row 1: joint 7 outside 1..6"),
    "nan-angle": (lambda lines: _set(lines, 3, 5, "nan"), "column 'q2' row 3 is nan"),
}


@pytest.mark.parametrize(("edit", "message"), BAD_TABLES.values(), ids=BAD_TABLES.keys())
def test_bad_tables_exit_2_naming_column_and_row(
    csv_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], edit: Any, message: str
) -> None:
    """Empty tables, missing columns, NaN/inf values and unknown joints: exit code 2 and a
    message naming the column and row."""
    lines = csv_path.read_text().splitlines()
    bad = _write(tmp_path / "bad.csv", "\n".join(edit(lines)) + "\n")
    code = run(["train", str(bad), "--out", str(tmp_path / "b"), "--folds", "2", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err


def test_bad_options_exit_2(
    csv_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Unknown methods, a single fold, a missing file: exit code 2 with the reason."""
    out = str(tmp_path / "b")
    assert run(["train", str(csv_path), "--out", out, "--methods", "median,svm"]) == 2
    assert "svm" in capsys.readouterr().err
    assert run(["train", str(csv_path), "--out", out, "--folds", "1"]) == 2
    assert "--folds 1" in capsys.readouterr().err
    assert run(["train", str(tmp_path / "none.csv"), "--out", out]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert run(["train", str(csv_path), "--out", out, "--folds", "20", "--quiet"]) == 2
    assert "at least 20 distinct start configurations" in capsys.readouterr().err


def test_train_time_input_flag(csv_path: Path, tmp_path: Path) -> None:
    """--time-input puts the sweep time last in the inputs; the bundle predicts warm."""
    out = tmp_path / "b"
    code = run(
        ["train", str(csv_path), "--out", str(out), "--folds", "0", "--methods", "gpr",
         "--time-input", "--quiet"]
    )  # fmt: skip
    assert code == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["time_input"] is True
    assert manifest["feature_order"]["combined"][-1] == "t_h"
    assert manifest["time_default_s"] == manifest["time_range_s"][1]
