"""The RTDE server (port 30004, protocol v2): recipes, data packages streamed each cycle to
every started connection through a bounded queue, input packages applied to the controller.
"""

from __future__ import annotations

import contextlib
import queue
import socket
import struct
import threading
from typing import Any

from .codec import INPUT_TYPES, OUTPUT_TYPES, TYPE_FORMATS, struct_for
from .constants import MAX_RECIPES, MAX_RTDE_PACKAGE, OUTPUT_QUEUE_PACKAGES
from .controller import Controller


class _OutputRecipe:
    def __init__(self, rid: int, names: list[str], decim: int, ctl: Controller) -> None:
        self.rid = rid
        self.names = names
        self.decim = decim
        types = [OUTPUT_TYPES[n] for n in names]
        self.struct = struct_for(types)
        self.getters = [ctl.getter(n) for n in names]
        self.vector = [TYPE_FORMATS[t][0].isdigit() for t in types]
        self.header = struct.pack(">HBB", 4 + self.struct.size, ord("U"), rid)

    def pack(self) -> bytes:
        vals: list[Any] = []
        for g, vec in zip(self.getters, self.vector, strict=True):
            v = g()
            if vec:
                vals.extend(v)
            else:
                vals.append(v)
        return self.header + self.struct.pack(*vals)


