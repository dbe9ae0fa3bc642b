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

from timedexec._types import FloatArray
from timedexec.drivers import RobotState
from timedexec.execution._plan import JointPlan

__all__ = ["CycleLog", "ExecutionResult", "intake_echo"]


class CycleLog:
    """Per-cycle record of the loop: one row per state package handled.

    Columns (numpy arrays from :meth:`arrays`): ``arrival_s`` (host arrival), ``controller_s``
    (controller time stamp of the cycle commanded), ``sequence``, ``send_s`` (host time the
    command left; NaN when none was sent), ``qd_cmd`` (n, 6), ``q`` (n, 6) reported,
    ``clipped`` (a limit clipped the command), ``coasted`` (the cycle's package was late: the
    command went out from the estimate, the row repeats the previous package), ``target_s``
    (the cycle-locked send time aimed at; NaN without the lock or without a command),
    ``target_qd`` (n, 6): the controller's target speed in the package (NaN where the
    protocol has none; :func:`intake_echo`).
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
            "target_qd": np.empty((cap, 6)),
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
        tqd = state.target_qd
        if tqd is None:
            c["target_qd"][i] = math.nan
        else:
            c["target_qd"][i] = tqd
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


def intake_echo(log: dict[str, NDArray[Any]], *, depth: int = 16) -> dict[str, float]:
    """Which command each controller cycle took, read back from the packages' ``target_qd``
    (a UR reports the speed it commands; the speedj ramp the executor sends reaches each
    command within a cycle): the controller-side view of missed cycles, without its truth.

    Each package's target is matched to the one command among the last ``depth`` sent
    before it with exactly that value (packages whose target matches none, or several
    equal commands, are left out). Between two consecutive matched packages the command
    index should step by one: a step of 0 is a cycle that took no new command (``repeats``),
    a step of k > 1 means k - 1 commands were overwritten before a cycle took them
    (``overwritten``).

    Returns
    -------
    dict
        ``packages``, ``matched`` (consecutive matched pairs), ``coverage`` (matched pairs
        / package pairs: low where targets do not equal commands, e.g. after a missed
        cycle the next ramp does not finish within one), ``repeats``, ``overwritten``,
        ``missed_fraction`` (repeats / matched pairs; NaN without pairs).
    """
    sent = np.isfinite(log["send_s"])
    send_s, cmds = log["send_s"][sent], log["qd_cmd"][sent]
    keep = ~log["coasted"] & np.all(np.isfinite(log["target_qd"]), axis=1)
    seq, arrival, target = log["sequence"][keep], log["arrival_s"][keep], log["target_qd"][keep]
    _, first = np.unique(seq, return_index=True)  # a package logged twice counts once
    index = np.full(len(first), -1)
    for n, k in enumerate(np.sort(first)):
        hi = int(np.searchsorted(send_s, arrival[k]))
        lo = max(0, hi - depth)
        scale = np.maximum(1.0, np.abs(target[k]))
        same = np.flatnonzero(np.all(np.abs(cmds[lo:hi] - target[k]) <= 1e-9 * scale, axis=1))
        if len(same) == 1:
            index[n] = lo + int(same[0])
    pairs = (index[1:] >= 0) & (index[:-1] >= 0)
    step = (index[1:] - index[:-1])[pairs]
    repeats, over = int(np.sum(step == 0)), int(np.sum(np.maximum(step - 1, 0)))
    n_pairs = int(pairs.sum())
    return {
        "packages": len(first),
        "matched": n_pairs,
        "coverage": n_pairs / (len(first) - 1) if len(first) > 1 else math.nan,
        "repeats": repeats,
        "overwritten": over,
        "missed_fraction": repeats / n_pairs if n_pairs else math.nan,
    }
