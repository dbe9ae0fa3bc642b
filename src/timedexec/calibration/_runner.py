"""The live calibration runner: trials over any RobotDriver and gyro, into a recording.

Per trial (DESIGN.md §1): wait until the robot is still; wait for a state package and
time-stamp it on arrival (trial time 0); on that arrival send the single-joint command
(rapid acceleration to the calibration speed, rapid deceleration, a pause, the same back to
the start pose), the later segments on later package arrivals; record every package (raw
bytes and parsed) and the gyro stream until the window ends; append the trial to the
recording. A still recording (for the PSD and the zero-rate) opens the sweep.

Resumable: each trial is appended atomically, so a run killed at any moment loses at most
the trial in flight; ``resume=True`` skips the recorded trials. Each run of the command is a
*session* (its own host clock origin and gyro stream); the per-trial ``session`` field lets
extraction fit the gyro clock per session.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from timedexec._progress import Progress
from timedexec._signal import ONSET_FRACTION
from timedexec.drivers import RobotDriver, RobotState
from timedexec.errors import ConfigError, DriverTimeout, RecordingError
from timedexec.recording import (
    Field,
    RecordingReader,
    RecordingWriter,
    SweepPlan,
    SweepProtocol,
    trial_fields,
    trial_layout,
)
from timedexec.sensors import GyroSamples

__all__ = ["CalibrationResult", "GyroSource", "run_calibration"]

FloatArray = NDArray[np.float64]
#: Raw bytes kept per state package (RTDE and RSI packages are a few hundred bytes).
RAW_BYTES = 1024


class GyroSource(Protocol):
    """What the runner needs of a gyro: samples that have arrived, with raw counts."""

    def read(self, n: int | None = None, *, timeout_s: float | None = 1.0) -> GyroSamples: ...


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`run_calibration` did."""

    path: Path
    n_planned: int
    n_recorded_now: int
    session: int

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        return {
            "recording": str(self.path),
            "planned": self.n_planned,
            "recorded_now": self.n_recorded_now,
            "session": self.session,
        }


def _live_fields(settings: SweepProtocol, truth: bool) -> list[Field]:
    lay = trial_layout(settings)
    return [
        *trial_fields(settings, truth=False),
        Field(
            "session", (), "int32", "", "run of the command that recorded the trial (resume count)"
        ),
        Field(
            "state_raw",
            (lay.n_packages, RAW_BYTES),
            "uint8",
            "",
            "raw bytes of each package (truncated)",
        ),
        Field(
            "state_raw_len", (lay.n_packages,), "int32", "B", "length of each package's raw bytes"
        ),
        *(
            [
                Field(
                    "true_onset_s",
                    (),
                    "float64",
                    "s",
                    "physical onset (simulated robots), trial time",
                ),
                Field(
                    "true_actuation_delay_s", (), "float64", "s", "ground truth (simulated robots)"
                ),
                Field(
                    "true_response_delay_s", (), "float64", "s", "ground truth (simulated robots)"
                ),
            ]
            if truth
            else []
        ),
    ]


class _Session:
    """One run: the driver, the gyro buffer and the host clock origin."""

    def __init__(
        self, driver: RobotDriver, gyro: GyroSource, settings: SweepProtocol, origin_s: float
    ) -> None:
        self.driver = driver
        self.gyro = gyro
        self.settings = settings
        self.origin_s = origin_s
        self.buffer: deque[GyroSamples] = deque()
        self.last: RobotState | None = None

    def clock(self) -> float:
        return float(getattr(self.driver, "clock", time.monotonic)())

    def state(self, timeout_s: float = 0.5) -> RobotState:
        st = self.driver.read_state(timeout_s=timeout_s)
        self.last = st
        got = self.gyro.read(timeout_s=0.0)
        if len(got):
            self.buffer.append(got)
            horizon = st.host_time_s - 5.0
            while self.buffer and len(self.buffer[0]) and self.buffer[0].arrival_s[-1] < horizon:
                self.buffer.popleft()
        return st

    def samples(self) -> GyroSamples:
        return GyroSamples.concatenate(list(self.buffer))

    def wait_still(
        self, *, min_s: float, speed_eps: float = 2e-3, packages: int = 10
    ) -> RobotState:
        start = self.state()
        quiet = 0
        while True:
            st = self.state()
            quiet = quiet + 1 if np.abs(st.qd).max() < speed_eps else 0
            if quiet >= packages and st.host_time_s - start.host_time_s >= min_s:
                return st
            if st.host_time_s - start.host_time_s > 30.0:
                raise DriverTimeout(
                    "the robot did not come to rest within 30 s; check it is not moving"
                )

    def move_to(self, q_target: FloatArray, *, tol_rad: float = 5e-4) -> None:
        """Drive to ``q_target`` with speed commands (works on every driver)."""
        spec = self.settings.spec
        vmax = 0.5 * np.asarray(spec.qd_max_rad_s)
        st = self.state()
        t_start = st.host_time_s
        while True:
            err = q_target - st.q
            if np.abs(err).max() < tol_rad and np.abs(st.qd).max() < 0.01:
                break
            qd = np.clip(3.0 * err, -vmax, vmax)
            qd = np.where(np.abs(err) < tol_rad, 0.0, qd)
            self.driver.speedj(qd, 4.0, 0.0)
            st = self.state()
            if st.host_time_s - t_start > 60.0:
                raise DriverTimeout(
                    f"moving to the start configuration took over 60 s (error "
                    f"{np.abs(err).max():.4f} rad); check the robot is enabled and free to move"
                )
        self.driver.speedj(np.zeros(6), 4.0, 0.0)


