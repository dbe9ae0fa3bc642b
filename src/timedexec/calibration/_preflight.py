"""Pre-flight of a calibration sweep: the gyro streams, and it turns with the robot.

Before the first trial (and before anything is written) the runner checks, in this order:

1. **Stream** (robot at rest): the gyro delivers a valid frame within
   :data:`STARTUP_S` (a sensor that resets when its port is opened boots meanwhile), then
   valid frames at its nominal rate, within :data:`RATE_BAND`, over a window of
   :data:`STREAM_WINDOW_S` of robot time, one of the windows within :data:`SETTLE_S` (what
   a port buffered before it was opened arrives faster than real time at first: a
   pseudo-terminal delivered 14,000 samples/s in the first half second). A silent port, a
   port that sends something else (wrong device, wrong baud rate) and a sensor configured
   for another rate fail here, within seconds, naming the port and what arrived.
2. **Motion** (at the first trial's start pose): the robot makes the first trial's motion
   (one joint out and back, ``profile.displacement_rad`` each way) while the gyro is read.
   The robot must travel at least :data:`MIN_TRAVEL_FRACTION` of the commanded distance,
   and the gyro's peak rate (10 ms mean, zero-rate removed) must lie within
   :data:`MOTION_BAND` of the joint's peak speed as the robot reports it (over the same
   10 ms, by the controller's stamps; the commanded speed where the state has no stamps):
   a single revolute joint turning at ``v`` turns the flange, and any sensor fixed to it,
   at ``|omega| = v`` whatever the mounting orientation. The reported speed, not the
   commanded one: a host that stalls mid-pulse makes an RSI robot catch up on its late
   corrections faster than commanded (the CI run of 2026-11-29: the KR 5 twin's gyro saw
   0.61 rad/s at 0.40 commanded, and the check blamed the gyro's full scale), and a
   pendant's speed override makes it slower. A gyro that is not on this robot's flange
   (a ``sim://`` gyro next to a real robot, the wrong port) sees nothing; a wrong
   full-scale setting scales the peak by 2 or more.

Errors: :class:`~timedexec.errors.ConfigError` for the gyro (exit 2 through the CLI: the
``--imu`` given is not a working gyro on this robot), :class:`~timedexec.errors.DriverError`
when the robot does not move (exit 3: a robot fault).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from timedexec.calibration._session import Session, gyro_name
from timedexec.errors import ConfigError, DriverError

__all__ = [
    "MIN_TRAVEL_FRACTION",
    "MOTION_BAND",
    "RATE_BAND",
    "SETTLE_S",
    "STARTUP_S",
    "STREAM_WINDOW_S",
    "PreflightReport",
    "check_motion",
    "check_stream",
]

#: Robot time allowed for the first valid frame, s: an Arduino-style sensor that resets when
#: its port opens streams after about 1.5 s.
STARTUP_S = 3.0
#: Robot time allowed for the delivered rate to settle into :data:`RATE_BAND`, s.
SETTLE_S = 3.0
#: Robot time over which the stream is counted, s. The reader delivers in reads of about
#: 20 ms, so the count is exact to one read: +-4 % of 0.5 s.
STREAM_WINDOW_S = 0.5
#: Accepted delivered rate / nominal rate: +-15 % (+-4 % read granularity, +-1 % clock
#: error of a crystal, the rest for a busy host; a sensor at another DLPF setting, 1 kHz,
#: or a lossy link losing a sixth of its frames fails).
RATE_BAND = (0.85, 1.15)
#: Accepted gyro peak / commanded joint speed. The robot reaches the commanded speed in the
#: hold phase (simulated UR10: 0.97-1.01); a wrong full-scale setting gives x0.5 or x2.
MOTION_BAND = (0.6, 1.5)
#: The robot must travel at least this fraction of the commanded out distance.
MIN_TRAVEL_FRACTION = 0.5
_SMOOTH_S = 0.01  # moving mean of the rate magnitude: the noise drops ~9x at 8 kHz
_BASELINE_S = 0.2  # still recording before the motion: the zero-rate to remove


@dataclass(frozen=True, kw_only=True)
class PreflightReport:
    """What the pre-flight measured.

    Attributes
    ----------
    gyro : str
        The gyro as messages name it (its port).
    samples : int
        Samples delivered in the stream window.
    rate_hz : float
        Delivered samples per second of robot time, Hz.
    nominal_rate_hz : float
        What the protocol expects, Hz.
    joint : int or None
        Joint moved by the motion check (1-based); None if it was not run.
    commanded_rad_s : float or None
        Commanded joint speed, rad/s.
    travel_rad : float or None
        Largest joint travel the robot reported, rad.
    gyro_peak_rad_s : float or None
        Largest 10 ms mean rate magnitude the gyro saw (zero-rate removed), rad/s.
    reported_peak_rad_s : float or None
        Largest 10 ms mean speed of the joint by its reported positions, rad/s (what the
        gyro's peak is checked against; None without controller stamps).
    """

    gyro: str
    samples: int
    rate_hz: float
    nominal_rate_hz: float
    joint: int | None = None
    commanded_rad_s: float | None = None
    travel_rad: float | None = None
    gyro_peak_rad_s: float | None = None
    reported_peak_rad_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation."""
        return asdict(self)


def _stream_words(gyro: object) -> str:
    """What the gyro's reader counted (bytes, frames, CRC errors), if it counts."""
    stats = getattr(gyro, "stats", None)
    if stats is None:
        return ""
    return (
        f" ({stats.bytes_read} bytes read, {stats.frames_ok} valid frames, "
        f"{stats.checksum_errors} checksum errors, {stats.resync_bytes_skipped} bytes "
        "outside frames)"
    )


def check_stream(sess: Session) -> PreflightReport:
    """Wait for the gyro's first valid frame, then count what it delivers in windows of
    :data:`STREAM_WINDOW_S` of robot time until one is within :data:`RATE_BAND`.

    Raises
    ------
    ConfigError
        Nothing within :data:`STARTUP_S`, or bytes without valid frames, or a rate outside
        :data:`RATE_BAND` of the nominal one in every window until :data:`SETTLE_S`; the
        message names the gyro, what was seen (the last window) and what to check.
    """
    name = gyro_name(sess.gyro)
    nominal = float(sess.settings.gyro.nominal_rate_hz)
    sess.catch_up()  # windows in the robot's present time, not in a queue's past
    sess.discard_gyro()  # what queued up since the port was opened is no measure
    t_a = sess.state().host_time_s
    w_a = time.monotonic()
    st = sess.state()
    # A sensor boots in real time: wait STARTUP_S of it too. A virtual robot's time can run
    # ahead of the host clock (a simulated robot with a real port, to check the wiring):
    # hold it back meanwhile, or its 3 s passed in a tenth of one and a booting sensor, or
    # one that sends garbage every 20 ms, had sent nothing yet.
    while not len(sess.samples_since(t_a)) and (
        st.host_time_s < t_a + STARTUP_S or time.monotonic() < w_a + STARTUP_S
    ):
        ahead = (st.host_time_s - t_a) - (time.monotonic() - w_a)
        if ahead > 0:
            time.sleep(min(ahead, 0.02))
        st = sess.state()
    if not len(sess.samples_since(t_a)):
        waited = st.host_time_s - t_a
        seen = _stream_words(sess.gyro)
        stats = getattr(sess.gyro, "stats", None)
        if stats is not None and stats.bytes_read > 0:
            raise ConfigError(
                f"gyro {name} sent data but no valid gyro frame in {waited:.1f} s{seen}: "
                "it is not the gyro, or it runs at another baud rate or protocol; check "
                "--imu and the sensor's firmware (docs/gyro-protocol.md)"
            )
        raise ConfigError(
            f"gyro {name} delivered nothing in {waited:.1f} s{seen}: check that the sensor "
            "is powered and streaming and that --imu names its port"
        )
    lo, hi = RATE_BAND
    settled = st.host_time_s + SETTLE_S
    while True:
        t_b = st.host_time_s
        while st.host_time_s < t_b + STREAM_WINDOW_S:
            st = sess.state()
        # The rate on the clock that stamps the samples: those that arrived in the last
        # window before the newest one. Counted against the robot's package times instead,
        # a simulated robot that runs behind the host clock (it computes its cycles no
        # faster than real time on a slow machine) inflated the rate by its lag.
        arrival = sess.samples().arrival_s
        elapsed = STREAM_WINDOW_S
        n = int(np.count_nonzero(arrival > arrival[-1] - elapsed)) if len(arrival) else 0
        rate = n / elapsed
        if lo * nominal <= rate <= hi * nominal or st.host_time_s >= settled:
            break
    if not lo * nominal <= rate <= hi * nominal:
        raise ConfigError(
            f"gyro {name} delivered {rate:,.0f} samples/s ({n} in {elapsed:.2f} s)"
            f"{_stream_words(sess.gyro)}, expected {nominal:,.0f} (+-{(hi - 1) * 100:.0f} %): "
            "check the sensor's rate setting (8 kHz, DLPF off) and its USB connection"
        )
    return PreflightReport(gyro=name, samples=n, rate_hz=rate, nominal_rate_hz=nominal)


def check_motion(
    sess: Session, stream: PreflightReport, joint: int, direction: float
) -> PreflightReport:
    """Move ``joint`` as a trial does and check that the robot moved and the gyro turned.

    Call it with the robot at rest at the trial's start pose.

    Raises
    ------
    DriverError
        The robot travelled less than :data:`MIN_TRAVEL_FRACTION` of the commanded distance.
    ConfigError
        The gyro stopped, saw no motion, or a peak outside :data:`MOTION_BAND` of the
        commanded speed; naming the gyro, the joint, the speed and what it saw.
    """
    settings = sess.settings
    prof = settings.profile
    name = stream.gyro
    st = sess.state()
    t_b = st.host_time_s
    while st.host_time_s < t_b + _BASELINE_S:
        st = sess.state()
    still = sess.samples_since(t_b)
    if not len(still):
        raise ConfigError(f"gyro {name} stopped delivering samples{_stream_words(sess.gyro)}")
    zero = still.rate_rad_s.mean(axis=0)
    q0 = st.q[joint - 1]
    pulse = sess.pulse(joint, direction)
    travel = max(abs(p.q[joint - 1] - q0) for p in pulse.packages)
    t_end = pulse.t0 + prof.record_s + 0.1  # the last samples are still on their way
    while st.host_time_s < t_end:
        st = sess.state()
    moving = sess.samples_since(pulse.t0)
    commanded = prof.speed_rad_s
    want = prof.displacement_rad
    if travel < MIN_TRAVEL_FRACTION * want:
        raise DriverError(
            f"the robot did not move: joint {joint} was commanded {want:.3f} rad at "
            f"{commanded:.2f} rad/s and travelled {travel:.4f} rad; check that it is enabled "
            "(remote control, no protective stop) and free to move"
        )
    if not len(moving):
        raise ConfigError(
            f"gyro {name} stopped delivering samples during the motion check"
            f"{_stream_words(sess.gyro)}"
        )
    k = max(1, round(_SMOOTH_S * stream.nominal_rate_hz))
    magnitude = np.linalg.norm(moving.rate_rad_s - zero, axis=1)
    if len(magnitude) >= k:
        magnitude = np.convolve(magnitude, np.full(k, 1.0 / k), mode="valid")
    peak = float(magnitude.max())
    reported = _reported_peak_speed(pulse.packages, joint, _SMOOTH_S)
    speed = commanded if reported is None else reported
    lo, hi = MOTION_BAND
    turned = (
        f"{commanded:.2f} rad/s"
        if reported is None
        else f"{reported:.2f} rad/s by its reported positions (commanded {commanded:.2f})"
    )
    what = (
        f"gyro {name} saw {peak:.3f} rad/s at most while joint {joint} turned at "
        f"{turned} ({travel:.3f} rad out and back)"
    )
    if peak < lo * speed:
        hint = (
            "is it fixed to this robot's flange, and is --imu its port? A sim:// gyro "
            "simulates a sensor of its own, not one on this robot"
            if peak < 0.1 * speed
            else "check that it is fixed rigidly to the flange and its full-scale setting "
            f"({settings.gyro.full_scale_dps} deg/s expected)"
        )
        raise ConfigError(f"{what}, expected about {speed:.2f} rad/s: {hint}")
    if peak > hi * speed:
        raise ConfigError(
            f"{what}, expected about {speed:.2f} rad/s: check its full-scale setting "
            f"({settings.gyro.full_scale_dps} deg/s expected)"
        )
    return PreflightReport(
        gyro=name,
        samples=stream.samples,
        rate_hz=stream.rate_hz,
        nominal_rate_hz=stream.nominal_rate_hz,
        joint=joint,
        commanded_rad_s=commanded,
        travel_rad=travel,
        gyro_peak_rad_s=peak,
        reported_peak_rad_s=reported,
    )


def _reported_peak_speed(packages: list[Any], joint: int, window_s: float) -> float | None:
    """The joint's largest mean speed over ``window_s`` (at least one controller period)
    by the reported positions, dated by the controller's stamps (a package held up and
    delivered in a burst moves no speed), rad/s; None where the stamps do not advance."""
    if len(packages) < 2:
        return None
    t = np.array([p.controller_time_s for p in packages], dtype=float)
    q = np.array([p.q[joint - 1] for p in packages], dtype=float)
    steps = np.diff(t)
    if not np.all(np.isfinite(steps)) or np.any(steps <= 0.0):
        return None
    m = min(len(t) - 1, max(1, round(window_s / float(np.median(steps)))))
    return float(np.max(np.abs(q[m:] - q[:-m]) / (t[m:] - t[:-m])))
