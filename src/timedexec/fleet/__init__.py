"""timedexec.fleet: many robots at once, on a Dask cluster or on local processes.

A manifest (:func:`read_manifest`; one line per robot: name, robot model, recording or
``sim://`` sweep, deployed model) goes through :func:`run_fleet`: per robot, as one task,
extraction -> training with cross-validation -> evaluation -> a drift check of the deployed
model (:func:`run_robot`), then a fleet report with a figure comparing robots and the list
of robots that need a new calibration. Dask (dask.distributed, the ``timedexec[dask]``
extra) is the engine: :func:`connect` and :func:`on_cluster` attach to a scheduler, and the
latter routes every joblib fan-out of the library through it. See docs/fleet.md.
"""

from __future__ import annotations

from timedexec.fleet._cluster import (
    INSTALL_HINT,
    SCHEDULER_ENV,
    connect,
    on_cluster,
    require_dask,
)
from timedexec.fleet._drift import DRIFT_STATES, drift_check
from timedexec.fleet._manifest import (
    MANIFEST_COLUMNS,
    FleetManifest,
    RobotEntry,
    SimSource,
    parse_manifest,
    parse_sim_source,
    read_manifest,
)
from timedexec.fleet._pipeline import STAGES, FleetSettings, RobotResult, run_robot
from timedexec.fleet._report import FLEET_COLUMNS, fleet_document, fleet_rows, write_fleet_report
from timedexec.fleet._run import FleetResult, run_fleet

__all__ = [
    "DRIFT_STATES",
    "FLEET_COLUMNS",
    "INSTALL_HINT",
    "MANIFEST_COLUMNS",
    "SCHEDULER_ENV",
    "STAGES",
    "FleetManifest",
    "FleetResult",
    "FleetSettings",
    "RobotEntry",
    "RobotResult",
    "SimSource",
    "connect",
    "drift_check",
    "fleet_document",
    "fleet_rows",
    "on_cluster",
    "parse_manifest",
    "parse_sim_source",
    "read_manifest",
    "require_dask",
    "run_fleet",
    "run_robot",
    "write_fleet_report",
]
