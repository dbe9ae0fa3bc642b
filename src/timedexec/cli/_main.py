"""The ``timedexec`` command: the parser built from the command table, and the map from
errors to exit codes.

Each command lives in its own module (``_simulate``, ``_train``, ...) exposing
``add_parser(sub)``; :data:`COMMANDS` lists them in the order ``--help`` shows. Results go
to stdout (or the file named), progress and status to stderr; :data:`EXIT_CODES_HELP` is
the documented contract of the exit codes and :func:`_exit_code` implements it.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Sequence

from timedexec._version import __version__
from timedexec.cli import (
    _calibrate,
    _check,
    _demo,
    _discrepancy,
    _evaluate,
    _extract,
    _fleet,
    _gyro,
    _monitor,
    _report,
    _ros,
    _serve,
    _simulate,
    _train,
)
from timedexec.cli._common import (
    EXIT_INTERRUPTED,
    JSON_CONVENTION,
    StdoutClosed,
    check_json_path,
)
from timedexec.errors import (
    ConfigError,
    DriverError,
    ModelError,
    ProtocolError,
    RecordingError,
    SensorError,
    TimedExecError,
)

__all__ = ["COMMANDS", "EXIT_CODES_HELP", "build_parser", "main"]

#: The subcommands, in the order of the workflow (and of ``timedexec --help``).
COMMANDS = (
    _simulate,
    _serve,
    _gyro,
    _calibrate,
    _check,
    _extract,
    _train,
    _evaluate,
    _discrepancy,
    _fleet,
    _monitor,
    _ros,
    _report,
    _demo,
)

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_BAD_INPUT = 2
EXIT_FAULT = 3
EXIT_STDOUT_CLOSED = 141  # 128 + SIGPIPE, as `yes | head` reports for `yes`

#: Error classes -> exit code; the first row that matches wins. Faults come first:
#: ``DriverTimeout`` is a ``TimeoutError`` and ``SensorError`` an ``OSError``, and a robot
#: that stops answering is not bad input.
EXIT_CODES: tuple[tuple[tuple[type[BaseException], ...], int], ...] = (
    ((DriverError, SensorError, ConnectionError, TimeoutError), EXIT_FAULT),
    (
        (
            ConfigError,
            RecordingError,
            ModelError,
            ProtocolError,
            FileNotFoundError,
            IsADirectoryError,
            NotADirectoryError,
            PermissionError,
        ),
        EXIT_BAD_INPUT,
    ),
    ((TimedExecError,), EXIT_FAILURE),
)

_REPORTED = tuple(cls for classes, _ in EXIT_CODES for cls in classes)

#: The exit codes as ``timedexec --help`` (and the README) state them.
EXIT_CODES_HELP = (
    "exit codes:\n"
    "  0    success\n"
    "  1    any other failure\n"
    "  2    bad input: an invalid option or value, a missing or unreadable file, a bad\n"
    "       recording, delay table, model bundle or protocol data in a file (ConfigError,\n"
    "       RecordingError, ModelError, ProtocolError); the message says how to fix it\n"
    "  3    robot, sensor or network fault: a driver error, a robot or gyro that stopped\n"
    "       answering, stale robot state, a lost connection (DriverError, DriverTimeout,\n"
    "       StaleStateError, SensorError, ConnectionError, TimeoutError)\n"
    "  130  interrupted (Ctrl-C); `serve` exits 0 on Ctrl-C or SIGTERM, its normal stop\n"
    "  141  stdout closed by its reader (`timedexec ... | head`): output stops quietly\n"
    "Errors are one line on stderr (`timedexec COMMAND: error: ...`); a traceback means a\n"
    "bug in timedexec (exit 1): please report it."
)

_EPILOG = (
    "workflow:\n"
    "  timedexec calibrate --robot-url ur://HOST --imu /dev/ttyUSB0 --trials N --out rec.h5\n"
    "      (or: timedexec simulate --robot ur10 --trials N --out rec.h5)\n"
    "  timedexec extract rec.h5 --out delays.csv\n"
    "  timedexec train delays.csv --out model/ --json cv.json\n"
    "  timedexec evaluate --robot ur10 --model model/\n"
    "  timedexec report rec.h5 delays.csv model/ --out report/\n\n"
    "output:\n"
    "  Results go to stdout (or the file named), progress and status to stderr.\n"
    f"  {JSON_CONVENTION}\n"
    "  Output files are written whole (a new file renamed into place). An output that is\n"
    "  one of the command's inputs or another output, or that is a symlink, device, FIFO or\n"
    "  folder, is refused before any work (exit 2); an existing regular file is replaced,\n"
    "  with a note on stderr (an existing recording only continues, with --resume).\n"
    "  --jobs above the CPU count is capped at it, with a warning.\n\n"
    f"{EXIT_CODES_HELP}\n\n"
    "`timedexec COMMAND --help` describes each command."
)


def build_parser() -> argparse.ArgumentParser:
    """The ``timedexec`` parser with one subcommand per module of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="timedexec",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_EPILOG,
        description=(
            "Measure, model and compensate the actuation and response delays of industrial "
            "robot arms. Every command runs on the embedded simulated robots when no robot "
            "is attached."
        ),
    )
    parser.add_argument("--version", action="version", version=f"timedexec {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``timedexec`` command line.

    Parameters
    ----------
    argv : sequence of str, optional
        The arguments after the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        The exit code, as :data:`EXIT_CODES_HELP` documents it. Errors of timedexec (and
        the faults and file errors it names) are reported as one line on stderr; any other
        exception is a bug and propagates with its traceback.
    """
    parser = build_parser()
    command: str | None = None
    try:
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help, --version, or a usage error argparse reported
            code = _system_exit_code(exc)
        else:
            command = args.command
            if command is None:
                parser.print_help(sys.stderr)
                code = EXIT_BAD_INPUT
            else:
                check_json_path(args)
                code = int(args.func(args))
        sys.stdout.flush()  # a closed pipe shows here when the output fitted in the buffer
        return code
    except KeyboardInterrupt:
        _say(command, "interrupted")
        return EXIT_INTERRUPTED
    except StdoutClosed:
        return _stdout_closed()
    except BrokenPipeError as exc:
        # Only `out` writes stdout, so this is a socket, unless stdout itself is gone.
        if _stdout_is_broken():
            return _stdout_closed()
        return _fail(command, exc)
    except _REPORTED as exc:
        return _fail(command, exc)


def _exit_code(exc: BaseException) -> int:
    for classes, code in EXIT_CODES:
        if isinstance(exc, classes):
            return code
    return EXIT_FAILURE


def _fail(command: str | None, exc: BaseException) -> int:
    if isinstance(exc, OSError) and not isinstance(exc, TimedExecError) and exc.filename:
        message = f"{exc.filename}: {exc.strerror or exc}"
    else:
        message = str(exc) or type(exc).__name__
    _say(command, f"error: {message}")
    return _exit_code(exc)


def _say(command: str | None, message: str) -> None:
    """One line on stderr, prefixed with the command; a closed stderr is ignored."""
    prefix = "timedexec" if command is None else f"timedexec {command}"
    with contextlib.suppress(OSError, ValueError):
        print(f"{prefix}: {message}", file=sys.stderr, flush=True)


def _system_exit_code(exc: SystemExit) -> int:
    if exc.code is None:
        return EXIT_OK
    return exc.code if isinstance(exc.code, int) else EXIT_FAILURE


def _stdout_is_broken() -> bool:
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        return True
    except (OSError, ValueError):
        return False
    return False


def _stdout_closed() -> int:
    """Exit quietly after stdout's reader went away.

    Python's own idiom: point the stdout descriptor at devnull, so the interpreter's final
    flush of what is still buffered cannot fail with a second BrokenPipeError.
    """
    with contextlib.suppress(AttributeError, OSError, ValueError):
        fd = sys.stdout.fileno()
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, fd)
        finally:
            os.close(devnull)
    return EXIT_STDOUT_CLOSED
