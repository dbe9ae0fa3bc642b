"""One robot of the fleet, start to end: sweep -> delay table -> models -> evaluation -> drift.

:func:`run_robot` is the unit of work the fleet schedules (one Dask task, or one local
job): it is a plain function of its arguments, writes only inside ``OUT/robots/NAME``
(each file whole, through a temporary file and a rename), and returns a
:class:`RobotResult`. Run twice, it writes the same files and returns the same summary, so a
task that Dask reruns after losing its worker changes nothing. Its numerical work runs with
single-threaded BLAS wherever it runs (a laptop, a loky worker, a Dask worker), so the
numbers do not depend on where it ran.

A robot whose data cannot be used (a damaged or missing recording, too few configurations
for the folds, a deployed model that does not load) is reported as failed with the stage
and the reason; nothing is raised, so the other robots complete.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import resource
import socket
import tempfile
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._files import make_dir, write_atomic
from timedexec.errors import ConfigError, RecordingError, TimedExecError
from timedexec.fleet._drift import drift_check
from timedexec.fleet._manifest import RobotEntry
from timedexec.learning import DEFAULT_METHODS

__all__ = ["STAGES", "FleetSettings", "RobotResult", "run_robot"]

#: The stages of a robot's run, in order (``simulate`` only for a ``sim://`` source).
STAGES = ("simulate", "fetch", "extract", "train", "evaluate", "drift")
_MAX_SEED = 2**32 - 1


@dataclass(frozen=True, kw_only=True)
class FleetSettings:
    """How every robot of a fleet is processed (the same for all).

    Attributes
    ----------
    methods : tuple of str
        Delay models to cross-validate and train: registered methods
        (:data:`timedexec.learning.METHODS`); default the paper's four.
    folds : int
        Cross-validation folds (>= 2), split by start configuration.
    seed : int
        Seed of the folds and the estimators.
    extract_method : str
        ``fit`` (default) or ``extrema``.
    eval_configs : int
        Held-out simulated configurations of the evaluation (0 skips it).
    eval_draws : int
        Simulated trials behind the evaluation's oracle (>= 2).
    eval_seed : int
        Plan seed of the held-out set.
    drift_ms : float
        Smallest shift from the deployed model the drift check reports, ms.
    drift_alpha : float
        False-alarm probability of the drift check per robot.
    """

    methods: tuple[str, ...] = DEFAULT_METHODS
    folds: int = 10
    seed: int = 0
    extract_method: str = "fit"
    eval_configs: int = 300
    eval_draws: int = 20
    eval_seed: int = 20_261
    drift_ms: float = 1.0
    drift_alpha: float = 1e-3

    def __post_init__(self) -> None:
        from timedexec.extraction import METHODS as EXTRACT_METHODS
        from timedexec.learning import check_methods

        object.__setattr__(self, "methods", check_methods(self.methods))
        ints = (
            ("folds", self.folds, 2, None),
            ("seed", self.seed, 0, _MAX_SEED),
            ("eval_configs", self.eval_configs, 0, None),
            ("eval_draws", self.eval_draws, 2, None),
            ("eval_seed", self.eval_seed, 0, _MAX_SEED),
        )
        for name, value, low, high in ints:
            if (
                isinstance(value, bool)
                or not isinstance(value, int)
                or value < low
                or (high is not None and value > high)
            ):
                top = "" if high is None else f" and <= {high}"
                raise ConfigError(f"{name}={value!r} must be an integer >= {low}{top}")
        if self.extract_method not in EXTRACT_METHODS:
            raise ConfigError(
                f"extract_method={self.extract_method!r}; choose one of {', '.join(EXTRACT_METHODS)}"
            )
        if not (
            isinstance(self.drift_ms, int | float)
            and math.isfinite(self.drift_ms)
            and self.drift_ms > 0
        ):
            raise ConfigError(
                f"drift_ms={self.drift_ms!r} must be a positive number of milliseconds"
            )
        if not (isinstance(self.drift_alpha, int | float) and 0 < self.drift_alpha < 1):
            raise ConfigError(f"drift_alpha={self.drift_alpha!r} must lie in (0, 1), e.g. 0.001")

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (round-trips through :meth:`from_dict`)."""
        return {
            "methods": list(self.methods),
            "folds": self.folds,
            "seed": self.seed,
            "extract_method": self.extract_method,
            "eval_configs": self.eval_configs,
            "eval_draws": self.eval_draws,
            "eval_seed": self.eval_seed,
            "drift_ms": self.drift_ms,
            "drift_alpha": self.drift_alpha,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FleetSettings:
        """The settings :meth:`to_dict` wrote."""
        known = set(cls().to_dict())
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"unknown fleet setting(s): {', '.join(sorted(unknown))}")
        values = dict(data)
        if "methods" in values:
            values["methods"] = tuple(values["methods"])
        return cls(**values)


