"""A gyro on the RSI twin.

:class:`~timedexec.twins.RSITwin` has no ``imu_link`` option (the UR twin has).
Its ``controller_factory`` hook gives access to the physics' flange rate:
``controller_factory=rsi_gyro_factory(link)`` builds the simulated controller inside the
twin's process with a gyro twin (:class:`~timedexec.twins.GyroTwin`) on a pty at
``link``, fed by ``CycleResult.flange_rate_rad_s``. The factory does not learn the twin's
clock origin, so the caller hands it over with :func:`publish_controller_origin` right after
the twin started (before any motion; until then the robot is still and the rate is zero).
"""

from __future__ import annotations

import json
import math
import os
import threading
from typing import Any

import numpy as np

from timedexec._realtime import try_realtime
from timedexec._types import FloatArray
from timedexec.errors import ConfigError

__all__ = ["publish_controller_origin", "rsi_gyro_factory"]


_FACTORY_PREFIX = "rsi_gyro_"
_RSI_PHYSICS_RATE_HZ = 4000.0  # as the UR twin: a cycle's physics well inside real time
_RATE_WAIT_S = 0.25  # longest wait of the gyro for the physics (a late physics thread)
_DEFAULT_RT_PRIORITY = 10  # as the UR twin's threads


def rsi_gyro_factory(
    link_path: str | os.PathLike[str], *, rt_priority: int | None = _DEFAULT_RT_PRIORITY
) -> str:
    """``controller_factory`` for :class:`~timedexec.twins.RSITwin` that adds a gyro.

    The returned ``"module:name"`` builds the default simulated controller (physics at
    4 kHz, as the UR twin) inside the twin's process and starts a gyro twin whose pty is
    linked at ``link_path``, fed by the physics' flange rate; its clock (``gyro`` line:
    ``start_time_s``, ``true_rate_hz``, ``dlpf_group_delay_s``) goes to
    ``link_path + ".truth.jsonl"``. After the twin started, call
    :func:`publish_controller_origin` with its ``t0_host_s``.

    Parameters
    ----------
    link_path : path
        Where the gyro's pty is linked (open it with :func:`~timedexec.sensors.open_gyro`).
    rt_priority : int or None
        SCHED_FIFO priority for the twin's threads (set where the factory runs, before the
        twin starts its threads, which inherit it), as the UR twin does: a real controller
        runs its cycle at real-time priority, and on a loaded machine a normal-priority twin
        falls behind by tens of ms. Needs root or CAP_SYS_NICE, silently skipped without.
        None leaves the scheduling alone.
    """
    options = {"link": os.fspath(link_path), "rt_priority": rt_priority}
    encoded = json.dumps(options, sort_keys=True).encode().hex()
    return f"{__name__}:{_FACTORY_PREFIX}{encoded}"


def _origin_path(link_path: str) -> str:
    return link_path + ".origin.json"


def publish_controller_origin(link_path: str | os.PathLike[str], t0_host_s: float) -> None:
    """Hand the RSI twin's clock origin (``RSITwin.t0_host_s``) to its gyro (see
    :func:`rsi_gyro_factory`); call it right after the twin started."""
    if not math.isfinite(t0_host_s):
        raise ConfigError(f"t0_host_s={t0_host_s!r} is not a host time; start the twin first")
    target = _origin_path(os.fspath(link_path))
    tmp = target + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump({"t0_monotonic_s": float(t0_host_s)}, fh)
    os.replace(tmp, target)


