"""Does a gyro meet what calibration needs? (``timedexec gyro check``, docs/gyro-kit.md).

A calibration sweep assumes the stream of ``docs/gyro-protocol.md`` at 8 kHz, with no lost
or damaged frames to speak of, from a sensor at rest whose full-scale range the recording
states. :func:`check_gyro` opens a port, measures for a while and hands the samples to
:func:`check_gyro_samples`, which computes the figures and names each shortfall with what
to fix:

- **sample rate** from the lower-envelope clock fit (the reader's own), its error against
  the nominal rate and its **drift** against the host clock (the rate of the second half of
  the measurement minus that of the first);
- **lost samples** (counter gaps) and **corrupted frames** (checksum failures) and garbage
  bytes, from the parser's counters;
- **noise density at rest** per axis, °/s/√Hz, from first differences (a slow drift or a
  constant bias does not count);
- the **full-scale range** the noise suggests: the sensor's typical noise density is known,
  so its noise in LSB says which range (131 / 65.5 / 32.8 / 16.4 LSB per °/s) the firmware
  set, to within the part's spread. A stated range whose expected noise is off by more than
  a factor 1.6 from the measured one (the ranges are a factor 2 apart) is reported.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec.errors import ConfigError
from timedexec.sensors._clock import fit_clock_lower_envelope
from timedexec.sensors._reader import SENSITIVITY_LSB_PER_DPS, GyroSamples, open_gyro

__all__ = [
    "TYPICAL_NOISE_DENSITY_DPS_RTHZ",
    "GyroCheckLimits",
    "GyroCheckResult",
    "check_gyro",
    "check_gyro_samples",
]

#: Typical rate-noise density of the supported parts, °/s/√Hz (datasheets: MPU-6000
#: 0.005, ICM-42688-P 0.0028); the full-scale inference compares the measured noise with it.
TYPICAL_NOISE_DENSITY_DPS_RTHZ: dict[str, float] = {"mpu6000": 0.005, "icm42688p": 0.0028}

#: Measured / expected noise beyond which the stated range is doubted (ranges are 2x apart).
_RANGE_RATIO = 1.6
#: Fewer samples than this leave the figures meaningless.
_MIN_SAMPLES = 200


@dataclass(frozen=True, kw_only=True)
class GyroCheckLimits:
    """What calibration needs of a gyro stream; validated when built.

    Attributes
    ----------
    nominal_rate_hz : float
        The rate extraction assumes, Hz (8000: the MPU-6000 with DLPF_CFG = 0).
    max_rate_error : float
        Largest relative sample-rate error (0.02: the MEMS clock is within about ±1 % over
        temperature; the clock model fits the rest).
    max_drift_ppm : float
        Largest change of the sample rate between the two halves of the check, ppm of the
        nominal rate (a board still warming up drifts; the clock model follows slow drift,
        but a sweep should start warm); the check adds the measurement's resolution, 0.6 ms
        over half the check's length (+120 ppm at 10 s).
    max_lost_fraction : float
        Largest fraction of samples lost (0.001: a gap now and then is handled, a device or
        link that drops frames steadily is not healthy).
    max_corrupt_fraction : float
        Largest number of corrupted frames per frame received (0.0001; USB itself is
        checksummed, so corruption means a UART or firmware fault).
    max_noise_density_dps_rthz : float
        Largest noise density at rest per axis, °/s/√Hz (0.02: four times the MPU-6000's
        typical; above it the sensor moved or is faulty).
    """

    nominal_rate_hz: float = 8000.0
    max_rate_error: float = 0.02
    max_drift_ppm: float = 500.0
    max_lost_fraction: float = 1e-3
    max_corrupt_fraction: float = 1e-4
    max_noise_density_dps_rthz: float = 0.02

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if isinstance(value, bool) or not (
                isinstance(value, int | float) and math.isfinite(value) and value > 0
            ):
                raise ConfigError(f"GyroCheckLimits: {name}={value!r} must be a positive number")
        if self.max_rate_error >= 1 or self.max_lost_fraction >= 1:
            raise ConfigError(
                "GyroCheckLimits: max_rate_error and max_lost_fraction are fractions below 1 "
                f"(got {self.max_rate_error!r}, {self.max_lost_fraction!r})"
            )

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation."""
        return asdict(self)


