"""timedexec.evaluation: held-out evaluation of compensation strategies on the simulator.

Two measurements with the simulator's ground truth, one module each, both comparing the
same strategies (``none``, ``constant``, ``median``, ``model``, ``oracle``):

* ``_onset``: the onset timing of every strategy on held-out start configurations
  (:func:`evaluate` -> :class:`Evaluation`; :class:`SimulatedOracle`, the true conditional
  mean), optionally checked on a carousel seam (:func:`timedexec.tasks.track_seam`);
* ``_welding``: the conveyor weld measured at the torch from the simulator's physical joint
  angles (:func:`evaluate_conveyor` -> :class:`ConveyorEvaluation`, :func:`run_weld`), and
  the same welds through the real clients against the protocol twins
  (:func:`weld_on_twin`; as an evaluation of the strategies, ``_twin_weld``:
  :func:`evaluate_conveyor_twin`).

This is the layer that runs the simulator; the tasks it evaluates (:mod:`timedexec.tasks`)
and the executor never import it.
"""

from __future__ import annotations

from timedexec.evaluation._onset import (
    STRATEGIES,
    Evaluation,
    SimulatedOracle,
    evaluate,
    held_out_capacity,
    warm_effects,
)
from timedexec.evaluation._twin_weld import evaluate_conveyor_twin
from timedexec.evaluation._welding import (
    TRACKING_SOURCES,
    ConveyorEvaluation,
    conveyor_cells,
    evaluate_conveyor,
    phase_seeds,
    physical_tracking_delays,
    run_weld,
    sweep_tracking_model,
    weld_on_twin,
)

__all__ = [
    "STRATEGIES",
    "TRACKING_SOURCES",
    "ConveyorEvaluation",
    "Evaluation",
    "SimulatedOracle",
    "conveyor_cells",
    "evaluate",
    "evaluate_conveyor",
    "evaluate_conveyor_twin",
    "held_out_capacity",
    "phase_seeds",
    "physical_tracking_delays",
    "run_weld",
    "sweep_tracking_model",
    "warm_effects",
    "weld_on_twin",
]
