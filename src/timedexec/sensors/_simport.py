"""``sim://`` ports: a simulated gyro inside this process, read like a pyserial port.

No pty, no thread: every ``read`` produces the frames the simulated sensor has taken since
the port was opened (real time, its own clock error), so tests and examples run anywhere.
URL form::

    sim://[?rate_dps=X,Y,Z][&bias_dps=X,Y,Z][&clock_error_ppm=P]
          [&noise_density_dps_rthz=D][&seed=S]

``rate_dps`` is a constant true rate (default still).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from timedexec.errors import ConfigError

__all__ = ["SIM_URL_PARAMS", "SimGyroPort", "parse_sim_url"]

#: Query parameters a ``sim://`` URL accepts.
SIM_URL_PARAMS = ("rate_dps", "bias_dps", "clock_error_ppm", "noise_density_dps_rthz", "seed")


def _floats(url: str, key: str, text: str, count: int) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ConfigError(
            f"{key}={text!r} in {url!r} must be {count} comma-separated finite numbers"
        )
    return values


def parse_sim_url(url: str) -> dict[str, Any]:
    """Parse a ``sim://`` URL into keyword arguments for the simulated sensor.

    Raises
    ------
    ConfigError
        For another scheme, a host/path part, an unknown parameter or a bad value.
    """
    parts = urlsplit(url)
    if parts.scheme != "sim":
        raise ConfigError(f"{url!r} is not a sim:// URL")
    if parts.netloc or parts.path not in ("", "/"):
        raise ConfigError(
            f"{url!r}: a sim:// URL takes only query parameters, e.g. "
            "'sim://?rate_dps=0,0,10'; allowed: " + ", ".join(SIM_URL_PARAMS)
        )
    out: dict[str, Any] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False):
        if key == "rate_dps":
            out["rate_dps"] = _floats(url, key, value, 3)
        elif key == "bias_dps":
            out["bias_dps"] = _floats(url, key, value, 3)
        elif key in ("clock_error_ppm", "noise_density_dps_rthz"):
            out[key] = _floats(url, key, value, 1)[0]
        elif key == "seed":
            try:
                out["seed"] = int(value)
            except ValueError:
                raise ConfigError(f"seed={value!r} in {url!r} must be an integer") from None
        else:
            raise ConfigError(
                f"unknown parameter {key!r} in {url!r}; allowed: " + ", ".join(SIM_URL_PARAMS)
            )
    return out


class SimGyroPort:
    """A pyserial-like port (``read``, ``in_waiting``, ``cancel_read``, ``close``) that
    streams a simulated gyro in real time.

    Parameters
    ----------
    url : str
        The ``sim://`` URL (see the module docstring).
    full_scale_dps : int
        Range of the simulated sensor, °/s.
    nominal_rate_hz : float
        Nominal sample rate, Hz.
    timeout : float or None
        Read timeout, s, as in pyserial (None blocks, 0 does not wait).
    """

    def __init__(
        self,
        url: str,
        *,
        full_scale_dps: int = 500,
        nominal_rate_hz: float = 8000.0,
        timeout: float | None = 0.05,
    ) -> None:
        # Imported here: sensors sits below sim in the layer order, and importing the sim
        # package only when a sim:// port is opened keeps plain serial use free of it.
        import numpy as np

        from timedexec.sim import GyroFrameSource, constant_rate_source

        params = parse_sim_url(url)
        rate_dps = params.pop("rate_dps", None)
        source = None
        if rate_dps is not None:
            source = constant_rate_source(np.radians(rate_dps).tolist())
        self.source = GyroFrameSource(
            source, full_scale_dps=full_scale_dps, nominal_rate_hz=nominal_rate_hz, **params
        )
        self.port = url
        self.timeout = timeout
        self.is_open = True
        self._buf = bytearray()
        self._ahead = bytearray()
        self._ahead_s = 0.05
        self._released = 0
        self._cancel = threading.Event()
        self.start_time_s = time.monotonic()

    def _produce(self) -> None:
        # Generate ahead in blocks, then release what is due: the release is a cheap slice,
        # so the caller's time stamp follows the due time closely (as it would for bytes
        # arriving from a device) instead of absorbing the generation time.
        elapsed = time.monotonic() - self.start_time_s
        if self.source.samples_due(elapsed + self._ahead_s / 2) > self.source.samples_generated:
            target = self.source.samples_due(elapsed + self._ahead_s)
            self._ahead += self.source.generate(target - self.source.samples_generated)
        due = self.source.samples_due(time.monotonic() - self.start_time_s)
        release = (due - self._released) * 11
        if release > 0:
            self._buf += self._ahead[:release]
            del self._ahead[:release]
            self._released = due

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read."""
        self._produce()
        return len(self._buf)

    def read(self, size: int = 1) -> bytes:
        """Read up to ``size`` bytes, waiting at most ``timeout`` for all of them."""
        if not self.is_open:
            raise ConfigError(f"port {self.port!r} is closed")
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while True:
            self._produce()
            if len(self._buf) >= size or self._cancel.is_set():
                break
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                break
            missing_samples = math.ceil((size - len(self._buf)) / 11)
            wait = missing_samples / self.source.true_rate_hz
            if deadline is not None:
                wait = min(wait, deadline - now)
            self._cancel.wait(max(wait, 1e-4))
        self._cancel.clear()
        out = bytes(self._buf[:size])
        del self._buf[:size]
        return out

    def cancel_read(self) -> None:
        """Make a blocked :meth:`read` return now."""
        self._cancel.set()

    def reset_input_buffer(self) -> None:
        """Discard everything produced so far."""
        self._produce()
        self._buf.clear()

    def close(self) -> None:
        """Close the port. Idempotent."""
        self.is_open = False
        self._cancel.set()
