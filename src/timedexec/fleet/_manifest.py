"""The fleet manifest: one line per robot (name, robot model, where its sweep comes from).

A manifest is a CSV file with a header line::

    name,robot,source,deployed
    cell-01,ur10,recordings/cell-01.h5,models/cell-01
    cell-02,kr5,s3://plant-a/sweeps/cell-02.h5,kr5-sim
    sim-03,ur10,sim://ur10?trials=2000&seed=3,ur10-sim

``name`` names the robot's folder in the output (letters, digits, ``.``, ``_``, ``-``);
``robot`` is the robot model (``ur10``, ``ur10e``, ``kr5``); ``source`` is a recording
(a path, relative to the manifest's folder, or an fsspec URL such as ``s3://...``) or
``sim://ROBOT?trials=N[&seed=S][&repeats=R][&effects=E]`` (a sweep the batch simulator
records on the cluster); ``deployed`` (optional) is the model bundle the robot runs today
(a folder, relative to the manifest's folder, or a shipped model's name): the drift check
compares it with the new measurements. Blank lines and lines starting with ``#`` are
skipped; a field may be quoted (CSV).

Everything is checked when the manifest is read, so that a typo stops the run before any
work and names the line.
"""

from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from timedexec.drivers import SCHEMES, RobotURL
from timedexec.errors import ConfigError, RecordingError
from timedexec.robots import ROBOT_NAMES

__all__ = ["MANIFEST_COLUMNS", "FleetManifest", "RobotEntry", "SimSource", "read_manifest"]

#: The manifest's columns, in order; ``deployed`` may be left out.
MANIFEST_COLUMNS = ("name", "robot", "source", "deployed")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


@dataclass(frozen=True, kw_only=True)
class SimSource:
    """A sweep the batch simulator records (``sim://ROBOT?trials=N&seed=S...``).

    Attributes
    ----------
    robot : str
        Robot model.
    trials : int
        Trials of the sweep (>= 1).
    seed : int
        Seed of the plan and the simulation (same seed, same recording).
    repeats : int
        Repeats per condition (>= 2: the noise floor needs replicates).
    effects : str
        Effect set: ``default``, ``base`` or a comma list of effect names.
    """

    robot: str
    trials: int
    seed: int = 0
    repeats: int = 10
    effects: str = "default"

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form."""
        return {
            "robot": self.robot,
            "trials": self.trials,
            "seed": self.seed,
            "repeats": self.repeats,
            "effects": self.effects,
        }


@dataclass(frozen=True, kw_only=True)
class RobotEntry:
    """One robot of the fleet, as the manifest names it (paths made absolute).

    Attributes
    ----------
    name : str
        Unique name; the robot's output folder is ``OUT/robots/NAME``.
    robot : str
        Robot model (``ur10``, ``ur10e``, ``kr5``).
    source : str
        As written in the manifest (for reports).
    recording : str or None
        Absolute path or fsspec URL of the recording; None for a simulated sweep.
    sim : SimSource or None
        The simulated sweep, for a ``sim://`` source.
    deployed : str or None
        The deployed model bundle: an absolute folder path or a shipped model's name.
    line : int
        Line of the manifest (1-based), for messages.
    """

    name: str
    robot: str
    source: str
    recording: str | None = None
    sim: SimSource | None = None
    deployed: str | None = None
    line: int = 0

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (the manifest's fields as written)."""
        return {
            "name": self.name,
            "robot": self.robot,
            "source": self.source,
            "deployed": self.deployed_label,
        }

    @property
    def deployed_label(self) -> str | None:
        """The deployed model as a report shows it: a shipped name, or the folder's name."""
        if self.deployed is None:
            return None
        return Path(self.deployed).name if os.sep in self.deployed else self.deployed


@dataclass(frozen=True)
class FleetManifest:
    """The robots of a fleet, in the manifest's order."""

    entries: tuple[RobotEntry, ...]
    path: str = "<manifest>"
    extra: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self) -> Any:
        return iter(self.entries)

    @property
    def names(self) -> tuple[str, ...]:
        """The robots' names."""
        return tuple(e.name for e in self.entries)


def parse_sim_source(url: str, robot: str, where: str = "sim source") -> SimSource:
    """Parse ``sim://ROBOT?trials=N[&seed=S][&repeats=R][&effects=E]`` (the sweep form of
    the robot URL grammar, :meth:`timedexec.drivers.RobotURL.parse`).

    Raises
    ------
    ConfigError
        Another robot than ``robot``, a missing ``trials``, an unknown or repeated key, a
        bad number or an unknown effect (the message names ``where`` and the fix).
    """
    from timedexec.effects import parse_effects

    try:
        parsed = RobotURL.parse(url, sweep=True)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if parsed.robot is not None and parsed.robot != robot:
        raise ConfigError(
            f"{where}: {url!r} simulates {parsed.robot!r} but the robot column says {robot!r}; "
            "make them agree"
        )
    options = parsed.options
    effects = options.get("effects") or "default"
    parse_effects(effects, robot)  # unknown names: ConfigError listing the vocabulary
    return SimSource(
        robot=robot,
        trials=options["trials"],
        seed=options.get("seed", 0),
        repeats=options.get("repeats", 10),
        effects=effects,
    )


