"""What the KUKA RSI driver returns: :class:`RSIState` (one frame), :class:`RSIStats`
(counters of the answer thread) and :class:`RSICommandRecord` (when a command left); see
:mod:`timedexec.drivers._rsi`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from timedexec._types import FloatArray
from timedexec.drivers._base import RobotState

__all__ = ["RSICommandRecord", "RSIState", "RSIStats"]


@dataclass(frozen=True, kw_only=True)
class RSIState(RobotState):
    """A :class:`~timedexec.drivers.RobotState` with the RSI-specific fields.

    Attributes
    ----------
    ipoc : int
        The frame's IPOC.
    q_setpoint : ndarray, shape (6,), or None
        ``ASPos`` (set-point axis positions), rad, if the configuration sends it.
    cartesian : ndarray, shape (6,), or None
        ``RIst``: X, Y, Z (m), A, B, C (rad), if sent.
    robot_late_count : int or None
        The controller's late-answer counter ``<Delay D>``, if sent.
    correction : ndarray, shape (6,)
        The absolute correction sent in the answer to this frame, rad.
    answer_host_time_s : float
        ``time.monotonic()`` right after the answer left, s.
    """

    ipoc: int = 0
    q_setpoint: FloatArray | None = None
    cartesian: FloatArray | None = None
    robot_late_count: int | None = None
    correction: FloatArray = field(default_factory=lambda: np.zeros(6))
    answer_host_time_s: float = math.nan


@dataclass(frozen=True, kw_only=True)
class RSIStats:
    """Counters of the answer thread (a snapshot; see :meth:`KukaRSIDriver.stats`).

    Attributes
    ----------
    frames : int
        ``<Rob>`` frames received and parsed (empty RSI <= 2.3 start frames excluded).
    answers : int
        ``<Sen>`` answers sent.
    late_answers : int
        Answers that left more than one period after their frame arrived (the robot would
        count them late).
    max_answer_latency_s, mean_answer_latency_s : float
        Receive-to-send time of the answers, s (``nan`` before the first answer).
    protocol_errors : int
        Datagrams rejected by the parser (not answered).
    last_protocol_error : str
        Message of the last rejection.
    empty_frames : int
        Empty ``<Rob>`` frames ignored.
    missed_cycles : int
        Controller cycles without a frame, from IPOC gaps.
    clamped_cycles : int
        Cycles in which the correction was held at a position or correction limit.
    queue_overflows : int
        States dropped because nobody read them (the queue keeps the newest ``queue_size``).
    sessions : int
        RSI sessions seen (a session starts with the first frame after a silence).
    robot_late_count : int
        The last ``<Delay D>`` value reported by the robot (-1 if not sent).
    ignored_frames : int
        Datagrams from addresses other than the robot's, dropped unanswered.
    last_foreign_address : str
        ``ip:port`` of the last of them (``"-"`` if none).
    peer_address : str
        ``ip:port`` the driver answers (``"-"`` before the first frame).
    ipoc_tick_s : float
        Seconds per IPOC unit in use (``"auto"`` resolved on the second frame).
    """

    frames: int = 0
    answers: int = 0
    late_answers: int = 0
    max_answer_latency_s: float = math.nan
    mean_answer_latency_s: float = math.nan
    protocol_errors: int = 0
    last_protocol_error: str = ""
    empty_frames: int = 0
    missed_cycles: int = 0
    clamped_cycles: int = 0
    queue_overflows: int = 0
    sessions: int = 0
    robot_late_count: int = -1
    ignored_frames: int = 0
    last_foreign_address: str = "-"
    peer_address: str = "-"
    ipoc_tick_s: float = math.nan


@dataclass(frozen=True, kw_only=True)
class RSICommandRecord:
    """When a motion command was issued and when it first left in an answer.

    Attributes
    ----------
    kind : str
        ``"speedj"`` or ``"stop"``.
    qd_rad_s : ndarray, shape (6,)
        Target joint speeds, rad/s (zeros for stop).
    acceleration_rad_s2 : float
        Leading-axis acceleration, rad/s².
    duration_s : float
        Hold duration, s (``inf`` for stop).
    call_host_s : float
        ``time.monotonic()`` when the method was called, s.
    first_answer_host_s : float
        ``time.monotonic()`` when the first answer carrying it left, s (``nan`` if never).
    first_answer_ipoc : int
        IPOC of that answer (-1 if never).
    """

    kind: str
    qd_rad_s: FloatArray
    acceleration_rad_s2: float
    duration_s: float
    call_host_s: float
    first_answer_host_s: float = math.nan
    first_answer_ipoc: int = -1
