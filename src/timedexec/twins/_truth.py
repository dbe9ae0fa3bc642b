"""The protocol twins' ground truth: one reader of their JSON-lines files, and the truth
of a live calibration run against a twin.

A live run (:func:`~timedexec.calibration.run_calibration` through ``ur://`` or ``rsi://``)
against the UR twin (:class:`~timedexec.twins.URTwin`) or the RSI twin
(:class:`~timedexec.twins.RSITwin`) records what a real robot would give; the twin
keeps the truth on its side, in controller time. :func:`twin_truth_table` joins the two with
the definitions the simulator uses (``timedexec._signal.ONSET_FRACTION``,
``timedexec.sim``):

* **true actuation delay** = the instant the actuated joint's physical speed reaches
  ``ONSET_FRACTION`` x the commanded speed (the twin's ground-truth onset, controller time
  mapped to host time) minus the instant the commanded ramp reaches that speed after the
  command was sent (recorded send time + ``ONSET_FRACTION`` x speed / acceleration);
* **true response delay** = the mean over the trial's packages of host arrival minus the
  instant the package's state was sampled (controller time mapped to host time): the RTDE
  ``timestamp`` for UR, the IPOC's cycle boundary for RSI. Beside it, the ages weighted by
  the squared reported speed (what a time-shift fit of the reported motion measures), which
  differs from the mean when a package was held up in a trial (an overloaded machine).

Controller time ``t`` happens at host time ``t0_monotonic_s + t`` (both twins publish
``t0_monotonic_s``; :func:`time.monotonic` is shared by every process of the machine).

What the recording lacks
------------------------
Recordings keep host times relative to each trial's trigger package; the absolute host time
of that package (the session's clock origin) is not stored. :class:`~timedexec.drivers.HostTimeTap` wraps the
driver given to the runner and logs the absolute host time of every package by controller
time, which anchors each trial (``host_times=`` of :func:`twin_truth_table`).

Gyro time base of a twin's pseudo-terminal
------------------------------------------
Extraction subtracts the header's ``gyro.transport_latency_s`` (the simulated sensor's
``usb_latency_s``, 0.8 ms) from the lower envelope of block arrival times. A pty has a
different minimum latency, so it must be measured and put into the settings given to the
runner, as a user must do for a real sensor (:func:`measure_gyro_transport_latency`
measures it against the twin's sample clock; for a real sensor the same number comes from
an external reference such as a sync pulse the sensor time-stamps, or a USB analyser).
"""

from __future__ import annotations

import bisect
import json
import math
import os
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._signal import ONSET_FRACTION
from timedexec._types import FloatArray
from timedexec.delays import DelayTable
from timedexec.drivers import HostTimeTap
from timedexec.errors import ConfigError, ProtocolError, RecordingError
from timedexec.recording import RecordingReader
from timedexec.sim import default_settings

__all__ = [
    "GyroClockTruth",
    "TruthComparison",
    "TwinTruth",
    "compare_with_truth",
    "envelope_transport_latency",
    "gyro_window_start_s",
    "iter_truth_records",
    "measure_gyro_transport_latency",
    "read_twin_truth",
    "twin_truth_table",
]


def iter_truth_records(path: str | os.PathLike[str]) -> Iterator[dict[str, Any]]:
    """The records of a twin's truth file in order, skipping a line still being written.

    A twin appends one JSON object per line while it runs; the last line may be partial
    when the file is read during the run, and is skipped (it is complete on the next read).
    """
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.strip()
            if not line:
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line being written right now
            if isinstance(record, dict):
                yield record


def _lookup(times: Mapping[float, float], keys: FloatArray, what: str) -> FloatArray:
    """Host time of each controller time in ``keys`` (exact match, else within 1 µs)."""
    out = np.full(keys.shape, np.nan)
    sorted_keys = sorted(times)
    for i, k in enumerate(keys.tolist()):
        if not math.isfinite(k):
            continue
        hit = times.get(k)
        if hit is None:
            j = bisect.bisect_left(sorted_keys, k)
            near = [c for c in sorted_keys[max(0, j - 1) : j + 1] if abs(c - k) < 1e-6]
            if not near:
                raise RecordingError(
                    f"{what}: no logged package with controller time {k!r}; pass the "
                    "HostTimeTap that wrapped the driver of this very run"
                )
            hit = times[near[0]]
        out[i] = hit
    return out