class RtdeConnection:
    """One RTDE client connection: served in its accept thread, with a bounded writer queue.

    Data packages that do not fit the queue (a client not reading, e.g. SIGSTOPped) are
    dropped and counted rather than buffered or allowed to block the controller.
    """

    def __init__(self, sock: socket.socket, ctl: Controller, server: RtdeServer) -> None:
        self.sock = sock
        self.ctl = ctl
        self.server = server
        self.outputs: list[_OutputRecipe] = []
        self.inputs: dict[int, tuple[list[str], struct.Struct, list[bool]]] = {}
        self.next_input_id = 1
        self.next_output_id = 1
        self.started = False
        self.closed = False
        self.queue: queue.Queue[bytes | None] = queue.Queue(maxsize=OUTPUT_QUEUE_PACKAGES)
        self.dropped = 0
        threading.Thread(target=self._writer, daemon=True).start()

    def publish(self, ctl: Controller) -> None:
        """Called by the controller each cycle; enqueue due data packages (drop if full)."""
        if not self.started or self.closed:
            return
        for rec in self.outputs:
            if ctl.cycle % rec.decim == 0:
                try:
                    self.queue.put_nowait(rec.pack())
                except queue.Full:
                    self.dropped += 1

    def _reply(self, ptype: str, payload: bytes) -> None:
        pkg = struct.pack(">HB", 3 + len(payload), ord(ptype)) + payload
        with contextlib.suppress(queue.Full):
            self.queue.put(pkg, timeout=1.0)

    def _writer(self) -> None:
        while True:
            pkg = self.queue.get()
            if pkg is None or self.closed:
                return
            try:
                self.sock.sendall(pkg)
            except OSError:
                self.close()
                return

    def _recv_exact(self, n: int) -> bytes | None:
        buf = b""
        while len(buf) < n:
            try:
                chunk = self.sock.recv(n - len(buf))
            except OSError:
                return None
            if not chunk:
                return None
            buf += chunk
        return buf

    def serve(self) -> None:
        """Read and handle packages until the connection ends (runs in the accept thread)."""
        try:
            while not self.closed:
                head = self._recv_exact(3)
                if head is None:
                    break
                size, ptype = struct.unpack(">HB", head)
                if size < 3 or size > MAX_RTDE_PACKAGE:
                    self.ctl.event("rtde_abuse", size=size)
                    break
                payload = self._recv_exact(size - 3) if size > 3 else b""
                if payload is None:
                    break
                if not self._handle(chr(ptype), payload):
                    break
        finally:
            self.close()

    def _handle(self, ptype: str, p: bytes) -> bool:
        ctl = self.ctl
        if ptype == "V":
            if len(p) != 2:
                return False
            (ver,) = struct.unpack(">H", p)
            self._reply("V", struct.pack(">B", 1 if ver == 2 else 0))
            return True
        if ptype == "v":
            self._reply("v", struct.pack(">IIII", *ctl.version))
            return True
        if ptype == "O":
            if len(p) < 8:
                return False
            (freq,) = struct.unpack(">d", p[:8])
            names = [n for n in p[8:].decode("ascii", "replace").split(",") if n]
            types = [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            ok = names and "NOT_FOUND" not in types and 0 < freq <= ctl.rate_hz
            rid = 0
            if self.next_output_id > MAX_RECIPES:
                ctl.event("rtde_abuse", reason="too_many_output_recipes")
                return False
            if ok:
                rid = self.next_output_id
                self.next_output_id += 1
                decim = max(1, round(ctl.rate_hz / freq))
                self.outputs.append(_OutputRecipe(rid, names, decim, ctl))
            ctl.event(
                "rtde_output_setup",
                frequency=freq,
                recipe=rid,
                fields=len(names),
                not_found="|".join(
                    n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"
                ),
            )
            self._reply("O", struct.pack(">B", rid) + ",".join(types).encode())
            return True
        if ptype == "I":
            names = [n for n in p.decode("ascii", "replace").split(",") if n]
            types = [INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            with ctl.lock:
                owners = self.server.owners
                for i, n in enumerate(names):
                    if types[i] != "NOT_FOUND" and owners.get(n, self) is not self:
                        types[i] = "IN_USE"
                ok = bool(names) and all(t not in ("NOT_FOUND", "IN_USE") for t in types)
                if ok:
                    for n in names:
                        owners[n] = self
            rid = 0
            if self.next_input_id > MAX_RECIPES:
                ctl.event("rtde_abuse", reason="too_many_input_recipes")
                return False
            if ok:
                rid = self.next_input_id
                self.next_input_id += 1
                real = [INPUT_TYPES[n] for n in names]
                self.inputs[rid] = (
                    names,
                    struct_for(real),
                    [TYPE_FORMATS[t][0].isdigit() for t in real],
                )
                ctl.event("rtde_input_setup", recipe=rid, fields="|".join(names))
            else:
                ctl.event("rtde_input_refused", types="|".join(types))
            self._reply("I", struct.pack(">B", rid) + ",".join(types).encode())
            return True
        if ptype == "S":
            self.started = True
            self._reply("S", b"\x01")
            return True
        if ptype == "P":
            self.started = False
            self._reply("P", b"\x01")
            return True
        if ptype == "U":
            if not p:
                return False
            rec = self.inputs.get(p[0])
            if rec is None:
                return True  # unknown recipe id: ignored, as the controller does
            names, st, vec = rec
            if len(p) - 1 != st.size:
                ctl.event("rtde_abuse", reason="input_size")
                return False
            flat = list(st.unpack(p[1:]))
            values: list[Any] = []
            for is_vec in vec:
                if is_vec:
                    values.append(tuple(flat[:6]))
                    del flat[:6]
                else:
                    values.append(flat.pop(0))
            ctl.apply_inputs(names, values)
            return True
        if ptype == "M":
            return True  # text message from client: ignored
        ctl.event("rtde_abuse", reason=f"type_{ord(ptype)}")
        return False

    def close(self) -> None:
        """Close the socket and release input ownership."""
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(OSError):
            self.sock.close()
        with contextlib.suppress(queue.Full):
            self.queue.put_nowait(None)
        with self.ctl.lock:
            owners = self.server.owners
            for n in [n for n, o in owners.items() if o is self]:
                del owners[n]
            if self in self.ctl.connections:
                self.ctl.connections.remove(self)
        self.ctl.event("rtde_disconnected", dropped=self.dropped)


class RtdeServer:
    """Accepts RTDE connections."""

    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        self.owners: dict[str, RtdeConnection] = {}

    def on_accept(self, sock: socket.socket) -> None:
        """Register a new connection and serve it until it closes."""
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = RtdeConnection(sock, self.ctl, self)
        with self.ctl.lock:
            self.ctl.connections.append(conn)
        self.ctl.event("rtde_connected")
        conn.serve()
