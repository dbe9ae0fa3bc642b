"""What every ``timedexec`` subcommand shares: the help formatter, the ``--json``
convention, the common options and the one way results reach stdout.

A command module builds its parser with :func:`add_command` and the ``add_*`` helpers,
and prints its result with :func:`emit` (or :func:`out` for plain text), so that every
command reads the same options the same way and a closed stdout is recognised in one place.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from timedexec.errors import ConfigError
from timedexec.robots import ROBOT_NAMES

__all__ = [
    "JSON_CONVENTION",
    "Formatter",
    "StdoutClosed",
    "add_command",
    "add_jobs",
    "add_json",
    "add_period",
    "add_quiet",
    "add_robot",
    "add_seed",
    "check_json_path",
    "emit",
    "out",
    "robot_name",
    "warn",
]

#: The ``--json`` convention, as the top-level ``--help`` and the README state it.
JSON_CONVENTION = (
    "--json [PATH] (simulate, calibrate, extract, train, evaluate, discrepancy, demo): the\n"
    "  command's machine-readable result. Bare --json (or --json -) prints the JSON on stdout\n"
    "  instead of the text; --json PATH writes it to PATH and prints the text as usual.\n"
    "  Put a bare --json after the positional arguments, or write --json=-."
)


class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Help formatter of every command: descriptions keep their line breaks, options show
    their defaults."""


class StdoutClosed(Exception):
    """The reader of stdout went away (``timedexec ... | head``); raised by :func:`out`."""


def add_command(sub: Any, name: str, *, help: str, description: str) -> argparse.ArgumentParser:
    """Add the subcommand ``name`` to the subparsers ``sub`` with the shared formatter."""
    parser: argparse.ArgumentParser = sub.add_parser(
        name, help=help, description=description, formatter_class=Formatter
    )
    return parser


def robot_name(value: str) -> str:
    """argparse type of ``--robot``: a built-in robot name, case-insensitive, lower-cased."""
    key = value.strip().lower()
    if key not in ROBOT_NAMES:
        raise argparse.ArgumentTypeError(
            f"unknown robot {value!r}; choose one of {', '.join(ROBOT_NAMES)}"
        )
    return key


def add_robot(
    parser: argparse.ArgumentParser,
    *,
    required: bool = False,
    default: str | None = None,
    help: str = "simulated robot",
) -> None:
    """``--robot ROBOT``: one of the built-in robots (checked when parsing: exit 2)."""
    parser.add_argument(
        "--robot",
        type=robot_name,
        required=required,
        default=default,
        metavar="ROBOT",
        help=f"{help}: {', '.join(ROBOT_NAMES)}",
    )


def add_seed(
    parser: argparse.ArgumentParser, *, default: int = 0, help: str = "random seed"
) -> None:
    """``--seed N``: the seed of every random choice of the command (same seed, same output)."""
    parser.add_argument("--seed", type=int, default=default, help=help)


def add_period(
    parser: argparse.ArgumentParser,
    *,
    help: str = "controller period, s (kr5: 0.012 or 0.004)",
) -> None:
    """``--period S``: the controller period, s (default: the robot's)."""
    parser.add_argument("--period", type=float, metavar="S", help=help)


def add_jobs(parser: argparse.ArgumentParser, *, help: str = "worker processes (joblib)") -> None:
    """``--jobs N``: worker processes; results never depend on it."""
    parser.add_argument("--jobs", type=int, default=1, help=help)


def add_quiet(parser: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress on stderr."""
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def add_json(parser: argparse.ArgumentParser, what: str) -> None:
    """``--json [PATH]`` as :data:`JSON_CONVENTION` describes; ``what`` names the document.

    ``args.json`` is ``None`` (text only), ``"-"`` (JSON on stdout, no text) or a path.
    """
    parser.add_argument(
        "--json",
        nargs="?",
        const="-",
        default=None,
        metavar="PATH",
        help=f"{what} as JSON: bare --json or '-' prints it on stdout instead of the text, "
        "PATH writes it there",
    )


def check_json_path(args: argparse.Namespace) -> None:
    """Refuse a ``--json PATH`` whose folder does not exist before any work is done.

    Raises
    ------
    ConfigError
        Naming the option, the path and the missing folder.
    """
    dest = getattr(args, "json", None)
    if dest is None or dest == "-":
        return
    folder = Path(dest).parent
    if not folder.is_dir():
        raise ConfigError(f"--json {dest}: the folder {folder} does not exist; create it first")


def out(text: str) -> None:
    """Print ``text`` on stdout (flushed); a closed pipe raises :class:`StdoutClosed`."""
    try:
        print(text, flush=True)
    except BrokenPipeError as exc:
        raise StdoutClosed from exc


def emit(args: argparse.Namespace, result: Mapping[str, Any], text: str) -> None:
    """Deliver a command's result by the ``--json`` convention.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options; ``args.json`` as set by :func:`add_json` (absent: text only).
    result : mapping
        The machine-readable result (JSON-serialisable).
    text : str
        The human-readable result.

    Raises
    ------
    RecordingError
        If ``--json PATH`` cannot be written (the path and the reason named).
    """
    dest = getattr(args, "json", None)
    if dest == "-":
        out(json.dumps(result, indent=2))
        return
    if dest is not None:
        from timedexec._files import write_atomic

        write_atomic(dest, json.dumps(result, indent=2) + "\n")
        text += f"\nwrote the JSON result to {dest}"
    out(text)


def warn(command: str, message: str) -> None:
    """A warning line on stderr, prefixed with the command."""
    print(f"timedexec {command}: warning: {message}", file=sys.stderr)
