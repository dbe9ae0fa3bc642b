"""Build helpers of the firmware tests (tests/test_firmware*.py): one place that knows how
the firmware/ Makefile is driven and when a missing toolchain skips a test (a developer
machine) or fails it (CI, where .ci/run installs the toolchain from Debian's packages)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

FIRMWARE_DIR = Path(__file__).resolve().parents[1] / "firmware"

#: Debian packages .ci/run installs for the firmware tests.
DEBIAN_PACKAGES = (
    "gcc make gcc-avr avr-libc binutils-avr arduino-core-avr simavr libsimavr-dev pkg-config"
)


def require(ok: bool, what: str) -> None:
    """Skip (or under CI fail) when ``what`` is missing, naming the packages to install."""
    if ok:
        return
    message = f"{what} is not installed; apt-get install {DEBIAN_PACKAGES}"
    if os.environ.get("CI"):
        pytest.fail(f"CI must run the firmware tests: {message} (.ci/run installs them)")
    pytest.skip(message)


def host_compiler() -> str:
    """The host C compiler for the shared encoder (skips without one)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    require(cc is not None and shutil.which("make") is not None, "a host C compiler (cc) and make")
    assert cc is not None
    return cc


def make(build_dir: Path, *targets: str, timeout_s: float = 300.0, **variables: str) -> None:
    """``make -C firmware BUILD=build_dir [VAR=value ...] targets``; failure shows make's output."""
    args = ["make", "-C", str(FIRMWARE_DIR), f"BUILD={build_dir}", "-j2"]
    args += [f"{k}={v}" for k, v in variables.items()] + list(targets)
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s)
    if proc.returncode:
        pytest.fail(f"{' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
