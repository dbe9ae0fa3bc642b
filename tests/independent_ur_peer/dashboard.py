"""The dashboard server (port 29999): one reply per command line, as PolyScope 3.x / 5.x words
them.
"""

from __future__ import annotations

import contextlib
import posixpath
import socket

from .constants import MAX_DASHBOARD_LINE, PAUSED, PLAYING, SAFETY_NORMAL, STOPPED
from .controller import Controller
from .physics import StopMotion

_STATE_NAMES = {STOPPED: "STOPPED", PLAYING: "PLAYING", PAUSED: "PAUSED"}


def _dashboard_reply(ctl: Controller, line: str) -> str | None:
    """Answer one dashboard command; None closes the connection."""
    cmd = line.strip()
    low = cmd.lower()
    major, minor, bugfix, build = ctl.version
    if low == "polyscopeversion":
        return f"URSoftware {major}.{minor}.{bugfix}.{build} (Jan 01 2024)"
    if low == "version":
        return f"Version: {major}.{minor}.{bugfix}.{build}"
    if low == "get serial number":
        return "20215500" + f"{sum(map(ord, ctl.model)) % 10000:04d}"
    if low == "get robot model":
        return ctl.model.rstrip("eE")
    if low == "robotmode":
        return "Robotmode: RUNNING"
    if low == "safetymode":
        return "Safetymode: " + (
            "NORMAL" if ctl.safety_mode == SAFETY_NORMAL else "PROTECTIVE_STOP"
        )
    if low == "safetystatus":
        return "Safetystatus: " + (
            "NORMAL" if ctl.safety_mode == SAFETY_NORMAL else "PROTECTIVE_STOP"
        )
    if low == "programstate":
        name = posixpath.basename(ctl.loaded_urp) if ctl.loaded_urp else "<unnamed>"
        return f"{_STATE_NAMES[ctl.runtime_state]} {name}"
    if low == "running":
        return "Program running: " + ("true" if ctl.runtime_state == PLAYING else "false")
    if low == "is in remote control":
        return "true"
    if low == "get loaded program":
        return f"Loaded program: {ctl.loaded_urp}" if ctl.loaded_urp else "No program loaded"
    if low.startswith("load "):
        with ctl.dashboard_lock:
            return ctl.load_urp(cmd[5:].strip())
    if low == "stop":
        if ctl.runtime_state == STOPPED:
            return "Failed to execute: stop"
        ctl.program_stop("dashboard")
        return "Stopped"
    if low == "pause":
        if ctl.runtime_state != PLAYING:
            return "Failed to execute: pause"
        ctl.runtime_state = PAUSED
        ctl.arm.motion = StopMotion(ctl.stop_decel)
        return "Pausing program"
    if low == "play" and ctl.loaded_urp is not None:
        with ctl.dashboard_lock:
            return "Starting program" if ctl.play_urp() else "Failed to execute: play"
    if low == "play":
        if ctl.program_text is None:
            return "Failed to execute: play"
        ctl.load_program(ctl.program_text)
        return "Starting program"
    if low == "power on":
        return "Powering on"
    if low == "power off":
        return "Powering off"
    if low == "brake release":
        return "Brake releasing"
    if low == "unlock protective stop":
        ctl.safety_mode = SAFETY_NORMAL
        return "Protective stop releasing"
    if low == "close popup":
        return "closing popup"
    if low == "close safety popup":
        return "closing safety popup"
    if low == "quit":
        return None
    return f"could not understand: '{cmd}'"


def serve_dashboard(sock: socket.socket, ctl: Controller) -> None:
    buf = b""
    try:
        sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
        while not ctl.stop_event.is_set():
            chunk = sock.recv(4096)
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                reply = _dashboard_reply(ctl, raw.decode("utf-8", "replace"))
                if reply is None:
                    sock.sendall(b"Disconnected\n")
                    return
                sock.sendall(reply.encode() + b"\n")
            if len(buf) > MAX_DASHBOARD_LINE:
                ctl.event("dashboard_abuse", buffered=len(buf))
                return
    except OSError:
        return
    finally:
        with contextlib.suppress(OSError):
            sock.close()
