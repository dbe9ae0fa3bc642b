"""The UR twin's ground-truth file: JSON lines appended (and flushed) as they happen.

Lines (read back by :func:`timedexec.twins.read_twin_truth` and
:func:`timedexec.twins.iter_truth_records`):

* ``{"event": "meta", ...}`` once at start, ``{"event": "gyro", ...}`` with a gyro twin;
* ``{"event": "command", **record}`` whenever a command record of the simulated controller
  is new or changed (rewritten until complete, or :data:`TRUTH_OPEN_S` old); the control
  script's own per-cycle setpoints of a Cartesian motion are left out (the motion's first
  command stands for it, under the motion's kind: ``MoveL``, ``SpeedL``, ``ServoL``);
* ``{"event": "program_stop", "time_s", "reason", ...}`` when the program stops (reason
  ``watchdog`` with ``variable``, ``min_frequency_hz``, ``last_update_s``; ``stopScript``;
  ``dashboard stop``), controller time.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from timedexec.twins._urscript import _as_record, _field

#: Ground-truth records still open (onsets pending) are rewritten for this long, s.
TRUTH_OPEN_S = 10.0


def json_safe(value: Any) -> Any:
    """``value`` with NaN/inf as None and numpy values as plain lists and numbers."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return [json_safe(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return json_safe(value.item())
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def truth_complete(record: Mapping[str, Any]) -> bool:
    """Whether a truth record can no longer change."""
    if record.get("superseded"):
        return record.get("intake_s") is None or record.get("reference_start_s") is not None
    if record.get("intake_s") is None or record.get("reference_start_s") is None:
        return False
    onset = record.get("onset_s") or []
    moved = record.get("moved_joints")
    if moved is None:
        return all(v is not None for v in onset)
    return all(onset[j - 1] is not None for j in moved)


class TruthLog:
    """Appends a twin's ground truth to ``path`` (None: keeps nothing; every method is
    then a no-op)."""

    def __init__(self, path: str | os.PathLike[str] | None) -> None:
        self._file = open(path, "a", encoding="utf-8") if path else None  # noqa: SIM115
        self._written: dict[int, str] = {}
        self._open: dict[int, Any] = {}
        self._last_id = 0

    @property
    def enabled(self) -> bool:
        """Whether a file is written."""
        return self._file is not None

    def line(self, record: Mapping[str, Any]) -> None:
        """Append one record (made JSON-safe) and flush."""
        if self._file is None:
            return
        self._file.write(json.dumps(json_safe(record), sort_keys=True) + "\n")
        self._file.flush()

    def commands(self, sim: Any, silent: set[int], kinds: dict[int, str]) -> None:
        """Append new and changed command records of ``sim`` (skipping the ids in
        ``silent``, reporting the ids in ``kinds`` under that kind)."""
        if self._file is None:
            return
        truth = getattr(sim, "truth", None)
        if truth is None:
            events: list[Any] = sim.truth_records()
            fresh = [e for e in events if int(e["id"]) > self._last_id]
        else:
            fresh = []
            for event in reversed(truth):
                if int(_field(event, "id")) <= self._last_id:
                    break
                fresh.append(event)
            fresh.reverse()
        for event in fresh:
            key = int(_field(event, "id"))
            self._last_id = max(self._last_id, key)
            if key in silent:  # a Cartesian motion's later setpoints: not commands
                silent.discard(key)
                continue
            self._open[key] = event
        horizon_s = float(sim.time_s) - TRUTH_OPEN_S
        for key, event in list(self._open.items()):
            record = json_safe(_as_record(event))
            if key in kinds:
                record["kind"] = kinds[key]
            line = json.dumps({"event": "command", **record}, sort_keys=True)
            if self._written.get(key) != line:
                self._written[key] = line
                self._file.write(line + "\n")
                self._file.flush()
            if truth_complete(record) or float(record.get("arrival_s") or 0.0) < horizon_s:
                del self._open[key]
                del self._written[key]
                kinds.pop(key, None)

    def close(self) -> None:
        if self._file is not None:
            with contextlib.suppress(OSError, ValueError):
                self._file.close()
