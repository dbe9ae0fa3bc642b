"""The numbered examples run headless and print their results (the README promises it)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
# Arguments that keep each example to seconds; the slow ones run in the slow tier.
FAST = {"01_calibrate_simulated_ur10.py": ["--trials", "6"]}
SLOW = {"05_real_ur.py": ["--trials", "4"]}


def run(name: str, args: list[str], tmp_path: Path) -> str:
    # A clean environment (headless, no user configuration), keeping PYTHONPATH for runs
    # from a source tree that is not installed.
    env = {"MPLBACKEND": "Agg", "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    if "PYTHONPATH" in os.environ:
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
        env=env,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def others() -> list[str]:
    return sorted(p.name for p in EXAMPLES.glob("[0-9][0-9]_*.py") if p.name not in FAST | SLOW)


@pytest.mark.parametrize("name", sorted(FAST))
def test_fast_examples(name, tmp_path):
    """Example 01 calibrates the simulated UR10 and reports an error against ground truth."""
    out = run(name, FAST[name], tmp_path)
    assert "ms" in out


@pytest.mark.parametrize("name", others())
def test_other_examples(name, tmp_path):
    """Every other numbered example runs headless with its defaults and prints units."""
    out = run(name, [], tmp_path)
    assert any(unit in out for unit in ("ms", " s", "cm", "mm", "rad"))


@pytest.mark.slow
@pytest.mark.realtime_twin
@pytest.mark.parametrize("name", sorted(SLOW))
def test_slow_examples(name, tmp_path):
    """Example 05 talks to the UR twin through the real ur_rtde client and a pty gyro."""
    out = run(name, SLOW[name], tmp_path)
    assert "actuation delay: median" in out