def __getattr__(name: str) -> Any:
    """``rsi_gyro_<hex JSON options>``: the factory :func:`rsi_gyro_factory` names."""
    if name.startswith(_FACTORY_PREFIX):
        options = json.loads(bytes.fromhex(name[len(_FACTORY_PREFIX) :]))

        def factory(robot: str, **kwargs: Any) -> _GyroControllerSim:
            try_realtime(options.get("rt_priority"))
            return _GyroControllerSim(robot, link_path=str(options["link"]), **kwargs)

        return factory
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _GyroControllerSim:
    """ControllerSim plus a gyro twin fed by its flange rate (runs inside the RSI twin)."""

    def __init__(self, robot: str, *, link_path: str, seed: int = 0, **kwargs: Any) -> None:
        from timedexec.sim import ControllerSim

        self._sim = ControllerSim(robot, seed=seed, physics_rate_hz=_RSI_PHYSICS_RATE_HZ, **kwargs)
        self._link = link_path
        self._seed = seed
        self._cond = threading.Condition()
        self._t: list[FloatArray] = []
        self._w: list[FloatArray] = []
        self._upto_s = -math.inf
        self._origin: float | None = None
        self._gyro: Any = None
        self.rate_timeouts = 0
        self.moved_before_origin = False

    def __getattr__(self, name: str) -> Any:
        if name == "_sim":
            raise AttributeError(name)
        return getattr(self._sim, name)

    def cycle(self) -> Any:
        result = self._sim.cycle()
        sim = self._sim
        times = np.asarray(result.substep_time_s, dtype=np.float64)
        # The rates are the speeds at the end of each substep (JointBank.step); a CycleResult
        # that stamps them with the substep's start is shifted to the end (the onset truth's
        # convention), one that already stamps the end is left alone.
        if times.size and abs(times[0] - float(result.packet.sample_time_s)) < 1e-12:
            times = times + sim.dt_s
        with self._cond:
            self._t.append(times)
            self._w.append(np.asarray(result.flange_rate_rad_s, dtype=np.float64))
            keep = max(4, int(2.0 / sim.period_s))
            if len(self._t) > keep:
                del self._t[:-keep]
                del self._w[:-keep]
            self._upto_s = float(sim.time_s)
            self._cond.notify_all()
        if self._gyro is None:
            self._start_gyro()
        return result

    def _controller_origin(self) -> float | None:
        if self._origin is None:
            try:
                with open(_origin_path(self._link), encoding="utf-8") as fh:
                    self._origin = float(json.load(fh)["t0_monotonic_s"])
            except (OSError, ValueError, KeyError):
                return None
        return self._origin

    def _flange_rate(self, times_s: FloatArray) -> FloatArray:
        latest = float(times_s.max()) if times_s.size else -math.inf
        with self._cond:
            timed_out = not self._cond.wait_for(
                lambda: self._upto_s >= latest, timeout=_RATE_WAIT_S
            )
            t = np.concatenate(self._t)
            w = np.concatenate(self._w)
        if timed_out:
            self.rate_timeouts += 1
            self._report()
        return np.stack([np.interp(times_s, t, w[:, i]) for i in range(3)], axis=1)

    def _report(self) -> None:
        """Append the factory's problem counters to the sidecar (rare events only)."""
        line = {
            "event": "rsi_gyro",
            "rate_timeouts": self.rate_timeouts,
            "moved_before_origin": self.moved_before_origin,
        }
        with open(self._link + ".truth.jsonl", "a", encoding="utf-8") as fh:
            fh.write(json.dumps(line, sort_keys=True) + "\n")

    def _rate_source(self, t0_s: float, t1_s: float) -> FloatArray:
        k = max(1, math.ceil((t1_s - t0_s) * 8000.0 - 1e-9))
        origin = self._controller_origin()
        if origin is None:  # before the origin is published the robot has not moved
            if self._sim.truth and not self.moved_before_origin:
                self.moved_before_origin = True
                self._report()
            return np.zeros((k, 3))
        grid = self._gyro.start_time_s - origin + t0_s + np.arange(k) * ((t1_s - t0_s) / k)
        return self._flange_rate(grid)

    def _start_gyro(self) -> None:
        from timedexec.twins._gyro import GyroTwin

        gyro = GyroTwin(self._rate_source, link_path=self._link, seed=self._seed)
        self._gyro = gyro
        gyro.start()
        line = {
            "event": "gyro",
            "link_path": self._link,
            "slave_path": gyro.slave_path,
            "start_time_s": gyro.start_time_s,
            "true_rate_hz": gyro.true_rate_hz,
            "clock_error_ppm": gyro.clock_error_ppm,
            "dlpf_group_delay_s": gyro.source.dlpf_group_delay_s,
            "physics_rate_hz": _RSI_PHYSICS_RATE_HZ,
        }
        with open(self._link + ".truth.jsonl", "w", encoding="utf-8") as fh:
            fh.write(json.dumps(line, sort_keys=True) + "\n")
