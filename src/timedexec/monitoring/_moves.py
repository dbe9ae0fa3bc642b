"""Moves and their observed lag, from a robot's own command and state stream (no gyro).

A *move* is a joint's commanded speed leaving zero from rest. Its observed lag is the time
from sending that command to the state stream showing the motion: actuation + response
(+ a constant). It is measured with sub-period resolution by inverting the commanded ramp:
the reported displacement ``d_p`` of every package ``p`` arriving during the first part of
the ramp is mapped to the host instant ``t*(d_p)`` at which the *commanded* displacement
reached ``d_p``; the lag of that package is ``arrival_p - t*(d_p)``, and the move's lag the
median over the packages in the window (displacements between ``LOW_FRACTION`` and
``HIGH_FRACTION`` of the commanded displacement at the end of the first acceleration).

The commanded speed is piecewise linear in host time: a calibration trial's trapezoid from
its send time (``profile.acceleration_rad_s2``), or the executor's commands, each reached one
controller period after it was sent (the speedj ramp the executor sets). Sources:

* :func:`moves_from_recording`: a calibration recording (every trial a move from rest);
* :class:`MoveExtractor`: the rows of a :class:`~timedexec.execution.CycleLog`, fed in
  chunks (live or from a saved log, :func:`save_cycle_log` / :func:`load_cycle_log`).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.errors import ConfigError, RecordingError

__all__ = [
    "HIGH_FRACTION",
    "LOG_FORMAT",
    "LOW_FRACTION",
    "Move",
    "MoveExtractor",
    "collapse_conditions",
    "load_cycle_log",
    "move_lag_s",
    "moves_from_recording",
    "moves_from_trials",
    "save_cycle_log",
]


#: Lower and upper edge of the onset window, fractions of the commanded displacement at the
#: end of the first acceleration. Below 2 % the joint is still breaking away (and a real
#: encoder's noise counts); above 60 % the velocity loop's catch-up distorts the lag.
LOW_FRACTION = 0.02
HIGH_FRACTION = 0.6
#: Moves whose first commands left within this of the first's are one plan, s: the
#: executor sends each joint's share of a trajectory early by the joint's predicted
#: actuation delay (UR: a few ms apart; KR 5: up to ~0.1 s). Below the 0.3 s rest a
#: joint needs between two moves, so a plan holds each joint once.
PLAN_WINDOW_S = 0.15
#: Format name of a saved cycle log (.npz).
LOG_FORMAT = "timedexec-cycle-log"
_LOG_COLUMNS = ("arrival_s", "controller_s", "sequence", "send_s", "qd_cmd", "q")


@dataclass(frozen=True)
class Move:
    """One move of one joint from rest, as the monitor sees it.

    Attributes
    ----------
    joint : int
        Joint, 1-based.
    direction : int
        +1 or -1.
    q_start_rad : ndarray, shape (6,)
        Reported configuration when the command left, rad.
    send_s : float
        Host time the first command of the move left, s.
    lag_s : float
        Observed lag (actuation + response + a constant of the method), s; NaN when the
        window held no package.
    packages : int
        Packages the lag is the median of.
    sweep_time_s : float
        Time since the robot started working, s, when known (a recording's ``t0_s``); NaN
        otherwise.
    source : int
        Trial index (recording) or log row of the first command.
    """

    joint: int
    direction: int
    q_start_rad: FloatArray
    send_s: float
    lag_s: float
    packages: int
    sweep_time_s: float = math.nan
    source: int = -1


def _displacement_at(t_knot: FloatArray, v_knot: FloatArray) -> FloatArray:
    """Commanded displacement at each knot of a piecewise-linear speed (trapezoid rule)."""
    return np.concatenate(([0.0], np.cumsum(0.5 * (v_knot[1:] + v_knot[:-1]) * np.diff(t_knot))))


def _invert(
    t_knot: FloatArray, v_knot: FloatArray, p_knot: FloatArray, d: FloatArray
) -> FloatArray:
    """Host instants at which the commanded displacement reaches ``d`` (exact for the
    piecewise-linear speed: a quadratic per segment)."""
    i = np.clip(np.searchsorted(p_knot, d, side="right") - 1, 0, len(t_knot) - 2)
    dt = t_knot[i + 1] - t_knot[i]
    slope = np.where(dt > 0, (v_knot[i + 1] - v_knot[i]) / np.where(dt > 0, dt, 1.0), 0.0)
    rest = d - p_knot[i]
    disc = np.maximum(v_knot[i] ** 2 + 2.0 * slope * rest, 0.0)
    den = v_knot[i] + np.sqrt(disc)
    tau = np.where(den > 0, 2.0 * rest / np.where(den > 0, den, 1.0), np.nan)
    return np.asarray(t_knot[i] + tau, dtype=float)


def move_lag_s(
    t_knot: FloatArray,
    v_knot: FloatArray,
    arrival_s: FloatArray,
    displacement_rad: FloatArray,
) -> tuple[float, int]:
    """Observed lag of one move and the packages it rests on.

    Parameters
    ----------
    t_knot, v_knot : ndarray
        Commanded speed (positive in the move's direction) as a piecewise-linear function
        of host time: knots, s and rad/s; ``v_knot[0] = 0`` at ``t_knot[0]`` (the send).
    arrival_s : ndarray
        Host arrival of the packages after the send, in order, s.
    displacement_rad : ndarray
        Their reported displacement from rest in the move's direction, rad.

    Returns
    -------
    (float, int)
        The median lag over the onset window (s; NaN when no package is in it) and the
        number of packages used.
    """
    p_knot = _displacement_at(t_knot, v_knot)
    dv = np.diff(v_knot)
    stop = np.flatnonzero(dv <= 0)
    end = int(stop[0]) if len(stop) else len(v_knot) - 1
    ref = float(p_knot[end])
    if not ref > 0:
        return math.nan, 0
    lo, hi = LOW_FRACTION * ref, HIGH_FRACTION * ref
    above = np.flatnonzero(displacement_rad >= hi)
    last = int(above[0]) if len(above) else len(displacement_rad)
    d = displacement_rad[:last]
    use = np.flatnonzero(d > lo)
    if not len(use):
        return math.nan, 0
    t_star = _invert(t_knot[: end + 1], v_knot[: end + 1], p_knot[: end + 1], d[use])
    lags = arrival_s[:last][use] - t_star
    lags = lags[np.isfinite(lags)]
    if not len(lags):
        return math.nan, 0
    return float(np.median(lags)), len(lags)


# ----------------------------------------------------------------------------- recordings
def _unit_factor(reader: Any, name: str, kind: str) -> float:
    from timedexec.extraction import UNITS

    fld = reader.fields.get(name)
    unit = None if fld is None else fld.unit
    if unit is None:
        raise RecordingError(
            f"{reader.path}: field {name!r} is missing; a calibration recording holds it "
            "(docs/recording-format.md, 'Per-trial fields')"
        )
    factor = UNITS[kind].get(unit)
    if factor is None:
        raise RecordingError(
            f"{reader.path}: field {name!r} has unit {unit!r}; use one of "
            f"{', '.join(repr(u) for u in UNITS[kind])}"
        )
    return float(factor)


def moves_from_recording(
    path: str | os.PathLike[str], *, collapse_repeats: bool = True
) -> tuple[list[Move], dict[str, Any]]:
    """The moves of a calibration recording's robot stream (no gyro needed).

    Each trial is a move from rest: its joint and direction from ``cmd_qd_rad_s``, the start
    configuration from the last package before the send, the commanded trapezoid from the
    header's ``profile``. Moves are returned in the order the trials ran (``t0_s``).

    ``collapse_repeats`` (default): consecutive trials of one condition (same joint,
    direction and start configuration: a sweep's repeats) become one move whose lag is their
    median. Their residuals against the model share the model's error at that pose, so
    they are not independent; a sequential test fed every repeat would count one pose's
    error ten times (false alarms).

    Returns
    -------
    (list of Move, dict)
        The moves and ``{robot, period_s, source}``.

    Raises
    ------
    RecordingError
        Not a recording, or a field, unit or header key missing (named, with the fix).
    """
    from timedexec.recording import RecordingReader

    with RecordingReader(path) as r:
        header = r.header
        try:
            acc = float(header["profile"]["acceleration_rad_s2"])
            speed = float(header["profile"]["speed_rad_s"])
            period = float(header["controller_period_s"])
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(
                f"{path}: header key {exc} missing or not a number; the monitor needs "
                "profile.acceleration_rad_s2, profile.speed_rad_s and controller_period_s"
            ) from exc
        robot = header.get("robot", {})
        robot_name = str(robot.get("name", "")) if isinstance(robot, dict) else str(robot)
        ts = _unit_factor(r, "state_host_time_s", "time")
        cs = _unit_factor(r, "cmd_send_time_s", "time")
        qs = _unit_factor(r, "state_q_rad", "angle")
        vs = _unit_factor(r, "cmd_qd_rad_s", "speed")
        t0s = _unit_factor(r, "t0_s", "time")
        trial = r.read("trial")
        t0 = r.read("t0_s").astype(float) * t0s
        send = r.read("cmd_send_time_s").astype(float) * cs
        qd = r.read("cmd_qd_rad_s").astype(float) * vs
        arrival = r.read("state_host_time_s").astype(float) * ts
        q = r.read("state_q_rad").astype(float) * qs
    trials = {
        "trial": trial,
        "t0_s": t0,
        "cmd_send_time_s": send,
        "cmd_qd_rad_s": qd,
        "state_host_time_s": arrival,
        "state_q_rad": q,
    }
    moves = moves_from_trials(trials, acceleration_rad_s2=acc, speed_rad_s=speed)
    if collapse_repeats:
        moves = collapse_conditions(moves)
    return moves, {"robot": robot_name, "period_s": period, "source": str(path)}


def moves_from_trials(
    trials: dict[str, NDArray[Any]], *, acceleration_rad_s2: float, speed_rad_s: float
) -> list[Move]:
    """The moves of calibration trials given as arrays (SI units, the recording's per-trial
    fields ``trial``, ``t0_s``, ``cmd_send_time_s``, ``cmd_qd_rad_s``, ``state_host_time_s``,
    ``state_q_rad``; e.g. a batch of the batch simulator), in the order they ran."""
    acc, speed = float(acceleration_rad_s2), float(speed_rad_s)
    if not (acc > 0 and speed > 0):
        raise ConfigError(
            f"acceleration_rad_s2={acc!r} and speed_rad_s={speed!r} must be > 0 (the trial profile)"
        )
    trial = np.asarray(trials["trial"])
    t0 = np.asarray(trials["t0_s"], dtype=float)
    send = np.asarray(trials["cmd_send_time_s"], dtype=float)
    qd = np.asarray(trials["cmd_qd_rad_s"], dtype=float)
    arrival = np.asarray(trials["state_host_time_s"], dtype=float)
    q = np.asarray(trials["state_q_rad"], dtype=float)
    order = np.argsort(t0, kind="stable")
    ramp_s = speed / acc
    t_knot = np.array([0.0, ramp_s])
    v_knot = np.array([0.0, speed])
    moves: list[Move] = []
    for i in order:
        nz = np.flatnonzero(qd[i] != 0)
        if len(nz) != 1:
            continue  # not a single-joint trial
        col = int(nz[0])
        sign = 1 if qd[i, col] > 0 else -1
        a, qq = arrival[i], q[i]
        ok = np.isfinite(a) & np.all(np.isfinite(qq), axis=1)
        a, qq = a[ok], qq[ok]
        before = np.flatnonzero(a <= send[i])
        if not len(before):
            continue
        q0 = qq[before[-1]]
        after = a > send[i]
        lag, used = move_lag_s(
            t_knot + send[i],
            v_knot * abs(qd[i, col]) / speed,
            a[after],
            sign * (qq[after, col] - q0[col]),
        )
        moves.append(
            Move(
                joint=col + 1,
                direction=sign,
                q_start_rad=q0,
                send_s=float(t0[i] + send[i]),
                lag_s=lag,
                packages=used,
                sweep_time_s=float(t0[i]),
                source=int(trial[i]),
            )
        )
    return moves


def collapse_conditions(moves: list[Move]) -> list[Move]:
    """Merge runs of consecutive moves of one condition (joint, direction, start
    configuration within 1 µrad) into one move: median lag, packages summed."""
    out: list[Move] = []
    group: list[Move] = []

    def flush() -> None:
        if not group:
            return
        lags = np.array([m.lag_s for m in group])
        ok = np.isfinite(lags)
        first = group[0]
        out.append(
            Move(
                joint=first.joint,
                direction=first.direction,
                q_start_rad=first.q_start_rad,
                send_s=first.send_s,
                lag_s=float(np.median(lags[ok])) if ok.any() else math.nan,
                packages=sum(m.packages for m in group),
                sweep_time_s=first.sweep_time_s,
                source=first.source,
            )
        )
        group.clear()

    for m in moves:
        if group and not (
            m.joint == group[0].joint
            and m.direction == group[0].direction
            and np.allclose(m.q_start_rad, group[0].q_start_rad, rtol=0.0, atol=1e-6)
        ):
            flush()
        group.append(m)
    flush()
    return out


# ----------------------------------------------------------------------------- cycle logs
def save_cycle_log(
    path: str | os.PathLike[str],
    arrays: dict[str, NDArray[Any]],
    *,
    period_s: float,
    robot: str = "",
) -> Path:
    """Write a cycle log (:meth:`CycleLog.arrays`, or ``ExecutionResult.log``) as .npz.

    The file holds the columns ``arrival_s``, ``controller_s``, ``sequence``, ``send_s``,
    ``qd_cmd`` (n, 6), ``q`` (n, 6) (and ``coasted`` when present) plus ``meta``, a JSON
    string ``{format, format_version, period_s, robot}``; see docs/monitor.md.
    """
    from timedexec._files import write_atomic

    if not (math.isfinite(period_s) and period_s > 0):
        raise ConfigError(f"period_s={period_s!r} must be the controller period, s (> 0)")
    out = {k: np.asarray(arrays[k]) for k in _LOG_COLUMNS}
    if "coasted" in arrays:
        out["coasted"] = np.asarray(arrays["coasted"], dtype=bool)
    meta = {"format": LOG_FORMAT, "format_version": 1, "period_s": float(period_s), "robot": robot}
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, meta=np.array(json.dumps(meta)), **out)
    write_atomic(path, buf.getvalue())
    return Path(path)


def load_cycle_log(path: str | os.PathLike[str]) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """Read a cycle log written by :func:`save_cycle_log`: ``(arrays, meta)``.

    Raises
    ------
    RecordingError
        Not such a file, or a column missing or of the wrong shape (named).
    """
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise RecordingError(
            f"{path}: cannot read it as a cycle log (.npz) ({exc}); write one with "
            "timedexec.monitoring.save_cycle_log"
        ) from exc
    if "meta" not in data:
        raise RecordingError(f"{path}: not a timedexec cycle log (no 'meta'); see docs/monitor.md")
    try:
        meta = json.loads(str(data.pop("meta")))
    except ValueError as exc:
        raise RecordingError(f"{path}: unreadable 'meta' ({exc})") from exc
    meta = _check_log_meta(path, meta)
    n = None
    for k in _LOG_COLUMNS:
        if k not in data:
            raise RecordingError(f"{path}: column {k!r} is missing; see docs/monitor.md")
        n = len(data[k]) if n is None else n
        want = (n, 6) if k in ("qd_cmd", "q") else (n,)
        if data[k].shape != want:
            raise RecordingError(f"{path}: column {k!r} has shape {data[k].shape}, expected {want}")
        if data[k].dtype.kind not in "fiub":
            raise RecordingError(
                f"{path}: column {k!r} holds {data[k].dtype} values, not numbers; see "
                "docs/monitor.md"
            )
    _check_log_times(path, data)
    return data, meta


def _check_log_meta(path: str | os.PathLike[str], meta: Any) -> dict[str, Any]:
    """The cycle log's ``meta`` checked: an object of the right format, a finite positive
    period, a robot name (may be empty)."""
    where = f"{os.fspath(path)}: 'meta'"
    if not isinstance(meta, dict):
        raise RecordingError(
            f"{where} is a {type(meta).__name__}, not an object; see docs/monitor.md"
        )
    version = meta.get("format_version", 0)
    if meta.get("format") != LOG_FORMAT or not isinstance(version, int) or version > 1:
        raise RecordingError(
            f"{where}: format {meta.get('format')!r} version {version!r}; "
            f"this timedexec reads {LOG_FORMAT!r} version 1"
        )
    period = meta.get("period_s")
    if (
        isinstance(period, bool)
        or not isinstance(period, int | float)
        or not math.isfinite(period)
        or not 1e-4 <= period <= 1.0
    ):
        raise RecordingError(
            f"{where}: period_s={period!r} is not a controller period; it must be a number "
            "of seconds in 0.0001 .. 1 (e.g. 0.008 for a UR10); rewrite the log with "
            "save_cycle_log(path, arrays, period_s=...)"
        )
    robot = meta.get("robot", "")
    if not isinstance(robot, str):
        raise RecordingError(f"{where}: robot={robot!r} is not a robot name (a string)")
    return {**meta, "period_s": float(period), "robot": robot}


def _check_log_times(path: str | os.PathLike[str], data: dict[str, NDArray[Any]]) -> None:
    """Refuse a cycle log whose clocks cannot be a log: arrival and controller times
    non-finite or running backwards, reported positions not finite (a command of NaN is
    allowed: no command was sent that cycle)."""
    # A coasted row carries the cycle the executor commanded ahead of a late package, so
    # the package that then arrives may be dated before it: the packages' own times are
    # what must run forward.
    fresh = ~np.asarray(data.get("coasted", np.zeros(len(data["arrival_s"]), bool)), dtype=bool)
    for key in ("arrival_s", "controller_s"):
        t = np.asarray(data[key], dtype=float)
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise RecordingError(
                f"{os.fspath(path)}: {key} is {float(t[bad[0]])} at row {bad[0]} ({bad.size} such "
                "row(s)); every row of a cycle log is a state package with a finite time, s"
            )
        rows = np.flatnonzero(fresh) if key == "controller_s" else np.arange(t.size)
        back = np.flatnonzero(np.diff(t[rows]) < 0)
        if back.size:
            h, i = (int(r) for r in rows[back[0] : back[0] + 2])
            raise RecordingError(
                f"{os.fspath(path)}: {key} runs backwards at row {i} ({float(t[h])!r} -> "
                f"{float(t[i])!r} s; {back.size} such step(s)); a cycle log is in arrival order"
            )
    q = np.asarray(data["q"], dtype=float)
    bad_rows = np.flatnonzero(~np.isfinite(q).all(axis=1))
    if bad_rows.size:
        raise RecordingError(
            f"{os.fspath(path)}: q is not finite at row {bad_rows[0]} ({bad_rows.size} "
            "row(s)); the reported joint positions of every package must be numbers, rad"
        )


class MoveExtractor:
    """Moves from a cycle log fed in chunks of rows (:meth:`CycleLog.arrays`).

    A joint's move starts at the first row whose command for it is non-zero after at least
    ``rest_s`` of zero commands, with its reported position still (spread below
    ``still_rad``) over the packages of the last ``rest_s / 2``. The move is measured once
    the log reaches ``horizon_s`` past its send. Only the rows that a pending or a future
    move can need are kept (``rest_s + horizon_s``), so memory stays bounded.

    Parameters
    ----------
    period_s : float
        Controller period, s: each command's ramp lasts one period.
    rest_s : float
        Zero commands needed before a move counts as from rest, s.
    horizon_s : float
        How long after its send a move is measured, s (>= the largest actuation + response
        + the first acceleration; default 0.4 s covers the KR 5's ~0.1 s delays).
    still_rad : float
        Largest spread of the reported position at rest, rad.
    """

    def __init__(
        self,
        period_s: float,
        *,
        rest_s: float = 0.3,
        horizon_s: float = 0.4,
        still_rad: float = 2e-4,
    ) -> None:
        for name, value in (("period_s", period_s), ("rest_s", rest_s), ("horizon_s", horizon_s)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}={value!r} must be a positive number of seconds")
        self.period_s = float(period_s)
        self.rest_s = float(rest_s)
        self.horizon_s = float(horizon_s)
        self.still_rad = float(still_rad)
        self._buf: dict[str, NDArray[Any]] | None = None
        self._row0 = 0  # log row of the buffer's first row
        self._last_nonzero = np.full(6, -math.inf)  # host time of each joint's last command != 0
        self._v_prev = np.zeros(6)
        self._pending: list[tuple[int, int, float]] = []  # (log row, joint col, send_s)
        self._scanned = 0  # log rows already scanned for move starts

    def feed(self, arrays: dict[str, NDArray[Any]]) -> list[Move]:
        """Add the next rows of the log; return the moves that became measurable."""
        n_new = len(arrays["arrival_s"])
        if n_new == 0:
            return []
        cols = {k: np.asarray(arrays[k]) for k in _LOG_COLUMNS}
        cols["coasted"] = np.asarray(arrays.get("coasted", np.zeros(n_new, bool)), dtype=bool)
        if self._buf is None:
            self._buf = cols
        else:
            self._buf = {k: np.concatenate((self._buf[k], cols[k])) for k in cols}
        self._scan(n_new)
        done = self._measure()
        self._trim()
        return done

    def _scan(self, n_new: int) -> None:
        assert self._buf is not None
        b = self._buf
        start = len(b["arrival_s"]) - n_new
        send, qd = b["send_s"], b["qd_cmd"]
        for i in range(start, len(send)):
            if not math.isfinite(send[i]):
                continue
            v = qd[i]
            starting = (v != 0) & (self._v_prev == 0)
            for col in np.flatnonzero(starting):
                if send[i] - self._last_nonzero[col] >= self.rest_s:
                    self._pending.append((self._row0 + i, int(col), float(send[i])))
            self._last_nonzero[v != 0] = send[i]
            self._v_prev = np.where(np.isfinite(v), v, 0.0)

    def _measure(self) -> list[Move]:
        assert self._buf is not None
        b = self._buf
        newest = float(b["arrival_s"][-1])
        out: list[Move] = []
        # pending moves are in send order; the measurable ones are a prefix. Hold those a
        # move still to measure may share a plan with (its send within PLAN_WINDOW_S).
        unready = [p[2] for p in self._pending if newest < p[2] + self.horizon_s]
        hold_from = unready[0] - PLAN_WINDOW_S if unready else math.inf
        keep: list[tuple[int, int, float]] = []
        for row, col, t_send in self._pending:
            if newest < t_send + self.horizon_s or t_send >= hold_from:
                keep.append((row, col, t_send))
                continue
            move = self._one(row - self._row0, col, t_send)
            if move is not None:
                out.append(move)
        self._pending = keep
        return out

    def _one(self, i: int, col: int, t_send: float) -> Move | None:
        assert self._buf is not None
        b = self._buf
        arrival, send, q, qd = b["arrival_s"], b["send_s"], b["q"], b["qd_cmd"]
        fresh = ~b["coasted"]
        # Rest: the packages of the last rest_s / 2 before the send agree.
        before = fresh & (arrival <= t_send) & (arrival >= t_send - 0.5 * self.rest_s)
        idx = np.flatnonzero(before)
        if not len(idx):
            return None
        spread = np.ptp(q[idx, col])
        if spread > self.still_rad:
            return None
        q0 = q[idx[-1]].astype(float)
        sign = 1 if qd[i, col] > 0 else -1
        end = t_send + self.horizon_s
        cmd = np.flatnonzero(np.isfinite(send) & (send >= t_send) & (send < end))
        cmd = cmd[cmd >= i]
        v = sign * np.where(np.isfinite(qd[cmd, col]), qd[cmd, col], 0.0)
        t_knot = np.concatenate(([t_send], send[cmd] + self.period_s))
        v_knot = np.concatenate(([0.0], v))
        # A command sent before the previous one's ramp ended: keep knots in time order.
        t_knot = np.maximum.accumulate(t_knot)
        after = np.flatnonzero(fresh & (arrival > t_send) & (arrival < end))
        lag, used = move_lag_s(t_knot, v_knot, arrival[after], sign * (q[after, col] - q0[col]))
        return Move(
            joint=col + 1,
            direction=sign,
            q_start_rad=q0,
            send_s=t_send,
            lag_s=lag,
            packages=used,
            source=self._row0 + i,
        )

    def _trim(self) -> None:
        assert self._buf is not None
        b = self._buf
        newest = float(b["arrival_s"][-1])
        oldest_needed = min([p[2] for p in self._pending], default=newest) - self.rest_s
        cut = int(np.searchsorted(b["arrival_s"], oldest_needed, side="left"))
        # Keep the rows of pending moves (their first command row) too.
        if self._pending:
            cut = min(cut, min(p[0] for p in self._pending) - self._row0)
        cut = max(0, cut - 1)
        if cut > 0:
            self._buf = {k: v[cut:] for k, v in b.items()}
            self._row0 += cut
