"""Package version (one source of truth, read by pyproject-built metadata and recordings)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("timedexec")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
