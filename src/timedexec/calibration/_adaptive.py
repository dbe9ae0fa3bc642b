"""The adaptive calibration sweep: batches chosen by the model so far, resumable.

The sweep runs *batches* of units (:mod:`timedexec.calibration._design`). The first two are
space-filling; from then on batch ``n`` is chosen by a model fitted on the batches up to
``n - 2`` while batch ``n - 1`` runs on the robot (a background thread measures the
finished batch, fits, and chooses; the robot waits only if that takes longer than a
batch). The measured delays come from extracting each finished batch on its own
(:func:`~timedexec.extraction.extract_recording` of a copy of its trials): a live run needs
no simulator and no ground truth.

**The design state is in the recording.** The candidate pool is the sweep plan (its
``plan_*`` statics, written first: a sweep runs a subset of its rows); each chosen batch
is written as the static ``adaptive_batch_NNNN`` (its plan rows in run order) with
``adaptive_note_NNNN`` (the figures of the choice, :data:`NOTE_FIELDS`) before it runs; the
header holds the settings and the workspace. ``resume`` reads them, extracts the finished
batches again and goes on where the sweep stopped: every choice is a deterministic
function of the recorded trials (seeded fits, single-threaded BLAS), so a sweep killed and
resumed makes the choices an uninterrupted one makes, and on a deterministic robot (the
batch simulator, ``timedexec simulate --adaptive``) records the same trials.

A robot is driven through a :class:`TrialRunner`: :class:`DriverRunner` for any
:class:`~timedexec.drivers.RobotDriver` (``sim://``, ``ur://``, ``rsi://``) with its gyro;
the batch simulator has its own (``timedexec.sim.SimulatedRunner``).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from timedexec._types import FloatArray
from timedexec.calibration._design import (
    AdaptiveSettings,
    BatchChoice,
    DesignModel,
    Unit,
    Workspace,
    choose_batch,
    design_pool,
    first_batches,
    held_out_scale2,
    pool_configurations,
    rows_units,
    unit_rows,
)
from timedexec.delays import DelayTable
from timedexec.errors import RecordingError
from timedexec.learning import single_threaded_blas
from timedexec.recording import Field, RecordingReader, RecordingWriter, SweepPlan

__all__ = ["NOTE_FIELDS", "AdaptiveResult", "TrialRunner", "read_design_log", "run_adaptive"]


#: The figures of each batch's choice, in the order of an ``adaptive_note_NNNN`` static:
#: the robot time of the data the choice was made on (s), its trials, the estimated RMS
#: error of a new trial in the workspace with the units chosen so far, after this batch and
#: after ``stop_horizon_s`` more (s), the noise floor (s), the RMS error on the newest
#: measured batch predicted before the model saw it (s) and its trial count, and 1 where the
#: stopping rule fired. (Wall times are not recorded: the recording of a deterministic robot
#: does not depend on how fast the machine is; :class:`AdaptiveResult` has them.)
NOTE_FIELDS = (
    "robot_time_s",
    "trials",
    "error_s",
    "error_after_s",
    "error_horizon_s",
    "floor_s",
    "held_out_rmse_s",
    "held_out_trials",
    "stop",
)
_BATCH = "adaptive_batch_"
_NOTE = "adaptive_note_"


class TrialRunner(Protocol):
    """A robot an adaptive sweep runs trials on.

    Attributes
    ----------
    robot : str
        The robot's name.
    trial_s, move_s : float
        Nominal robot time of one trial and of a move to a new configuration, s (the
        design's costs).
    """

    robot: str
    trial_s: float
    move_s: float

    def header(self) -> dict[str, Any]:
        """The recording header (the sweep adds ``plan`` and ``adaptive``)."""
        ...

    def fields(self) -> list[Field]:
        """The recording's per-trial fields."""
        ...

    def prepare(self, out: Path, plan: SweepPlan, first_row: int, resume: bool) -> None:
        """Before anything is written: connect the session (a resumed one continues the
        sweep clock), run the pre-flight with plan row ``first_row``'s motion."""
        ...

    def begin(self, writer: RecordingWriter, plan: SweepPlan) -> None:
        """The statics the sweep opens with (the still recording) if missing."""
        ...

    def now_s(self) -> float:
        """The sweep clock now, s (robot time since the sweep started)."""
        ...

    def run(
        self, plan: SweepPlan, rows: NDArray[np.int64], until_s: float
    ) -> Iterator[dict[str, Any]]:
        """Run plan rows in order, yielding trial batches to append; stop before a trial
        that would end after ``until_s`` on the sweep clock."""
        ...

    def finish(self) -> None:
        """After the last trial (stop the robot)."""
        ...


@dataclass(frozen=True)
class AdaptiveResult:
    """What :func:`run_adaptive` did.

    Attributes
    ----------
    path : Path
        The recording.
    trials : int
        Trials the recording holds.
    recorded_now : int
        Trials this run recorded.
    robot_time_s : float
        The sweep clock at the end, s.
    stopped : str
        ``"converged"`` (the stopping rule), ``"budget"``, or ``"workspace"`` (every unit
        of the pool measured).
    notes : list of dict
        Per batch: its unit and trial counts and the figures of :data:`NOTE_FIELDS`.
    """

    path: Path
    trials: int
    recorded_now: int
    robot_time_s: float
    stopped: str
    notes: list[dict[str, float]] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        return {
            "recording": str(self.path),
            "trials": self.trials,
            "recorded_now": self.recorded_now,
            "robot_time_s": self.robot_time_s,
            "stopped": self.stopped,
            "batches": self.notes,
        }


def read_design_log(reader: RecordingReader) -> list[dict[str, float]]:
    """The batches of an adaptive recording: per batch ``batch``, ``units``, ``trials_planned``
    and the figures of :data:`NOTE_FIELDS` (NaN where not computed: the first two batches
    are chosen without a model); empty for a fixed sweep."""
    out: list[dict[str, float]] = []
    k = 0
    while reader.has_static(f"{_BATCH}{k:04d}"):
        rows = reader.static(f"{_BATCH}{k:04d}")
        note = reader.static(f"{_NOTE}{k:04d}")
        entry: dict[str, float] = {"batch": k, "trials_planned": len(rows)}
        entry.update({name: float(v) for name, v in zip(NOTE_FIELDS, note, strict=True)})
        out.append(entry)
        k += 1
    return out


# ------------------------------------------------------------------------ measuring


def _measure_batch(path: Path, trials: NDArray[np.int64], work: Path) -> DelayTable | None:
    """The measured delays of the recorded trials among ``trials``: their rows copied into
    a recording of their own (same header and statics) and extracted; None if none is
    recorded. Depends only on those trials' recorded bytes."""
    from timedexec.extraction import extract_recording

    with RecordingReader(path) as r:
        recorded = r.read("trial")
        pos = np.flatnonzero(np.isin(recorded, trials))
        if not pos.size:
            return None
        data = {name: r.read(name, pos) for name in r.fields}
        statics = {
            name: r.static(name) for name in r.static_names if not name.startswith(("adaptive_",))
        }
        header, fields = r.header, list(r.fields.values())
    tmp = work / f"batch-{int(trials[0])}.h5"
    try:
        with RecordingWriter(tmp, header=header, fields=fields, fsync=False) as w:
            for name, arr in statics.items():
                w.write_static(name, arr)
            w.append(data)
        return extract_recording(tmp, progress=False).table
    finally:
        for p in work.glob(f"{tmp.name}*"):
            p.unlink(missing_ok=True)


def _concat(tables: Sequence[DelayTable]) -> DelayTable:
    names = [n for n in tables[0] if all(n in t for t in tables)]
    return DelayTable(
        {n: np.concatenate([np.asarray(t[n]) for t in tables]) for n in names},
        source="adaptive sweep",
    )


class _Designer:
    """Measures finished batches and chooses the next ones (runs in the worker thread)."""

    def __init__(
        self,
        path: Path,
        plan: SweepPlan,
        settings: AdaptiveSettings,
        trial_s: float,
        move_s: float,
        work: Path,
    ) -> None:
        self.path = path
        self.plan = plan
        self.settings = settings
        self.trial_s = trial_s
        self.move_s = move_s
        self.work = work
        self.pool_q = pool_configurations(plan)
        n_pool = len(self.pool_q)
        ref_rng = np.random.default_rng([settings.seed, 0x4EF])
        self.reference = (
            np.arange(n_pool)
            if n_pool <= settings.reference_size
            else np.sort(ref_rng.choice(n_pool, settings.reference_size, replace=False))
        )
        self.tables: dict[int, DelayTable | None] = {}
        self.models: dict[int, DesignModel] = {}
        self.held: dict[int, dict[int, tuple[FloatArray, FloatArray]]] = {}
        self.wall_s: dict[int, float] = {}  # batch -> wall time its choice took

    def table(self, k: int, batches: Sequence[Sequence[Unit]]) -> DelayTable | None:
        if k not in self.tables:
            rows = np.concatenate([unit_rows(self.plan, u) for u in batches[k]])
            self.tables[k] = _measure_batch(self.path, rows, self.work)
        return self.tables[k]

    def model(self, k: int, batches: Sequence[Sequence[Unit]]) -> DesignModel:
        """The model of batches 0..k, its variances calibrated by the held-out errors of
        the newest batches (each predicted by the model before it)."""
        if k not in self.models:
            tables = [t for i in range(k + 1) if (t := self.table(i, batches)) is not None]
            if k >= 1 and (new := self.table(k, batches)) is not None:
                self.held[k] = self.model(k - 1, batches).held_out(new)
            recent = [self.held[i] for i in sorted(self.held) if i <= k][
                -self.settings.calibration_batches :
            ]
            self.models[k] = DesignModel.fit(
                _concat(tables),
                self.settings.joints,
                seed=self.settings.seed * 1_000_003 + k,
                scale2=held_out_scale2(recent, self.settings.joints),
                calibrated_by=len(recent),
            )
        return self.models[k]

    def choose(self, n: int, batches: Sequence[Sequence[Unit]]) -> tuple[BatchChoice, FloatArray]:
        """Batch ``n`` from the model of batches 0..n-2, batch n-1 pending; and its note.
        BLAS on one thread throughout (extraction too): the same sums in the same order on
        every run, so a resumed sweep chooses what an uninterrupted one chose."""
        with single_threaded_blas():
            return self._choose(n, batches)

    def _choose(self, n: int, batches: Sequence[Sequence[Unit]]) -> tuple[BatchChoice, FloatArray]:
        start = time.perf_counter()
        model = self.model(n - 2, batches)
        done = {u for b in batches[: n - 1] for u in b}
        pending = list(batches[n - 1])
        last = pending[-1][0] if pending else batches[n - 2][-1][0]
        recent = [self.held[i] for i in sorted(self.held) if i <= n - 2][
            -self.settings.calibration_batches :
        ]
        pooled = [r for h in recent for r, _ in h.values()]
        pooled_rmse = float(np.sqrt(np.mean(np.concatenate(pooled) ** 2))) if pooled else math.nan
        choice = choose_batch(
            model,
            self.pool_q,
            done=done,
            pending=pending,
            settings=self.settings,
            trial_s=self.trial_s,
            move_s=self.move_s,
            rng=np.random.default_rng([self.settings.seed, 0xC4, n]),
            reference=self.reference,
            start_q=self.pool_q[last],
            held_out_rmse_s=pooled_rmse,
        )
        data = [t for i in range(n - 1) if (t := self.tables.get(i)) is not None]
        t_end = max(float(np.max(t["t_start"])) for t in data) + self.trial_s
        held = self.held.get(n - 2, {})
        resid = np.concatenate([r for r, _ in held.values()]) if held else np.zeros(0)
        note = {
            "robot_time_s": t_end,
            "trials": float(model.trials),
            "error_s": choice.error_s,
            "error_after_s": choice.error_after_s,
            "error_horizon_s": choice.error_horizon_s,
            "floor_s": choice.floor_s,
            "held_out_rmse_s": float(np.sqrt(np.mean(resid**2))) if resid.size else math.nan,
            "held_out_trials": float(resid.size),
            "stop": float(choice.stop),
        }
        self.wall_s[n] = time.perf_counter() - start
        return choice, np.array([note[k] for k in NOTE_FIELDS], dtype=float)


# ----------------------------------------------------------------------------- state


@dataclass
class _State:
    batches: list[list[Unit]]
    notes: list[FloatArray]
    stop: bool


def _read_state(out: Path, plan: SweepPlan) -> _State:
    with RecordingReader(out) as r:
        log = []
        k = 0
        while r.has_static(f"{_BATCH}{k:04d}"):
            log.append((r.static(f"{_BATCH}{k:04d}"), r.static(f"{_NOTE}{k:04d}")))
            k += 1
    batches = [rows_units(plan, rows) for rows, _ in log]
    notes = [np.asarray(note, dtype=float) for _, note in log]
    # 1 where the stopping rule fired; NaN for the first two batches (chosen without a model)
    stop = bool(notes) and notes[-1][NOTE_FIELDS.index("stop")] == 1.0
    if stop:
        batches.pop()  # the stop is a note without units
    return _State(batches, notes, stop)


def _check_resumable(out: Path, header: dict[str, Any], resume: bool) -> bool:
    """Whether ``out`` exists (and may be continued: the same plan and settings)."""
    if not out.exists():
        return False
    if not resume:
        raise RecordingError(
            f"recording {out} already exists; refusing to overwrite it. To continue an "
            "interrupted sweep use --resume (resume=True); to start over delete it"
        )
    with RecordingReader(out) as r:
        old = r.header
    for key in ("plan", "adaptive"):
        if old.get(key) != header[key]:
            raise RecordingError(
                f"{out} was recorded with other adaptive settings ({key}: {old.get(key)}); "
                "resume with the same --budget-min, --workspace, --seed and adaptive options"
            )
    return True


def _progress(robot: str, k: int, units: int, rows: int, note: FloatArray) -> str:
    n = dict(zip(NOTE_FIELDS, note.tolist(), strict=True))
    if n["stop"]:
        return (
            f"adaptive {robot}: converged at {n['robot_time_s'] / 60:.1f} min of robot time "
            f"({int(n['trials'])} trials): estimated error {1e3 * n['error_s']:.2f} ms, "
            f"{1e3 * n['error_horizon_s']:.2f} ms with 10 more minutes (floor "
            f"{1e3 * n['floor_s']:.2f} ms), on the newest measured batch "
            f"{1e3 * n['held_out_rmse_s']:.2f} ms"
        )
    held = (
        f"; on the newest measured batch {1e3 * n['held_out_rmse_s']:.2f} ms"
        if math.isfinite(n["held_out_rmse_s"])
        else ""
    )
    return (
        f"adaptive {robot}: batch {k}, {units} units ({rows} trials) chosen at "
        f"{n['robot_time_s'] / 60:.1f} min of robot time from {int(n['trials'])} trials; "
        f"estimated error {1e3 * n['error_s']:.2f} ms -> {1e3 * n['error_after_s']:.2f} ms "
        f"after it, {1e3 * n['error_horizon_s']:.2f} ms with 10 more minutes (floor "
        f"{1e3 * n['floor_s']:.2f} ms){held}"
    )


def run_adaptive(
    runner: TrialRunner,
    out: str | os.PathLike[str],
    *,
    settings: AdaptiveSettings | None = None,
    workspace: Workspace | None = None,
    resume: bool = False,
    progress: bool = True,
) -> AdaptiveResult:
    """Run (or resume) an adaptive calibration sweep and record it.

    Parameters
    ----------
    runner : TrialRunner
        The robot (:class:`DriverRunner` for a driver and gyro).
    out : path
        Recording to write; refused if it exists unless ``resume``.
    settings : AdaptiveSettings, optional
        Budget, batches, stopping rule, seed (defaults: 45 min, 3-min batches).
    workspace : Workspace, optional
        Where the robot works (default: the calibration ranges).
    resume : bool
        Continue a sweep of the same settings.
    progress : bool
        One line per batch on stderr.

    Returns
    -------
    AdaptiveResult

    Raises
    ------
    RecordingError
        ``out`` exists (without ``resume``) or holds another sweep; the disk is full.
    ConfigError
        Invalid settings or workspace.
    """
    settings = settings or AdaptiveSettings()
    workspace = workspace or Workspace()
    out = Path(out)
    plan = design_pool(runner.robot, workspace, settings)
    design = {
        "plan": plan.meta(),
        "adaptive": {
            "settings": settings.to_dict(),
            "workspace": workspace.to_dict(),
            "note_fields": list(NOTE_FIELDS),
            "trial_s": runner.trial_s,
            "move_s": runner.move_s,
        },
    }
    existed = _check_resumable(out, design, resume)
    state = _read_state(out, plan) if existed else _State([], [], False)
    if not state.batches:
        state.batches = first_batches(plan, settings, runner.trial_s, runner.move_s)
    done_rows: set[int] = set()
    if existed:
        with RecordingReader(out) as r:
            done_rows = {int(t) for t in r.read("trial").tolist()} if r.n_trials else set()
    todo = [i for b in state.batches for u in b for i in _left(plan, u, done_rows)]
    runner.prepare(out, plan, todo[0] if todo else min(done_rows, default=0), existed)
    header = {**runner.header(), **design}
    n_before = len(done_rows)
    stopped = "converged" if state.stop else ""
    waits: dict[int, float] = {}
    work = Path(tempfile.mkdtemp(prefix="timedexec-adaptive-"))
    worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="adaptive-design")
    futures: dict[int, Future[tuple[BatchChoice, FloatArray]]] = {}
    designer = _Designer(out, plan, settings, runner.trial_s, runner.move_s, work)
    # BLAS on one thread for the whole sweep, entered here, in the robot's thread: the
    # designer's fits enter the same pin in their thread, and a thread count changed while
    # another thread runs BLAS corrupts OpenBLAS's buffers (a sweep died with "malloc():
    # invalid size" when the worker pinned and unpinned around each fit).
    pin = contextlib.ExitStack()
    pin.enter_context(single_threaded_blas())
    try:
        with RecordingWriter(out, header=header, fields=runner.fields(), resume=existed) as w:
            for name, arr in plan.to_arrays().items():
                if not w.has_static(name):
                    w.write_static(name, arr)
            runner.begin(w, plan)
            for k, units in enumerate(state.batches):
                if not w.has_static(f"{_BATCH}{k:04d}"):  # the first two, chosen without a model
                    _write_batch(w, plan, k, units, np.full(len(NOTE_FIELDS), math.nan))
            batches = state.batches
            k = 0
            while not stopped:
                if k >= len(batches):
                    if _pool_exhausted(plan, batches):
                        stopped = "workspace"
                        break
                    if runner.now_s() + runner.trial_s > settings.budget_s:
                        stopped = "budget"  # (a resumed sweep that had used its budget)
                        break
                    f = futures.pop(k, None) or worker.submit(designer.choose, k, list(batches))
                    wait = time.perf_counter()
                    choice, note = f.result()
                    waits[k] = time.perf_counter() - wait
                    _write_batch(w, plan, k, choice.units, note)
                    if progress:
                        rows = len(choice.units) * 2 * plan.repeats
                        print(_progress(runner.robot, k, len(choice.units), rows, note),
                              file=sys.stderr, flush=True)  # fmt: skip
                    if choice.stop:
                        stopped = "workspace" if _pool_exhausted(plan, batches) else "converged"
                        break
                    batches.append(choice.units)
                # While batch k runs, batch k+1 is chosen from the batches before k.
                if k + 1 >= max(len(batches), 2) and k + 1 not in futures:
                    futures[k + 1] = worker.submit(designer.choose, k + 1, list(batches))
                if not _run_units(runner, w, plan, batches[k], settings.budget_s, done_rows):
                    stopped = "budget"
                k += 1
            runner.finish()
            n_total = w.n_trials
    finally:
        worker.shutdown(wait=True, cancel_futures=True)  # no fit outlives the pin
        pin.close()
        shutil.rmtree(work, ignore_errors=True)
    with RecordingReader(out) as r:
        notes = read_design_log(r)
        t_end = float(r.read("t0_s").max()) + runner.trial_s if r.n_trials else 0.0
    for entry in notes:
        b = int(entry["batch"])
        entry["design_wall_s"] = designer.wall_s.get(b, math.nan)
        entry["wait_wall_s"] = waits.get(b, math.nan)
    return AdaptiveResult(out, n_total, n_total - n_before, t_end, stopped, notes)


