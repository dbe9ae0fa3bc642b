"""A robot side of KUKA RSI that starts RSI at its own pose, as the public
``kuka_rsi_simulator`` (ROS-Industrial's ``kuka_experimental``) does, ported without ROS.

Written from that simulator's documented behaviour, independent of ``timedexec.twins`` and
``timedexec._rsi_xml`` (its own XML in and out):

* **its own start pose**: RSI starts wherever the arm stands (default A1..A6 = 0, -90, 90,
  0, 90, 0 degrees, the simulator's), not where a sweep would like it;
* **lock-step**: it sends a ``<Rob>`` frame (``AIPos`` the arm's pose, ``ASPos`` the start
  pose, ``<Delay D>`` its late counter, ``<IPOC>``) and waits for the answer, up to
  **1 s** (the simulator's socket timeout); a missing answer counts one late cycle and the
  arm holds. Unlike the simulator (which sleeps half a cycle after each answer, so its
  frames come at whatever rate the answers allow) the next frame leaves on the cycle's
  clock, so that the driver's IPOC/host-period check sees the configured period;
* **absolute corrections from the start pose**: ``AK`` A1..A6 (degrees) is the total
  offset from the start pose; the arm's pose is start + correction, applied when the
  answer arrives and the arm moves there linearly over the cycle after the next frame
  leaves (a cycle of pipeline; it holds while it waits for an answer); each frame reports
  where the arm is when it leaves.
  There are no correction limits here: a controller's AXISCORR limits are the driver's
  ``max_correction_deg`` to respect.

It also gives a flange gyro's true rate (:meth:`LockStepRSIPeer.rate_source`, for
``timedexec.twins.GyroTwin``): ``joint_axis_in_tool(q) · qd`` of that piecewise-linear
motion.
"""

from __future__ import annotations

import bisect
import re
import socket
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np

from timedexec.robots import get_robot, joint_axis_in_tool

_AK = re.compile(rb"<AK\s([^>]*)/?>")
_ATTR = re.compile(rb'(A[1-6])\s*=\s*"([^"]*)"')
_IPOC = re.compile(rb"<IPOC>\s*(\d+)\s*</IPOC>")

#: The simulator's start pose, degrees.
SIMULATOR_START_DEG = (0.0, -90.0, 90.0, 0.0, 90.0, 0.0)


