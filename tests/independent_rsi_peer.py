"""A minimal KUKA RSI robot side for tests, written from KUKA's documented behaviour only.

Independent of ``timedexec.twins`` and ``timedexec._rsi_xml`` (its own XML in and out),
so that the driver is also tested against something that did not grow up with it. What it
does, from the RSI documentation (Ethernet RSI XML, KSS 8.x):

* it is the UDP *client*: every cycle (12 ms ``#IPO``, 4 ms ``#IPO_FAST``) it sends a
  ``<Rob TYPE="KUKA">`` frame with ``AIPos``/``ASPos`` (degrees), ``<Delay D="n"/>`` (its
  late counter) and ``<IPOC>`` (a time stamp advancing by ``ipoc_step`` per frame) from its
  own source port to the PC's port, whether or not the PC answered;
* an answer counts only if it echoes the IPOC of the latest frame and arrives before the
  next frame leaves; otherwise the cycle is late and the counter goes up (answers echoing an
  older IPOC are late, never applied); when the counter reaches ``timeout_packets`` RSI stops
  ("RSITimeout") and no frame is sent any more;
* the first frame leaves ``first_frame_delay_s`` after start (a robot program takes a
  while to reach ``RSI_ON``).

It moves nothing but numbers (``AIPos`` at ``q_deg``, or advancing at a constant
``qd_deg_s``, whatever the answers say): it is a protocol peer, not a simulator. Usable as a spoofer too: a peer bound to another source
address sending plausible frames to the same port.
"""

from __future__ import annotations

import contextlib
import math
import re
import socket
import threading
import time
from collections.abc import Sequence

_SEN_IPOC = re.compile(rb"<IPOC>\s*(\d+)\s*</IPOC>")


def rob_frame(ipoc: int, q_deg: Sequence[float], delay: int) -> bytes:
    """A ``<Rob>`` frame as KSS sends it (axes in degrees)."""
    axes = " ".join(f'A{i + 1}="{v:.4f}"' for i, v in enumerate(q_deg))
    return (
        f'<Rob TYPE="KUKA"><RIst X="0.0" Y="0.0" Z="0.0" A="0.0" B="0.0" C="0.0"/>'
        f'<AIPos {axes}/><ASPos {axes}/><Delay D="{delay}"/><IPOC>{ipoc}</IPOC></Rob>'
    ).encode("ascii")


