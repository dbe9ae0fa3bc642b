"""timedexec.cli: the ``timedexec`` command, a thin layer over the library."""

from __future__ import annotations

from timedexec.cli._main import main

__all__ = ["main"]
