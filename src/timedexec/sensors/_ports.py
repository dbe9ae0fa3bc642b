"""Gyro port backends, chosen by URL like ``serial.serial_for_url``.

- a device path (``/dev/ttyUSB0``, ``/dev/ttyACM0``, a pty ``/dev/pts/N``, ``COM3``):
  a pyserial port;
- ``sim://[?rate_dps=X,Y,Z&...]``: a simulated sensor inside this process (no pty,
  :class:`~timedexec.sensors.SimGyroPort`).

pyserial's network URLs (``socket://``) are not accepted: the reader relies on
``in_waiting`` reporting a byte count, which their handlers do not.
"""

from __future__ import annotations

from typing import Protocol

import serial

from timedexec.errors import ConfigError, SensorError
from timedexec.sensors._settings import GyroSettings

__all__ = ["SUPPORTED_URL_SCHEMES", "Port", "open_port"]

#: URL schemes ``open_gyro`` accepts besides plain device paths.
SUPPORTED_URL_SCHEMES = ("sim",)


class Port(Protocol):
    """What the reader needs from a port (pyserial ``Serial`` or :class:`SimGyroPort`)."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def close(self) -> None: ...


def open_port(url: str, settings: GyroSettings) -> Port:
    """Open the port behind ``url`` with the serial settings of ``settings``.

    Parameters
    ----------
    url : str
        A device path or ``sim://...``.
    settings : GyroSettings
        Baud rate, read timeout (s), exclusive access; for ``sim://`` the full-scale range
        (°/s) and the nominal rate (Hz) of the simulated sensor.

    Raises
    ------
    ConfigError
        An unsupported URL scheme, or settings the port rejects.
    SensorError
        The device cannot be opened (the message says what to check).
    """
    if "://" in url:
        scheme = url.split("://", 1)[0].lower()
        if scheme not in SUPPORTED_URL_SCHEMES:
            raise ConfigError(
                f"unsupported gyro URL scheme {scheme!r} in {url!r}; use a device path such "
                "as /dev/ttyUSB0 or one of " + ", ".join(f"{s}://" for s in SUPPORTED_URL_SCHEMES)
            )
        if scheme == "sim":
            from timedexec.sensors._simport import SimGyroPort

            return SimGyroPort(
                url,
                full_scale_dps=settings.full_scale_dps,
                nominal_rate_hz=settings.nominal_rate_hz,
                timeout=settings.read_timeout_s,
            )
    try:
        port: Port = serial.serial_for_url(
            url,
            baudrate=settings.baudrate,
            timeout=settings.read_timeout_s,
            exclusive=settings.exclusive,
        )
    except serial.SerialException as exc:
        raise SensorError(
            f"cannot open gyro port {url!r}: {exc}. Check that the sensor is plugged in and "
            "the path is right (ls /dev/ttyUSB* /dev/ttyACM* /dev/serial/by-id/), that you "
            "may open it (group 'dialout'), and that no other program holds it"
        ) from exc
    except ValueError as exc:
        raise ConfigError(f"gyro port {url!r} rejected the settings: {exc}") from exc
    return port