@dataclass(frozen=True, kw_only=True)
class GyroCheckResult:
    """Figures of one gyro check and the verdict.

    Attributes
    ----------
    port : str
        What was checked.
    duration_s : float
        Measured span (first to last sample, host clock), s.
    samples : int
        Samples received in the span.
    rate_hz : float
        Sample rate on the host clock (lower-envelope fit), Hz; NaN without data.
    clock_error_ppm : float
        ``rate_hz`` against the nominal rate, ppm.
    drift_ppm : float
        Rate of the second half minus that of the first, ppm of the nominal rate.
    missing_samples : int
        Samples missing from the counter sequence (gaps) within the span.
    lost_fraction : float
        ``missing_samples / (samples + missing_samples)``.
    corrupted_frames : int
        Frames whose checksum failed.
    garbage_bytes : int
        Bytes that belonged to no valid frame.
    corrupt_fraction : float
        ``corrupted_frames / samples`` (1.0 when nothing valid arrived).
    noise_density_dps_rthz : tuple of 3 float
        White-noise density at rest per axis (x, y, z), °/s/√Hz, with the stated range.
    noise_std_lsb : tuple of 3 float
        Per-sample noise per axis, LSB.
    full_scale_dps : int
        The range the user stated (what a recording will say), °/s.
    inferred_full_scale_dps : int or None
        The range the noise suggests for the stated sensor; None without data.
    sensor : str
        The part the noise inference assumed (a key of :data:`TYPICAL_NOISE_DENSITY_DPS_RTHZ`).
    limits : GyroCheckLimits
        What was required.
    problems : tuple of str
        One line per shortfall, each saying what to fix; empty when the gyro is fit.
    """

    port: str
    duration_s: float
    samples: int
    rate_hz: float
    clock_error_ppm: float
    drift_ppm: float
    missing_samples: int
    lost_fraction: float
    corrupted_frames: int
    garbage_bytes: int
    corrupt_fraction: float
    noise_density_dps_rthz: tuple[float, float, float]
    noise_std_lsb: tuple[float, float, float]
    full_scale_dps: int
    inferred_full_scale_dps: int | None
    sensor: str
    limits: GyroCheckLimits
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        """True when the gyro meets every requirement."""
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON representation (NaN becomes None), with ``ok``."""
        out = asdict(self)
        out["ok"] = self.ok
        for key, value in out.items():
            if isinstance(value, float) and not math.isfinite(value):
                out[key] = None
        out["noise_density_dps_rthz"] = [_finite_or_none(v) for v in self.noise_density_dps_rthz]
        out["noise_std_lsb"] = [_finite_or_none(v) for v in self.noise_std_lsb]
        out["problems"] = list(self.problems)
        return out

    def summary(self) -> str:
        """The human-readable report (what ``timedexec gyro check`` prints)."""
        head = (
            f"{self.port}: meets what calibration needs"
            if self.ok
            else f"{self.port}: does NOT meet what calibration needs "
            f"({len(self.problems)} problem{'s' if len(self.problems) != 1 else ''})"
        )
        nominal = self.limits.nominal_rate_hz
        expected = self.samples + self.missing_samples
        noise = "  ".join(
            f"{axis} {v:.4f}" for axis, v in zip("xyz", self.noise_density_dps_rthz, strict=True)
        )
        inferred = (
            "no data"
            if self.inferred_full_scale_dps is None
            else f"the noise suggests ±{self.inferred_full_scale_dps} °/s ({self.sensor})"
        )
        lines = [
            head,
            f"  sample rate     {self.rate_hz:.1f} Hz (clock {self.clock_error_ppm:+.0f} ppm vs "
            f"{nominal:g} Hz; drift {self.drift_ppm:+.0f} ppm over {self.duration_s:.1f} s)",
            f"  lost samples    {self.missing_samples} of {expected} "
            f"({100 * self.lost_fraction:.3f} %)",
            f"  corrupted       {self.corrupted_frames} frames, {self.garbage_bytes} garbage bytes",
            f"  noise at rest   {noise} °/s/√Hz",
            f"  full scale      ±{self.full_scale_dps} °/s stated; {inferred}",
        ]
        if self.problems:
            lines.append("problems:")
            lines += [f"  - {p}" for p in self.problems]
        return "\n".join(lines)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _check_sensor(sensor: str) -> str:
    key = str(sensor).strip().lower().replace("-", "")
    if key not in TYPICAL_NOISE_DENSITY_DPS_RTHZ:
        raise ConfigError(
            f"sensor={sensor!r} is not a supported part; use one of "
            f"{', '.join(sorted(TYPICAL_NOISE_DENSITY_DPS_RTHZ))}"
        )
    return key


def _check_full_scale(full_scale_dps: int) -> int:
    if isinstance(full_scale_dps, bool) or full_scale_dps not in SENSITIVITY_LSB_PER_DPS:
        raise ConfigError(
            f"full_scale_dps={full_scale_dps!r} is not a gyro range; use one of "
            f"{sorted(SENSITIVITY_LSB_PER_DPS)} (°/s)"
        )
    return int(full_scale_dps)


#: How far the lower envelope of one half's arrivals may sit from the sample clock at its
#: ends, s (USB or a pty; the drift allowance in :func:`check_gyro_samples`).
_ENVELOPE_RES_S = 3e-4


def _rate_hz(n: NDArray[np.int64], t: NDArray[np.float64], nominal_hz: float) -> float:
    fit = fit_clock_lower_envelope(n, t, nominal_rate_hz=nominal_hz)
    return fit.rate_hz if fit.method != "nominal" else math.nan


def check_gyro_samples(
    samples: GyroSamples,
    *,
    corrupted_frames: int,
    garbage_bytes: int,
    full_scale_dps: int = 500,
    sensor: str = "mpu6000",
    limits: GyroCheckLimits | None = None,
    port: str = "",
) -> GyroCheckResult:
    """The figures and verdict of a gyro check from a recording of the sensor at rest.

    Parameters
    ----------
    samples : GyroSamples
        The samples of the measurement (``counter_unwrapped``, ``arrival_s``, ``raw``).
    corrupted_frames, garbage_bytes : int
        Checksum failures and bytes outside valid frames over the same span (the reader's
        :class:`GyroStats` difference).
    full_scale_dps : int
        The range the recordings will state, °/s.
    sensor : str
        ``"mpu6000"`` or ``"icm42688p"`` (its typical noise sets the range inference).
    limits : GyroCheckLimits, optional
        What calibration needs; default :class:`GyroCheckLimits()`.
    port : str
        Name used in the report.

    Returns
    -------
    GyroCheckResult
    """
    fs = _check_full_scale(full_scale_dps)
    part = _check_sensor(sensor)
    lim = GyroCheckLimits() if limits is None else limits
    nominal = lim.nominal_rate_hz
    n = np.asarray(samples.counter_unwrapped, dtype=np.int64)
    t = np.asarray(samples.arrival_s, dtype=np.float64)
    raw = np.asarray(samples.raw, dtype=np.float64).reshape(-1, 3)
    count = int(n.shape[0])
    problems: list[str] = []

    if count >= 2:
        missing = int(n[-1] - n[0] + 1 - count)
        duration = float(t[-1] - t[0])
    else:
        missing, duration = 0, 0.0
    lost = missing / (count + missing) if count + missing else 0.0
    corrupt = corrupted_frames / count if count else 1.0

    rate = drift = clock_ppm = math.nan
    density = std_lsb = (math.nan, math.nan, math.nan)
    inferred: int | None = None
    if count < _MIN_SAMPLES:
        problems.append(
            f"only {count} valid samples arrived ({corrupted_frames} corrupted frames, "
            f"{garbage_bytes} garbage bytes): check the port name, that the board runs the "
            "firmware of docs/gyro-kit.md (its LED blinks when no sensor answers on SPI: "
            "check the wiring), and for a UART the baud rate (2 Mbaud)"
        )
    else:
        rate = _rate_hz(n, t, nominal)
        half = count // 2
        drift = (
            (_rate_hz(n[half:], t[half:], nominal) - _rate_hz(n[:half], t[:half], nominal))
            / nominal
            * 1e6
        )
        clock_ppm = (rate / nominal - 1.0) * 1e6
        # First differences: white noise of std s gives differences of std s·√2, a slow
        # drift or a constant bias gives nothing. Only differences between adjacent samples.
        adjacent = np.diff(n) == 1
        diffs = np.diff(raw, axis=0)[adjacent]
        std = diffs.std(axis=0) / math.sqrt(2.0) if diffs.shape[0] > 1 else np.full(3, np.nan)
        std_lsb = (float(std[0]), float(std[1]), float(std[2]))
        fs_rate = rate if math.isfinite(rate) else nominal
        per_rthz = math.sqrt(fs_rate / 2.0)
        sens = SENSITIVITY_LSB_PER_DPS[fs]
        density = tuple(float(s / sens / per_rthz) for s in std)  # type: ignore[assignment]
        typical = TYPICAL_NOISE_DENSITY_DPS_RTHZ[part] * per_rthz  # °/s per sample
        measured = float(np.median(std))
        if measured > 0:
            ratios = {
                r: measured / (typical * s) for r, s in sorted(SENSITIVITY_LSB_PER_DPS.items())
            }
            inferred = min(ratios, key=lambda r: abs(math.log(ratios[r])))
            if inferred != fs and abs(math.log(ratios[fs])) > math.log(_RANGE_RATIO):
                problems.append(
                    f"the noise ({measured:.1f} LSB per sample) is {ratios[fs]:.2f} times what "
                    f"a {part} at ±{fs} °/s gives and fits ±{inferred} °/s: the firmware's "
                    f"range and the one you state differ, so every rate would be off by "
                    f"{SENSITIVITY_LSB_PER_DPS[fs] / SENSITIVITY_LSB_PER_DPS[inferred]:.2g}x; "
                    f"state --full-scale-dps {inferred} (and in the sensor profile) or build "
                    f"the firmware with FS_DPS={fs}; confirm by turning the sensor 90° by hand"
                )

        if not abs(rate / nominal - 1.0) <= lim.max_rate_error:
            hint = (
                " (1 kHz: the sensor's low-pass filter is on, DLPF_CFG != 0, or SMPLRT_DIV "
                "!= 0; flash the firmware of docs/gyro-kit.md)"
                if abs(rate / 1000.0 - 1.0) < 0.05
                else ""
            )
            problems.append(
                f"sample rate {rate:.1f} Hz is {100 * (rate / nominal - 1):+.1f} % from the "
                f"{nominal:g} Hz calibration needs (allowed ±{100 * lim.max_rate_error:g} %)" + hint
            )
        # Each half's rate comes from the lower envelope of its arrivals, which a burst of
        # late reads at a half's end moves (a good twin read -629 ppm over a 2 s check
        # through a pty, CI 2026-11-29: ~0.3 ms at each of the two halves' ends, inferred
        # from that one reading, not measured apart): the allowance adds that resolution,
        # 2 x 0.3 ms over a half's length (+120 ppm at the default 10 s, +600 at 2 s).
        allowed = lim.max_drift_ppm + 2 * _ENVELOPE_RES_S / max(duration / 2, 1e-9) * 1e6
        if not abs(drift) <= allowed:
            problems.append(
                f"the sample clock drifted {drift:+.0f} ppm between the two halves of the "
                f"check (allowed ±{allowed:.0f} ppm: {lim.max_drift_ppm:g} plus the "
                f"measurement's resolution over {duration:.1f} s): let the board warm up in "
                "its enclosure and check again, or check for longer (--duration-s)"
            )
        for axis, value in zip("xyz", std_lsb, strict=True):
            if value == 0.0:
                problems.append(
                    f"rate {axis} did not change over {count} samples: the sensor is not "
                    "sampling (check MISO and CS, and that WHO_AM_I matched)"
                )
        worst = int(np.nanargmax(density)) if np.any(np.isfinite(density)) else 0
        if density[worst] > lim.max_noise_density_dps_rthz:
            problems.append(
                f"noise density {density[worst]:.4f} °/s/√Hz on axis {'xyz'[worst]} exceeds "
                f"{lim.max_noise_density_dps_rthz:g}: keep the sensor still during the check; "
                "if it was still, check its supply, its mounting and --full-scale-dps"
            )
    if count + missing and lost > lim.max_lost_fraction:
        problems.append(
            f"{missing} of {count + missing} samples lost ({100 * lost:.3f} %, allowed "
            f"{100 * lim.max_lost_fraction:g} %): the device or the link drops frames; use a "
            "USB port on the computer itself (no hub), make sure no other program reads the "
            "port, and look at the firmware's LED (on: an overrun happened)"
        )
    if count >= _MIN_SAMPLES and corrupt > lim.max_corrupt_fraction:
        problems.append(
            f"{corrupted_frames} corrupted frames and {garbage_bytes} garbage bytes for "
            f"{count} good frames ({100 * corrupt:.3f} %, allowed "
            f"{100 * lim.max_corrupt_fraction:g} %): the byte stream is damaged; for a UART "
            "check the baud rate (2 Mbaud), the cable and the ground; over USB it is a "
            "firmware fault"
        )
    return GyroCheckResult(
        port=port,
        duration_s=duration,
        samples=count,
        rate_hz=rate,
        clock_error_ppm=clock_ppm,
        drift_ppm=drift,
        missing_samples=missing,
        lost_fraction=lost,
        corrupted_frames=int(corrupted_frames),
        garbage_bytes=int(garbage_bytes),
        corrupt_fraction=corrupt,
        noise_density_dps_rthz=density,  # type: ignore[arg-type]
        noise_std_lsb=std_lsb,
        full_scale_dps=fs,
        inferred_full_scale_dps=inferred,
        sensor=part,
        limits=lim,
        problems=tuple(problems),
    )


def check_gyro(
    url: str,
    *,
    duration_s: float = 10.0,
    settle_s: float = 0.5,
    full_scale_dps: int = 500,
    sensor: str = "mpu6000",
    limits: GyroCheckLimits | None = None,
    progress: Callable[[str], None] | None = None,
    **settings: Any,
) -> GyroCheckResult:
    """Open a gyro, measure it at rest for ``duration_s`` and check it.

    Parameters
    ----------
    url : str
        The port (``/dev/ttyACM0``, a pty, ``sim://``), as for :func:`open_gyro`.
    duration_s : float
        Measurement, s (10 s: the rate to a few ppm, the noise to about 1 %).
    settle_s : float
        Stream discarded first, s (the port just opened; the device may still be filling
        its buffer).
    full_scale_dps : int
        The range the recordings will state, °/s.
    sensor : str
        ``"mpu6000"`` or ``"icm42688p"``.
    limits : GyroCheckLimits, optional
        What calibration needs.
    progress : callable, optional
        Called with one-line status messages.
    **settings
        Further :class:`GyroSettings` fields for the reader.

    Returns
    -------
    GyroCheckResult

    Raises
    ------
    ConfigError
        A bad setting.
    SensorError
        The port cannot be opened or the stream fails.
    """
    fs = _check_full_scale(full_scale_dps)
    _check_sensor(sensor)
    for name, value in (("duration_s", duration_s), ("settle_s", settle_s)):
        if isinstance(value, bool) or not (
            isinstance(value, int | float) and math.isfinite(value) and 0 <= value <= 3600
        ):
            raise ConfigError(f"{name}={value!r} must be within 0..3600 s")
    if duration_s < 0.5:
        raise ConfigError(f"duration_s={duration_s!r} is too short; measure at least 0.5 s")
    lim = GyroCheckLimits() if limits is None else limits
    say = progress or (lambda _message: None)
    parts: list[GyroSamples] = []
    with open_gyro(
        url,
        full_scale_dps=fs,
        nominal_rate_hz=lim.nominal_rate_hz,
        buffer_s=max(60.0, 2.0 * duration_s),
        **settings,
    ) as gyro:
        time.sleep(settle_s)
        gyro.read(timeout_s=0)
        before = gyro.stats
        say(f"measuring {url} for {duration_s:g} s; keep the sensor still")
        end = time.monotonic() + duration_s
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(0.25, left))
            parts.append(gyro.read(timeout_s=0))
        parts.append(gyro.read(timeout_s=0))
        after = gyro.stats
    samples = GyroSamples.concatenate([p for p in parts if len(p)] or parts[:1])
    return check_gyro_samples(
        samples,
        corrupted_frames=after.checksum_errors - before.checksum_errors,
        garbage_bytes=after.resync_bytes_skipped - before.resync_bytes_skipped,
        full_scale_dps=fs,
        sensor=sensor,
        limits=lim,
        port=url,
    )
