"""What every ``timedexec`` subcommand shares: the help formatter, the ``--json``
convention, the common options and the one way results reach stdout.

A command module builds its parser with :func:`add_command` and the ``add_*`` helpers,
and prints its result with :func:`emit` (or :func:`out` for plain text), so that every
command reads the same options the same way and a closed stdout is recognised in one place.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import math
import os
import shlex
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from timedexec.errors import ConfigError, RecordingError, TimedExecError
from timedexec.robots import ROBOT_NAMES

__all__ = [
    "EXIT_INTERRUPTED",
    "JSON_CONVENTION",
    "MAX_SEED",
    "MAX_TRIALS",
    "Formatter",
    "StdoutClosed",
    "add_command",
    "add_jobs",
    "add_json",
    "add_period",
    "add_quiet",
    "add_robot",
    "add_seed",
    "check_files",
    "check_json_path",
    "cpu_count",
    "emit",
    "float_arg",
    "int_arg",
    "note",
    "out",
    "robot_name",
    "shell_command",
    "sweep_stopped",
    "used_jobs",
    "warn",
]

#: Largest accepted ``--seed`` (seeds are 32-bit unsigned integers, as in scikit-learn).
MAX_SEED = 2**32 - 1

#: The ``--json`` convention, as the top-level ``--help`` and the README state it.
JSON_CONVENTION = (
    "--json [PATH] (simulate, calibrate, check, extract, train, evaluate, discrepancy, fleet,\n"
    "  monitor, demo): the command's machine-readable result. Bare --json (or --json -) prints the\n"
    "  JSON on stdout instead of the text; --json PATH writes it to PATH and prints the text\n"
    "  as usual.\n"
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


#: The most trials a sweep may plan: 300 times the paper's 33,500 (a fleet's worth).
MAX_TRIALS = 10_000_000


def int_arg(
    low: int | None = None, high: int | None = None, *, fix: str = ""
) -> Callable[[str], int]:
    """argparse type: an integer in ``[low, high]`` (None: unbounded on that side).

    The message of a bad value names the value, the allowed range and, with ``fix``, what
    to do; argparse prefixes the option (``argument --seed: -1 is out of range; ...``) and
    exits 2.
    """

    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"invalid int value: {text!r}; {_range_words(low, high, 'an integer')}{fix}"
            ) from None
        if (low is not None and value < low) or (high is not None and value > high):
            raise argparse.ArgumentTypeError(
                f"{value} is out of range; {_range_words(low, high, 'an integer')}{fix}"
            )
        return value

    return parse


def float_arg(
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    unit: str = "",
    fix: str = "",
) -> Callable[[str], float]:
    """argparse type: a finite number in ``[low, high]`` (``(low, high]`` with ``low_open``).

    NaN and infinities are refused at the boundary, with a message naming the value, the
    allowed range (in ``unit``) and, with ``fix``, what to do (argparse names the option).
    """
    lo = "" if low is None else ("> " if low_open else ">= ") + f"{low:g}"
    hi = "" if high is None else f"<= {high:g}"
    span = " and ".join(w for w in (lo, hi) if w)
    words = f"use a finite number{' ' + span if span else ''}{' ' + unit if unit else ''}"

    def parse(text: str) -> float:
        try:
            value = float(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"invalid float value: {text!r}; {words}{fix}"
            ) from None
        bad = not math.isfinite(value)
        if low is not None:
            bad |= value <= low if low_open else value < low
        if high is not None:
            bad |= value > high
        if bad:
            raise argparse.ArgumentTypeError(f"{text.strip()} is out of range; {words}{fix}")
        return value

    return parse


def _range_words(low: int | None, high: int | None, noun: str) -> str:
    if low is not None and high is not None:
        return f"use {noun} from {low} to {high}"
    if low is not None:
        return f"use {noun} >= {low}"
    if high is not None:
        return f"use {noun} <= {high}"
    return f"use {noun}"


def add_seed(
    parser: argparse.ArgumentParser, *, default: int = 0, help: str = "random seed"
) -> None:
    """``--seed N``: the seed of every random choice of the command (same seed, same output);
    0 .. :data:`MAX_SEED` (exit 2 outside)."""
    parser.add_argument(
        "--seed",
        type=int_arg(0, MAX_SEED),
        default=default,
        help=f"{help} (0 .. {MAX_SEED})",
    )


def add_period(
    parser: argparse.ArgumentParser,
    *,
    help: str = "controller period, s (kr5: 0.012 or 0.004)",
) -> None:
    """``--period S``: the controller period, s (default: the robot's); finite and > 0."""
    period = float_arg(0.0, low_open=True, unit="s")
    parser.add_argument("--period", type=period, metavar="S", help=help)


def add_jobs(parser: argparse.ArgumentParser, *, help: str = "worker processes (joblib)") -> None:
    """``--jobs N``: worker processes, >= 1 or -1 (one per CPU); results never depend on it.

    More than the CPUs of this machine are accepted and capped at the CPU count with a
    warning on stderr (:func:`used_jobs`): more workers than CPUs only add start-up time
    and memory.
    """
    parser.add_argument(
        "--jobs",
        type=_jobs,
        default=1,
        help=f"{help}; -1: one per CPU; more than the CPUs are capped at the CPU count "
        "(with a warning)",
    )


def _jobs(text: str) -> int:
    value = int_arg(-1, 4096)(text)
    if value == 0:
        raise argparse.ArgumentTypeError(
            "0 is out of range; use a worker count >= 1, or -1 for one per CPU"
        )
    return value


def cpu_count() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def used_jobs(command: str, jobs: int) -> int:
    """The worker count a command uses for ``--jobs jobs``: ``-1`` stays (one per CPU);
    more than :func:`cpu_count` is capped at it, with a warning on stderr naming both."""
    cpus = cpu_count()
    if jobs > cpus:
        warn(
            command,
            f"--jobs {jobs} is more than the {cpus} CPU(s) of this machine; using {cpus} "
            "(results do not depend on --jobs)",
        )
        return cpus
    return jobs


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


def check_files(
    args: argparse.Namespace,
    command: str,
    *,
    inputs: Mapping[str, Any] | None = None,
    outputs: Mapping[str, Any] | None = None,
    folders: Mapping[str, Any] | None = None,
    what: Mapping[str, str] | None = None,
    devices: Sequence[str] = (),
) -> None:
    """The output-path policy (:func:`timedexec._files.check_paths`) for a command, before
    any work: ``--json PATH`` is added to the outputs; the notes (existing outputs that will
    be replaced) go to stderr unless ``--quiet``.

    Raises
    ------
    ConfigError
        An output that is an input or another output, or not a regular file, or in a
        missing folder (see :func:`~timedexec._files.check_paths`).
    """
    from timedexec._files import check_paths

    outs = dict(outputs or {})
    describe = dict(what or {})
    dest = getattr(args, "json", None)
    if dest is not None and dest != "-":
        outs["--json"] = dest
        describe.setdefault("--json", "the JSON result")
    notes = check_paths(
        inputs=inputs, outputs=outs, folders=folders, what=describe, devices=devices
    )
    if not getattr(args, "quiet", False):
        for text in notes:
            note(command, text)


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


def note(command: str, message: str) -> None:
    """A status line on stderr, prefixed with the command."""
    print(f"timedexec {command}: note: {message}", file=sys.stderr)


#: Exit code of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130

#: errno of a write that failed for want of room or because the storage failed: a sweep
#: that stops on one of these is continued with ``--resume`` once the cause is fixed.
_STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS})


