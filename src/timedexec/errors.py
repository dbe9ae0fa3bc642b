"""Exceptions of timedexec.

One base class, :class:`TimedExecError`; every subclass also inherits the builtin exception
it refines, so ``except ValueError`` keeps working for callers that do not know timedexec.
Vendor errors (ur_rtde, h5py, pyserial) are converted at the boundary with
``raise ... from exc``.
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "DatingWarning",
    "DriverError",
    "DriverTimeout",
    "ModelError",
    "ProtocolError",
    "RecordingError",
    "SensorError",
    "StaleStateError",
    "ThermalStateWarning",
    "TimedExecError",
    "UnreachableError",
]


class TimedExecError(Exception):
    """Base class of every error raised by timedexec."""


class ConfigError(TimedExecError, ValueError):
    """A setting, argument or input value is invalid; the message says how to fix it."""


class RecordingError(TimedExecError, OSError):
    """A recording cannot be written, read or resumed."""


class ProtocolError(TimedExecError, ValueError):
    """Bytes from a robot controller or sensor do not follow the protocol."""


class DriverError(TimedExecError, RuntimeError):
    """A robot driver failed (connection lost, robot stopped, command refused)."""


class DriverTimeout(DriverError, TimeoutError):
    """A robot or sensor did not answer in time; no stale data is handed out."""


class SensorError(TimedExecError, OSError):
    """The gyro/IMU stream failed (port, framing, clock)."""


class ModelError(TimedExecError, ValueError):
    """A delay model or model bundle is invalid, corrupt or for another robot."""


class StaleStateError(DriverTimeout):
    """The state stream is older than the executor allows; the robot was stopped."""


class UnreachableError(ConfigError):
    """The target cannot be reached by the deadline at the requested confidence.

    Attributes
    ----------
    miss_s : float
        How late the robot would arrive (at the requested confidence), s.
    """

    def __init__(self, message: str, *, miss_s: float) -> None:
        super().__init__(message)
        self.miss_s = float(miss_s)


class ThermalStateWarning(UserWarning):
    """A delay model was asked about a robot in another thermal state than the one it was
    trained in (a model of a warm robot queried for one just powered on, or the reverse);
    its delays may be off by the warm-up drift. Not an error: the answer is given."""


class DatingWarning(UserWarning):
    """The intake probe dated the state with little to spare: the cycle each package was
    sampled in was chosen by the mean response delay within an eighth of a period of the
    next one, or an echo depth given was contradicted by it
    (:meth:`timedexec.execution.IntakeFix.dated`). Not an error: the dating is used."""