# --------------------------------------------------------------------------- truth files


def read_twin_truth(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a twin's JSON-lines ground truth (UR twin, RSI twin or the RSI gyro sidecar).

    Returns
    -------
    dict
        ``meta`` (the last ``meta`` line: ``t0_monotonic_s``, ``period_s``, robot, for RSI
        ``ipoc_start`` and ``ipoc_step``), ``commands`` (latest record per command id,
        controller time, s), ``gyro`` (the last ``gyro`` line: the gyro twin's
        ``start_time_s``, ``true_rate_hz``, ``dlpf_group_delay_s``), ``rsi`` (RSI stop
        reason and counters), ``rsi_gyro`` (problems of the RSI gyro factory: rate requests
        that timed out waiting for the physics, motion before the origin was published).
    """
    out: dict[str, Any] = {"meta": {}, "commands": {}, "gyro": {}, "rsi": {}, "rsi_gyro": {}}
    for record in iter_truth_records(path):
        event = record.pop("event", "")
        if event == "command":
            out["commands"][int(record["id"])] = record
        elif event in ("meta", "gyro", "rsi", "rsi_gyro"):
            out[event] = record
    return out


# --------------------------------------------------------------------------- the truth table


@dataclass(frozen=True)
class TwinTruth:
    """Ground truth per recorded trial of a live run against a twin (rows in trial order).

    Attributes
    ----------
    trial, joint, direction : ndarray of int, shape (n,)
        Plan index, actuated joint (1-based), direction.
    true_onset_s : ndarray, shape (n,)
        Physical onset of the actuated joint, trial time (s after the trigger package).
    true_actuation_delay_s, true_response_delay_s : ndarray, shape (n,)
        Ground truth, s (NaN where the twin recorded no onset); the response delay is the
        mean age of the trial's packages on arrival (the simulator's definition).
    true_response_delay_motion_s : ndarray, shape (n,)
        The package ages weighted by the squared reported speed of the actuated joint, s:
        what a time-shift fit of the reported motion measures. Equal to the mean while
        every package is equally old; apart when packages were delayed unevenly.
    package_age_spread_s : ndarray, shape (n,)
        Oldest minus youngest package age on arrival within the trial, s (a package held
        up in the controller or in transit shows here).
    t0_host_s : ndarray, shape (n,)
        :func:`time.monotonic` of each trial's trigger package, s.
    n_packages : ndarray of int, shape (n,)
        Packages averaged for the response delay.
    """

    trial: NDArray[np.int64]
    joint: NDArray[np.int64]
    direction: NDArray[np.int64]
    true_onset_s: FloatArray
    true_actuation_delay_s: FloatArray
    true_response_delay_s: FloatArray
    true_response_delay_motion_s: FloatArray
    package_age_spread_s: FloatArray
    t0_host_s: FloatArray
    n_packages: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.trial.shape[0])


def _ipoc_of(raw: NDArray[np.uint8], length: int) -> int:
    from timedexec._rsi_xml import parse_rob

    try:
        frame = parse_rob(bytes(raw[:length]))
    except ProtocolError as exc:
        raise RecordingError(f"a recorded RSI package does not parse ({exc})") from exc
    if frame is None:
        raise RecordingError("a recorded RSI package is an empty <Rob> frame")
    return int(frame.ipoc)


def twin_truth_table(
    recording_path: str | os.PathLike[str],
    truth_path: str | os.PathLike[str],
    t0_monotonic_s: float | None = None,
    *,
    host_times: Mapping[float, float] | HostTimeTap | None = None,
    trial_t0_host_s: ArrayLike | None = None,
    onset_threshold_rad_s: float | None = None,
) -> TwinTruth:
    """The true actuation and response delay of every trial of a live run against a twin.

    Parameters
    ----------
    recording_path : path
        Recording written by :func:`~timedexec.calibration.run_calibration`.
    truth_path : path
        The twin's ground-truth file (``truth_path`` of the UR or RSI twin; the RSI twin
        writes it when it stops).
    t0_monotonic_s : float, optional
        Host time of controller time 0, s; default: the truth file's ``meta`` line.
    host_times : mapping or HostTimeTap
        Controller time -> host arrival time of the run's packages (the
        :class:`HostTimeTap` that wrapped the driver); anchors each trial's trigger package.
    trial_t0_host_s : array_like, shape (n,), optional
        Instead of ``host_times``: :func:`time.monotonic` of each recorded trial's trigger
        package, in recording order.
    onset_threshold_rad_s : float, optional
        Speed at which the twin's simulated controller marked onsets; default: its
        :func:`~timedexec.sim.default_settings` value. It must equal ``ONSET_FRACTION`` x the
        recorded calibration speed, or the truth would use another onset than extraction.

    Returns
    -------
    TwinTruth

    Raises
    ------
    ConfigError
        If the twin's onset threshold does not match the recording's profile, or no anchor
        is given.
    RecordingError
        If a package cannot be anchored or parsed.
    """
    truth = read_twin_truth(truth_path)
    meta = truth["meta"]
    if t0_monotonic_s is None:
        if "t0_monotonic_s" not in meta:
            raise ConfigError(
                f"{truth_path}: no meta line with t0_monotonic_s; pass t0_monotonic_s="
            )
        t0_monotonic_s = float(meta["t0_monotonic_s"])
    with RecordingReader(recording_path) as r:
        header = r.header
        trial = r.read("trial").astype(np.int64)
        send = r.read("cmd_send_time_s")
        host = r.read("state_host_time_s")
        ctrl = r.read("state_controller_time_s")
        qd_reported = r.read("state_qd_rad_s")
        plan_joint = r.static("plan_joint")
        plan_dir = r.static("plan_direction")
        kuka = str(header["robot"].get("vendor", "")) == "kuka" or "ipoc_start" in meta
        raw = r.read("state_raw") if kuka else None
        raw_len = r.read("state_raw_len") if kuka else None
    robot = str(header["robot"]["name"])
    profile = header["profile"]
    speed = float(profile["speed_rad_s"])
    accel = float(profile["acceleration_rad_s2"])
    level = ONSET_FRACTION * speed
    threshold = (
        default_settings(robot).servo.onset_threshold_rad_s
        if onset_threshold_rad_s is None
        else float(onset_threshold_rad_s)
    )
    if not math.isclose(threshold, level, rel_tol=1e-9):
        raise ConfigError(
            f"the twin marks onsets at {threshold} rad/s but the recording's profile defines "
            f"the onset at ONSET_FRACTION x speed = {level} rad/s; run the twin with "
            f"settings whose servo.onset_threshold_rad_s is {level}, or pass the threshold "
            "it used as onset_threshold_rad_s"
        )

    # Absolute host time of every trial's trigger package.
    n = len(trial)
    if trial_t0_host_s is not None:
        t0_host = np.asarray(trial_t0_host_s, dtype=np.float64).reshape(-1)
        if t0_host.shape != (n,):
            raise ConfigError(f"trial_t0_host_s has {t0_host.size} values for {n} trials")
    elif host_times is not None:
        times = host_times.host_times if isinstance(host_times, HostTimeTap) else host_times
        t0_host = _lookup(times, ctrl[:, 0].astype(np.float64), str(recording_path))
    else:
        raise ConfigError(
            "anchor the recording to the host clock: pass host_times= (the HostTimeTap that "
            "wrapped the driver) or trial_t0_host_s="
        )

    # Sampling instant of every package, host time.
    if kuka:
        assert raw is not None
        assert raw_len is not None
        ipoc_start = int(meta["ipoc_start"])
        ipoc_step = int(meta["ipoc_step"])
        period = float(meta["period_s"])
        sample_ctrl = np.full(host.shape, np.nan)
        for i, k in zip(*np.nonzero(np.isfinite(host)), strict=True):
            ipoc = _ipoc_of(raw[i, k], int(raw_len[i, k]))
            sample_ctrl[i, k] = (ipoc - ipoc_start) / ipoc_step * period
    else:
        sample_ctrl = ctrl.astype(np.float64)  # RTDE timestamp = sampling instant
    age = (t0_host[:, None] + host) - (t0_monotonic_s + sample_ctrl)
    ok = np.isfinite(age)
    count = ok.sum(axis=1)
    age0 = np.where(ok, age, 0.0)
    response = np.where(count > 0, age0.sum(axis=1) / np.maximum(count, 1), np.nan)
    spread = np.where(
        count > 0,
        np.max(np.where(ok, age, -np.inf), axis=1) - np.min(np.where(ok, age, np.inf), axis=1),
        np.nan,
    )
    joint = plan_joint[trial].astype(np.int64)
    speed_sq = np.where(ok, qd_reported[np.arange(n), :, joint - 1].astype(np.float64) ** 2, 0.0)
    weight = speed_sq.sum(axis=1)
    response_motion = np.where(
        weight > 0, (age0 * speed_sq).sum(axis=1) / np.where(weight > 0, weight, 1.0), np.nan
    )

    # Onset: the first onset of the actuated joint after the command left.
    direction = plan_dir[trial].astype(np.int64)
    records = list(truth["commands"].values())
    send_host = t0_host + send
    onset_host = np.full(n, np.nan)
    for i in range(n):
        after = send_host[i] - t0_monotonic_s  # controller time the command left
        col = int(joint[i]) - 1
        later = [
            float(rec["onset_s"][col])
            for rec in records
            if rec.get("onset_s")
            and rec["onset_s"][col] is not None
            and float(rec["onset_s"][col]) >= after
        ]
        if later:
            onset_host[i] = t0_monotonic_s + min(later)
    actuation = onset_host - (send_host + level / accel)
    order = np.argsort(trial)
    return TwinTruth(
        trial=trial[order],
        joint=joint[order],
        direction=direction[order],
        true_onset_s=(onset_host - t0_host)[order],
        true_actuation_delay_s=actuation[order],
        true_response_delay_s=response[order],
        true_response_delay_motion_s=response_motion[order],
        package_age_spread_s=spread[order],
        t0_host_s=t0_host[order],
        n_packages=count.astype(np.int64)[order],
    )


# --------------------------------------------------------------------------- comparison


@dataclass(frozen=True)
class TruthComparison:
    """Extracted delays against the twin's truth, per trial (s) and summarised (ms).

    Attributes
    ----------
    trial : ndarray of int, shape (n,)
    flag : ndarray of str, shape (n,)
        The extraction's flag ("" when measured).
    actuation_error_s, response_error_s : ndarray, shape (n,)
        Extracted minus true, s (NaN for flagged trials).
    response_motion_error_s : ndarray, shape (n,)
        Extracted response delay minus the motion-weighted package age, s.
    """

    trial: NDArray[np.int64]
    flag: NDArray[Any]
    actuation_error_s: FloatArray
    response_error_s: FloatArray
    response_motion_error_s: FloatArray

    @property
    def n_flagged(self) -> int:
        """Trials the extraction flagged."""
        return int(np.sum(self.flag != ""))

    def summary(self) -> dict[str, float | int]:
        """Trials, flagged, and RMS / max |error| / mean error of both delays (the response
        delay also against the motion-weighted age: ``response_motion_*``), ms."""
        out: dict[str, float | int] = {"trials": len(self.trial), "flagged": self.n_flagged}
        for name, err in (
            ("actuation", self.actuation_error_s),
            ("response", self.response_error_s),
            ("response_motion", self.response_motion_error_s),
        ):
            e = err[np.isfinite(err)] * 1e3
            out[f"{name}_rms_ms"] = float(np.sqrt(np.mean(e**2))) if e.size else math.nan
            out[f"{name}_max_ms"] = float(np.max(np.abs(e))) if e.size else math.nan
            out[f"{name}_mean_ms"] = float(np.mean(e)) if e.size else math.nan
        return out


def compare_with_truth(table: DelayTable, truth: TwinTruth) -> TruthComparison:
    """Match an extracted delay table to the twin's truth by trial.

    Raises
    ------
    ConfigError
        If the trials differ.
    """
    trial = np.asarray(table["trial"], dtype=np.int64)
    order = np.argsort(trial)
    if not np.array_equal(trial[order], truth.trial):
        raise ConfigError(
            f"the delay table holds trials {trial[order].tolist()}, the truth "
            f"{truth.trial.tolist()}; compare the table extracted from the same recording"
        )
    flag = np.asarray(table["flag"] if "flag" in table else [""] * len(trial), dtype=object)
    response = np.asarray(table["response_delay"], float)[order]
    return TruthComparison(
        trial=truth.trial,
        flag=flag[order],
        actuation_error_s=np.asarray(table["actuation_delay"], float)[order]
        - truth.true_actuation_delay_s,
        response_error_s=response - truth.true_response_delay_s,
        response_motion_error_s=response - truth.true_response_delay_motion_s,
    )


# --------------------------------------------------------------------------- gyro latency


@dataclass(frozen=True)
class GyroClockTruth:
    """The gyro twin's true sample clock: sample ``k`` is taken at
    ``start_time_s + k / true_rate_hz`` (host :func:`time.monotonic`, s)."""

    start_time_s: float
    true_rate_hz: float
    dlpf_group_delay_s: float

    @classmethod
    def from_truth(cls, path: str | os.PathLike[str]) -> GyroClockTruth:
        """From a truth file's ``gyro`` line (UR twin with ``imu_link``, RSI gyro sidecar)."""
        gyro = read_twin_truth(path)["gyro"]
        if not gyro:
            raise ConfigError(
                f"{path} has no gyro line; start the UR twin with imu_link= or the RSI twin "
                "with controller_factory=rsi_gyro_factory(link)"
            )
        return cls(
            float(gyro["start_time_s"]),
            float(gyro["true_rate_hz"]),
            float(gyro["dlpf_group_delay_s"]),
        )


