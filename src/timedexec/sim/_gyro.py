"""The simulated MPU-6000 itself, without transport: true rates -> frame bytes.

:class:`GyroFrameSource` samples a true angular rate at 8 kHz × (1 + clock error) on its own
clock, adds bias and white noise, quantises to the full-scale range and frames the samples as
described in ``docs/gyro-protocol.md``. The rate sources (constant, sine, step) feed it.
The pseudo-terminal server that streams these bytes in real time is
:class:`timedexec.twins.GyroTwin`; the ``sim://`` gyro port of :mod:`timedexec.sensors`
reads them in process.

The frame encoder here is the device side and deliberately independent of
``timedexec.sensors``' decoder; a test checks that both produce identical bytes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError

__all__ = [
    "DEFAULT_BIAS_DPS",
    "FULL_SCALE_SENSITIVITY",
    "GyroFrameSource",
    "RateSource",
    "constant_rate_source",
    "device_frames",
    "sine_rate_source",
    "step_rate_source",
]

#: ``rate_source(t0_s, t1_s)`` -> true angular rate, rad/s, tool frame; see GyroTwin.
RateSource = Callable[[float, float], NDArray[np.float64]]

#: Sensitivity per full-scale range, LSB per °/s (MPU-6000 datasheet, ±3 %).
FULL_SCALE_SENSITIVITY: dict[int, float] = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
#: Default zero-rate offset of the simulated sensor, °/s per axis.
DEFAULT_BIAS_DPS: tuple[float, float, float] = (0.8, -0.5, 0.3)

_WRAP = 65536
_FRAME_DTYPE = np.dtype(
    [("sync", "u1", (2,)), ("counter", "<u2"), ("rate", "<i2", (3,)), ("crc", "u1")]
)


def _crc8_table() -> NDArray[np.uint8]:
    """CRC-8, polynomial 0x07, MSB first (the device firmware's table)."""
    out = np.zeros(256, dtype=np.uint8)
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = (c << 1) ^ (0x107 << 8) if c & 0x8000 else c << 1
        out[i] = (c >> 8) & 0xFF
    return out


_CRC_TABLE = _crc8_table()


def device_frames(counter: NDArray[np.uint16], raw: NDArray[np.int16]) -> bytes:
    """Frame samples the way the device firmware does (column-wise CRC loop): the
    reference the host encoder `timedexec.sensors.encode_frames` is tested against."""
    rec = np.empty(counter.shape[0], dtype=_FRAME_DTYPE)
    rec["sync"] = (0xA5, 0x5A)
    rec["counter"] = counter
    rec["rate"] = raw
    as_bytes = rec.view(np.uint8).reshape(-1, _FRAME_DTYPE.itemsize)
    crc = np.zeros(counter.shape[0], dtype=np.uint8)
    for col in range(2, 10):
        crc = _CRC_TABLE[crc ^ as_bytes[:, col]]
    rec["crc"] = crc
    return rec.tobytes()


def _validate_common(
    *,
    clock_error_ppm: float,
    noise_density_dps_rthz: float,
    bias_dps: Sequence[float],
    full_scale_dps: int,
    nominal_rate_hz: float,
    dlpf_group_delay_s: float,
) -> NDArray[np.float64]:
    if full_scale_dps not in FULL_SCALE_SENSITIVITY:
        raise ConfigError(
            f"full_scale_dps={full_scale_dps!r} is not an MPU-6000 range; use one of "
            f"{sorted(FULL_SCALE_SENSITIVITY)} (°/s)"
        )
    if not (math.isfinite(clock_error_ppm) and abs(clock_error_ppm) < 100_000):
        raise ConfigError(
            f"clock_error_ppm={clock_error_ppm!r} must be finite and within ±100000 ppm "
            "(a real MEMS clock is within about ±10000)"
        )
    if not (math.isfinite(noise_density_dps_rthz) and noise_density_dps_rthz >= 0):
        raise ConfigError(
            f"noise_density_dps_rthz={noise_density_dps_rthz!r} must be >= 0 "
            "(MPU-6000: about 0.005 °/s/√Hz)"
        )
    bias = np.asarray(bias_dps, dtype=np.float64)
    if bias.shape != (3,) or not np.all(np.isfinite(bias)):
        raise ConfigError(f"bias_dps must be 3 finite values (°/s, x y z), got {bias_dps!r}")
    if not (math.isfinite(nominal_rate_hz) and nominal_rate_hz > 0):
        raise ConfigError(f"nominal_rate_hz={nominal_rate_hz!r} must be positive, Hz")
    if not (math.isfinite(dlpf_group_delay_s) and dlpf_group_delay_s >= 0):
        raise ConfigError(
            f"dlpf_group_delay_s={dlpf_group_delay_s!r} must be >= 0 s (0.98e-3 with DLPF_CFG=0)"
        )
    return bias


class GyroFrameSource:
    """The sensor itself, without transport: turns true rates into frame bytes.

    Pure computation, no threads and no clock reads; the pty twin (:class:`GyroTwin`) and
    the in-process ``sim://`` port of ``timedexec.sensors`` both drive one.

    Parameters
    ----------
    rate_source : callable, optional
        ``rate_source(t0_s, t1_s)`` -> true angular rate in rad/s for the samples in
        ``[t0_s, t1_s)``: shape (3,) (constant over the interval) or (k, 3) (values at
        ``t0_s + i·(t1_s - t0_s)/k``, i = 0..k-1, interpolated linearly to the sample times;
        exact when k equals the number of samples). None = still.
    clock_error_ppm : float
        Sensor clock error: the true sample rate is ``nominal_rate_hz·(1 + ppm·1e-6)``.
    noise_density_dps_rthz : float
        White rate-noise density, °/s/√Hz; per-sample std = density·√(nominal_rate_hz/2).
    bias_dps : sequence of 3 float
        Zero-rate offset, °/s.
    full_scale_dps : int
        Range, one of 250, 500, 1000, 2000 °/s.
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    dlpf_group_delay_s : float
        Sample k carries the true rate at ``t_k - dlpf_group_delay_s``, s.
    seed : int
        Seed of the noise generator.
    record_truth : bool
        Keep the true rate of every sample (see :meth:`truth`).
    """

    def __init__(
        self,
        rate_source: RateSource | None = None,
        *,
        clock_error_ppm: float = 3000.0,
        noise_density_dps_rthz: float = 0.005,
        bias_dps: Sequence[float] = DEFAULT_BIAS_DPS,
        full_scale_dps: int = 500,
        nominal_rate_hz: float = 8000.0,
        dlpf_group_delay_s: float = 0.98e-3,
        seed: int = 0,
        record_truth: bool = False,
    ) -> None:
        self.bias_dps = _validate_common(
            clock_error_ppm=clock_error_ppm,
            noise_density_dps_rthz=noise_density_dps_rthz,
            bias_dps=bias_dps,
            full_scale_dps=full_scale_dps,
            nominal_rate_hz=nominal_rate_hz,
            dlpf_group_delay_s=dlpf_group_delay_s,
        )
        self.rate_source = rate_source
        self.clock_error_ppm = float(clock_error_ppm)
        self.noise_density_dps_rthz = float(noise_density_dps_rthz)
        self.full_scale_dps = int(full_scale_dps)
        self.nominal_rate_hz = float(nominal_rate_hz)
        self.dlpf_group_delay_s = float(dlpf_group_delay_s)
        self.sensitivity_lsb_per_dps = FULL_SCALE_SENSITIVITY[self.full_scale_dps]
        self.noise_std_dps = self.noise_density_dps_rthz * math.sqrt(self.nominal_rate_hz / 2)
        self._rng = np.random.default_rng(seed)
        self._record = record_truth
        self._truth: list[NDArray[np.float64]] = []
        self.samples_generated = 0

    @property
    def true_rate_hz(self) -> float:
        """The sensor's actual sample rate, Hz."""
        return self.nominal_rate_hz * (1e6 + self.clock_error_ppm) / 1e6

    def sample_time_s(self, k: ArrayLike) -> NDArray[np.float64]:
        """Time at which sample ``k`` is taken, on the twin's time base, s."""
        return np.asarray(k, dtype=np.float64) / self.true_rate_hz

    def samples_due(self, elapsed_s: float) -> int:
        """Number of samples taken at or before ``elapsed_s`` (t_k <= elapsed_s)."""
        if elapsed_s < 0:
            return 0
        return math.floor(elapsed_s * self.true_rate_hz) + 1

    def true_rates(self, k0: int, m: int) -> NDArray[np.float64]:
        """True rate carried by samples k0..k0+m-1, rad/s, shape (m, 3)."""
        f = self.true_rate_hz
        t_content = np.arange(k0, k0 + m, dtype=np.float64) / f - self.dlpf_group_delay_s
        if self.rate_source is None or m == 0:
            return np.zeros((m, 3))
        t0 = k0 / f - self.dlpf_group_delay_s
        t1 = (k0 + m) / f - self.dlpf_group_delay_s
        out = np.asarray(self.rate_source(t0, t1), dtype=np.float64)
        if out.shape == (3,):
            return np.broadcast_to(out, (m, 3)).copy()
        if out.ndim != 2 or out.shape[1] != 3 or out.shape[0] < 1:
            raise ConfigError(
                f"rate_source returned shape {out.shape}; it must return (3,) or (k, 3) "
                "angular rates in rad/s"
            )
        k = out.shape[0]
        if k == m:
            return out
        grid = t0 + np.arange(k) * ((t1 - t0) / k)
        return np.stack([np.interp(t_content, grid, out[:, a]) for a in range(3)], axis=1)

    def generate(self, m: int) -> bytes:
        """Frame the next ``m`` samples.

        Returns
        -------
        bytes
            ``11·m`` bytes of frames for samples ``samples_generated`` .. ``+ m - 1``.
        """
        k0 = self.samples_generated
        rates = self.true_rates(k0, m)
        if self._record:
            self._truth.append(rates)
        dps = np.degrees(rates) + self.bias_dps
        if self.noise_std_dps > 0:
            dps = dps + self._rng.normal(0.0, self.noise_std_dps, size=(m, 3))
        raw = np.clip(np.rint(dps * self.sensitivity_lsb_per_dps), -32768, 32767).astype(np.int16)
        counter = (np.arange(k0, k0 + m) % _WRAP).astype(np.uint16)
        self.samples_generated = k0 + m
        return device_frames(counter, raw)

    def truth(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Recorded ground truth (needs ``record_truth=True``).

        Returns
        -------
        index : ndarray of int64, shape (n,)
            Sample index k (counter = k % 65536).
        rate_rad_s : ndarray of float64, shape (n, 3)
            True rate each sample carries (at ``t_k - dlpf_group_delay_s``), rad/s, before
            bias, noise and quantisation.
        """
        if not self._record:
            raise ConfigError("truth() needs record_truth=True when the source is built")
        rates = np.concatenate(self._truth) if self._truth else np.zeros((0, 3))
        return np.arange(rates.shape[0], dtype=np.int64), rates


def constant_rate_source(rate_rad_s: Sequence[float]) -> RateSource:
    """A source returning the same rate (rad/s, shape (3,)) at all times."""
    value = np.asarray(rate_rad_s, dtype=np.float64)
    if value.shape != (3,):
        raise ConfigError(f"rate_rad_s must be 3 values (rad/s), got {rate_rad_s!r}")

    def source(t0_s: float, t1_s: float) -> NDArray[np.float64]:
        return value

    return source


def _grid(t0_s: float, t1_s: float, grid_hz: float) -> NDArray[np.float64]:
    k = max(math.ceil((t1_s - t0_s) * grid_hz), 1)
    grid: NDArray[np.float64] = t0_s + np.arange(k, dtype=np.float64) * ((t1_s - t0_s) / k)
    return grid


def sine_rate_source(
    amplitude_rad_s: float,
    frequency_hz: float,
    *,
    axis: int = 2,
    phase_rad: float = 0.0,
    grid_hz: float = 64_000.0,
) -> RateSource:
    """Rate ``amplitude·sin(2π·f·t + phase)`` on one axis (0, 1, 2 = x, y, z), rad/s."""
    if axis not in (0, 1, 2):
        raise ConfigError(f"axis={axis!r} must be 0, 1 or 2 (x, y, z)")
    omega = 2.0 * math.pi * frequency_hz

    def source(t0_s: float, t1_s: float) -> NDArray[np.float64]:
        t = _grid(t0_s, t1_s, grid_hz)
        out = np.zeros((t.shape[0], 3))
        out[:, axis] = amplitude_rad_s * np.sin(omega * t + phase_rad)
        return out

    return source


def step_rate_source(
    rate_rad_s: float,
    step_time_s: float,
    *,
    axis: int = 2,
    duration_s: float = math.inf,
    grid_hz: float = 64_000.0,
) -> RateSource:
    """Rate ``rate_rad_s`` on one axis during ``[step_time_s, step_time_s + duration_s)``."""
    if axis not in (0, 1, 2):
        raise ConfigError(f"axis={axis!r} must be 0, 1 or 2 (x, y, z)")

    def source(t0_s: float, t1_s: float) -> NDArray[np.float64]:
        t = _grid(t0_s, t1_s, grid_hz)
        out = np.zeros((t.shape[0], 3))
        on = (t >= step_time_s) & (t < step_time_s + duration_s)
        out[on, axis] = rate_rad_s
        return out

    return source
