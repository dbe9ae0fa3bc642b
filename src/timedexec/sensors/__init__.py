"""timedexec.sensors: the gyro/IMU stream over pyserial (see docs/gyro-protocol.md).

- Frames: :func:`encode_frames`, :class:`FrameParser` (vectorised, resynchronising).
- Counter: :class:`CounterUnwrapper` (wraps, gaps), :func:`unwrap_counter` (offline),
  :func:`relative_counter_rows` (recorded windows of a lossy stream: duplicates, gaps).
- Clock: :class:`SensorClock` (lower-envelope fit of host_time = a + b·n),
  :func:`fit_clock_lower_envelope`, :func:`fit_clock_least_squares`;
  :func:`fit_clock_drifting` -> :class:`DriftingClockFit` (blended windows, each a curved
  lower envelope, that follow oscillator drift; window length chosen from the data).
- Reader: :func:`open_gyro` -> :class:`GyroReader` (background thread, ring buffer,
  zero-rate calibration), :class:`GyroSamples`, :class:`GyroStats`, :class:`GyroSettings`.
- Check: :func:`check_gyro` -> :class:`GyroCheckResult` (rate and drift, lost and corrupted
  frames, noise at rest, inferred range, against :class:`GyroCheckLimits`), the analysis
  alone :func:`check_gyro_samples` (``timedexec gyro check``, docs/gyro-kit.md).
"""

from __future__ import annotations

from timedexec.sensors._check import (
    TYPICAL_NOISE_DENSITY_DPS_RTHZ,
    GyroCheckLimits,
    GyroCheckResult,
    check_gyro,
    check_gyro_samples,
)
from timedexec.sensors._clock import (
    ClockFit,
    SensorClock,
    fit_clock_least_squares,
    fit_clock_lower_envelope,
)
from timedexec.sensors._clock_drift import DriftingClockFit, fit_clock_drifting
from timedexec.sensors._frames import (
    CRC8_POLY,
    FRAME_SIZE,
    SYNC,
    FrameParser,
    ParsedFrames,
    crc8,
    encode_frames,
)
from timedexec.sensors._ports import SUPPORTED_URL_SCHEMES
from timedexec.sensors._reader import (
    GyroReader,
    GyroSamples,
    GyroStats,
    ZeroRateCalibration,
    open_gyro,
    raw_to_rad_s,
)
from timedexec.sensors._settings import DLPF_GROUP_DELAY_S, SENSITIVITY_LSB_PER_DPS, GyroSettings
from timedexec.sensors._simport import SimGyroPort, parse_sim_url
from timedexec.sensors._unwrap import (
    CounterUnwrapper,
    UnwrapResult,
    relative_counter_rows,
    unwrap_counter,
)

__all__ = [
    "CRC8_POLY",
    "DLPF_GROUP_DELAY_S",
    "FRAME_SIZE",
    "SENSITIVITY_LSB_PER_DPS",
    "SUPPORTED_URL_SCHEMES",
    "SYNC",
    "TYPICAL_NOISE_DENSITY_DPS_RTHZ",
    "ClockFit",
    "CounterUnwrapper",
    "DriftingClockFit",
    "FrameParser",
    "GyroCheckLimits",
    "GyroCheckResult",
    "GyroReader",
    "GyroSamples",
    "GyroSettings",
    "GyroStats",
    "ParsedFrames",
    "SensorClock",
    "SimGyroPort",
    "UnwrapResult",
    "ZeroRateCalibration",
    "check_gyro",
    "check_gyro_samples",
    "crc8",
    "encode_frames",
    "fit_clock_drifting",
    "fit_clock_least_squares",
    "fit_clock_lower_envelope",
    "open_gyro",
    "parse_sim_url",
    "raw_to_rad_s",
    "relative_counter_rows",
    "unwrap_counter",
]
