"""The bookkeeping of a run: the per-cycle log of the loop and the result of an execution.

:class:`CycleLog` gets one row per state package the loop handles (arrival, controller time,
sequence number, send time, command, reported position, whether a limit clipped the command
or the command went out from the estimate); :meth:`CycleLog.timing` turns it into send-time
statistics. :class:`ExecutionResult` is what :meth:`TimedExecutor.execute` returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec.drivers import RobotState
from timedexec.execution._plan import JointPlan

__all__ = ["CycleLog", "ExecutionResult"]

FloatArray = NDArray[np.float64]


class CycleLog:
    """Per-cycle record of the loop: one row per state package handled.

    Columns (numpy arrays from :meth:`arrays`): ``arrival_s`` (host arrival), ``controller_s``
    (controller time stamp of the cycle commanded), ``sequence``, ``send_s`` (host time the
    command left; NaN when none was sent), ``qd_cmd`` (n, 6), ``q`` (n, 6) reported,
    ``clipped`` (a limit clipped the command), ``coasted`` (the cycle's package was late: the
    command went out from the estimate, the row repeats the previous package), ``target_s``
    (the cycle-locked send time aimed at; NaN without the lock or without a command).
    :meth:`work` gives the loop's own work per row (s; NaN where not measured).

    Rows are written into preallocated arrays (capacity doubling from ``capacity``), so a
    row costs no Python list, tuple or array allocation.
    """

    def __init__(self, capacity: int = 4096) -> None:
        self._n = 0
        self._alloc(max(16, int(capacity)))

    def _alloc(self, cap: int) -> None:
        old = self.__dict__.get("_cols")
        cols = {
            "arrival_s": np.empty(cap),
            "controller_s": np.empty(cap),
            "sequence": np.empty(cap, np.int64),
            "send_s": np.empty(cap),
            "target_s": np.empty(cap),
            "clipped": np.empty(cap, bool),
            "coasted": np.empty(cap, bool),
            "qd_cmd": np.empty((cap, 6)),
            "q": np.empty((cap, 6)),
            "work_s": np.empty(cap),
        }
        if old is not None:
            for key, arr in cols.items():
                arr[: self._n] = old[key][: self._n]
        self._cols = cols
        self._cap = cap

    def __len__(self) -> int:
        return self._n

    def add(
        self,
        state: RobotState,
        send_s: float,
        qd_cmd: FloatArray | None,
        clipped: bool,
        *,
        controller_s: float | None = None,
        work_s: float = math.nan,
        target_s: float = math.nan,
    ) -> None:
        """Append a row (``controller_s``: the cycle commanded, default the package's;
        ``work_s``: the loop's own work for it, s; ``target_s``: the send time aimed at)."""
        i = self._n
        if i >= self._cap:
            self._alloc(2 * self._cap)
        c = self._cols
        ctrl = state.controller_time_s if controller_s is None else controller_s
        c["arrival_s"][i] = state.host_time_s
        c["controller_s"][i] = ctrl
        c["sequence"][i] = state.sequence
        c["send_s"][i] = send_s
        c["target_s"][i] = target_s
        c["clipped"][i] = clipped
        c["coasted"][i] = controller_s is not None and controller_s != state.controller_time_s
        if qd_cmd is None:
            c["qd_cmd"][i] = math.nan
        else:
            c["qd_cmd"][i] = qd_cmd
        c["q"][i] = state.q
        c["work_s"][i] = work_s
        self._n = i + 1

    def clear(self) -> None:
        """Forget every row."""
        self._n = 0

    def arrays(self, start: int = 0) -> dict[str, NDArray[Any]]:
        """The log from row ``start`` on as arrays (copies)."""
        n = self._n
        start = min(max(int(start), 0), n)
        return {key: arr[start:n].copy() for key, arr in self._cols.items() if key != "work_s"}

    def work(self, start: int = 0) -> FloatArray:
        """The loop's own work per row from ``start`` on (package read to command handed to
        the driver, without any wait for the send phase), s; NaN where nothing was sent."""
        return np.asarray(self._cols["work_s"][start : self._n].copy())

    def timing(self, start: int = 0, *, window_s: float = 0.5) -> dict[str, Any]:
        """Send-time statistics of the loop.

        The ideal send time of the command answering package ``k`` is the earliest the
        package can arrive: its controller time stamp mapped to the host clock by a
        lower-envelope clock model (the minimum of arrival minus controller time over a
        sliding ``window_s``). The send-time error is the actual send time minus that
        (network, client polling and the executor's own work). ``missed`` counts controller
        cycles without a handled package (sequence gaps).
        """
        from scipy.ndimage import minimum_filter1d

        arr = self.arrays(start)
        if len(arr["arrival_s"]) < 2:
            return {"cycles": len(arr["arrival_s"]), "missed": 0}
        ctrl = arr["controller_s"]
        period = float(np.median(np.diff(ctrl)))
        off = np.where(arr["coasted"], np.inf, arr["arrival_s"] - ctrl)
        size = max(1, round(window_s / period))
        env = minimum_filter1d(off, size=size, mode="nearest")
        sent = np.isfinite(arr["send_s"])
        err = (arr["send_s"] - (ctrl + env))[sent]
        proc = (arr["send_s"] - arr["arrival_s"])[sent & ~arr["coasted"]]
        gaps = np.diff(arr["sequence"][~arr["coasted"]])
        q = [50, 90, 99, 99.9]
        return {
            "cycles": len(ctrl),
            "expected_cycles": int(arr["sequence"][-1] - arr["sequence"][0] + 1),
            "missed": int(np.sum(np.maximum(gaps - 1, 0))),
            "commands": int(sent.sum()),
            "coasted": int(arr["coasted"].sum()),
            "period_s": period,
            "send_error_s": {f"p{p:g}": float(np.percentile(err, p)) for p in q}
            | {"mean": float(err.mean()), "max": float(err.max())},
            "processing_s": {f"p{p:g}": float(np.percentile(proc, p)) for p in q}
            | {"max": float(proc.max())},
        }


@dataclass
class ExecutionResult:
    """What :meth:`TimedExecutor.execute` did.

    Attributes
    ----------
    plan : JointPlan
        The executed plan (scheduled).
    actuation_s, actuation_std_s : ndarray (6,)
        The per-joint shift applied and its predicted single-trial std, s.
    response_s : float
        The response delay states were back-dated by, s.
    first_send_s, last_send_s : float
        Host times of the first and last command, s.
    log : dict
        :meth:`CycleLog.arrays` of the execution.
    """

    plan: JointPlan
    actuation_s: FloatArray
    actuation_std_s: FloatArray
    response_s: float
    first_send_s: float
    last_send_s: float
    log: dict[str, NDArray[Any]] = field(repr=False)

    @classmethod
    def from_log(
        cls,
        plan: JointPlan,
        log: dict[str, NDArray[Any]],
        *,
        actuation_s: FloatArray,
        actuation_std_s: FloatArray,
        response_s: float,
    ) -> ExecutionResult:
        """The result of executing ``plan`` whose rows of the cycle log are ``log``
        (:meth:`CycleLog.arrays`), with the shifts and response delay the loop used (s;
        the arrays are copied). The first and last send times are read from the log."""
        sends = log["send_s"][np.isfinite(log["send_s"])]
        return cls(
            plan=plan,
            actuation_s=actuation_s.copy(),
            actuation_std_s=actuation_std_s.copy(),
            response_s=response_s,
            first_send_s=float(sends[0]) if len(sends) else math.nan,
            last_send_s=float(sends[-1]) if len(sends) else math.nan,
            log=log,
        )

    @property
    def missed_cycles(self) -> int:
        """Controller cycles without a handled package during the execution."""
        seq = self.log["sequence"]
        return int(np.sum(np.maximum(np.diff(seq) - 1, 0))) if len(seq) > 1 else 0