def _resolve_recording(source: str, base: Path, where: str) -> str:
    """An absolute path (a local file, or a ``file://`` URL) or the fsspec URL as written."""
    parts = urlsplit(source)
    scheme = parts.scheme.lower()
    if scheme in SCHEMES:  # a live robot (sim:// sources never come here)
        raise ConfigError(
            f"{where}: {source!r} is a live robot; the fleet does not calibrate live robots "
            "(a cluster worker is not on the robot's network): record the sweep at the cell "
            f"with `timedexec calibrate --robot-url {source} ... --out NAME.h5` and list the "
            "recording here"
        )
    if scheme == "file":
        return os.path.abspath(parts.path)
    if len(scheme) > 1:  # s3://, gs://, http(s):// ... (one letter: a Windows drive)
        return source
    return os.path.abspath(base / source)


def _resolve_deployed(value: str, base: Path) -> str:
    """A folder relative to the manifest's folder if it exists there, else the value as
    written (a shipped model's name, or a path the loader will report)."""
    candidate = base / value
    if candidate.exists() or os.sep in value or value.startswith("."):
        return os.path.abspath(candidate)
    return value


def parse_manifest(
    text: str, *, base: str | os.PathLike[str] = ".", source: str = "<manifest>"
) -> FleetManifest:
    """Parse a manifest's text (see the module's docstring).

    Parameters
    ----------
    text : str
        The CSV text, header first.
    base : path
        Folder that relative paths in the manifest are relative to.
    source : str
        The manifest's name, for messages.

    Raises
    ------
    ConfigError
        A missing or unknown column, an empty or duplicate name, an unknown robot, a bad
        source; the message names the line.
    """
    base_path = Path(base)
    lines = [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise ConfigError(
            f"{source}: the manifest is empty; write a header line "
            f"`{','.join(MANIFEST_COLUMNS)}` and one line per robot"
        )
    rows = list(csv.reader(io.StringIO("\n".join(line for _, line in lines))))
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in MANIFEST_COLUMNS[:3] if c not in header]
    unknown = [c for c in header if c not in MANIFEST_COLUMNS]
    if missing or unknown or len(set(header)) != len(header):
        raise ConfigError(
            f"{source} line {lines[0][0]}: the header must name the columns "
            f"{', '.join(MANIFEST_COLUMNS[:3])} (and optionally deployed), each once; got "
            f"{', '.join(header) or 'nothing'}"
        )
    entries: list[RobotEntry] = []
    seen: dict[str, int] = {}
    for (number, _), row in zip(lines[1:], rows[1:], strict=True):
        where = f"{source} line {number}"
        if len(row) != len(header):
            raise ConfigError(f"{where}: {len(row)} fields, the header has {len(header)}")
        rec = {k: v.strip() for k, v in zip(header, row, strict=True)}
        name = rec["name"]
        if not _NAME.match(name):
            raise ConfigError(
                f"{where}: name {name!r} must be 1-64 letters, digits, '.', '_' or '-' "
                "(it names the robot's output folder), starting with a letter or digit"
            )
        if name in seen:
            raise ConfigError(
                f"{where}: name {name!r} is also on line {seen[name]}; names must be unique"
            )
        seen[name] = number
        robot = rec["robot"].lower()
        if robot not in ROBOT_NAMES:
            raise ConfigError(
                f"{where}: unknown robot {rec['robot']!r}; choose one of {', '.join(ROBOT_NAMES)}"
            )
        src = rec["source"]
        if not src:
            raise ConfigError(
                f"{where}: the source is empty; give a recording or sim://{robot}?trials=N"
            )
        deployed_text = rec.get("deployed", "")
        deployed = _resolve_deployed(deployed_text, base_path) if deployed_text else None
        if urlsplit(src).scheme.lower() == "sim":
            sim = parse_sim_source(src, robot, where)
            entries.append(
                RobotEntry(
                    name=name, robot=robot, source=src, sim=sim, deployed=deployed, line=number
                )
            )
        else:
            recording = _resolve_recording(src, base_path, where)
            entries.append(
                RobotEntry(
                    name=name, robot=robot, source=src, recording=recording,
                    deployed=deployed, line=number,
                )
            )  # fmt: skip
    if not entries:
        raise ConfigError(f"{source}: the manifest names no robot; add one line per robot")
    return FleetManifest(tuple(entries), path=source)


def read_manifest(path: str | os.PathLike[str]) -> FleetManifest:
    """Read a manifest file; relative paths in it are relative to its folder.

    Raises
    ------
    RecordingError
        The file cannot be read.
    ConfigError
        Its content is wrong (see :func:`parse_manifest`).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise RecordingError(f"manifest {p} does not exist; check the path") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"cannot read manifest {p}: {exc}") from exc
    return parse_manifest(text, base=p.parent.resolve(), source=str(p))