class IndependentRSIPeer:
    """A robot controller's RSI side on a thread (context manager).

    Parameters
    ----------
    pc_address : (str, int)
        The PC's RSI address (where the driver listens).
    period_s : float
        Cycle, s.
    ipoc_start, ipoc_step : int
        First IPOC and its advance per frame (12 at 12 ms on a KR C4: milliseconds; 1 on
        a KR C2 counting frames).
    first_frame_delay_s : float
        Wait before the first frame, s.
    source_host : str
        Address to send from (a loopback alias such as 127.0.0.2 plays another machine).
    timeout_packets : int
        Late cycles after which RSI stops.
    q_deg : sequence of 6 float
        The axis angles reported, degrees.
    qd_deg_s : sequence of 6 float or None
        Constant axis speeds, deg/s: frame k reports ``q_deg + qd_deg_s * k * period_s``
        (None: still).
    max_frames : int or None
        Stop after this many frames (None: run until closed or timed out).
    """

    def __init__(
        self,
        pc_address: tuple[str, int],
        *,
        period_s: float = 0.012,
        ipoc_start: int = 400_000_000,
        ipoc_step: int = 12,
        first_frame_delay_s: float = 0.0,
        source_host: str = "127.0.0.1",
        timeout_packets: int = 100,
        q_deg: Sequence[float] = (0.0, -68.75, 80.21, 0.0, 34.38, 0.0),
        qd_deg_s: Sequence[float] | None = None,
        max_frames: int | None = None,
    ) -> None:
        self.pc_address = pc_address
        self.period_s = period_s
        self.ipoc_start = ipoc_start
        self.ipoc_step = ipoc_step
        self.first_frame_delay_s = first_frame_delay_s
        self.timeout_packets = timeout_packets
        self.q_deg = list(q_deg)
        self.qd_deg_s = [0.0] * 6 if qd_deg_s is None else list(qd_deg_s)
        self.max_frames = max_frames
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((source_host, 0))
        self.sock.settimeout(0.0005)
        self.address: tuple[str, int] = self.sock.getsockname()
        self.frames_sent = 0
        self.late = 0
        self.answers_in_time = 0
        self.answers_stale = 0
        self.answers_total = 0
        self.reason = "running"
        self.first_frame_host_s = math.nan
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="independent-rsi-peer", daemon=True)

    def __enter__(self) -> IndependentRSIPeer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop sending and release the socket."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self.sock.close()
        if self.reason == "running":
            self.reason = "stopped"

    def _run(self) -> None:
        if self._stop.wait(self.first_frame_delay_s):
            return
        start = time.monotonic()
        ipoc = self.ipoc_start
        latest = -1  # IPOC of the latest frame sent
        answered = True  # the latest frame has its answer
        k = 0
        while not self._stop.is_set():
            due = start + k * self.period_s
            # Until this cycle's frame is due, take answers.
            while True:
                now = time.monotonic()
                if now >= due:
                    break
                try:
                    self.sock.settimeout(max(1e-4, due - now))
                    data = self.sock.recv(4096)
                except (TimeoutError, BlockingIOError):
                    continue
                except OSError:
                    time.sleep(min(0.001, max(0.0, due - now)))
                    continue
                self.answers_total += 1
                m = _SEN_IPOC.search(data)
                echo = int(m.group(1)) if m else -1
                if echo == latest and not answered:
                    answered = True
                    self.answers_in_time += 1
                else:
                    self.answers_stale += 1  # an older IPOC (or a repeat): not taken
            if latest >= 0 and not answered:
                self.late += 1
                if self.late >= self.timeout_packets:
                    self.reason = "RSITimeout"
                    return
            if self.max_frames is not None and self.frames_sent >= self.max_frames:
                self.reason = "done"
                return
            with contextlib.suppress(OSError):  # nobody listening yet: the cycle counts late
                q = [
                    q0 + v * k * self.period_s
                    for q0, v in zip(self.q_deg, self.qd_deg_s, strict=True)
                ]
                self.sock.sendto(rob_frame(ipoc, q, self.late), self.pc_address)
            if self.frames_sent == 0:
                self.first_frame_host_s = time.monotonic()
            self.frames_sent += 1
            latest, answered = ipoc, False
            ipoc += self.ipoc_step
            k += 1


def main(argv: Sequence[str] | None = None) -> int:
    """Run a peer from the command line (in its own process, as another machine would);
    print ``frames_sent answers_total late reason`` when it ends."""
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--port", type=int, required=True, help="the PC's RSI port")
    p.add_argument("--pc", default="127.0.0.1", help="the PC's address")
    p.add_argument("--source-host", default="127.0.0.1", help="address to send from")
    p.add_argument("--delay", type=float, default=0.0, help="first-frame delay, s")
    p.add_argument("--frames", type=int, required=True, help="frames to send")
    p.add_argument("--period", type=float, default=0.012, help="cycle, s")
    p.add_argument("--q-deg", type=float, nargs=6, default=None, help="AIPos, degrees")
    args = p.parse_args(argv)
    kwargs = {} if args.q_deg is None else {"q_deg": args.q_deg}
    peer = IndependentRSIPeer(
        (args.pc, args.port),
        period_s=args.period,
        first_frame_delay_s=args.delay,
        source_host=args.source_host,
        max_frames=args.frames,
        timeout_packets=10**9,  # a spoofer expects no answers
        **kwargs,
    )
    print(f"{peer.address[0]}:{peer.address[1]}", flush=True)
    with peer:
        peer._thread.join()
    print(peer.frames_sent, peer.answers_total, peer.late, peer.reason, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