def _stillrecording(sess: _Session, duration_s: float) -> dict[str, NDArray[Any]]:
    st = sess.state()
    t_end = st.host_time_s + duration_s + 0.1
    while st.host_time_s < t_end:
        st = sess.state()
    s = sess.samples()
    block = sess.settings.gyro.block_samples
    n = len(s) - len(s) % block
    raw = s.raw[:n]
    arrival = s.arrival_s[block - 1 : n : block] - sess.origin_s
    return {
        "still_gyro_raw": raw,
        "still_gyro_counter": (s.counter_unwrapped[:n] % 65536).astype(np.uint16),
        "still_gyro_block_host_time_s": arrival,
    }


def _trial(
    sess: _Session, plan: SweepPlan, i: int, session: int, truth: bool
) -> dict[str, NDArray[Any]]:
    settings = sess.settings
    prof = settings.profile
    lay = trial_layout(settings)
    period = settings.controller_period_s
    joint = int(plan.joint[i])
    direction = float(plan.direction[i])
    qd = np.zeros(6)
    qd[joint - 1] = direction * prof.speed_rad_s
    a = prof.acceleration_rad_s2
    ramp = prof.speed_rad_s / a
    # Trigger: the arrival of a package; the command leaves on that arrival.
    trigger = sess.state()
    t0 = trigger.host_time_s
    sess.driver.speedj(qd, a, 0.0)
    t_send = float(getattr(sess.driver, "last_send_s", sess.clock()))
    if not math.isfinite(t_send) or t_send < t0:
        t_send = sess.clock()
    # Later segments on later arrivals: decelerate, pause, back, decelerate.
    pulse = prof.pulse_s
    segments = [
        (t_send + ramp + prof.hold_s, np.zeros(6)),
        (t_send + pulse + prof.pause_s, -qd),
        (t_send + 2 * pulse + prof.pause_s - ramp, np.zeros(6)),
    ]
    packages = [trigger]
    while True:
        st = sess.state()
        if segments and st.host_time_s >= segments[0][0] - 0.5 * period:
            sess.driver.speedj(segments.pop(0)[1], a, 0.0)
        if st.host_time_s >= t0 + prof.record_s:
            break
        packages.append(st)
    while segments:  # a slow stream: finish the motion anyway
        sess.driver.speedj(segments.pop(0)[1], a, 0.0)
    # Gyro: wait until the window has arrived, then take G samples from its start.
    t_need = t0 + prof.record_s + 0.01
    st = sess.last or trigger
    while st.host_time_s < t_need:
        st = sess.state()
    samples = sess.samples()
    start = int(np.searchsorted(samples.host_time_s, t0 - prof.pre_s))
    first = (
        int(samples.counter_unwrapped[start])
        if start < len(samples)
        else int(samples.counter_unwrapped[-1]) + 1
    )
    while len(samples) - start < lay.n_gyro:
        sess.state()  # may drop the oldest buffered chunks: find the window's start again
        samples = sess.samples()
        start = int(np.searchsorted(samples.counter_unwrapped, first))
    sel = slice(start, start + lay.n_gyro)
    block = settings.gyro.block_samples
    arrivals = samples.arrival_s[sel][block - 1 :: block] - t0

    p = lay.n_packages
    host = np.full(p, np.nan)
    ctrl = np.full(p, np.nan)
    q = np.full((p, 6), np.nan)
    qdr = np.full((p, 6), np.nan)
    raw = np.zeros((p, RAW_BYTES), np.uint8)
    raw_len = np.zeros(p, np.int32)
    for k, pkg in enumerate(packages[:p]):
        host[k] = pkg.host_time_s - t0
        ctrl[k] = pkg.controller_time_s
        q[k] = pkg.q
        qdr[k] = pkg.qd
        b = pkg.raw[:RAW_BYTES]
        raw[k, : len(b)] = np.frombuffer(b, np.uint8)
        raw_len[k] = len(pkg.raw)
    out: dict[str, NDArray[Any]] = {
        "trial": np.array([i], np.int64),
        "t0_s": np.array([t0 - sess.origin_s]),
        "cmd_send_time_s": np.array([t_send - t0]),
        "cmd_qd_rad_s": qd[None, :],
        "state_host_time_s": host[None],
        "state_controller_time_s": ctrl[None],
        "state_q_rad": q[None].astype(np.float32),
        "state_qd_rad_s": qdr[None].astype(np.float32),
        "gyro_raw": samples.raw[sel][None],
        "gyro_counter": (samples.counter_unwrapped[sel] % 65536).astype(np.uint16)[None],
        "gyro_block_host_time_s": arrivals.astype(np.float32)[None],
        "session": np.array([session], np.int32),
        "state_raw": raw[None],
        "state_raw_len": raw_len[None],
    }
    if truth:
        drv: Any = sess.driver
        onset = drv.true_onset_s(joint, t_send)
        level = ONSET_FRACTION * prof.speed_rad_s
        out["true_onset_s"] = np.array([onset - t0])
        out["true_actuation_delay_s"] = np.array([onset - (t_send + level / a)])
        out["true_response_delay_s"] = np.array([drv.true_response_delay_s(t0, t0 + prof.record_s)])
    return out


