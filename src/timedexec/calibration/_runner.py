"""The live calibration runner: trials over any RobotDriver and gyro, into a recording.

Per trial (DESIGN.md §1): wait until the robot is still; wait for a state package and
time-stamp it on arrival (trial time 0); on that arrival send the single-joint command
(rapid acceleration to the calibration speed, rapid deceleration, a pause, the same back to
the start pose), the later segments on later package arrivals; record every package (raw
bytes and parsed) and the gyro stream until the window ends; append the trial to the
recording. A still recording (for the PSD and the zero-rate) opens the sweep.

Before anything is written, a pre-flight (:mod:`timedexec.calibration._preflight`) checks
that the gyro streams at its rate and turns with the robot, so that a wrong port or a gyro
that is not on the flange ends the run at once with a message, not with a sweep of
flagged trials or an empty recording.

Resumable: each trial is appended atomically, so a run killed at any moment loses at most
the trial in flight; ``resume=True`` skips the recorded trials. Each run of the command is a
*session* (its own host clock origin and gyro stream); the per-trial ``session`` field lets
extraction fit the gyro clock per session.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._progress import Progress
from timedexec._signal import ONSET_FRACTION
from timedexec.calibration._preflight import PreflightReport, check_motion, check_stream
from timedexec.calibration._session import GyroSource, Session, gyro_name
from timedexec.drivers import RobotDriver
from timedexec.errors import ConfigError, RecordingError, SensorError
from timedexec.recording import (
    Field,
    RecordingReader,
    RecordingWriter,
    SweepPlan,
    SweepProtocol,
    trial_fields,
    trial_layout,
)

__all__ = ["CalibrationResult", "DriverRunner", "run_calibration"]

#: Raw bytes kept per state package (RTDE and RSI packages are a few hundred bytes).
RAW_BYTES = 1024
#: Robot time the runner waits for gyro samples that are late before calling it a fault, s
#: (USB and the reader deliver within tens of milliseconds).
GYRO_STALL_S = 2.0


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`run_calibration` did.

    Attributes
    ----------
    path : Path
        The recording.
    n_planned : int
        Trials in the plan.
    n_recorded_now : int
        Trials this run recorded.
    session : int
        This run's session number (0 for the first run, +1 per resume).
    preflight : PreflightReport or None
        What the pre-flight measured (None if it did not run).
    origin_s : float
        This session's sweep clock zero on the driver's host clock, s: its trials' ``t0_s``
        plus this is the driver's time (NaN where unknown).
    """

    path: Path
    n_planned: int
    n_recorded_now: int
    session: int
    preflight: PreflightReport | None = None
    origin_s: float = math.nan

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        return {
            "recording": str(self.path),
            "planned": self.n_planned,
            "recorded_now": self.n_recorded_now,
            "session": self.session,
            "preflight": None if self.preflight is None else self.preflight.to_dict(),
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


def _gyro_stalled(sess: Session, what: str) -> SensorError:
    return SensorError(
        f"gyro {gyro_name(sess.gyro)} stopped delivering samples ({what}; nothing for "
        f"{GYRO_STALL_S:.0f} s); check the sensor and its USB connection, then resume: the "
        "recording keeps every finished trial"
    )


def _stillrecording(sess: Session, duration_s: float) -> dict[str, NDArray[Any]]:
    st = sess.state()
    t_end = st.host_time_s + duration_s + 0.1
    while st.host_time_s < t_end:
        st = sess.state()
    s = sess.samples()
    block = sess.settings.gyro.block_samples
    n = len(s) - len(s) % block
    if n == 0:
        raise _gyro_stalled(sess, "the still recording")
    raw = s.raw[:n]
    arrival = s.arrival_s[block - 1 : n : block] - sess.origin_s
    return {
        "still_gyro_raw": raw,
        "still_gyro_counter": (s.counter_unwrapped[:n] % 65536).astype(np.uint16),
        "still_gyro_block_host_time_s": arrival,
    }


def _trial(
    sess: Session, plan: SweepPlan, i: int, session: int, truth: bool
) -> dict[str, NDArray[Any]]:
    settings = sess.settings
    prof = settings.profile
    lay = trial_layout(settings)
    joint = int(plan.joint[i])
    direction = float(plan.direction[i])
    qd = np.zeros(6)
    qd[joint - 1] = direction * prof.speed_rad_s
    a = prof.acceleration_rad_s2
    pulse = sess.pulse(joint, direction)
    t0, t_send, packages, trigger = pulse.t0, pulse.t_send, pulse.packages, pulse.trigger
    # Gyro: wait until the window has arrived, then take G samples from its start.
    t_need = t0 + prof.record_s + 0.01
    st = sess.last or trigger
    while st.host_time_s < t_need:
        st = sess.state()
    samples = sess.samples()
    if not len(samples):
        raise _gyro_stalled(sess, f"trial {i}")
    start = int(np.searchsorted(samples.host_time_s, t0 - prof.pre_s))
    first = (
        int(samples.counter_unwrapped[start])
        if start < len(samples)
        else int(samples.counter_unwrapped[-1]) + 1
    )
    while len(samples) - start < lay.n_gyro:
        st = sess.state()  # may drop the oldest buffered chunks: find the window's start again
        if st.host_time_s > t_need + GYRO_STALL_S:
            raise _gyro_stalled(sess, f"trial {i}")
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
        # the mean age of the packages this trial records (the first n_packages of the
        # window; the window itself may hold one more, which the recording drops)
        last = packages[: lay.n_packages][-1].host_time_s
        out["true_response_delay_s"] = np.array([drv.true_response_delay_s(t0, last)])
    return out


@dataclass(frozen=True)
class _Recorded:
    """What an earlier run recorded (nothing for a new recording)."""

    done: NDArray[np.int64]
    session: int
    last_t0_s: float
    has_still: bool
    power_on: float | None = None  # the header's power_on_s


def sweep_origin(driver: RobotDriver, last_t0_s: float) -> float:
    """Host time of the sweep clock's zero: now for a new recording; for a resumed one, so
    that the sweep clock goes on 10 s after the last recorded trial (its sessions' host
    clocks are unrelated)."""
    now = float(getattr(driver, "clock", time.monotonic)())
    return now if not math.isfinite(last_t0_s) else now - (last_t0_s + 10.0)


def power_on_header(driver: RobotDriver, origin: float) -> dict[str, float]:
    """``{"power_on_s": ...}``, the sweep time of the robot's power-on, when the driver knows
    it (``power_on_s``, its host time: the simulated robots), else nothing: the recording's
    thermal clock (time since power-on) is then unknown."""
    power_on = getattr(driver, "power_on_s", None)
    if power_on is None:
        return {}
    return {"power_on_s": float(power_on) - origin}


def _recorded_so_far(out: Path, resume: bool, plan: SweepPlan) -> _Recorded:
    """Read what ``out`` holds, without writing, so the pre-flight runs before any write.

    Raises
    ------
    RecordingError
        ``out`` exists and ``resume`` is False, or it holds another plan.
    """
    nothing = _Recorded(np.zeros(0, np.int64), 0, -math.inf, False)
    if not out.exists():
        return nothing
    if not resume:
        raise RecordingError(
            f"recording {out} already exists; refusing to overwrite it. To continue an "
            "interrupted sweep use --resume (resume=True); to start over delete it"
        )
    with RecordingReader(out) as r:
        if r.header.get("plan") != plan.meta():
            raise RecordingError(
                f"{out} holds another plan ({r.header.get('plan')}); resume with the same "
                "--trials/--seed or --plan"
            )
        has_still = r.has_static("still_gyro_raw")
        if not r.n_trials:
            return _Recorded(nothing.done, 0, -math.inf, has_still, r.header.get("power_on_s"))
        return _Recorded(
            np.unique(r.read("trial")),
            int(r.read("session").max()) + 1,
            float(r.read("t0_s").max()),
            has_still,
            r.header.get("power_on_s"),
        )


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
    preflight: bool = True,
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
        The calibration motion, controller period and the gyro's constants
        (``SweepProtocol.for_robot(robot)`` with the sensor's measured constants).
    resume : bool
        Continue a run of the same plan.
    progress : bool
        Progress with ETA on stderr.
    source : str
        Where the data came from (the robot URL), for the header.
    preflight : bool, default True
        Check the gyro stream and that the gyro turns with the robot before anything is
        written (see :mod:`timedexec.calibration._preflight`); the robot makes the first
        trial's motion once more.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    ConfigError
        The pre-flight found the gyro silent, sending something else, at the wrong rate,
        or not turning with the robot (the message names it and what it saw); nothing was
        written.
    DriverError
        The robot did not move in the pre-flight, or stopped answering.
    SensorError
        The gyro stopped delivering samples during the sweep (resume afterwards).
    RecordingError
        The recording cannot be written (disk full: resume when there is room) or resumed.
    """
    if plan.robot != protocol.robot:
        raise ConfigError(f"plan is for {plan.robot}, the protocol for {protocol.robot}")
    truth = hasattr(driver, "true_onset_s")
    header = {
        "source": source or "live",
        "robot": protocol.spec.to_dict(),
        "profile": protocol.profile.to_dict(),
        "controller_period_s": protocol.controller_period_s,
        "gyro": protocol.gyro.to_dict(),
        "plan": plan.meta(),
        "time_origin": "trial time 0 = host arrival of the trigger state package",
    }
    out = Path(out)
    before = _recorded_so_far(out, resume, plan)
    todo = np.setdiff1d(np.arange(len(plan)), before.done)
    origin = sweep_origin(driver, before.last_t0_s)
    if before.power_on is not None:
        header["power_on_s"] = before.power_on  # as the first session recorded it
    elif not out.exists():
        header.update(power_on_header(driver, origin))
    sess = Session(driver, gyro, protocol, origin)
    if len(todo) or not before.has_still:
        sess.catch_up()  # no motion planned on packages that waited in a queue
    report = None
    if preflight and (len(todo) or not before.has_still):
        report = check_stream(sess)
        if len(todo):
            first = int(todo[0])
            sess.move_to(plan.q_start_rad[first])
            sess.wait_still(min_s=0.2)
            report = check_motion(
                sess, report, int(plan.joint[first]), float(plan.direction[first])
            )
    with RecordingWriter(
        out, header=header, fields=_live_fields(protocol, truth), resume=resume
    ) as w:
        if resume and w.header.get("plan") != plan.meta():
            raise RecordingError(
                f"{out} holds another plan ({w.header.get('plan')}); resume with the same "
                "--trials/--seed or --plan"
            )
        for name, arr in plan.to_arrays().items():
            if not w.has_static(name):
                w.write_static(name, arr)
        todo = np.setdiff1d(np.arange(len(plan)), w.completed_trials)
        if not w.has_static("still_gyro_raw"):
            if len(todo):
                sess.move_to(plan.q_start_rad[todo[0]])
            sess.wait_still(min_s=0.2)
            for name, arr in _stillrecording(sess, protocol.still_s).items():
                w.write_static(name, arr)
        bar = Progress(len(todo), f"calibrate {protocol.robot}", enabled=progress)
        try:
            current = None
            for i in todo:
                if current is None or not np.allclose(plan.q_start_rad[i], current):
                    sess.move_to(plan.q_start_rad[i])
                    current = plan.q_start_rad[i]
                sess.wait_still(min_s=protocol.trial_gap_s)
                w.append(_trial(sess, plan, int(i), before.session, truth))
                bar.update()
        finally:
            bar.close()
        driver.stop()
    return CalibrationResult(out, len(plan), len(todo), before.session, report, origin)


class DriverRunner:
    """An adaptive sweep's robot: any :class:`~timedexec.drivers.RobotDriver` with its gyro
    (the trials, still recording, sessions and pre-flight of :func:`run_calibration`).

    Parameters
    ----------
    driver : RobotDriver
        Connected driver.
    gyro : GyroSource
        The gyro on the flange.
    protocol : SweepProtocol
        Motion, controller period, the gyro's constants.
    source : str
        Where the data came from (the robot URL), for the header.
    preflight : bool
        Check the gyro stream and that it turns with the robot before anything is written.
    """

    def __init__(
        self,
        driver: RobotDriver,
        gyro: GyroSource,
        protocol: SweepProtocol,
        *,
        source: str = "",
        preflight: bool = True,
    ) -> None:
        self.driver = driver
        self.gyro = gyro
        self.protocol = protocol
        self.robot = protocol.robot
        prof = protocol.profile
        # a trial: the record window after the trigger, then the stillness the next needs
        self.trial_s = prof.record_s + protocol.trial_gap_s + prof.pre_s
        self.move_s = protocol.config_move_s
        self.source = source
        self.preflight = preflight
        self.truth = hasattr(driver, "true_onset_s")
        self.report: PreflightReport | None = None
        self._sess: Session | None = None
        self._session = 0
        self._power_on: float | None = None
        self._current: NDArray[np.float64] | None = None

    def header(self) -> dict[str, Any]:
        """The header of :func:`run_calibration` (without the plan)."""
        header: dict[str, Any] = {
            "source": self.source or "live",
            "robot": self.protocol.spec.to_dict(),
            "profile": self.protocol.profile.to_dict(),
            "controller_period_s": self.protocol.controller_period_s,
            "gyro": self.protocol.gyro.to_dict(),
            "time_origin": "trial time 0 = host arrival of the trigger state package",
        }
        if self._power_on is not None:
            header["power_on_s"] = self._power_on
        return header

    def fields(self) -> list[Field]:
        """The live recording's fields (sessions, raw packages, truth on a simulator)."""
        return _live_fields(self.protocol, self.truth)

    def prepare(self, out: Path, plan: SweepPlan, first_row: int, resume: bool) -> None:
        """Continue the sweep clock of a resumed recording, then the pre-flight."""
        last_t0 = -math.inf
        if resume:
            with RecordingReader(out) as r:
                self._power_on = r.header.get("power_on_s")
                if r.n_trials:
                    last_t0 = float(r.read("t0_s").max())
                    self._session = int(r.read("session").max()) + 1
        origin = sweep_origin(self.driver, last_t0)
        if not resume:
            self._power_on = power_on_header(self.driver, origin).get("power_on_s")
        sess = Session(self.driver, self.gyro, self.protocol, origin)
        self._sess = sess
        sess.catch_up()
        if self.preflight:
            report = check_stream(sess)
            sess.move_to(plan.q_start_rad[first_row])
            self._current = plan.q_start_rad[first_row]
            sess.wait_still(min_s=0.2)
            self.report = check_motion(
                sess, report, int(plan.joint[first_row]), float(plan.direction[first_row])
            )

    def begin(self, writer: RecordingWriter, plan: SweepPlan) -> None:
        """The still recording, where the sweep's first configuration waits."""
        sess = self._session_()
        if not writer.has_static("still_gyro_raw"):
            sess.wait_still(min_s=0.2)
            for name, arr in _stillrecording(sess, self.protocol.still_s).items():
                writer.write_static(name, arr)

    def _session_(self) -> Session:
        if self._sess is None:
            raise ConfigError("DriverRunner: call prepare() first")
        return self._sess

    def now_s(self) -> float:
        """The sweep clock now, s."""
        sess = self._session_()
        return sess.clock() - sess.origin_s

    @property
    def origin_s(self) -> float:
        """This session's sweep clock zero on the driver's host clock, s (NaN before
        :meth:`prepare`)."""
        return math.nan if self._sess is None else self._sess.origin_s

    @property
    def session(self) -> int:
        """This session's number in the recording (0 for a new one, +1 per resume)."""
        return self._session

    def run(
        self, plan: SweepPlan, rows: NDArray[np.int64], until_s: float
    ) -> Iterator[dict[str, Any]]:
        """Each row as one trial (move when the configuration changes, wait until still)."""
        sess = self._session_()
        for i in rows.tolist():
            if self.now_s() + self.trial_s > until_s:
                return
            q = plan.q_start_rad[i]
            if self._current is None or not np.allclose(q, self._current):
                sess.move_to(q)
                self._current = q
            sess.wait_still(min_s=self.protocol.trial_gap_s)
            yield _trial(sess, plan, int(i), self._session, self.truth)

    def finish(self) -> None:
        """Stop the robot."""
        self.driver.stop()
