"""The pendant's programs as the UR twin's dashboard server sees them: ``load``, ``play``,
``pause``, ``stop``, ``programState``, ``get loaded program`` and the External Control URCap.

A real cell often runs ``ur_rtde`` without remote control: the pendant plays a program
(``.urp``) holding the **External Control** node of Universal Robots' URCap. When that
program starts, the node connects to the PC configured in the installation (port 50002 by
default), sends ``request_program\\n`` and runs the script the PC answers with; ``ur_rtde``
serves it with ``RTDEControlInterface(..., flags=FLAG_USE_EXT_UR_CAP, ur_cap_port=50002)``
and waits until the program runs. The twin has one such program installed,
:data:`EXTERNAL_CONTROL_URP`; ``load`` of any other path answers ``File not found``.

The replies follow the dashboard server's documentation (PolyScope 3.4+ / 5.x, "Dashboard
Server, port 29999"): ``Loading program: <path>`` / ``File not found: <path>``,
``Starting program`` / ``Failed to execute: play`` (no program loaded, or the program fails
to start: here the URCap cannot fetch its script), ``Pausing program`` / ``Failed to
execute: pause``, ``Loaded program: <path>`` / ``No program loaded``, ``programState`` as
``<STATE> <program>``. Not emulated: a paused program resumes by fetching its script again
(a real one continues where it paused); any other ``.urp`` file.
"""

from __future__ import annotations

import posixpath
import socket
import time
from collections.abc import Callable

from timedexec.errors import ProtocolError
from timedexec.twins._urscript import (
    SCRIPT_MAX_LINE_BYTES,
    SCRIPT_MAX_PROGRAM_BYTES,
    _LineReader,
)

__all__ = [
    "EXTERNAL_CONTROL_PORT",
    "EXTERNAL_CONTROL_URP",
    "ProgramStore",
    "fetch_external_control_script",
]

#: The one program installed on the twin's pendant: a program whose only node is the
#: External Control URCap's.
EXTERNAL_CONTROL_URP = "/programs/external_control.urp"
#: Port the External Control URCap asks for its script (its installation default, and
#: ``ur_rtde``'s ``ur_cap_port`` default).
EXTERNAL_CONTROL_PORT = 50002
#: How long the URCap waits for the PC's script before the program fails to start, s.
FETCH_TIMEOUT_S = 5.0
#: The line that closes the script the PC sends (the URCap's control-loop marker).
_LOOP_END = "# NODE_CONTROL_LOOP_ENDS"


def fetch_external_control_script(host: str, port: int, timeout_s: float = FETCH_TIMEOUT_S) -> str:
    """What the External Control node does when its program starts: connect to
    ``host:port``, send ``request_program\\n`` and read the script the PC sends.

    The URCap splits the script at its markers (``# HEADER_BEGIN`` ... ``# HEADER_END``,
    ``# NODE_CONTROL_LOOP_BEGINS`` ... ``# NODE_CONTROL_LOOP_ENDS``): the script is complete
    at the closing marker (``ur_rtde`` keeps the connection open after it) or when the PC
    closes the connection.

    Raises
    ------
    ProtocolError
        Nobody listens, the PC sends no complete script within ``timeout_s``, or a line or
        the script is longer than the script port's limits.
    """
    deadline = time.monotonic() + timeout_s
    lines_in = _LineReader(SCRIPT_MAX_LINE_BYTES, "External Control")
    lines: list[str] = []
    size = 0
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.sendall(b"request_program\n")
            while True:
                sock.settimeout(max(deadline - time.monotonic(), 0.001))
                chunk = sock.recv(65536)
                if not chunk:
                    if lines:
                        return "\n".join(lines)
                    raise ProtocolError(f"{host}:{port} closed without sending a script")
                for line in lines_in.feed(chunk):
                    lines.append(line)
                    size += len(line) + 1
                    if size > SCRIPT_MAX_PROGRAM_BYTES:
                        raise ProtocolError(
                            f"{host}:{port} sent more than {SCRIPT_MAX_PROGRAM_BYTES} bytes "
                            f"without {_LOOP_END!r}"
                        )
                    if line.strip() == _LOOP_END:
                        return "\n".join(lines)
    except TimeoutError as exc:
        raise ProtocolError(
            f"no complete script from {host}:{port} within {timeout_s} s (it must end with "
            f"{_LOOP_END!r} or close the connection)"
        ) from exc
    except OSError as exc:
        raise ProtocolError(f"cannot fetch the script from {host}:{port} ({exc})") from exc


class ProgramStore:
    """The loaded program and the dashboard commands that act on programs.

    Parameters
    ----------
    external_control : (host, port)
        Where the installed program's External Control node asks for its script.
    start_program : callable
        Runs a script as the controller program (the server's script-upload path).
    request_stop : callable
        Asks the control loop to stop the running program.
    log : callable
        The twin's log.
    """

    def __init__(
        self,
        external_control: tuple[str, int],
        *,
        start_program: Callable[[str], None],
        request_stop: Callable[[], None],
        log: Callable[[str], None],
    ) -> None:
        self.external_control = (str(external_control[0]), int(external_control[1]))
        self._start_program = start_program
        self._request_stop = request_stop
        self._log = log
        #: Path of the loaded program (None: none loaded).
        self.loaded: str | None = None
        #: Whether the program that runs (or ran last) was started from :attr:`loaded`;
        #: False after a script upload on port 30003 replaced it.
        self.from_loaded = False
        self.paused = False

    def script_uploaded(self) -> None:
        """A script came in on port 30003: it replaces the program (as on a controller)."""
        self.from_loaded = False
        self.paused = False

    def reply(self, command: str, playing: bool) -> str | None:
        """The answer to a program command, or None if ``command`` is not one."""
        low = command.lower()
        if low.startswith("load "):
            return self._load(command[5:].strip())
        if low == "play":
            return self._play(playing)
        if low == "pause":
            if not playing:
                return "Failed to execute: pause"
            self.paused = True
            self._request_stop()
            return "Pausing program"
        if low == "stop":
            self.paused = False
            self._request_stop()
            return "Stopped"
        if low == "get loaded program":
            return "No program loaded" if self.loaded is None else f"Loaded program: {self.loaded}"
        if low == "programstate":
            return f"{self._state(playing)} {self._name(playing)}"
        if low == "isprogramsaved":
            return f"true {self._name(playing)}" if self.loaded else "false <unnamed>"
        return None

    def _state(self, playing: bool) -> str:
        if playing:
            return "PLAYING"
        return "PAUSED" if self.paused else "STOPPED"

    def _name(self, playing: bool) -> str:
        if (self.from_loaded or not playing) and self.loaded is not None:
            return posixpath.basename(self.loaded)
        return "rtde_control" if playing else "<unnamed>"

    def _load(self, path: str) -> str:
        if posixpath.normpath(path) != EXTERNAL_CONTROL_URP:
            return f"File not found: {path}"
        self.loaded = EXTERNAL_CONTROL_URP
        self.from_loaded = False
        self.paused = False
        return f"Loading program: {path}"

    def _play(self, playing: bool) -> str:
        if self.loaded is None:
            return "Failed to execute: play"
        if playing and self.from_loaded:
            return "Starting program"
        host, port = self.external_control
        try:
            script = fetch_external_control_script(host, port)
        except ProtocolError as exc:
            # The URCap shows a popup and the program does not start.
            self._log(f"External Control: {exc}; the program does not start")
            return "Failed to execute: play"
        self._start_program(script)
        self.from_loaded = True
        self.paused = False
        return "Starting program"