def _true_index(clock: GyroClockTruth, counter: NDArray[Any], arrival_s: FloatArray) -> FloatArray:
    """The twin's sample index k of each 16-bit counter value (k mod 65536 = counter), the
    wraps resolved by the arrival time (any sample arrives within 4 s of being taken)."""
    c = np.asarray(counter, dtype=np.int64) % 65536
    k_est = (np.asarray(arrival_s, dtype=np.float64) - clock.start_time_s) * clock.true_rate_hz
    k: FloatArray = c + 65536.0 * np.round((k_est - c) / 65536.0)
    return k


def measure_gyro_transport_latency(
    reader: Any,
    clock: GyroClockTruth,
    *,
    duration_s: float = 3.0,
    settle_s: float = 1.0,
    poll_s: float = 0.01,
) -> float:
    """Minimum latency from taking a sample to the host read that delivers it, s.

    This is the constant the lower-envelope clock fit cannot observe (``timedexec.sensors``)
    and extraction subtracts as ``gyro.transport_latency_s``: measured on the newest sample
    of each read against the twin's true sample clock. Samples of the first ``settle_s``
    are dropped (a pty holds a backlog when it is opened, delivered faster than real time).

    Parameters
    ----------
    reader : GyroReader
        Open reader of the twin's pty (samples read here are consumed).
    clock : GyroClockTruth
        The twin's sample clock.
    duration_s, settle_s, poll_s : float
        How long to measure, to drain first, and how often to take samples, s.

    Raises
    ------
    ConfigError
        If no sample came.
    """
    start = time.monotonic()
    deadline = start + settle_s + duration_s
    best = math.inf
    while time.monotonic() < deadline:
        time.sleep(poll_s)
        s = reader.read(timeout_s=0.0)
        if not len(s) or time.monotonic() < start + settle_s:
            continue
        arrival = np.asarray(s.arrival_s, dtype=np.float64)
        taken = clock.start_time_s + _true_index(clock, s.counter_unwrapped, arrival) / (
            clock.true_rate_hz
        )
        newest = np.append(np.flatnonzero(np.diff(arrival)), len(arrival) - 1)
        best = min(best, float(np.min(arrival[newest] - taken[newest])))
    if not math.isfinite(best):
        raise ConfigError(
            f"no gyro samples in {settle_s + duration_s} s of reading; is the twin's gyro "
            "streaming to this port?"
        )
    return best