@dataclass(frozen=True, kw_only=True)
class RobotResult:
    """What one robot's run produced.

    Attributes
    ----------
    entry : RobotEntry
        The robot, as the manifest names it.
    status : str
        ``ok`` or ``failed``.
    failed_stage : str or None
        The stage that failed (one of :data:`STAGES`).
    error : str or None
        Why, in one line (``RecordingError: recording ... is damaged ...``).
    summary : dict
        The numbers of the run, deterministic (the same wherever and however often it
        ran): ``extraction``, ``training``, ``evaluation``, ``drift``, ``decision``.
    costs : dict
        Per stage: ``wall_s``, ``cpu_s``, ``peak_rss_mb`` (the process's high-water mark
        at the end of the stage), ``read_mb`` (bytes the process read, /proc/self/io
        ``rchar``; None where not available). Not deterministic.
    worker : str
        ``host:pid`` of the process that ran it.
    """

    entry: RobotEntry
    status: str
    failed_stage: str | None = None
    error: str | None = None
    summary: dict[str, Any] = field(default_factory=dict)
    costs: dict[str, dict[str, float | None]] = field(default_factory=dict)
    worker: str = ""

    @property
    def name(self) -> str:
        """The robot's name."""
        return self.entry.name

    @property
    def ok(self) -> bool:
        """Whether every stage ran."""
        return self.status == "ok"

    def to_dict(self, *, costs: bool = False) -> dict[str, Any]:
        """JSON-safe form; ``costs=True`` adds the costs and the worker (not deterministic)."""
        out: dict[str, Any] = {
            **self.entry.to_dict(),
            "status": self.status,
            "failed_stage": self.failed_stage,
            "error": self.error,
            **self.summary,
        }
        if costs:
            out["costs"] = self.costs
            out["worker"] = self.worker
        return out


def failed_result(entry: RobotEntry, stage: str, error: str, *, worker: str = "") -> RobotResult:
    """A :class:`RobotResult` for a robot whose run did not return (e.g. its worker died)."""
    return RobotResult(
        entry=entry,
        status="failed",
        failed_stage=stage,
        error=error,
        summary={"drift": {"state": "not run"}, "decision": _decision(None, stage, error)},
        worker=worker,
    )


# ------------------------------------------------------------------------ measuring


