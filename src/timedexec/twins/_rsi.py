"""A simulated KUKA controller speaking Ethernet RSI XML over UDP (the robot side of RSI).

The twin plays ``RSI_ON(#ABSOLUTE)`` (or ``#RELATIVE``) followed by ``RSI_MOVECORR()`` on a
simulated KR 5: every controller cycle (12 ms ``#IPO``; 4 ms ``#IPO_FAST``) it sends a
``<Rob TYPE="KUKA">`` frame from an ephemeral source port to the PC's RSI port, waits for the
``<Sen>`` answer echoing the frame's IPOC, and feeds the correction to the stepped simulated
controller (:class:`timedexec.sim.ControllerSim`). It behaves like KSS where it matters for
timing:

* **Clock.** Controller time ``t`` happens at host time ``t0_host_s + t``
  (:func:`time.monotonic`, shared by every process of the machine). Cycle ``k`` starts at
  ``k * period_s``.
* **State on the wire.** Frame ``k`` carries the state sampled at boundary ``k``
  (``AIPos`` = physical joint angles, ``ASPos`` = the controller's set-point, ``RIst`` = the
  flange pose from forward kinematics) and leaves at the simulated controller's send time
  (packing phase, plus one period with the ``response_extra_cycle`` effect), so the
  response delay, including KUKA's extra cycle, reaches the PC.
* **IPOC.** ``ipoc_start + k * ipoc_step``; the default step is the period in milliseconds
  (KR C4: 12 per 12 ms frame, 4 per 4 ms); ``ipoc_step=1`` mimics KR C2 / RSI 2.x.
* **Answers and the late counter.** An answer counts if it echoes the IPOC of the latest
  frame and arrives before the next frame leaves; one echoing an older IPOC than a frame
  already sent is late at once and not applied, as on KSS (unless the twin itself sent the
  two frames back to back, behind real time). Otherwise the cycle is late: the counter
  (sent as ``<Delay D>``) goes up and the correction of the previous cycle stays in force
  (absolute mode) or nothing is added (relative mode). When the counter reaches
  ``timeout_packets`` (KSS's ETHERNET object ``Timeout``, default 100) RSI stops with
  "RSITimeout" (KSS29002) and the robot brakes. KUKA's documentation does not say whether
  the counter restarts after an answer in time; ``late_counter="cumulative"`` (default)
  never resets it, ``"consecutive"`` resets it on every answer in time.
* **Corrections.** Absolute mode: the correction is the total offset from the pose at RSI
  start; relative mode: increments are summed. The commanded joint position (start pose +
  total correction) goes to the simulated controller as a :class:`~timedexec.sim.ServoJ`
  reached linearly over one period, i.e. a position reference that is updated once per
  cycle, which is what RSI does to the KSS set-point. Only a changed correction is
  submitted. A correction beyond ``max_correction_deg`` (the AXISCORR limits) stops RSI
  ("correction_limit"), and so does a commanded position outside the joint limits
  ("software_limit", the software limit switches).

  Why ServoJ and not SpeedJ from the increments: RSI corrections *are* positions; the
  simulated controller takes a ServoJ through the same register, intake at the next cycle
  boundary and command pipeline as any command, so the actuation delay is the simulator's
  own, and the position loop follows the reference without the drift a sequence of speed
  commands accumulates (each SpeedJ restarts the reference from the measured position, so
  lost time is never caught up).
* **Processes and threads.** The twin runs in its own process (``backend="process"``, the
  default; ``"thread"`` runs it in the caller's process for debugging, with less honest
  timing). Inside, one thread steps the physics once per period and another sends frames
  at their send times and receives answers, so a frame never waits for the physics of the
  cycle being computed (the state of boundary ``k`` is read before ``cycle()`` computes
  ``k -> k+1`` and checked against the packet ``cycle()`` returns). The process lowers its
  own GIL switch interval to 0.2 ms so that the I/O thread gets the interpreter promptly.
  How late frames left against their scheduled send time is recorded
  (:meth:`RSITwin.status`), so a run on an overloaded machine can be recognised.

Ground truth: :meth:`ControllerSim.truth_records` (one record per command, controller time)
goes to the JSON-lines file ``truth_path`` when the twin stops (a ``"meta"`` line with
``t0_monotonic_s``, then ``"command"`` lines, then an ``"rsi"`` line with the stop reason),
and is returned by :meth:`RSITwin.truth`; the frames sent and the answers received are
returned by :meth:`RSITwin.frames` and :meth:`RSITwin.answers`.

A slow robot program: ``first_frame_delay_s`` holds the first frame back (a KUKA needs
seconds to reach ``RSI_ON``). The truth's ``"rsi"`` line has ``last_motion_s``: when the
arm came to rest (faster than 0.02 rad/s for the last time, controller time).

Fault injection for tests: :meth:`RSITwin.stall` / :meth:`RSITwin.pause` (frames are lost
for a while), :meth:`RSITwin.drop_frames`, :meth:`RSITwin.drop_answers` and
:meth:`RSITwin.kill` (the controller's process dies).

The twin is split into :mod:`timedexec.twins._rsi_config` (settings and status),
:mod:`timedexec.twins._rsi_engine` (the physics thread and I/O loop inside the twin) and
this module (the handle, :class:`RSITwin`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import multiprocessing
import os
import socket
import threading
import time
from typing import Any, Literal, Self

import numpy as np
from numpy.typing import ArrayLike

from timedexec._types import FloatArray
from timedexec.effects import EffectSet
from timedexec.errors import ConfigError
from timedexec.twins._lifecycle import Twin
from timedexec.twins._rsi_config import STOP_REASONS, RSITwinConfig, RSITwinStatus
from timedexec.twins._rsi_engine import (
    _N_SLOTS,
    _S_ANSWERS,
    _S_CYCLES,
    _S_DONE,
    _S_DROPPED,
    _S_FRAMES,
    _S_LATE,
    _S_LATE_SENDS,
    _S_LATE_TOTAL,
    _S_MAX_LATENESS,
    _S_PEEK_MISMATCH,
    _S_PROTO,
    _S_REASON,
    _S_STALE,
    _S_STOP_TIME,
    _twin_main,
)

__all__ = [
    "STOP_REASONS",
    "RSITwin",
    "RSITwinConfig",
    "RSITwinStatus",
    "free_udp_port",
    "read_rsi_truth",
]


class RSITwin(Twin):
    """Simulated KUKA controller sending RSI frames to a PC port (context manager).

    Driven by the verbs every twin shares (:class:`~timedexec.twins.Twin`): ``start``,
    ``stop``, ``kill`` and ``stall`` (frames lost for a while, as :meth:`pause`). RSI runs
    over UDP without connections, so ``drop`` has no meaning; :meth:`drop_frames` and
    :meth:`drop_answers` lose single datagrams instead.

    Parameters
    ----------
    port : int, optional
        The PC's RSI port (where :class:`~timedexec.drivers.KukaRSIDriver` listens).
    backend : {"process", "thread"}, optional
        Run the twin in its own process (default; honest timing) or in a thread.
    effects : EffectSet, optional
        Simulated effects (default: the robot's default set).
    **settings
        Any other :class:`RSITwinConfig` field (``period_s``, ``q0_rad``, ``mode``,
        ``timeout_packets``, ``max_correction_deg``, ``truth_path`` ...).

    Examples
    --------
    >>> with KukaRSIDriver(0) as drv, RSITwin(drv.port, truth_path="truth.jsonl") as twin:
    ...     state = drv.read_state(timeout_s=1.0)          # doctest: +SKIP
    ...     drv.speedj([0, 0.3, 0, 0, 0, 0], 2.0, 0.5)      # doctest: +SKIP
    """

    def __init__(
        self,
        port: int = 49152,
        *,
        backend: Literal["process", "thread"] = "process",
        effects: EffectSet | None = None,
        q0_rad: ArrayLike | None = None,
        max_correction_deg: float | ArrayLike = 90.0,
        **settings: Any,
    ) -> None:
        if backend not in ("process", "thread"):
            raise ConfigError(f"backend={backend!r} must be 'process' or 'thread'")
        limits = np.broadcast_to(np.asarray(max_correction_deg, dtype=float), (6,))
        cfg_kwargs: dict[str, Any] = dict(settings)
        if effects is not None:
            cfg_kwargs["effects"] = tuple(effects.to_dict())
        if q0_rad is not None:
            cfg_kwargs["q0_rad"] = tuple(float(x) for x in np.asarray(q0_rad, dtype=float))
        if "truth_path" in cfg_kwargs and cfg_kwargs["truth_path"] is not None:
            cfg_kwargs["truth_path"] = os.fspath(cfg_kwargs["truth_path"])
        try:
            self.config = RSITwinConfig(
                port=port, max_correction_deg=tuple(limits.tolist()), **cfg_kwargs
            )
        except TypeError as exc:
            allowed = sorted(f.name for f in dataclasses.fields(RSITwinConfig))
            raise ConfigError(f"RSITwin: {exc}; settings are {allowed}") from None
        self.backend = backend
        self._ctx = multiprocessing.get_context("spawn")
        self._shared: Any = None
        self._conn: Any = None
        self._worker: Any = None
        self._ready: dict[str, Any] = {}
        self._results: dict[str, Any] | None = None

    # ---------------------------------------------------------------- lifecycle
    def start(self, timeout_s: float = 30.0) -> Self:
        """Start the twin and wait until its first frame is scheduled.

        Raises
        ------
        ConfigError
            If the twin could not start (the message carries its error).
        """
        if self._worker is not None:
            return self
        self._shared = self._ctx.Array("d", _N_SLOTS, lock=False)
        self._shared[_S_MAX_LATENESS] = -math.inf
        self._shared[_S_STOP_TIME] = math.nan
        parent, child = self._ctx.Pipe(duplex=True)
        self._conn = parent
        args = (self.config.to_dict(), child, self._shared, self.backend == "process")
        if self.backend == "process":
            self._worker = self._ctx.Process(
                target=_twin_main, args=args, name="rsi-twin", daemon=True
            )
        else:
            self._worker = threading.Thread(
                target=_twin_main, args=args, name="rsi-twin", daemon=True
            )
        self._worker.start()
        deadline = time.monotonic() + timeout_s
        while not parent.poll(0.05):
            if not self._worker.is_alive() or time.monotonic() > deadline:
                alive = self._worker.is_alive()
                self._kill()
                self._worker = None
                raise ConfigError(
                    f"RSI twin did not start within {timeout_s} s"
                    if alive
                    else "RSI twin process exited during start-up (with the spawn start "
                    "method the calling script needs an `if __name__ == '__main__':` guard)"
                )
        kind, payload = parent.recv()
        if kind != "ready":
            self._results = payload
            self._join()
            detail = (payload or {}).get("rsi", {}).get("detail", "unknown error")
            raise ConfigError(f"RSI twin failed to start: {detail}")
        self._ready = payload
        return self

    def stop(self, timeout_s: float = 30.0) -> RSITwinStatus:
        """Stop RSI (if still running), let the physics settle, collect the ground truth."""
        if self._worker is None:
            return self.status()
        if self._results is None:
            with contextlib.suppress(OSError, BrokenPipeError):
                self._conn.send(("stop",))
            self._collect(timeout_s)
        self._join()
        return self.status()

    def _collect(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while self._results is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._conn.poll(remaining):
                self._kill()
                self._results = {"rsi": {"reason": "error", "detail": "twin did not finish"}}
                return
            try:
                kind, payload = self._conn.recv()
            except EOFError:
                self._results = {"rsi": {"reason": "error", "detail": "twin exited"}}
                return
            if kind == "done":
                self._results = payload

    def _join(self) -> None:
        if self._worker is not None:
            self._worker.join(timeout=10.0)

    def _kill(self) -> None:
        worker = self._worker
        if isinstance(worker, multiprocessing.process.BaseProcess) and worker.is_alive():
            worker.terminate()
            worker.join(timeout=5.0)

    def kill(self) -> None:
        """Kill the twin's process abruptly (SIGKILL), as a crashed controller: frames stop
        at once, no ground truth is written, and :meth:`status` reports ``"error"``.

        Raises
        ------
        ConfigError
            With ``backend="thread"`` (a thread cannot be killed).
        """
        worker = self._worker
        if worker is None:
            return
        if not isinstance(worker, multiprocessing.process.BaseProcess):
            raise ConfigError("kill() needs backend='process'; a thread cannot be killed")
        if worker.is_alive():
            worker.kill()
            worker.join(timeout=5.0)
        if self._results is None:
            self._results = {"rsi": {"reason": "error", "detail": "killed by RSITwin.kill()"}}

    @property
    def is_alive(self) -> bool:
        """Whether the twin's process (or thread) runs."""
        return self._worker is not None and bool(self._worker.is_alive())

    # ---------------------------------------------------------------- fault injection
    def _control(self, *msg: Any) -> None:
        if self._conn is None:
            raise ConfigError("the twin is not running; start() it first")
        self._conn.send(msg)

    def pause(self, duration_s: float) -> None:
        """Lose every frame for ``duration_s`` (s), as a pulled cable would: the robot
        keeps running its cycles and counts them late."""
        self._control("pause", float(duration_s))

    def _stall(self, seconds: float) -> None:
        self.pause(seconds)

    def drop(self) -> None:
        """RSI has no connections to drop (UDP): raises NotImplementedError.

        Raises
        ------
        NotImplementedError
            Always; lose datagrams with :meth:`drop_frames` / :meth:`drop_answers`, or
            the whole stream for a while with :meth:`stall`.
        """
        raise NotImplementedError(
            "RSITwin.drop(): RSI runs over UDP without connections; use drop_frames(n), "
            "drop_answers(n) or stall(seconds)"
        )

    def drop_frames(self, n: int) -> None:
        """Lose the next ``n`` frames on their way to the PC."""
        self._control("drop_frames", int(n))

    def drop_answers(self, n: int) -> None:
        """Lose the next ``n`` answers on their way to the robot."""
        self._control("drop_answers", int(n))

    # ---------------------------------------------------------------- observation
    @property
    def t0_host_s(self) -> float:
        """``time.monotonic()`` of controller time 0 (host time = t0_host_s + controller)."""
        return float(self._ready.get("t0_host_s", math.nan))

    @property
    def source_port(self) -> int:
        """The robot's ephemeral UDP source port."""
        return int(self._ready.get("source_port", 0))

    @property
    def start_pose_rad(self) -> FloatArray:
        """Pose at RSI start, rad, shape (6,)."""
        return np.asarray(self._ready.get("q_start_rad", [math.nan] * 6), dtype=float)

    @property
    def period_s(self) -> float:
        """RSI cycle period, s."""
        return float(self._ready.get("period_s", self.config.period_s))

    def controller_time_of_ipoc(self, ipoc: int) -> float:
        """Controller time (s) of the cycle boundary a frame's IPOC belongs to."""
        return (int(ipoc) - self.config.ipoc_start) / self.config.ipoc_increment * self.period_s

    def status(self) -> RSITwinStatus:
        """Live counters and, once RSI stopped, the reason."""
        sh = self._shared
        if sh is None:
            return RSITwinStatus(reason="running")
        reason = STOP_REASONS[int(sh[_S_REASON])]
        detail = ""
        if self._results is not None:
            rsi = self._results.get("rsi", {})
            reason = rsi.get("reason", reason)
            detail = rsi.get("detail", "")
        return RSITwinStatus(
            reason=reason,
            detail=detail,
            frames_sent=int(sh[_S_FRAMES]),
            frames_dropped=int(sh[_S_DROPPED]),
            answers_in_time=int(sh[_S_ANSWERS]),
            stale_answers=int(sh[_S_STALE]),
            late_count=int(sh[_S_LATE]),
            late_total=int(sh[_S_LATE_TOTAL]),
            protocol_errors=int(sh[_S_PROTO]),
            late_sends=int(sh[_S_LATE_SENDS]),
            max_send_lateness_s=max(0.0, float(sh[_S_MAX_LATENESS])),
            peek_mismatches=int(sh[_S_PEEK_MISMATCH]),
            cycles=int(sh[_S_CYCLES]),
            stop_time_s=float(sh[_S_STOP_TIME]),
            finished=bool(sh[_S_DONE]),
        )

    def wait_stopped(self, timeout_s: float) -> RSITwinStatus:
        """Wait until RSI stops by itself (RSITimeout, limits); returns the status.

        Raises
        ------
        TimeoutError
            If RSI still runs after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while self.status().running:
            if time.monotonic() > deadline:
                raise TimeoutError(f"RSI twin still running after {timeout_s} s")
            time.sleep(0.005)
        return self.status()

    def _finished_results(self, timeout_s: float = 30.0) -> dict[str, Any]:
        if self._results is None:
            if self._worker is None:
                raise ConfigError("the twin never ran; use it as a context manager")
            if self.status().running:
                raise ConfigError(
                    "ground truth is complete only once RSI stopped; call stop() (or wait "
                    "for RSITimeout) first"
                )
            self._collect(timeout_s)
        return self._results or {}

    def truth(self) -> list[dict[str, Any]]:
        """Ground truth per command (``ControllerSim.truth_records()``, controller time)."""
        return list(self._finished_results().get("truth", []))

    def frames(self) -> list[dict[str, Any]]:
        """Every frame the controller sent: cycle, ipoc, sample_time_s, send_time_s
        (scheduled), sent_s (actual, None if lost), q_rad, q_set_rad, late_count."""
        return list(self._finished_results().get("frames", []))

    def answers(self) -> list[dict[str, Any]]:
        """Every valid answer received: ipoc, arrival_s, in_time, correction_rad."""
        return list(self._finished_results().get("answers", []))


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port on ``host`` that is free right now (for a twin or a driver to bind)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def read_rsi_truth(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read an RSI twin's ground-truth file (a view of
    :func:`~timedexec.twins.read_twin_truth`; a line still being written is skipped).

    Returns
    -------
    dict
        ``meta`` (robot, period_s, t0_monotonic_s, ipoc_start, ipoc_step, start pose),
        ``commands`` (list of :meth:`ControllerSim.truth_records` rows in file order,
        controller time, s) and ``rsi`` (stop reason, detail and counters).
    """
    from timedexec.twins._truth import read_twin_truth

    truth = read_twin_truth(path)
    return {
        "meta": truth["meta"],
        "commands": list(truth["commands"].values()),
        "rsi": truth["rsi"],
    }