def envelope_transport_latency(
    recording_path: str | os.PathLike[str], clock: GyroClockTruth, truth: TwinTruth
) -> float:
    """The transport latency that the recording's block arrivals imply, s (a diagnostic).

    Extraction fits the lower envelope of the block arrivals and subtracts the header's
    ``gyro.transport_latency_s`` from it; the gyro time base is right when that constant
    equals this one: the lower-envelope line's mean height above the twin's true sample
    times, over all recorded blocks. The difference to the value measured before the run
    (:func:`measure_gyro_transport_latency`) shifts every extracted actuation delay by its
    negative and every response delay by itself.
    """
    from timedexec.sensors import fit_clock_lower_envelope

    with RecordingReader(recording_path) as r:
        block = int(r.header["gyro"]["block_samples"])
        t0 = r.read("t0_s")
        arrivals = r.read("gyro_block_host_time_s").astype(np.float64)
        counters = r.read("gyro_counter")
        still_t = r.static("still_gyro_block_host_time_s").astype(np.float64)
        still_c = r.static("still_gyro_counter")
        trial = r.read("trial")
    order = np.argsort(trial)
    if not np.array_equal(trial[order], truth.trial):
        raise ConfigError("the truth table belongs to another recording (trials differ)")
    origin = float(np.median(truth.t0_host_s - t0[order]))  # host time of sweep time 0
    t_parts = [origin + still_t, *(origin + t0[:, None] + arrivals)]
    c_parts = [still_c[block - 1 :: block][: len(still_t)], *counters[:, block - 1 :: block]]
    t_all = np.concatenate([np.ravel(t) for t in t_parts])
    c_all = np.concatenate([np.ravel(c) for c in c_parts])
    k = _true_index(clock, c_all, t_all).astype(np.int64)
    fit = fit_clock_lower_envelope(k, t_all, nominal_rate_hz=clock.true_rate_hz)
    taken = clock.start_time_s + k / clock.true_rate_hz
    return float(np.mean(fit.to_host_time(k) - taken))


def gyro_window_start_s(
    recording_path: str | os.PathLike[str], clock: GyroClockTruth, truth: TwinTruth
) -> FloatArray:
    """When each trial's recorded gyro window starts, trial time (s), in ``truth``'s order.

    The runner should record from ``-profile.pre_s`` on (to within a sample and the clock
    fit's latency, well under 1 ms); a later start means it lost the beginning of the window
    (pre-command samples give extraction its zero-rate).
    """
    with RecordingReader(recording_path) as r:
        trial = r.read("trial")
        first_counter = r.read("gyro_counter")[:, 0]
        first_arrival = r.read("gyro_block_host_time_s")[:, 0].astype(np.float64)
    order = np.argsort(trial)
    if not np.array_equal(trial[order], truth.trial):
        raise ConfigError("the truth table belongs to another recording (trials differ)")
    arrival = truth.t0_host_s + first_arrival[order]
    k = _true_index(clock, first_counter[order], arrival)
    start: FloatArray = clock.start_time_s + k / clock.true_rate_hz - truth.t0_host_s
    return start