def run_calibration(
    driver: RobotDriver,
    gyro: GyroSource,
    plan: SweepPlan,
    out: str | os.PathLike[str],
    *,
    protocol: SweepProtocol,
    resume: bool = False,
    progress: bool = True,
    source: str = "",
) -> CalibrationResult:
    """Run (or resume) a calibration sweep and record it.

    Parameters
    ----------
    driver : RobotDriver
        Connected driver (``sim://``, ``ur://``, ``rsi://``).
    gyro : GyroSource
        The gyro on the flange (a :class:`~timedexec.sensors.GyroReader` or a virtual one).
    plan : SweepPlan
        The trials.
    out : path
        Recording to write; refused if it exists unless ``resume``.
    protocol : SweepProtocol
        The calibration motion, controller period and the gyro's constants (a simulated
        robot's: ``default_settings(robot).protocol``).
    resume : bool
        Continue a run of the same plan.
    progress : bool
        Progress with ETA on stderr.
    source : str
        Where the data came from (the robot URL), for the header.
    """
    settings = protocol
    if plan.robot != settings.robot:
        raise ConfigError(f"plan is for {plan.robot}, the settings for {settings.robot}")
    truth = hasattr(driver, "true_onset_s")
    header = {
        "source": source or "live",
        "robot": settings.spec.to_dict(),
        "profile": settings.profile.to_dict(),
        "controller_period_s": settings.controller_period_s,
        "gyro": settings.gyro.to_dict(),
        "plan": plan.meta(),
        "time_origin": "trial time 0 = host arrival of the trigger state package",
    }
    out = Path(out)
    with RecordingWriter(
        out, header=header, fields=_live_fields(settings, truth), resume=resume
    ) as w:
        if resume and w.header.get("plan") != plan.meta():
            raise RecordingError(
                f"{out} holds another plan ({w.header.get('plan')}); resume with the same "
                "--trials/--seed or --plan"
            )
        for name, arr in plan.to_arrays().items():
            if not w.has_static(name):
                w.write_static(name, arr)
        done = w.completed_trials
        session = 0
        last_t0 = -math.inf
        if len(done):
            with RecordingReader(out) as r:
                session = int(r.read("session").max()) + 1
                last_t0 = float(r.read("t0_s").max())
        todo = np.setdiff1d(np.arange(len(plan)), done)
        now = float(getattr(driver, "clock", time.monotonic)())
        origin = now if not math.isfinite(last_t0) else now - (last_t0 + 10.0)
        sess = _Session(driver, gyro, settings, origin)
        if not w.has_static("still_gyro_raw"):
            if len(todo):
                sess.move_to(plan.q_start_rad[todo[0]])
            sess.wait_still(min_s=0.2)
            for name, arr in _stillrecording(sess, settings.still_s).items():
                w.write_static(name, arr)
        bar = Progress(len(todo), f"calibrate {settings.robot}", enabled=progress)
        current = None
        for i in todo:
            if current is None or not np.allclose(plan.q_start_rad[i], current):
                sess.move_to(plan.q_start_rad[i])
                current = plan.q_start_rad[i]
            sess.wait_still(min_s=settings.trial_gap_s)
            w.append(_trial(sess, plan, int(i), session, truth))
            bar.update()
        bar.close()
        driver.stop()
    return CalibrationResult(out, len(plan), len(todo), session)
