"""The gyro entry of a recording header: what extraction must know of the sensor.

A leaf of :mod:`timedexec.recording` (it imports nothing of the package): the schema
(:mod:`timedexec.recording._schema`) and the sweep protocol
(:mod:`timedexec.recording._sweep_protocol`) both use it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

from timedexec._validation import DictMixin, check_non_negative, check_positive
from timedexec.errors import ConfigError

__all__ = ["FULL_SCALE_RANGES_DPS", "GyroHeader"]

#: MPU-6000 full-scale ranges, °/s.
FULL_SCALE_RANGES_DPS = (250, 500, 1000, 2000)


#: Largest plausible group delay of a gyro's own filter, s (the MPU-6000's slowest DLPF
#: setting delays 18.6 ms; docs/sensor-constants.md).
MAX_GROUP_DELAY_S = 0.05
#: Largest plausible sample-to-host latency of a flange gyro, s (USB: about 1 ms).
MAX_TRANSPORT_LATENCY_S = 0.05
#: Output rates a gyro for calibration can have, Hz.
MIN_RATE_HZ, MAX_RATE_HZ = 100.0, 100_000.0
_WHY = {
    "group_delay_s": "the MPU-6000's slowest filter setting delays 18.6 ms",
    "transport_latency_s": "a USB gyro's samples reach the host within about 1 ms",
}


@dataclass(frozen=True, kw_only=True)
class GyroHeader(DictMixin):
    """What extraction must know of the gyro (a recording header's ``gyro`` entry).

    Parameters
    ----------
    full_scale_dps : int
        ±250/500/1000/2000 °/s; sensitivity 32768/full_scale LSB per °/s.
    nominal_rate_hz : float
        Nominal output rate, Hz (8000 with the DLPF off).
    block_samples : int
        Samples the host receives together (one USB transfer).
    group_delay_s : float
        Group delay of the sensor's internal filter, s (MPU-6000 DLPF_CFG=0: 0.98 ms).
        The default is the simulator's sensor; a recording must state it
        (:meth:`from_header`), see docs/sensor-constants.md.
    transport_latency_s : float
        Minimum latency from sampling to host arrival, s (not observable from arrival
        times: measure it, e.g. against a sync pulse the sensor time-stamps). The default is
        the simulator's USB latency; a recording must state it.
    """

    full_scale_dps: int = 500
    nominal_rate_hz: float = 8000.0
    block_samples: int = 8
    group_delay_s: float = 0.00098
    transport_latency_s: float = 0.0008

    def __post_init__(self) -> None:
        if self.full_scale_dps not in FULL_SCALE_RANGES_DPS:
            raise ConfigError(
                f"gyro: full_scale_dps={self.full_scale_dps!r} is not one of "
                f"{', '.join(map(str, FULL_SCALE_RANGES_DPS))}"
            )
        if not isinstance(self.block_samples, int) or self.block_samples < 1:
            raise ConfigError(f"gyro: block_samples={self.block_samples!r} must be an int >= 1")
        check_positive("gyro", nominal_rate_hz=self.nominal_rate_hz)
        check_non_negative(
            "gyro", group_delay_s=self.group_delay_s, transport_latency_s=self.transport_latency_s
        )
        # Units: a value typed in ms (0.98 for 0.98 ms) would date every gyro sample a
        # second off and every delay with it. Nothing a flange gyro does takes this long.
        for key, value, largest in (
            ("group_delay_s", self.group_delay_s, MAX_GROUP_DELAY_S),
            ("transport_latency_s", self.transport_latency_s, MAX_TRANSPORT_LATENCY_S),
        ):
            if value > largest:
                raise ConfigError(
                    f"gyro: {key}={value!r} s is not plausible (at most {largest:g} s: "
                    f"{_WHY[key]}); the constants are in seconds — if {value:g} is in "
                    f"milliseconds, give {key}={value / 1e3:g}"
                )
        if not MIN_RATE_HZ <= self.nominal_rate_hz <= MAX_RATE_HZ:
            raise ConfigError(
                f"gyro: nominal_rate_hz={self.nominal_rate_hz!r} is out of range; use "
                f"{MIN_RATE_HZ:g} .. {MAX_RATE_HZ:g} Hz (8000 for an MPU-6000 with its DLPF "
                "off; the rate is in Hz, not kHz)"
            )

    @property
    def lsb_per_dps(self) -> float:
        """Sensitivity, LSB per °/s."""
        return 32768.0 / self.full_scale_dps

    #: Keys a recording's (or a sensor profile's) gyro entry must state: the two constants
    #: are measured per sensor and host (docs/sensor-constants.md), never assumed to be 0.
    REQUIRED_KEYS: ClassVar[tuple[str, ...]] = ("group_delay_s", "transport_latency_s")
    #: Unit of each numeric key (SI); read-only.
    UNITS: ClassVar[Mapping[str, str]] = MappingProxyType(
        {
            "full_scale_dps": "°/s",
            "nominal_rate_hz": "Hz",
            "block_samples": "samples",
            "group_delay_s": "s",
            "transport_latency_s": "s",
            "lsb_per_dps": "LSB/(°/s)",
        }
    )

    @classmethod
    def from_header(cls, data: Any, *, source: str = "recording header") -> GyroHeader:
        """The gyro entry of a recording header (or a sensor profile), strictly.

        Unlike the constructor's defaults (the simulator's sensor), a header must state the
        group delay and the transport latency: a missing one is an error, not 0.

        Raises
        ------
        ConfigError
            Naming every missing or unknown key, or an invalid value.
        """
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: the gyro entry must be a JSON object, got {data!r}")
        missing = [k for k in cls.REQUIRED_KEYS if k not in data]
        if missing:
            raise ConfigError(
                f"{source}: gyro key(s) {', '.join(missing)} missing; measure them "
                "(docs/sensor-constants.md) and state them in seconds — they are never "
                "assumed to be 0"
            )
        known = {
            "full_scale_dps",
            "nominal_rate_hz",
            "block_samples",
            "group_delay_s",
            "transport_latency_s",
        }
        unknown = sorted(set(data) - known - {"lsb_per_dps", "units", "doc", "sensor"})
        if unknown:
            raise ConfigError(
                f"{source}: unknown gyro key(s) {', '.join(unknown)}; known: "
                f"{', '.join(sorted(known))}"
            )
        units = data.get("units", {})
        for key, unit in units.items() if isinstance(units, dict) else []:
            if key in cls.UNITS and unit not in (cls.UNITS[key], "s" if key.endswith("_s") else ""):
                raise ConfigError(
                    f"{source}: gyro {key} is given in {unit!r}; state it in {cls.UNITS[key]}"
                )
        kw: dict[str, Any] = {}
        try:
            for k in known:
                if k in data:
                    kw[k] = (
                        int(data[k]) if k in ("full_scale_dps", "block_samples") else float(data[k])
                    )
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: gyro {k} = {data[k]!r} is not a number") from exc
        return cls(**kw)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> GyroHeader:
        """Load a sensor profile: a JSON object with the gyro keys (SI units), e.g.
        ``{"full_scale_dps": 500, "nominal_rate_hz": 8000, "block_samples": 8,
        "group_delay_s": 0.00098, "transport_latency_s": 0.00072}``.

        Raises
        ------
        ConfigError
            An unreadable file, invalid JSON, or a profile :meth:`from_header` refuses.
        """
        p = os.fspath(path)
        try:
            with open(p, encoding="utf-8") as fh:
                data = json.load(fh)
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ConfigError(f"sensor profile {p}: cannot read it as JSON ({exc})") from exc
        if isinstance(data, dict) and "gyro" in data and isinstance(data["gyro"], dict):
            data = data["gyro"]
        return cls.from_header(data, source=f"sensor profile {p}")

    def to_dict(self) -> dict[str, Any]:
        """The header entry (with the derived ``lsb_per_dps``)."""
        return {**super().to_dict(), "lsb_per_dps": self.lsb_per_dps}