def _rchar() -> int | None:
    try:
        with open("/proc/self/io", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("rchar:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


@contextlib.contextmanager
def _meter(costs: dict[str, dict[str, float | None]], stage: str) -> Iterator[None]:
    """Record a stage's wall time, CPU time, peak RSS and bytes read into ``costs``."""
    wall, cpu, read = time.perf_counter(), time.process_time(), _rchar()
    try:
        yield
    finally:
        read_end = _rchar()
        costs[stage] = {
            "wall_s": time.perf_counter() - wall,
            "cpu_s": time.process_time() - cpu,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "read_mb": None if read is None or read_end is None else (read_end - read) / 1e6,
        }


@contextlib.contextmanager
def _single_threaded() -> Iterator[None]:
    """BLAS and OpenMP on one thread: results independent of where the task runs."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        yield
        return
    with threadpool_limits(limits=1):
        yield


# ------------------------------------------------------------------------ stages


def _simulate(entry: RobotEntry, folder: Path) -> Path:
    """Record the ``sim://`` sweep to ``folder/recording.h5`` (whole or not at all)."""
    from timedexec.effects import parse_effects
    from timedexec.sim import simulate_sweep

    assert entry.sim is not None
    sim = entry.sim
    final = folder / "recording.h5"
    fd, tmp_name = tempfile.mkstemp(prefix=".recording.", suffix=".h5.partial", dir=folder)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()  # the writer refuses an existing file
    try:
        simulate_sweep(
            sim.robot,
            sim.trials,
            tmp,
            seed=sim.seed,
            effects=parse_effects(sim.effects, sim.robot),
            repeats=sim.repeats,
            jobs=1,
            progress=False,
        )
        os.replace(tmp, final)
    finally:
        for leftover in (tmp, *folder.glob(f"{tmp.name}*")):
            with contextlib.suppress(OSError):
                leftover.unlink()
    return final


@contextlib.contextmanager
def _local_recording(location: str) -> Iterator[str]:
    """A local path for the recording at ``location`` (a path, or an fsspec URL copied to
    a temporary file of this machine for the time of the block)."""
    if "://" not in location:
        yield location
        return
    try:
        import fsspec
    except ImportError as exc:
        raise ConfigError(
            f"reading {location} needs fsspec (python3 -m pip install fsspec, and the "
            "filesystem's package, e.g. s3fs)"
        ) from exc
    try:
        fs, remote = fsspec.core.url_to_fs(location)
        exists = fs.exists(remote)
    except (ImportError, ValueError) as exc:  # unknown protocol, missing backend package
        raise ConfigError(f"cannot open {location}: {exc}") from exc
    if not exists:
        raise RecordingError(f"recording {location} does not exist; check the URL")
    with tempfile.TemporaryDirectory(prefix="timedexec-fleet-") as tmp:
        local = os.path.join(tmp, "recording.h5")
        try:
            fs.get_file(remote, local)
        except OSError as exc:
            raise RecordingError(f"cannot copy {location} to this machine: {exc}") from exc
        yield local


def _delay_stats(values: Any) -> dict[str, float | None]:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)] * 1e3
    if not v.size:
        return {"median_ms": None, "p2_5_ms": None, "p97_5_ms": None}
    lo, med, hi = np.percentile(v, [2.5, 50.0, 97.5])
    return {"median_ms": float(med), "p2_5_ms": float(lo), "p97_5_ms": float(hi)}


def _extraction_summary(result: Any) -> dict[str, Any]:
    table = result.table
    flags = [str(f) for f in table["flag"]] if "flag" in table else [""] * len(table)
    ok = np.array([not f for f in flags], dtype=bool)
    counts: dict[str, int] = {}
    for f in flags:
        if f:
            counts[f] = counts.get(f, 0) + 1
    joint = np.asarray(table["joint"], dtype=np.int64)
    out: dict[str, Any] = {
        "trials": len(table),
        "flagged": int((~ok).sum()),
        "flags": dict(sorted(counts.items())),
        "filter_cutoff_hz": float(result.cutoff_hz),
        "gyro_rate_error_ppm": float(result.clock_rate_error_ppm),
    }
    for name in ("actuation_delay", "response_delay"):
        values = np.asarray(table[name], dtype=float)
        out[name] = _delay_stats(values[ok])
        out[name]["per_joint_median_ms"] = {
            str(j): _delay_stats(values[ok & (joint == j)])["median_ms"]
            for j in sorted({int(x) for x in joint})
        }
        truth = f"true_{name}"
        if truth in table:
            err = (values - np.asarray(table[truth], dtype=float))[ok]
            err = err[np.isfinite(err)]
            out[name]["rmse_vs_truth_ms"] = (
                float(np.sqrt(np.mean(err**2)) * 1e3) if err.size else None
            )
    return out


def _training_summary(cv: Any) -> dict[str, Any]:
    scores = cv.to_dict()
    out: dict[str, Any] = {"folds": cv.folds, "configurations": cv.n_configurations}
    for delay in ("actuation_delay", "response_delay"):
        averages = {m: float(row["average"]) for m, row in scores[delay].items()}
        best = min(averages, key=lambda m: (not math.isfinite(averages[m]), averages[m]))
        floor = float(cv.noise_floor_ms[delay]["average"])
        model = "gpr" if "gpr" in averages else best
        out[delay] = {
            "cv_average_ms": averages,
            "best": best,
            "model": model,
            "model_error_ms": averages[model],
            "noise_floor_ms": floor,
            "error_over_floor": averages[model] / floor if floor > 0 else None,
        }
    return out


def _evaluation_summary(info: dict[str, Any]) -> dict[str, Any]:
    strategies = info.get("strategies", {})
    return {
        "trials": info.get("n_trials"),
        "configurations": info.get("n_configurations"),
        "timing_rms_ms": {k: float(v["timing_rms_ms"]) for k, v in strategies.items()},
        "coverage_95": info.get("coverage_95"),
        "notes": list(info.get("notes", [])),
    }