class LockStepRSIPeer:
    """The robot's RSI side on a thread (context manager).

    Parameters
    ----------
    pc_address : (str, int)
        Where the driver listens.
    start_deg : sequence of 6 float
        The pose at RSI start, degrees.
    period_s : float
        Cycle, s (12 ms: ``#IPO``).
    answer_timeout_s : float
        How long each frame waits for its answer, s (the simulator's 1 s).
    timeout_packets : int
        Late cycles after which RSI stops (no frame any more).
    robot : str
        Robot spec for the gyro's kinematics.
    first_frame_delay_s : float
        Wait before the first frame, s (a robot program reaches ``RSI_ON`` a while after
        the PC listens; a frame sent before is lost and waits out the answer timeout).
    wait_for_listener : bool
        Send the first frame only once a UDP socket is bound to the PC's port (Linux,
        ``/proc/net/udp``): the cell's order, PC first, whatever the test's timing.
    """

    def __init__(
        self,
        pc_address: tuple[str, int],
        *,
        start_deg: Sequence[float] = SIMULATOR_START_DEG,
        period_s: float = 0.012,
        answer_timeout_s: float = 1.0,
        timeout_packets: int = 100,
        robot: str = "kr5",
        first_frame_delay_s: float = 0.0,
        wait_for_listener: bool = False,
    ) -> None:
        self.first_frame_delay_s = float(first_frame_delay_s)
        self.wait_for_listener = wait_for_listener
        self.pc_address = pc_address
        self.start_deg = np.asarray(start_deg, dtype=float)
        self.period_s = float(period_s)
        self.answer_timeout_s = float(answer_timeout_s)
        self.timeout_packets = int(timeout_packets)
        self.spec = get_robot(robot)
        self.late = 0
        self.frames = 0
        self.stopped_reason: str | None = None
        self._ipoc = 500_000_000
        self._lock = threading.Lock()
        # (host time, pose in rad) at each applied answer: the arm reaches pose k at t_k
        self._t: list[float] = []
        self._q: list[np.ndarray] = []
        self._stop = threading.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(self.answer_timeout_s)
        self._thread = threading.Thread(target=self._run, name="lockstep-rsi-peer", daemon=True)

    def __enter__(self) -> LockStepRSIPeer:
        q0 = np.radians(self.start_deg)
        self._t, self._q = [time.monotonic()], [q0]
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=3 * self.answer_timeout_s)
        self._sock.close()

    # ------------------------------------------------------------------ the arm
    def pose_deg(self, at_s: float | None = None) -> np.ndarray:
        """The arm's pose at host time ``at_s`` (default now), degrees."""
        when = time.monotonic() if at_s is None else at_s
        with self._lock:
            t, q = self._t, self._q
            n = bisect.bisect_right(t, when)  # pose n-1 reached at or before `when`
            if n >= len(t):
                return np.degrees(q[-1])
            frac = min(1.0, max(0.0, 1.0 - (t[n] - when) / self.period_s))
            return np.degrees(q[n - 1] + frac * (q[n] - q[n - 1]))

    def rate_source(self, gyro_start_s: Callable[[], float]):  # type: ignore[no-untyped-def]
        """``rate_source(t0, t1)`` for a gyro whose time 0 is host time ``gyro_start_s()``:
        the flange's rate over the sample times, rad/s, (k, 3), one value per 0.125 ms."""

        def rates(t0: float, t1: float) -> np.ndarray:
            k = max(1, round((t1 - t0) * 8000))
            ts = gyro_start_s() + t0 + np.arange(k) * ((t1 - t0) / k)
            with self._lock:
                t, q = np.asarray(self._t), np.asarray(self._q)
            if len(t) < 2:  # RSI not started yet: the flange is still (no pose to index)
                return np.zeros((k, 3))
            # pose n is reached at t[n], moving from pose n-1 over the cycle before it (an
            # arm waiting for an answer holds)
            n = np.searchsorted(t, ts, side="right")
            m = np.clip(n, 1, len(t) - 1)
            moving = (n > 0) & (n < len(t)) & (ts >= t[m] - self.period_s)
            if not moving.any():
                return np.zeros((k, 3))
            qd = np.where(moving[:, None], (q[m] - q[m - 1]) / self.period_s, 0.0)  # (k, 6)
            # the axes barely turn within a burst (1 ms): at the burst's middle pose
            i = k // 2
            q_mid = q[m[i] - 1] + qd[i] * (ts[i] - (t[m[i]] - self.period_s))
            axes = joint_axis_in_tool(self.spec, q_mid, np.arange(1, 7))  # (6, 3)
            return qd @ axes

        return rates

    # ------------------------------------------------------------------ the protocol
    def _frame(self, q_deg: np.ndarray) -> bytes:
        def axes(v: np.ndarray) -> str:
            return " ".join(f'A{i + 1}="{x:.4f}"' for i, x in enumerate(v))

        return (
            f'<Rob TYPE="KUKA"><RIst X="0.0" Y="0.0" Z="0.0" A="0.0" B="0.0" C="0.0"/>'
            f"<AIPos {axes(q_deg)}/><ASPos {axes(self.start_deg)}/>"
            f'<Delay D="{self.late}"/><IPOC>{self._ipoc}</IPOC></Rob>'
        ).encode("ascii")

    def _run(self) -> None:
        step_ms = round(self.period_s * 1000)
        if self._stop.wait(self.first_frame_delay_s):
            return
        while self.wait_for_listener and not _udp_port_bound(self.pc_address[1]):
            if self._stop.wait(0.002):
                return
        next_s = time.monotonic()
        while not self._stop.is_set():
            q_deg = self.pose_deg()
            self._sock.sendto(self._frame(q_deg), self.pc_address)
            self.frames += 1
            corr = self._answer()
            if corr is None:
                self.late += 1
                if self.late >= self.timeout_packets:
                    self.stopped_reason = "RSITimeout"
                    return
            else:
                q_new = np.radians(self.start_deg + corr)
                with self._lock:  # reached two cycles on: well before the gyro asks
                    self._t.append(max(time.monotonic() + 2 * self.period_s,
                                       self._t[-1] + self.period_s))
                    self._q.append(q_new)
            self._ipoc += step_ms
            next_s += self.period_s
            wait = next_s - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            else:
                next_s = time.monotonic()  # an answer waited for: the cycle clock restarts

    def _answer(self) -> np.ndarray | None:
        """The absolute correction (degrees) of the answer echoing this frame's IPOC."""
        deadline = time.monotonic() + self.answer_timeout_s
        while True:
            self._sock.settimeout(max(1e-3, deadline - time.monotonic()))
            try:
                data = self._sock.recv(65536)
            except OSError:  # a timeout (TimeoutError), or the socket closed
                return None
            ipoc = _IPOC.search(data)
            ak = _AK.search(data)
            if ipoc is None or ak is None or int(ipoc.group(1)) != self._ipoc:
                if time.monotonic() >= deadline:
                    return None
                continue  # an answer to an older frame: late, never applied
            vals = dict(_ATTR.findall(ak.group(1)))
            try:
                corr = np.array([float(vals[f"A{i}".encode()]) for i in range(1, 7)])
            except (KeyError, ValueError):
                return None
            return corr if np.all(np.isfinite(corr)) else None


