"""Run a whole simulated calibration sweep into a recording (the ``simulate`` command)."""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec._progress import Progress
from timedexec.delays import DelayTable
from timedexec.effects import EffectSet, default_effects
from timedexec.errors import ConfigError, RecordingError
from timedexec.recording import RecordingReader, RecordingWriter, SweepPlan, trial_fields
from timedexec.robots import RobotSpec, get_robot
from timedexec.sim._batch import (
    SweepClock,
    iter_blocks,
    simulate_block,
    sweep_clock,
)
from timedexec.sim._settings import SimSettings, default_settings

__all__ = [
    "SweepResult",
    "simulate_delays",
    "simulate_sweep",
    "truth_table",
]


def _still_recording(
    settings: SimSettings, clock: SweepClock, seed: int
) -> dict[str, NDArray[Any]]:
    """The stationary gyro recording that opens the sweep (PSD, zero-rate)."""
    gyro = settings.gyro
    rng = np.random.default_rng([seed, 2])
    f = gyro.true_rate_hz
    n = int(settings.protocol.still_s * gyro.nominal_rate_hz)
    n -= n % gyro.block_samples
    first = math.ceil(-clock.gyro_offset_s * f)
    t = clock.gyro_offset_s + (first + np.arange(n)) / f
    sigma = gyro.noise_density_dps_rthz * math.sqrt(f / 2.0) * gyro.lsb_per_dps
    bias = clock.gyro_bias_dps + clock.gyro_bias_drift_dps_per_s * t[:, None]
    counts = bias * gyro.lsb_per_dps + rng.standard_normal((n, 3)) * sigma
    raw = np.clip(np.rint(counts), -32768, 32767).astype(np.int16)
    counter = ((clock.gyro_counter0 + first + np.arange(n)) % 65536).astype(np.uint16)
    last = t[gyro.block_samples - 1 :: gyro.block_samples]
    blocks = np.maximum.accumulate(
        last + gyro.usb_latency_s + rng.exponential(gyro.usb_jitter_s, last.shape)
    )
    return {
        "still_gyro_raw": raw,
        "still_gyro_counter": counter,
        "still_gyro_block_host_time_s": blocks,
    }


@dataclass(frozen=True)
class SweepResult:
    """What :func:`simulate_sweep` produced."""

    path: Path
    n_trials: int
    n_simulated: int
    bytes: int
    truth_path: Path | None

    def summary(self) -> dict[str, Any]:
        """JSON-safe summary."""
        return {
            "recording": str(self.path),
            "trials": self.n_trials,
            "simulated_now": self.n_simulated,
            "recording_bytes": self.bytes,
            "truth": str(self.truth_path) if self.truth_path else None,
        }


