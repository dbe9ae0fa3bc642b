"""Run a fleet: every robot's pipeline on a Dask cluster (or on local processes), then the report.

On a cluster, each robot is one task (``Client.submit(run_robot, ...)``), named
``timedexec-fleet-NAME-...`` on the dashboard. Dask reruns the task of a worker that dies
(the lost robot starts again on another worker; its files are rewritten whole, with the
same content), up to the scheduler's ``distributed.scheduler.allowed-failures``; a robot
whose task keeps killing its workers (e.g. a damaged file that crashes the HDF5 library)
is reported as failed and the others complete. Without a scheduler the same function runs
on local processes through joblib (``jobs``), or in this process (``jobs=1``).

Either way every robot's numbers are those of :func:`~timedexec.fleet.run_robot` run on
its own, with single-threaded BLAS: the fleet tables of a cluster run and of a local run
are the same bytes.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from timedexec._files import check_output_file, make_dir
from timedexec._progress import Progress
from timedexec.errors import ConfigError
from timedexec.fleet._cluster import connect
from timedexec.fleet._manifest import FleetManifest, RobotEntry, read_manifest
from timedexec.fleet._pipeline import FleetSettings, RobotResult, failed_result, run_robot
from timedexec.fleet._report import fleet_document, write_fleet_report

__all__ = ["FleetResult", "run_fleet"]


@dataclass(frozen=True)
class FleetResult:
    """The outcome of :func:`run_fleet`.

    Attributes
    ----------
    robots : tuple of RobotResult
        In the manifest's order.
    files : dict of str to Path
        The report's files (``fleet.csv``, ``fleet.json``, ``report.md``, ``fleet.png``,
        ``run.json``, ``costs.csv``).
    document : dict
        What ``fleet.json`` holds (settings, summary, every robot's numbers).
    wall_s : float
        Wall time of the run, s.
    run : dict
        Where it ran (``scheduler``, ``workers``, ``jobs``).
    """

    robots: tuple[RobotResult, ...]
    files: dict[str, Path] = field(default_factory=dict)
    document: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    run: dict[str, Any] = field(default_factory=dict)

    @property
    def failed(self) -> tuple[RobotResult, ...]:
        """The robots whose run failed."""
        return tuple(r for r in self.robots if not r.ok)

    @property
    def needs_recalibration(self) -> tuple[str, ...]:
        """Names of the robots that need a new calibration."""
        return tuple(
            r.name for r in self.robots if r.summary.get("decision", {}).get("needs_recalibration")
        )

    def summary_text(self) -> str:
        """A few lines for a terminal."""
        ok = len(self.robots) - len(self.failed)
        where = self.run.get("scheduler") or f"{self.run.get('jobs', 1)} local job(s)"
        lines = [
            f"fleet of {len(self.robots)} robots on {where}: {ok} processed, "
            f"{len(self.failed)} failed, in {self.wall_s:.1f} s"
        ]
        for r in self.robots:
            decision = r.summary.get("decision", {})
            state = r.summary.get("drift", {}).get("state")
            if r.ok:
                ext = r.summary["extraction"]
                act = ext["actuation_delay"]["median_ms"]
                resp = ext["response_delay"]["median_ms"]
                err = r.summary["training"]["actuation_delay"]
                lines.append(
                    f"  {r.name:<14} {r.entry.robot:<6} actuation {act:6.1f} ms  response "
                    f"{resp:5.1f} ms  model {err['model_error_ms']:.2f} ms (floor "
                    f"{err['noise_floor_ms']:.2f})  monitor {state}"
                    + ("  RECALIBRATE" if decision.get("needs_recalibration") else "")
                )
            else:
                lines.append(
                    f"  {r.name:<14} {r.entry.robot:<6} FAILED ({r.failed_stage}): {r.error}"
                )
            kept = r.summary.get("training", {}).get("deployed_kept_as")
            if kept:
                lines.append(
                    f"  {'':<14} the deployed model was this run's --out folder: kept as "
                    f"{kept} (still in force until you deploy the new "
                    f"{r.summary['training']['bundle']})"
                )
        for name in self.needs_recalibration:
            reason = next(r for r in self.robots if r.name == name).summary["decision"]["reason"]
            lines.append(f"needs a new calibration: {name}: {reason}")
        if "fleet.csv" in self.files:
            lines.append(
                f"fleet table: {self.files['fleet.csv']}; report: {self.files['report.md']}"
            )
        return "\n".join(lines)


def _clean_partials(out: Path, entries: Sequence[RobotEntry]) -> None:
    """Remove what killed attempts of an earlier run left (temporary recordings)."""
    for e in entries:
        folder = out / "robots" / e.name
        if folder.is_dir():
            for leftover in folder.glob(".recording.*.partial*"):
                with contextlib.suppress(OSError):
                    leftover.unlink()


def _run_local(
    entries: Sequence[RobotEntry],
    out: Path,
    settings: FleetSettings,
    jobs: int,
    done: Callable[[RobotResult], None],
) -> None:
    if jobs == 1:
        for e in entries:
            done(run_robot(e, str(out), settings))
        return
    from joblib import Parallel, delayed

    calls = (delayed(run_robot)(e, str(out), settings) for e in entries)
    for result in Parallel(n_jobs=jobs, return_as="generator_unordered")(calls):
        done(result)


def _run_cluster(
    client: Any,
    entries: Sequence[RobotEntry],
    out: Path,
    settings: FleetSettings,
    done: Callable[[RobotResult], None],
) -> None:
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    futures = {
        client.submit(
            run_robot,
            e,
            str(out),
            settings,
            key=f"timedexec-fleet-{e.name}-{token}",
            pure=False,
        ): e
        for e in entries
    }
    try:
        for future in as_completed(futures, loop=client.loop):  # type: ignore[no-untyped-call]
            entry = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # KilledWorker, a lost connection ...
                text = " ".join(str(exc).split()) or type(exc).__name__
                if type(exc).__name__ == "KilledWorker":
                    text = (
                        "the worker running it died on every attempt (a crash, e.g. the HDF5 "
                        "library on a damaged recording, or out of memory); run it alone with "
                        f"`timedexec extract` to see why ({text})"
                    )
                result = failed_result(entry, "worker", f"{type(exc).__name__}: {text}")
            done(result)
    finally:
        client.cancel(list(futures))


def run_fleet(
    manifest: FleetManifest | str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    scheduler: Any = None,
    jobs: int = 1,
    settings: FleetSettings | None = None,
    progress: bool = True,
) -> FleetResult:
    """Calibrate-to-report for every robot of a manifest, on a cluster or locally.

    Parameters
    ----------
    manifest : FleetManifest or path
        The robots (:func:`~timedexec.fleet.read_manifest`).
    out : path
        Output folder (created): ``robots/NAME/`` per robot and the fleet report. On a
        cluster it must be on storage every worker shares (the workers write the robots'
        files), as must the recordings.
    scheduler : str or distributed.Client, optional
        A Dask scheduler's address (``tcp://host:8786``) or a connected client; None runs
        on this machine.
    jobs : int
        Without a scheduler: robots processed at once in local processes (joblib; -1: one
        per CPU; 1: in this process). Ignored with a scheduler (every worker is used).
    settings : FleetSettings, optional
        How every robot is processed (default :class:`FleetSettings`).
    progress : bool
        A line on stderr as robots finish.

    Returns
    -------
    FleetResult

    Raises
    ------
    ConfigError
        A bad manifest, settings or ``jobs``; dask.distributed missing with a scheduler.
    ConnectionError
        The scheduler does not answer.
    RecordingError
        The output folder cannot be created.
    """
    settings = settings or FleetSettings()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or (jobs < 1 and jobs != -1):
        raise ConfigError(f"jobs={jobs!r} must be a positive integer, or -1 for one per CPU")
    fleet = manifest if isinstance(manifest, FleetManifest) else read_manifest(manifest)
    out_path = make_dir(out, "fleet output folder").resolve()
    for name in ("fleet.csv", "fleet.json", "report.md", "fleet.png", "run.json", "costs.csv"):
        check_output_file(out_path / name)
    _clean_partials(out_path, fleet.entries)
    start = time.perf_counter()
    results: dict[str, RobotResult] = {}
    bar = Progress(len(fleet), "fleet", enabled=progress)

    def done(result: RobotResult) -> None:
        results[result.name] = result
        bar.update()
        if progress and not result.ok:
            print(
                f"fleet: {result.name} failed ({result.failed_stage}): {result.error}",
                file=sys.stderr,
            )

    run: dict[str, Any] = {"scheduler": None, "jobs": jobs, "workers": None}
    if scheduler is None:
        _run_local(fleet.entries, out_path, settings, jobs, done)
    else:
        own = isinstance(scheduler, str)
        client = connect(scheduler) if own else scheduler
        try:
            run["scheduler"] = str(client.scheduler.address)
            run["workers"] = len(client.scheduler_info(n_workers=-1).get("workers", {}))
            _run_cluster(client, fleet.entries, out_path, settings, done)
        finally:
            if own:
                client.close()
    bar.close()
    ordered = tuple(results[e.name] for e in fleet.entries)
    wall = time.perf_counter() - start
    run["wall_s"] = wall
    name = Path(fleet.path).name
    files = write_fleet_report(out_path, ordered, settings, run=run, manifest_name=name)
    document = fleet_document(ordered, settings, manifest_name=name)
    return FleetResult(robots=ordered, files=files, document=document, wall_s=wall, run=run)
