"""Running the peer from a test: :func:`run_peer` starts it in a subprocess and yields a
:class:`PeerHandle` (events, the truth log as arrays, the controller clock).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@dataclasses.dataclass(frozen=True)
class Truth:
    """The truth log as arrays: ``t`` (s, controller time), ``runtime_state``, ``q`` (N x 6,
    rad), ``qd`` (N x 6, rad/s)."""

    t: Any
    runtime_state: Any
    q: Any
    qd: Any

    def rest_time_after(self, t_from: float) -> float | None:
        """First controller time >= ``t_from`` (s) from which every later row has qd == 0."""
        import numpy as np

        moving = np.any(self.qd != 0.0, axis=1)
        idx = np.nonzero(moving)[0]
        last_moving = idx[-1] if idx.size else -1
        if last_moving == len(self.t) - 1:
            return None
        return max(float(self.t[last_moving + 1]), t_from)


@dataclasses.dataclass(frozen=True)
class PeerEvent:
    """An ``#event`` line: controller time (s), kind and key=value fields."""

    time_s: float
    kind: str
    fields: dict[str, str]


class PeerHandle:
    """A running peer subprocess; see :func:`run_peer`."""

    def __init__(
        self,
        host: str,
        model: str,
        version: str,
        truth_path: Path,
        process: subprocess.Popen[bytes],
    ) -> None:
        self.host = host
        self.model = model
        self.version = version
        self.truth_path = truth_path
        self.process = process
        self.rate_hz = 500.0 if int(version.split(".")[0]) >= 4 else 125.0
        self.period_s = 1.0 / self.rate_hz

    def _lines(self) -> list[str]:
        text = self.truth_path.read_text(encoding="ascii", errors="replace")
        lines = text.split("\n")
        return lines[:-1]  # the last element is "" or a partly written line

    def read_truth(self) -> Truth:
        """Parse the truth log written so far into numpy arrays."""
        import numpy as np

        rows = [ln for ln in self._lines() if ln and ln[0].isdigit()]
        if not rows:
            e = np.zeros((0, 6))
            return Truth(np.zeros(0), np.zeros(0, dtype=int), e, e.copy())
        arr = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", ndmin=2)
        return Truth(arr[:, 0], arr[:, 1].astype(int), arr[:, 2:8], arr[:, 8:14])

    def events(self, kind: str | None = None) -> list[PeerEvent]:
        """Events logged so far, optionally only those of ``kind``."""
        out = []
        for ln in self._lines():
            if not ln.startswith("#event,"):
                continue
            _, t, k, detail = ln.split(",", 3)
            if kind is not None and k != kind:
                continue
            fields = dict(kv.split("=", 1) for kv in detail.split(";") if "=" in kv)
            out.append(PeerEvent(float(t), k, fields))
        return out

    def _clock_segments(self) -> list[tuple[float, float]]:
        """(controller time s, t0_monotonic s) from the start and from each clock slip."""
        segs = []
        for ev in self.events():
            if ev.kind in ("peer_started", "clock_slip"):
                segs.append((ev.time_s, float(ev.fields["t0_monotonic"])))
        if not segs:
            raise RuntimeError("peer has not logged its clock origin")
        return segs

    def to_peer_time(self, monotonic_s: float) -> float:
        """Convert a ``time.monotonic()`` reading (this machine) to controller time in s.

        The controller runs cycle k at monotonic ``t0 + k * dt`` or later; if it was starved for
        more than 0.1 s it logs a ``clock_slip`` with a new ``t0`` (the skipped wall interval
        maps to the controller time of the slip).
        """
        segs = self._clock_segments()
        t = monotonic_s - segs[0][1]
        for t_slip, t0 in segs[1:]:
            if monotonic_s - t0 >= t_slip:
                t = monotonic_s - t0
            elif t >= t_slip:
                t = t_slip
            else:
                break
        return t

    def to_host_times(self, peer_s: list[float]) -> list[float]:
        """Convert controller times (s) to ``time.monotonic()`` on this machine: the inverse
        of :meth:`to_peer_time`, each time by the clock segment it falls in."""
        segs = self._clock_segments()
        out = []
        for t in peer_s:
            t0 = segs[0][1]
            for t_slip, t0_slip in segs[1:]:
                if t >= t_slip:
                    t0 = t0_slip
            out.append(t + t0)
        return out

    def wait_event(self, kind: str, timeout: float = 5.0, after: float = -1.0) -> PeerEvent:
        """Wait (s) for an event of ``kind`` at controller time > ``after``."""
        end = time.monotonic() + timeout
        while True:
            for ev in self.events(kind):
                if ev.time_s > after:
                    return ev
            if time.monotonic() > end:
                raise TimeoutError(f"no {kind} event within {timeout} s")
            time.sleep(0.02)

    def wait_truth_until(self, t_peer: float, timeout: float = 5.0) -> Truth:
        """Wait until the truth log covers controller time ``t_peer`` (s); return it."""
        end = time.monotonic() + timeout
        while True:
            tr = self.read_truth()
            if len(tr.t) and tr.t[-1] >= t_peer:
                return tr
            if time.monotonic() > end:
                raise TimeoutError(f"truth log did not reach {t_peer} s")
            time.sleep(0.02)

    def stop(self, timeout: float = 5.0) -> int:
        """SIGTERM the peer and wait for it (s); returns its exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout)
        return int(self.process.returncode)


@contextlib.contextmanager
def run_peer(
    host: str,
    model: str = "UR10",
    version: str = "5.11.1",
    truth_path: str | os.PathLike[str] | None = None,
    extra_args: tuple[str, ...] = (),
    startup_timeout: float = 10.0,
) -> Iterator[PeerHandle]:
    """Start the peer on ``host`` in a subprocess; yield a :class:`PeerHandle`; stop it after.

    ``truth_path`` defaults to a temporary file removed afterwards. ``startup_timeout`` in s.
    """
    tmpdir = None
    if truth_path is None:
        tmpdir = tempfile.TemporaryDirectory(prefix="ur_peer_")
        path = Path(tmpdir.name) / "truth.csv"
    else:
        path = Path(truth_path)
    cmd = [
        sys.executable,
        "-S",  # the peer needs only the standard library; skip site-packages start-up cost
        "-m",
        __package__,
        "--host",
        host,
        "--model",
        model,
        "--version",
        version,
        "--truth",
        str(path),
        *extra_args,
    ]
    # the folder holding this package, first on the peer's path (-S leaves PYTHONPATH in)
    here = str(Path(__file__).resolve().parents[1])
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")])),
    }
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    handle = PeerHandle(host, model, version, path, proc)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], startup_timeout)
        line = proc.stdout.readline() if ready else b""
        if line.strip() != b"ready":
            proc.kill()
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"peer on {host} did not start: {line!r} {err}")
        yield handle
    finally:
        handle.stop()
        if tmpdir is not None:
            tmpdir.cleanup()
