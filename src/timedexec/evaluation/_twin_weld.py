"""The conveyor weld through the real clients against the protocol twins, as an evaluation.

:func:`evaluate_conveyor_twin` is ``timedexec evaluate --task conveyor --twin``: the
example's weld (``examples/02_conveyor_welding.py``: the built-in cell, a seam on a belt at
0.5 m/s) in real time, through ``ur_rtde`` against the UR twin for a UR, through RSI XML
against the RSI twin for the KR 5 (:func:`~timedexec.evaluation.weld_on_twin`: a fresh twin
per weld, each weld starting with the approach move), the torch measured from the twin's
ground truth (its physical joint angles at each package's sampling instant). The same
strategies as the simulator's evaluation (:func:`~timedexec.evaluation.evaluate_conveyor`),
in the same ``strategies`` JSON:

* the tracking delays behind ``constant``, ``median`` and ``model`` come from
  ``calibration_runs`` uncompensated welds through the client (measured as a real cell
  would: reported positions at their sampling instants, no truth); ``constant`` is their
  overall median, ``median`` the per-joint medians, ``model`` the delay model corrected
  by them (:meth:`~timedexec.tasks.TrackingDelays.calibrate_runs`: dead times and the
  friction offsets);
* ``oracle`` shifts by the mean physical tracking delay of those welds, from the twin's
  truth (what a perfect measurement would give);
* ``none`` streams the plan unshifted.

The twins run at one work point only (the calibration welds too), in real time: each
strategy's ``runs`` welds take about 5-10 s each.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from timedexec._progress import Progress
from timedexec._realtime import realtime
from timedexec._validation import check_counts
from timedexec.errors import ConfigError
from timedexec.evaluation._onset import STRATEGIES
from timedexec.evaluation._welding import (
    ConveyorEvaluation,
    _pool,
    physical_tracking_delays,
    weld_on_twin,
)
from timedexec.execution import check_model_robot, load_delay_model
from timedexec.robots import get_robot, get_robot_entry
from timedexec.tasks import (
    SEAM_KINDS,
    ConveyorRun,
    Seam,
    TrackingDelays,
    default_cell,
    measure_tracking_delays,
    plan_seam,
)

__all__ = ["evaluate_conveyor_twin"]

#: Seeds of the twins' runs (their publisher phase and jitter): calibration first.
_CAL_SEED = 9_000


def evaluate_conveyor_twin(
    robot: str,
    model: Any = None,
    *,
    seam: str = "straight",
    runs: int = 2,
    calibration_runs: int = 3,
    seed: int = 20_261,
    settle_s: float = 0.15,
    cruise_s: float = 0.6,
    realtime_priority: int | None = 5,
    progress: bool = False,
) -> ConveyorEvaluation:
    """Physical torch error of the strategies, welding through a real client against the
    robot's protocol twin in real time (module docstring).

    Parameters
    ----------
    robot : str
        A robot with a twin: ``ur10``, ``ur10e`` (``ur_rtde``), ``kr5`` (RSI XML).
    model : delay model, bundle path or None
        Default: the model shipped for the robot.
    seam : {"straight", "curved"}
    runs : int
        Welds per strategy (each a fresh twin, seeds ``seed``, ``seed + 1``, ...).
    calibration_runs : int
        Uncompensated welds behind constant, median, model and the oracle (>= 1).
    seed : int
        The twins' seeds.
    settle_s, cruise_s : float
        The error window after the meeting, s.
    realtime_priority : int or None
        SCHED_FIFO priority of the welding thread and the client's threads (they inherit
        it), where the OS allows it, as on a cell (README); the twins run their cycle at 10.
        None: normal scheduling (on a loaded machine the client then falls behind the
        twin's cycle: 30 ms of lag between calibration welds at load 15).

    Raises
    ------
    ConfigError
        Bad counts, an unknown seam, a model for another robot.
    """
    spec = get_robot(robot)
    if seam not in SEAM_KINDS:
        raise ConfigError(f"seam={seam!r}; choose one of {', '.join(SEAM_KINDS)}")
    check_counts(runs=(runs, 1), calibration_runs=(calibration_runs, 1))
    entry = get_robot_entry(spec.name)
    predictor = load_delay_model(entry.shipped_model if model is None else model)
    check_model_robot(predictor, spec.name, spec.controller_period_s)
    the_seam = Seam(kind=seam)  # type: ignore[arg-type]
    sp = plan_seam(default_cell(spec.name), the_seam, weld_s=settle_s + cruise_s + 0.05)
    t_begin = time.monotonic()
    bar = Progress(calibration_runs + runs * len(STRATEGIES), f"twin weld {spec.name}",
                   enabled=progress)  # fmt: skip

    def weld(strategies: dict[str, Any], k: int) -> dict[str, ConveyorRun]:
        with realtime(realtime_priority):
            out = weld_on_twin(sp, predictor, strategies, seed=k, settle_s=settle_s,
                               cruise_s=cruise_s)  # fmt: skip
        bar.update(len(strategies))
        return out

    cal = [weld({"none": None}, seed + _CAL_SEED + i)["none"] for i in range(calibration_runs)]
    measured = np.asarray([measure_tracking_delays(r) for r in cal])
    constant = float(np.median(measured))
    median = np.median(measured, axis=0)
    tracking = TrackingDelays.calibrate_runs(predictor, cal)
    oracle = np.mean([physical_tracking_delays(r) for r in cal], axis=0)
    shifts: dict[str, Any] = {
        "none": None,
        "constant": np.full(6, constant),
        "median": median,
        "model": tracking,
        "oracle": oracle,
    }
    results: dict[str, list[ConveyorRun]] = {name: [] for name in STRATEGIES}
    for r in range(runs):
        for name, run in weld(shifts, seed + r).items():
            results[name].append(run)
    bar.close()
    strategies = {name: _pool(results[name]) for name in STRATEGIES}
    details: dict[str, Any] = {
        "twin": True,
        "interface": entry.twin.interface,
        "weld_speed_m_s": the_seam.weld_speed_m_s,
        "settle_s": settle_s,
        "cruise_s": cruise_s,
        "n_runs": runs,
        "calibration_runs": calibration_runs,
        "seed": seed,
        "realtime_priority": realtime_priority,
        "tracking_ms": {
            "constant": constant * 1e3,
            "median": (median * 1e3).round(3).tolist(),
            "model_dead_time": (np.asarray(tracking.dead_time_s) * 1e3).round(3).tolist(),
            "oracle": (oracle * 1e3).round(3).tolist(),
            "calibration_measured": (measured * 1e3).round(3).tolist(),
        },
        "cell": sp.cell.to_dict(),
        "notes": list(tracking.notes),
        "elapsed_s": time.monotonic() - t_begin,
    }
    return ConveyorEvaluation(
        robot=spec.name,
        seam=seam,
        speed_m_s=float(sp.cell.conveyor.speed_m_s),
        strategies=strategies,
        details=details,
        examples={name: runs_[0] for name, runs_ in results.items() if runs_},
        tracking_model=tracking,
    )
