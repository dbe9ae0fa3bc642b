"""The ``timedexec`` command: a thin layer over the library.

Results go to stdout (or the file named), progress and status to stderr. Every subcommand
returns an exit code: 0 success, 2 bad input (a :class:`~timedexec.errors.ConfigError` or
:class:`~timedexec.errors.RecordingError`), 1 any other failure.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from timedexec._version import __version__
from timedexec.errors import TimedExecError

__all__ = ["main"]


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="timedexec",
        description=(
            "Measure, model and compensate the actuation and response delays of industrial "
            "robot arms. Every command runs on the embedded simulated robots when no robot "
            "is attached."
        ),
    )
    parser.add_argument("--version", action="version", version=f"timedexec {__version__}")
    parser.add_subparsers(dest="command", metavar="COMMAND")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``timedexec`` command line; return the process exit code."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args))
    except TimedExecError as exc:
        print(f"timedexec {args.command}: error: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError | OSError) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
