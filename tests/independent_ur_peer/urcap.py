"""The External Control URCap: the script request to the PC, splitting the fetched text at its
markers, and recognising ur_rtde's control script in it.
"""

from __future__ import annotations

import contextlib
import re
import socket
import time

from .constants import (
    HEADER_BEGIN,
    HEADER_END,
    LOOP_BEGINS,
    LOOP_ENDS,
    MAX_URCAP_LINE,
    MAX_URCAP_SCRIPT,
    URCAP_CONNECT_TIMEOUT_S,
    URCAP_FETCH_TIMEOUT_S,
    URCAP_REQUEST,
)

_MARKERS = (HEADER_BEGIN, HEADER_END, LOOP_BEGINS, LOOP_ENDS)


def _marker_positions(lines: list[str]) -> list[tuple[str, int]]:
    """(marker, line index) of every marker line; a marker stands alone on its line, blanks
    around it allowed (as the URCap's own match of these lines)."""
    return [(ln.strip(), i) for i, ln in enumerate(lines) if ln.strip() in _MARKERS]


def split_external_control(text: str) -> tuple[str, str] | None:
    """Split a fetched script into (header, control loop), the parts the URCap inserts once and
    at its node. None unless the four markers appear once each, in their order."""
    lines = text.split("\n")
    found = _marker_positions(lines)
    if [m for m, _ in found] != list(_MARKERS):
        return None
    (_, hb), (_, he), (_, lb), (_, le) = found
    return "\n".join(lines[hb + 1 : he]), "\n".join(lines[lb + 1 : le])


def _defines(text: str, name: str) -> bool:
    return re.search(rf"^[ \t]*def[ \t]+{name}[ \t]*\(", text, re.M) is not None


def _calls(text: str, name: str) -> bool:
    return re.search(rf"\b{name}[ \t]*\(", text) is not None


def is_rtde_control_script(text: str) -> bool:
    """Whether ``text`` is ur_rtde's control script, run here with its semantics.

    Uploaded on port 30003 it is ``def rtde_control(): ... end`` and is recognised, as it always
    was here, by that name. Fetched by the External Control URCap it has no ``def`` of its own
    and no such name: then the marked parts must show the script's protocol, a header defining
    ``rtde_cmd`` (reads the command register), ``signal_ready`` and ``process_cmd``, and a
    control loop that reads commands and hands them to ``process_cmd``.
    """
    if "rtde_control" in text:
        return True
    parts = split_external_control(text)
    if parts is None:
        return False
    header, loop = parts
    if not all(_defines(header, f) for f in ("rtde_cmd", "signal_ready", "process_cmd")):
        return False
    return _calls(loop, "rtde_cmd") and _calls(loop, "process_cmd")


def register_offset(text: str, kind: str) -> int:
    """``reg_offset_<kind>`` (``int`` or ``float``) assigned in the script; 0 when absent.

    ur_rtde 1.6.5 writes ``global reg_offset_int = # int register offset``, a newline, then the
    value (followed on that line by the next statement): the value may follow the ``=`` directly
    or after a comment that runs to the end of the line. ``==`` comparisons are not assignments.
    """
    m = re.search(rf"\breg_offset_{kind}[ \t]*=(?!=)[ \t]*(?:#[^\n]*)?\n?[ \t]*(\d+)", text)
    return int(m.group(1)) if m else 0


def _open_part(text: str) -> bool:
    """Whether a marked part of ``text`` was begun and not ended (or a marker is out of order)."""
    seq = [m for m, _ in _marker_positions(text.split("\n"))]
    closed = ([], [HEADER_BEGIN, HEADER_END], [LOOP_BEGINS, LOOP_ENDS], list(_MARKERS))
    return seq not in closed


def fetch_urcap_script(
    addr: tuple[str, int], timeout_s: float = URCAP_FETCH_TIMEOUT_S
) -> tuple[str | None, str]:
    """Request the script as the External Control URCap does; return ``(text, "ok")`` or
    ``(None, reason)``.

    Connect to the PC at ``addr`` (at most ``URCAP_CONNECT_TIMEOUT_S``), send
    ``request_program``, read lines until the ``# NODE_CONTROL_LOOP_ENDS`` line, or until the PC
    closes the connection with no marked part left open. The whole exchange is bounded by
    ``timeout_s`` (s), a line by ``MAX_URCAP_LINE`` and the text by ``MAX_URCAP_SCRIPT`` bytes.
    The connection is closed afterwards (the URCap closes its socket too).
    """
    deadline = time.monotonic() + timeout_s
    try:
        sock = socket.create_connection(addr, timeout=min(URCAP_CONNECT_TIMEOUT_S, timeout_s))
    except OSError as exc:
        return None, f"connect_failed:{type(exc).__name__}"
    lines: list[str] = []
    pending = b""
    total = 0
    try:
        sock.sendall(URCAP_REQUEST)
        while True:
            start = 0
            while (end := pending.find(b"\n", start)) >= 0:
                if end - start > MAX_URCAP_LINE:
                    return None, "line_too_long"
                line = pending[start:end].decode("utf-8", "replace").rstrip("\r")
                start = end + 1
                lines.append(line)
                if line.strip() == LOOP_ENDS:
                    text = "\n".join(lines) + "\n"
                    return (None, "incomplete") if _open_part(text) else (text, "ok")
            pending = pending[start:]
            if len(pending) > MAX_URCAP_LINE:
                return None, "line_too_long"
            left = deadline - time.monotonic()
            if left <= 0:
                return None, "timeout"
            sock.settimeout(left)
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                return None, "timeout"
            if not chunk:  # the PC closed the connection
                if pending:
                    lines.append(pending.decode("utf-8", "replace").rstrip("\r"))
                text = "\n".join(lines) + "\n"
                if not text.strip():
                    return None, "empty"
                return (None, "incomplete") if _open_part(text) else (text, "ok")
            total += len(chunk)
            if total > MAX_URCAP_SCRIPT:
                return None, "too_large"
            pending += chunk
    except OSError as exc:
        return None, f"connection_error:{type(exc).__name__}"
    finally:
        with contextlib.suppress(OSError):
            sock.close()