def _decision(
    drift: dict[str, Any] | None, failed_stage: str | None, error: str | None
) -> dict[str, Any]:
    """Does the robot need a new calibration, and why."""
    if failed_stage is not None:
        if failed_stage == "drift":
            return {
                "needs_recalibration": True,
                "reason": f"the deployed model could not be checked: {error}",
            }
        return {
            "needs_recalibration": True,
            "reason": f"no usable result ({failed_stage} failed): {error}",
        }
    if drift is None:
        return {
            "needs_recalibration": False,
            "reason": "no deployed model to check; the new model is ready to deploy",
        }
    if drift["state"] == "drift":
        return {
            "needs_recalibration": True,
            "reason": "drifted from the deployed model: " + "; ".join(drift["drifted"]),
        }
    return {"needs_recalibration": False, "reason": "the deployed model still fits"}


def _error_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, TimedExecError | OSError):
        return f"{type(exc).__name__}: {text}"
    # Anything else is a bug in timedexec: name where it happened.
    frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    where = f" (at {Path(frame.filename).name}:{frame.lineno})" if frame else ""
    return f"{type(exc).__name__}: {text}{where}"


def run_robot(
    entry: RobotEntry, out_dir: str | os.PathLike[str], settings: FleetSettings
) -> RobotResult:
    """Process one robot: its sweep, delay table, models, evaluation and drift check.

    Parameters
    ----------
    entry : RobotEntry
        The robot (recording paths absolute, readable where this runs).
    out_dir : path
        The fleet's output folder; this writes only in ``out_dir/robots/NAME``:
        ``recording.h5`` (a ``sim://`` source), ``delays.csv``, ``model/`` (the bundle,
        ``cv.json``), ``evaluation.json``, ``drift.json``, ``result.json`` and, when a stage
        failed on a bug, ``error.txt`` (the traceback).
    settings : FleetSettings

    Returns
    -------
    RobotResult
        Never raises for a robot's bad data: a failed stage is in the result.
    """
    folder = make_dir(Path(out_dir) / "robots" / entry.name, "robot output folder")
    costs: dict[str, dict[str, float | None]] = {}
    summary: dict[str, Any] = {}
    stage = "simulate" if entry.sim is not None else "fetch"
    failed: tuple[str, str] | None = None
    drift: dict[str, Any] | None = None
    worker = f"{socket.gethostname()}:{os.getpid()}"
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(_single_threaded())
            if entry.sim is not None:
                with _meter(costs, "simulate"):
                    recording = str(_simulate(entry, folder))
            else:
                assert entry.recording is not None
                with _meter(costs, "fetch"):
                    recording = stack.enter_context(_local_recording(entry.recording))
            stage = "extract"
            with _meter(costs, "extract"):
                table, period_s, summary["extraction"] = _extract(
                    recording, entry, settings, folder
                )
            # The drift check comes before anything is trained or saved: the deployed
            # bundle may be the one this run would replace (`--out` reused).
            stage = "drift"
            with _meter(costs, "drift"):
                drift = _drift(table, entry, settings, folder)
            stage = "train"
            with _meter(costs, "train"):
                model, summary["training"] = _train(table, period_s, entry, settings, folder)
            if settings.eval_configs > 0:
                stage = "evaluate"
                with _meter(costs, "evaluate"):
                    summary["evaluation"] = _evaluate(model, entry, settings, folder)
        except Exception as exc:  # a robot's failure is reported, never raised
            failed = (stage, _error_line(exc))
            if not isinstance(exc, TimedExecError | OSError):
                with contextlib.suppress(TimedExecError, OSError):
                    write_atomic(folder / "error.txt", "".join(traceback.format_exception(exc)))
    if drift is not None:
        summary["drift"] = drift
    elif failed is None:
        summary["drift"] = {"state": "no reference"}
    else:
        summary["drift"] = {"state": "error" if failed[0] == "drift" else "not run"}
    summary["decision"] = _decision(drift, *(failed if failed is not None else (None, None)))
    result = RobotResult(
        entry=entry,
        status="ok" if failed is None else "failed",
        failed_stage=None if failed is None else failed[0],
        error=None if failed is None else failed[1],
        summary=summary,
        costs=costs,
        worker=worker,
    )
    with contextlib.suppress(TimedExecError, OSError):
        write_atomic(
            folder / "result.json", json.dumps(result.to_dict(), indent=2, allow_nan=True) + "\n"
        )
    return result