def shell_command(command: str, options: Sequence[tuple[str, Any]]) -> str:
    """``timedexec COMMAND OPTION VALUE ...``, quoted for a POSIX shell.

    Parameters
    ----------
    command : str
        The subcommand (``"simulate"``).
    options : sequence of (str, value)
        Options in order: ``None`` and ``False`` are left out, ``True`` is a bare flag,
        anything else is ``--option VALUE`` (a value starting with ``-`` as
        ``--option=VALUE``, so that it cannot be taken for an option).
    """
    words = ["timedexec", command]
    for flag, value in options:
        if value is None or value is False:
            continue
        if value is True:
            words.append(flag)
        elif str(value).startswith("-"):
            words.append(shlex.quote(f"{flag}={value}"))
        else:
            words += [flag, shlex.quote(str(value))]
    return " ".join(words)


def _storage_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a failed write of a file (see above), or came from one.

    Only a :class:`~timedexec.errors.RecordingError` or a plain ``OSError`` counts: a gyro
    or robot that fails (``SensorError``, ``DriverError``, a lost connection) may also
    carry ``EIO`` (a USB adapter pulled out), and stays a fault (exit 3).
    """
    if isinstance(exc, (ConnectionError, TimeoutError, BlockingIOError)) or (
        isinstance(exc, TimedExecError) and not isinstance(exc, RecordingError)
    ):
        return False
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, OSError) and cur.errno in _STORAGE_ERRNOS:
            return True
        cur = cur.__cause__ or cur.__context__
    return False


def sweep_stopped(command: str, exc: BaseException, recording: str, resume: str) -> int:
    """End a resumable sweep that Ctrl-C or a failed write stopped, saying how to resume.

    Ctrl-C: one line on stderr, ``interrupted; ... resume with: RESUME`` (when the
    recording exists; else just ``interrupted``), and the exit code of an interrupt. A write
    that failed for want of room or because the storage failed (disk full, quota, I/O
    error), when the recording exists: a :class:`~timedexec.errors.RecordingError` whose
    one-line message ends with the resume command (exit 2). Anything else is raised as it
    is.

    Parameters
    ----------
    command : str
        The subcommand, for the message prefix.
    exc : BaseException
        What stopped the sweep.
    recording : str
        The recording (``--out``).
    resume : str
        The command that continues the sweep (:func:`shell_command` with ``--resume``).

    Returns
    -------
    int
        130 after Ctrl-C.

    Raises
    ------
    RecordingError
        After a failed write, with the resume command; otherwise ``exc`` itself.
    """
    exists = os.path.exists(recording)
    if isinstance(exc, KeyboardInterrupt):
        text = (
            f"interrupted; {recording} keeps every finished trial; resume with: {resume}"
            if exists
            else "interrupted"
        )
        with contextlib.suppress(OSError, ValueError):
            print(f"timedexec {command}: {text}", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    if exists and _storage_error(exc):
        message = str(exc) if isinstance(exc, RecordingError) else f"{recording}: {exc}"
        message = message.rstrip(". ")
        # the store's messages end "... then resume": complete them with the command
        joint = " with" if message.lower().endswith("resume") else "; once fixed, resume with"
        raise RecordingError(f"{message}{joint}: {resume}") from exc
    raise exc