def simulate_sweep(
    robot: str | RobotSpec,
    n_trials: int,
    out: str | os.PathLike[str],
    *,
    seed: int = 0,
    effects: EffectSet | None = None,
    settings: SimSettings | None = None,
    plan: SweepPlan | None = None,
    truth_path: str | os.PathLike[str] | None = None,
    resume: bool = False,
    jobs: int = 1,
    progress: bool = True,
    joints: Sequence[int] = (1, 2, 3, 5),
    repeats: int = 10,
    warm: bool = False,
) -> SweepResult:
    """Simulate a calibration sweep in virtual time and record it.

    Parameters
    ----------
    robot : str or RobotSpec
        A name in :data:`~timedexec.robots.ROBOT_NAMES` (or its spec).
    n_trials : int
        Trials (1 .. 10,000,000); ignored when ``plan`` is given.
    out : path
        The recording (HDF5). Refused if it exists, unless ``resume``.
    seed : int
        Same seed, same recording.
    effects, settings, plan : optional
        Default: the robot's default effects and settings, a plan drawn from ``seed``.
    truth_path : path, optional
        Where to write the ground-truth delay table (CSV; true delays in the delay columns).
    resume : bool
        Continue an interrupted run of the same command.
    jobs : int
        Worker processes (joblib); the output does not depend on it.
    progress : bool
        Progress with ETA on stderr.
    joints, repeats
        Of the plan drawn from ``seed``.
    warm : bool
        Start warm: the robot was powered on :data:`~timedexec.sim.WARM_START_S` before the
        sweep (a robot taken out of production); default cold, powered on as the sweep
        clock starts. The header's ``power_on_s`` says which (the sweep time of power-on).
    """
    spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
    settings = settings or default_settings(spec)
    effects = effects if effects is not None else default_effects(spec.name)
    if plan is None:
        plan = SweepPlan.generate(spec, n_trials, seed=seed, joints=joints, repeats=repeats)
    if isinstance(jobs, bool) or not isinstance(jobs, int) or (jobs < 1 and jobs != -1):
        raise ConfigError(f"jobs={jobs!r} must be a positive integer, or -1 for every worker")
    out = Path(out)
    if truth_path is not None:
        tp = Path(truth_path)
        if not (tp.parent if str(tp.parent) else Path(".")).is_dir():
            raise RecordingError(f"cannot write {tp}: directory {tp.parent} does not exist")
    clock = sweep_clock(plan, settings, seed, warm=bool(warm))
    header = sweep_header(spec, settings, effects, seed, clock, plan=plan)
    fields = trial_fields(settings.protocol)
    with RecordingWriter(out, header=header, fields=fields, resume=resume) as writer:
        if resume:
            old = writer.header
            if (
                old.get("seed") != seed
                or old.get("plan") != plan.meta()
                or old.get("power_on_s", 0.0) != clock.power_on_s
            ):
                raise RecordingError(
                    f"{out} was recorded with another plan, seed or thermal start "
                    f"({old.get('plan')}, seed {old.get('seed')}, power-on at "
                    f"{old.get('power_on_s', 0.0)} s); resume with the same arguments"
                )
        for name, arr in plan.to_arrays().items():
            if not writer.has_static(name):
                writer.write_static(name, arr)
        if not writer.has_static("still_gyro_raw"):
            for name, arr in _still_recording(settings, clock, seed).items():
                writer.write_static(name, arr)
        done = writer.completed_trials
        todo = len(plan) - len(done)
        bar = Progress(todo, f"simulate {spec.name}", enabled=progress)
        blocks = list(iter_blocks(len(plan), done))
        done_mask = np.zeros(len(plan), dtype=bool)
        done_mask[done] = True

        def run(rows: NDArray[np.int64]) -> dict[str, NDArray[Any]]:
            return simulate_block(spec, settings, effects, plan, clock, rows, seed)

        if jobs == 1:
            results = (run(rows) for rows in blocks)
        else:
            from joblib import Parallel, delayed

            results = Parallel(n_jobs=jobs, return_as="generator")(
                delayed(simulate_block)(spec, settings, effects, plan, clock, rows, seed)
                for rows in blocks
            )
        n_new = 0
        try:
            for batch in results:
                keep = ~done_mask[batch["trial"]]
                if not keep.all():
                    batch = {k: v[keep] for k, v in batch.items()}
                writer.append(batch)
                n_new += len(batch["trial"])
                bar.update(len(batch["trial"]))
        finally:
            bar.close()
            _stop_workers(results)
    written_truth = None
    if truth_path is not None:
        with RecordingReader(out) as reader:
            written_truth = truth_table(reader).to_csv(truth_path)
    return SweepResult(out, len(plan), n_new, out.stat().st_size, written_truth)


def _stop_workers(results: Any) -> None:
    """Close the block generator: when the sweep stops early (a full disk, Ctrl-C), the
    worker processes are told to stop now, and joblib's warning that blocks computed
    ahead went unused (expected then) does not follow the error message."""
    close = getattr(results, "close", None)
    if close is None:
        return
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*tasks have been successfully executed")
        close()


def sweep_header(
    spec: RobotSpec,
    settings: SimSettings,
    effects: EffectSet,
    seed: int,
    clock: SweepClock,
    *,
    plan: SweepPlan | None = None,
) -> dict[str, Any]:
    """The header of a simulated recording (the plan's summary when given; an adaptive
    sweep adds its own): what ``timedexec simulate`` and the adaptive sweep's
    :class:`~timedexec.sim.SimulatedRunner` write."""
    header: dict[str, Any] = {
        "source": "simulator",
        "robot": spec.to_dict(),
        "settings": settings.to_dict(),
        "effects": effects.to_dict(),
    }
    if plan is not None:
        header["plan"] = plan.meta()
    header.update({
        "seed": seed,
        "profile": settings.protocol.profile.to_dict(),
        "controller_period_s": settings.protocol.controller_period_s,
        "gyro": settings.protocol.gyro.to_dict(),
        "sim_truth": {**clock.to_dict(), "gyro_true_rate_hz": settings.gyro.true_rate_hz},
        "time_origin": "trial time 0 = host arrival of the trigger state package",
        "power_on_s": clock.power_on_s,
    })  # fmt: skip
    return header