def _udp_port_bound(port: int) -> bool:
    """Whether some UDP socket on this machine is bound to ``port`` (IPv4)."""
    try:
        with open("/proc/net/udp", encoding="ascii") as fh:
            lines = fh.readlines()[1:]
    except OSError:
        return True  # cannot tell: go ahead
    return any(int(line.split()[1].split(":")[1], 16) == port for line in lines)


class LockStepRig:
    """The peer and a flange gyro fed by its motion (``timedexec.twins.GyroTwin``) in a
    process of their own (context manager).

    In the test's process the robot side is one more Python thread beside the driver's,
    the gyro reader's and the calibration's: each waits for the interpreter lock up to its
    5 ms switch interval, and on a loaded machine the peer's cycles came late enough to
    hold its arm for whole cycles mid-pulse (four of eight trials flagged ``uncertain`` in
    one CI run). A robot's controller keeps its own time; here the peer does too.

    :meth:`peer` starts a peer (``LockStepRSIPeer``'s keyword arguments) that the gyro
    follows until the block ends; its late count is then :attr:`late`.
    """

    def __init__(self, pc_address: tuple[str, int], *, gyro_seed: int = 1) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_rig_main, args=(child, pc_address, gyro_seed),
                                 name="lockstep-rsi-rig", daemon=True)  # fmt: skip
        self.slave_path = ""
        self.late = 0

    def __enter__(self) -> LockStepRig:
        self._proc.start()
        if not self._conn.poll(60.0):
            self._proc.kill()
            raise RuntimeError("the RSI rig's process did not start within 60 s")
        self.slave_path = self._conn.recv()
        return self

    def __exit__(self, *exc: object) -> None:
        self._conn.send(("quit",))
        self._proc.join(timeout=10.0)
        if self._proc.is_alive():
            self._proc.kill()

    def peer(self, **kwargs: object) -> _RigPeer:
        """A peer in the rig's process for the ``with`` block (``LockStepRSIPeer``'s keyword
        arguments)."""
        return _RigPeer(self, kwargs)


class _RigPeer:
    def __init__(self, rig: LockStepRig, kwargs: dict[str, object]) -> None:
        self._rig, self._kwargs = rig, kwargs

    def __enter__(self) -> None:
        self._rig._conn.send(("start", self._kwargs))
        self._rig._conn.recv()

    def __exit__(self, *exc: object) -> None:
        self._rig._conn.send(("stop",))
        self._rig.late = self._rig._conn.recv()


def _rig_main(conn, pc_address: tuple[str, int], gyro_seed: int) -> None:  # type: ignore[no-untyped-def]
    from timedexec.twins import GyroTwin

    current: list[Callable[[float, float], np.ndarray]] = []

    def rates(t0: float, t1: float) -> np.ndarray:
        if current:
            return current[0](t0, t1)
        return np.zeros((max(1, round((t1 - t0) * 8000)), 3))

    gyro = GyroTwin(None, seed=gyro_seed)
    gyro.source.rate_source = rates
    with gyro:
        conn.send(gyro.slave_path)
        peer: LockStepRSIPeer | None = None
        while True:
            msg = conn.recv()
            if msg[0] == "start":
                peer = LockStepRSIPeer(pc_address, **msg[1])
                peer.__enter__()
                current[:] = [peer.rate_source(lambda: gyro.start_time_s)]
                conn.send("started")
            elif msg[0] == "stop" and peer is not None:
                peer.__exit__()
                current.clear()
                conn.send(peer.late)
                peer = None
            elif msg[0] == "quit":
                if peer is not None:
                    peer.__exit__()
                return
