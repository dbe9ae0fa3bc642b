"""One lifecycle for every protocol twin: the verbs a test or a benchmark drives them by."""

from __future__ import annotations

import abc
from types import TracebackType
from typing import Self

from timedexec.errors import ConfigError

__all__ = ["Twin"]


class Twin(abc.ABC):
    """Base of the protocol twins (:class:`~timedexec.twins.URTwin`,
    :class:`~timedexec.twins.RSITwin`, :class:`~timedexec.twins.GyroTwin`).

    Every twin is driven by the same verbs, and is a context manager (``with`` starts it
    and stops it):

    ``start()``
        Start serving and wait until the device is up; returns the twin.
    ``stop()``
        Stop cleanly (connections closed, ground truth written); idempotent.
    ``kill()``
        Vanish abruptly, as a crashed controller or an unplugged sensor.
    ``stall(seconds)``
        The stream to the client stops for ``seconds`` while the device runs on (its
        clock, physics and sampling continue); then it resumes.
    ``drop()``
        Close the clients' connections now; the twin keeps serving and accepts new ones.

    A verb the twin's protocol has no meaning for raises :class:`NotImplementedError`
    naming what to use instead (RSI is connectionless, so :meth:`RSITwin.drop
    <timedexec.twins.RSITwin.drop>` points to ``drop_frames``).
    """

    @abc.abstractmethod
    def start(self) -> Self:
        """Start the twin and wait until it serves; returns the twin."""

    @abc.abstractmethod
    def stop(self) -> object:
        """Stop the twin cleanly; idempotent."""

    @abc.abstractmethod
    def kill(self) -> None:
        """Stop the twin abruptly, as a crash would (nothing is flushed or written)."""

    @property
    @abc.abstractmethod
    def is_alive(self) -> bool:
        """Whether the twin runs (its process or thread is alive)."""

    def stall(self, seconds: float) -> None:
        """Stop the stream to the client for ``seconds`` (s) while the device runs on.

        Raises
        ------
        ConfigError
            If ``seconds`` is negative or NaN.
        NotImplementedError
            If the twin cannot stall its stream.
        """
        if not seconds >= 0:
            raise ConfigError(f"stall seconds={seconds!r} must be >= 0")
        self._stall(float(seconds))

    def _stall(self, seconds: float) -> None:
        raise NotImplementedError(f"{type(self).__name__} cannot stall its stream")

    def drop(self) -> None:
        """Close every client connection now; keep serving.

        Raises
        ------
        NotImplementedError
            If the twin's protocol has no connections to drop.
        """
        raise NotImplementedError(f"{type(self).__name__} has no connections to drop")

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