def _extract(
    recording: str, entry: RobotEntry, settings: FleetSettings, folder: Path
) -> tuple[Any, float | None, dict[str, Any]]:
    from timedexec.extraction import extract_recording
    from timedexec.recording import RecordingReader

    with RecordingReader(recording) as reader:
        header = reader.header
    robot = header.get("robot", {})
    robot_name = (
        str(robot.get("name", "")).lower() if isinstance(robot, dict) else str(robot).lower()
    )
    if robot_name and robot_name != entry.robot:
        raise ConfigError(
            f"{entry.source} is a sweep of {robot_name!r} but the manifest says {entry.robot!r} "
            f"(line {entry.line}); correct the robot column"
        )
    period = header.get("controller_period_s")
    result = extract_recording(recording, method=settings.extract_method, jobs=1, progress=False)
    result.table.to_csv(folder / "delays.csv")
    return result.table, (None if period is None else float(period)), _extraction_summary(result)


def _train(
    table: Any, period_s: float | None, entry: RobotEntry, settings: FleetSettings, folder: Path
) -> tuple[Any, dict[str, Any]]:
    from timedexec.learning import train_delay_models

    digest = hashlib.sha256((folder / "delays.csv").read_bytes()).hexdigest()
    result = train_delay_models(
        table,
        methods=settings.methods,
        folds=settings.folds,
        jobs=1,
        random_state=settings.seed,
        progress=False,
        period_s=period_s,
        source=f"robots/{entry.name}/delays.csv",  # relative: the same wherever OUT is
        source_sha256=digest,
    )
    model = result.model
    kept = _keep_deployed(entry, folder / "model")
    model.save(folder / "model")
    assert result.cv is not None
    write_atomic(folder / "model" / "cv.json", json.dumps(result.cv.to_dict(), indent=2) + "\n")
    training = _training_summary(result.cv)
    training["bundle"] = f"robots/{entry.name}/model"
    if kept is not None:
        training["deployed_kept_as"] = f"robots/{entry.name}/{kept.name}"
    return model, training


def _keep_deployed(entry: RobotEntry, target: Path) -> Path | None:
    """Move the deployed bundle out of the way when it is the folder a new model would be
    saved into (a fleet run whose ``--out`` holds the bundle the robot runs): it becomes
    ``model.vN`` (the next free N) and is returned. Anything else at ``target`` is this
    run's own earlier output and is replaced, as before.
    """
    if entry.deployed is None or not target.exists() or not os.path.isdir(entry.deployed):
        return None
    if not os.path.samefile(entry.deployed, target):
        return None
    n = 1
    while (target.parent / f"{target.name}.v{n}").exists():
        n += 1
    kept = target.parent / f"{target.name}.v{n}"
    os.rename(target, kept)
    return kept


def _evaluate(
    model: Any, entry: RobotEntry, settings: FleetSettings, folder: Path
) -> dict[str, Any]:
    from timedexec.effects import parse_effects
    from timedexec.evaluation import evaluate

    effects = None if entry.sim is None else parse_effects(entry.sim.effects, entry.robot)
    result = evaluate(
        entry.robot,
        model,
        n_configs=settings.eval_configs,
        seed=settings.eval_seed,
        draws=settings.eval_draws,
        effects=effects,
        progress=False,
    )
    info = result.to_dict()
    info.pop("elapsed_s", None)  # a wall time: the file holds only what the data decide
    write_atomic(folder / "evaluation.json", json.dumps(info, indent=2) + "\n")
    return _evaluation_summary(info)


def _drift(
    table: Any, entry: RobotEntry, settings: FleetSettings, folder: Path
) -> dict[str, Any] | None:
    if entry.deployed is None:
        with contextlib.suppress(OSError):
            (folder / "drift.json").unlink()
        return None
    from timedexec.learning import DelayModel

    deployed = DelayModel.load(entry.deployed, robot=entry.robot)
    drift = drift_check(deployed, table, drift_ms=settings.drift_ms, alpha=settings.drift_alpha)
    drift = {"deployed": entry.deployed_label, **drift}
    write_atomic(folder / "drift.json", json.dumps(drift, indent=2) + "\n")
    return drift
