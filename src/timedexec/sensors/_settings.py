"""The gyro stream's settings and the MPU-6000's constants: a leaf of the sensors package.

The reader (:mod:`timedexec.sensors._reader`) and the port backends
(:mod:`timedexec.sensors._ports`) both take a :class:`GyroSettings`; it imports nothing of
the package, so neither imports the other for it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

from timedexec.errors import ConfigError

__all__ = ["DLPF_GROUP_DELAY_S", "SENSITIVITY_LSB_PER_DPS", "GyroSettings", "check_positive_in"]

#: Group delay of the MPU-6000 DLPF with DLPF_CFG=0 (the 8 kHz setting), s. The motion a
#: sample describes happened this much before the sample was taken: subtract it.
DLPF_GROUP_DELAY_S = 0.98e-3
#: Gyro sensitivity per full-scale range, LSB per °/s (MPU-6000 datasheet, ±3 %).
SENSITIVITY_LSB_PER_DPS: dict[int, float] = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}


@dataclass(frozen=True, kw_only=True)
class GyroSettings:
    """Settings of a gyro stream; validated when built, round-trip through to_dict/from_dict.

    Attributes
    ----------
    full_scale_dps : int
        Configured range, one of 250, 500, 1000, 2000 °/s (sets the LSB scale).
    baudrate : int
        Serial speed, bit/s. 8 kHz × 11 bytes needs at least 880 000 (2 Mbaud); USB CDC
        devices ignore it.
    nominal_rate_hz : float
        Nominal sample rate, Hz (8000 with DLPF off).
    read_period_s : float
        Reader cycle, s: the thread sleeps, then reads everything waiting (or blocks for the
        next byte if nothing is), so it wakes about 1/read_period_s times per second instead
        of once per 1 ms USB frame. Each read is stamped when it returns; the clock model's
        lower envelope picks the reads that happened just after a burst landed, so polling
        costs no timing accuracy, only delivery latency.
    read_timeout_s : float
        Serial read timeout, s (how long one blocking read waits for data).
    buffer_s : float
        Ring-buffer capacity, s of samples; unread samples older than this are dropped.
    clock_window_s : float or None
        Fit the clock to the most recent window only (long runs, thermal drift); None = all.
    clock_refit_s : float
        Minimum wall time between clock refits triggered by :meth:`GyroReader.read`, s.
    dlpf_group_delay_s : float
        Group delay of the sensor's DLPF, s (0.98e-3 for DLPF_CFG=0).
    exclusive : bool
        Lock the port against other programs (POSIX ``flock``).
    """

    full_scale_dps: int = 500
    baudrate: int = 2_000_000
    nominal_rate_hz: float = 8000.0
    read_period_s: float = 0.02
    read_timeout_s: float = 0.05
    buffer_s: float = 60.0
    clock_window_s: float | None = None
    clock_refit_s: float = 0.2
    dlpf_group_delay_s: float = DLPF_GROUP_DELAY_S
    exclusive: bool = True

    def __post_init__(self) -> None:
        if self.full_scale_dps not in SENSITIVITY_LSB_PER_DPS or isinstance(
            self.full_scale_dps, bool
        ):
            raise ConfigError(
                f"full_scale_dps={self.full_scale_dps!r} is not an MPU-6000 range; use one of "
                f"{sorted(SENSITIVITY_LSB_PER_DPS)} (°/s)"
            )
        if (
            not isinstance(self.baudrate, int)
            or isinstance(self.baudrate, bool)
            or (self.baudrate <= 0)
        ):
            raise ConfigError(
                f"baudrate={self.baudrate!r} must be a positive integer (bit/s); 8 kHz frames "
                "need at least 880000, e.g. 2000000"
            )
        check_positive_in(self.nominal_rate_hz, "nominal_rate_hz", "Hz, 8000 for the MPU-6000")
        if (
            isinstance(self.read_period_s, bool)
            or not isinstance(self.read_period_s, int | float)
            or not 0 <= self.read_period_s <= 1.0
        ):
            raise ConfigError(
                f"read_period_s={self.read_period_s!r} must be within 0..1 s (default 0.02)"
            )
        check_positive_in(self.read_timeout_s, "read_timeout_s", "s, e.g. 0.05", upper=10.0)
        check_positive_in(self.buffer_s, "buffer_s", "s of samples, e.g. 60", upper=3600.0)
        if self.clock_window_s is not None:
            check_positive_in(self.clock_window_s, "clock_window_s", "s, or None for all data")
        if not (math.isfinite(self.clock_refit_s) and self.clock_refit_s >= 0):
            raise ConfigError(f"clock_refit_s={self.clock_refit_s!r} must be >= 0 s")
        if not (math.isfinite(self.dlpf_group_delay_s) and 0 <= self.dlpf_group_delay_s < 0.1):
            raise ConfigError(
                f"dlpf_group_delay_s={self.dlpf_group_delay_s!r} must be in [0, 0.1) s "
                "(0.98e-3 for DLPF_CFG=0)"
            )
        if not isinstance(self.exclusive, bool):
            raise ConfigError(f"exclusive={self.exclusive!r} must be True or False")

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GyroSettings:
        """Build from :meth:`to_dict` output; unknown keys are an error."""
        allowed = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - allowed)
        if unknown:
            raise ConfigError(
                f"unknown gyro setting(s) {', '.join(map(repr, unknown))}; allowed: "
                + ", ".join(sorted(allowed))
            )
        return cls(**data)


def check_positive_in(value: float, name: str, hint: str, *, upper: float = math.inf) -> None:
    """Raise :class:`ConfigError` unless ``0 < value <= upper`` (a finite real, not a bool)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not 0 < value <= upper
    ):
        bound = "" if math.isinf(upper) else f" and at most {upper}"
        raise ConfigError(f"{name}={value!r} must be positive{bound} ({hint})")