def _left(plan: SweepPlan, unit: Unit, done_rows: set[int]) -> list[int]:
    """The unit's rows not yet recorded."""
    return [i for i in unit_rows(plan, unit).tolist() if i not in done_rows]


def _pool_exhausted(plan: SweepPlan, batches: Sequence[Sequence[Unit]]) -> bool:
    n_units = (int(plan.config_index.max()) + 1) * len(plan.joints)
    return sum(len(b) for b in batches) >= n_units


def _write_batch(
    w: RecordingWriter, plan: SweepPlan, k: int, units: Sequence[Unit], note: FloatArray
) -> None:
    rows = np.concatenate([unit_rows(plan, u) for u in units]) if units else np.zeros(0, np.int64)
    w.write_static(f"{_BATCH}{k:04d}", rows, doc=f"plan rows of adaptive batch {k}, in run order")
    w.write_static(
        f"{_NOTE}{k:04d}",
        np.asarray(note, dtype=float),
        doc="the choice's figures: " + ", ".join(NOTE_FIELDS),
    )


def _run_units(
    runner: TrialRunner,
    w: RecordingWriter,
    plan: SweepPlan,
    units: Sequence[Unit],
    budget_s: float,
    done_rows: set[int],
) -> bool:
    """Run the units' rows not yet recorded, unit by unit; False when the budget ended
    the sweep."""
    for u in units:
        rows = np.asarray(_left(plan, u, done_rows), dtype=np.int64)
        if not rows.size:
            continue
        got = 0
        for batch in runner.run(plan, rows, budget_s):
            w.append(batch)
            trials = np.asarray(batch["trial"]).tolist()
            done_rows.update(int(t) for t in trials)
            got += len(trials)
        if got < len(rows):
            return False
    return True
