"""The batch simulator as the robot of an adaptive sweep (``timedexec simulate --adaptive``).

A :class:`SimulatedRunner` has what :func:`timedexec.calibration.run_adaptive` asks of a
robot (the recording's header, fields and still recording; trials of given plan rows; the
sweep clock) and answers with :func:`~timedexec.sim.simulate_block`, so an adaptive sweep
runs at the batch simulator's speed and records what ``timedexec simulate`` records.

It is deterministic: each unit (a joint's trials at a configuration) is simulated in one
call whose random stream is keyed by its first plan row, and the sweep clock steps from one
trial to the next by the protocol's trial time plus a jitter keyed by the row. A sweep
killed between two units and resumed therefore records what an uninterrupted one records.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec.effects import EffectSet, default_effects
from timedexec.errors import ConfigError
from timedexec.recording import (
    Field,
    RecordingReader,
    RecordingWriter,
    SweepPlan,
    trial_fields,
)
from timedexec.robots import RobotSpec, get_robot
from timedexec.sim._batch import simulate_block, sweep_clock
from timedexec.sim._settings import SimSettings, default_settings
from timedexec.sim._sweep import _still_recording, sweep_header

__all__ = ["SimulatedRunner"]


class SimulatedRunner:
    """The batch simulator behind an adaptive sweep (see the module docstring).

    Parameters
    ----------
    robot : str or RobotSpec
        A name in :data:`~timedexec.robots.ROBOT_NAMES` (or its spec).
    seed : int
        Same seed, same recording.
    effects, settings : optional
        Default: the robot's default effects and settings.
    warm : bool
        Start warm (powered on :data:`~timedexec.sim.WARM_START_S` before the sweep).
    """

    def __init__(
        self,
        robot: str | RobotSpec,
        *,
        seed: int = 0,
        effects: EffectSet | None = None,
        settings: SimSettings | None = None,
        warm: bool = False,
    ) -> None:
        self.spec = robot if isinstance(robot, RobotSpec) else get_robot(robot)
        self.robot = self.spec.name
        self.settings = settings or default_settings(self.spec)
        self.effects = effects if effects is not None else default_effects(self.spec.name)
        self.seed = int(seed)
        self.warm = bool(warm)
        protocol = self.settings.protocol
        prof = protocol.profile
        self.trial_s = prof.pre_s + prof.record_s + protocol.trial_gap_s
        self.move_s = protocol.config_move_s
        self._clock: Any = None
        self._next_t0 = 0.0
        self._last_config = -1

    def _sweep_clock(self, plan: SweepPlan) -> Any:
        if self._clock is None:
            self._clock = sweep_clock(plan, self.settings, self.seed, warm=self.warm)
        return self._clock

    def header(self) -> dict[str, Any]:
        """The header ``timedexec simulate`` writes (without the plan)."""
        if self._clock is None:
            raise ConfigError("SimulatedRunner: call prepare() first")
        return sweep_header(self.spec, self.settings, self.effects, self.seed, self._clock)

    def fields(self) -> list[Field]:
        """The fields of a simulated recording (ground truth included)."""
        return trial_fields(self.settings.protocol)

    def prepare(self, out: Path, plan: SweepPlan, first_row: int, resume: bool) -> None:
        """The sweep clock: after the still recording, or after the last recorded trial."""
        self._sweep_clock(plan)
        protocol = self.settings.protocol
        self._next_t0 = protocol.still_s + protocol.profile.pre_s
        self._last_config = -1
        if resume:
            with RecordingReader(out) as r:
                if r.n_trials:
                    t0 = r.read("t0_s")
                    last = int(np.argmax(t0))
                    row = int(r.read("trial", np.array([last]))[0])
                    self._last_config = int(plan.config_index[row])
                    self._next_t0 = float(t0[last]) + self.trial_s

    def begin(self, writer: RecordingWriter, plan: SweepPlan) -> None:
        """The still recording that opens the sweep."""
        if not writer.has_static("still_gyro_raw"):
            for name, arr in _still_recording(self.settings, self._sweep_clock(plan), self.seed).items():
                writer.write_static(name, arr)

    def now_s(self) -> float:
        """The sweep clock: when the next trial would start, s."""
        return self._next_t0 - self.settings.protocol.profile.pre_s

    def run(
        self, plan: SweepPlan, rows: NDArray[np.int64], until_s: float
    ) -> Iterator[dict[str, Any]]:
        """Simulate the rows (one unit) in one call; nothing if its last trial would end
        after ``until_s``."""
        rows = np.asarray(rows, dtype=np.int64)
        protocol = self.settings.protocol
        t0 = np.empty(len(rows))
        t = self._next_t0
        config = self._last_config
        for k, i in enumerate(rows.tolist()):
            if int(plan.config_index[i]) != config:
                t += protocol.config_move_s if config >= 0 else 0.0
                config = int(plan.config_index[i])
            t += float(np.random.default_rng([self.seed, 0x71, i]).uniform(0.0, protocol.controller_period_s))
            t0[k] = t
            t += self.trial_s
        if t0[-1] - protocol.profile.pre_s + self.trial_s > until_s:
            return
        times = np.full(len(plan), np.nan)
        times[rows] = t0
        clock = dataclasses.replace(self._sweep_clock(plan), t0_s=times)
        batch = simulate_block(self.spec, self.settings, self.effects, plan, clock, rows, self.seed)
        self._next_t0 = t
        self._last_config = config
        yield batch

    def finish(self) -> None:
        """Nothing to stop."""