def truth_table(reader: RecordingReader) -> DelayTable:
    """The ground-truth delay table of a simulated recording (true delays in the delay
    columns and again in ``true_*``, and ``t_since_power_on`` where the header gives the
    robot's power-on), sorted by trial."""
    if "true_actuation_delay_s" not in reader.fields:
        raise RecordingError("this recording holds no ground truth (it was not simulated)")
    trial = reader.read("trial")
    order = np.argsort(trial)
    trial = trial[order]
    q = reader.static("plan_q_start_rad")[trial]
    act = reader.read("true_actuation_delay_s")[order]
    resp = reader.read("true_response_delay_s")[order]
    cols: dict[str, Any] = {
        "trial": trial,
        "robot": str(reader.header["robot"]["name"]),
        "joint": reader.static("plan_joint")[trial],
        "direction": reader.static("plan_direction")[trial],
        **{f"q{i + 1}": q[:, i] for i in range(6)},
        "t_start": reader.read("t0_s")[order],
        "actuation_delay": act,
        "response_delay": resp,
        "true_actuation_delay": act,
        "true_response_delay": resp,
    }
    power_on = reader.header.get("power_on_s")
    if power_on is not None:
        cols["t_since_power_on"] = cols["t_start"] - float(power_on)
    return DelayTable(cols, source=str(reader.path) if hasattr(reader, "path") else "recording")


def simulate_delays(
    robot: str | RobotSpec,
    q_rad: Any,
    joint: Any,
    direction: Any,
    t_start_s: Any,
    *,
    effects: EffectSet | None = None,
    settings: SimSettings | None = None,
    seed: int = 0,
    jobs: int = 1,
) -> DelayTable:
    """True delays of the simulated robot for given conditions (no recording, no gyro).

    Parameters
    ----------
    robot : str or RobotSpec
    q_rad : array (n, 6)
        Start configurations, rad (inside the joint limits).
    joint, direction : array (n,)
        Actuated joint (1-based) and direction (+1/-1) per trial.
    t_start_s : array (n,)
        Sweep time of each trial, s (for ``thermal_drift``).
    effects, settings : optional
        Default: the robot's defaults.
    seed : int
        Seeds the timing randomness (packing phase, jitter).
    jobs : int
        Worker processes.

    Returns
    -------
    DelayTable
        True delays in ``actuation_delay``/``response_delay`` (and ``true_*``), plus the
        holding torque ``gravity_torque_nm`` and inertia ``inertia_kgm2`` of each trial.
    """
    spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
    settings = settings or default_settings(spec)
    effects = effects if effects is not None else default_effects(spec.name)
    q = np.asarray(q_rad, dtype=float)
    n = len(q)
    plan = SweepPlan(
        robot=spec.name,
        q_start_rad=q,
        joint=np.asarray(joint),
        direction=np.asarray(direction),
        config_index=np.arange(n),
        repeat=np.zeros(n, dtype=np.int64),
    )
    clock = sweep_clock(plan, settings, seed)
    clock = SweepClock(**{**clock.__dict__, "t0_s": np.asarray(t_start_s, dtype=float)})
    blocks = list(iter_blocks(n))
    if jobs == 1:
        parts = [
            simulate_block(spec, settings, effects, plan, clock, rows, seed, truth_only=True)
            for rows in blocks
        ]
    else:
        from joblib import Parallel, delayed

        parts = Parallel(n_jobs=jobs)(
            delayed(simulate_block)(
                spec, settings, effects, plan, clock, rows, seed, truth_only=True
            )
            for rows in blocks
        )
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return DelayTable(
        {
            "trial": np.arange(n),
            "robot": spec.name,
            "joint": plan.joint,
            "direction": plan.direction,
            **{f"q{i + 1}": q[:, i] for i in range(6)},
            "t_start": clock.t0_s,
            "actuation_delay": out["true_actuation_delay_s"],
            "response_delay": out["true_response_delay_s"],
            "true_actuation_delay": out["true_actuation_delay_s"],
            "true_response_delay": out["true_response_delay_s"],
            "gravity_torque_nm": out["true_gravity_torque_nm"],
            "inertia_kgm2": out["true_inertia_kgm2"],
        },
        source=f"simulated {spec.name}",
    )
