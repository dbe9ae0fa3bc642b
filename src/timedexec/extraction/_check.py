"""The recording contract as extraction reads it: required fields, header keys, units.

``docs/recording-format.md`` ("What extraction needs") is the human-readable form of the
tables here; :func:`check_recording` lists every way a file departs from it and
:func:`read_contract` (used by the extraction) raises on the first one.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from timedexec.errors import ConfigError, RecordingError, TimedExecError
from timedexec.recording import DamagedChunkError, RecordingReader, damage_note

__all__ = [
    "OPTIONAL_FIELDS",
    "REQUIRED_FIELDS",
    "REQUIRED_HEADER",
    "REQUIRED_STATICS",
    "UNITS",
    "Contract",
    "check_recording",
    "read_contract",
]

#: Per-trial fields extraction reads: name -> (unit kind, rank of one trial's value).
REQUIRED_FIELDS: dict[str, tuple[str, int]] = {
    "trial": ("none", 0),
    "t0_s": ("time", 0),
    "cmd_send_time_s": ("time", 0),
    "cmd_qd_rad_s": ("speed", 1),
    "state_host_time_s": ("time", 1),
    "state_q_rad": ("angle", 2),
    "state_qd_rad_s": ("speed", 2),
    "gyro_raw": ("rate", 2),
    "gyro_counter": ("none", 1),
    "gyro_block_host_time_s": ("time", 1),
}
#: Per-trial fields extraction reads where a recording has them (checked like the others).
OPTIONAL_FIELDS: dict[str, tuple[str, int]] = {
    "state_controller_time_s": ("time", 1),
}
#: Static arrays extraction reads.
REQUIRED_STATICS = (
    "plan_q_start_rad",
    "plan_joint",
    "plan_direction",
    "still_gyro_raw",
    "still_gyro_counter",
    "still_gyro_block_host_time_s",
)
#: Header keys extraction reads (dotted paths).
REQUIRED_HEADER = (
    "robot.name",
    "controller_period_s",
    "profile.speed_rad_s",
    "profile.acceleration_rad_s2",
    "profile.hold_s",
    "profile.pause_s",
    "gyro.nominal_rate_hz",
    "gyro.block_samples",
    "gyro.group_delay_s",
    "gyro.transport_latency_s",
)

#: Header keys that may be 0 (the rest must be positive).
_NON_NEGATIVE = (
    "profile.hold_s",
    "profile.pause_s",
    "gyro.group_delay_s",
    "gyro.transport_latency_s",
)

#: Accepted unit spellings -> factor to SI, per kind.
UNITS: dict[str, dict[str, float]] = {
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9},
    "angle": {"rad": 1.0, "deg": math.pi / 180, "°": math.pi / 180},
    "speed": {"rad/s": 1.0, "deg/s": math.pi / 180, "°/s": math.pi / 180, "dps": math.pi / 180},
    # gyro rates: counts need the header's sensitivity (filled in by read_contract)
    "rate": {
        "rad/s": 1.0,
        "deg/s": math.pi / 180,
        "°/s": math.pi / 180,
        "dps": math.pi / 180,
        "LSB": math.nan,
        "lsb": math.nan,
        "counts": math.nan,
        "": math.nan,
    },
    "none": {"": 1.0, "1": 1.0, "count": 1.0, "counts": 1.0},
}


@dataclass(frozen=True)
class Contract:
    """What extraction takes from a recording's header and field attributes.

    ``scale`` maps each required field to the factor that turns its stored values into SI
    (gyro rates into rad/s); ``latency_s`` is transport latency + filter group delay.
    """

    robot: str
    vendor: str
    period_s: float
    profile: dict[str, float]
    fs_hz: float
    block: int
    group_delay_s: float
    transport_latency_s: float
    scale: dict[str, float]

    @property
    def latency_s(self) -> float:
        """Constant subtracted from the fitted sample arrival times, s."""
        return self.group_delay_s + self.transport_latency_s


def _get(header: dict[str, Any], dotted: str) -> Any:
    node: Any = header
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def _problems(reader: RecordingReader) -> tuple[list[str], Contract | None]:
    """Every departure from the contract, and the contract if there is none."""
    problems: list[str] = []
    header = reader.header
    values: dict[str, Any] = {}
    for key in REQUIRED_HEADER:
        try:
            values[key] = _get(header, key)
        except KeyError:
            hint = ""
            if key in ("gyro.group_delay_s", "gyro.transport_latency_s"):
                hint = (" (a sensor constant: measure it, docs/sensor-constants.md, and give it "
                        "to `timedexec calibrate`; it is never assumed to be 0)")  # fmt: skip
            problems.append(f"header: key {key!r} is missing{hint}")
    for key, v in values.items():
        if key == "robot.name":
            continue
        try:
            f = float(v)
        except (TypeError, ValueError):
            problems.append(f"header: {key} = {v!r} is not a number")
            continue
        positive = key not in _NON_NEGATIVE
        if not math.isfinite(f) or f < 0 or (positive and f <= 0):
            need = "a positive" if positive else "a non-negative"
            problems.append(f"header: {key} = {v!r} must be {need} finite number (SI units)")
    gyro = header.get("gyro", {}) if isinstance(header.get("gyro"), dict) else {}
    lsb = gyro.get("lsb_per_dps")
    if lsb is None and "full_scale_dps" in gyro:
        try:
            lsb = 32768.0 / float(gyro["full_scale_dps"])
        except (TypeError, ValueError, ZeroDivisionError):
            lsb = None
    scale: dict[str, float] = {}
    for name, (kind, rank) in {**REQUIRED_FIELDS, **OPTIONAL_FIELDS}.items():
        fld = reader.fields.get(name)
        if fld is None:
            if name in REQUIRED_FIELDS:
                problems.append(f"field {name!r} is missing (/trials/{name})")
            continue
        if len(fld.shape) != rank:
            problems.append(
                f"field {name!r} has per-trial shape {fld.shape}; expected {rank} dimension(s)"
            )
        unit = fld.unit.strip()
        table = UNITS[kind]
        if unit not in table:
            problems.append(
                f"field {name!r} has unit {fld.unit!r}; accepted: "
                + ", ".join(repr(u) for u in table if u)
            )
            continue
        factor = table[unit]
        if kind == "rate" and math.isnan(factor):
            try:
                factor = math.pi / 180 / float(lsb)  # type: ignore[arg-type]
                if not (math.isfinite(factor) and factor > 0):
                    raise ValueError
            except (TypeError, ValueError, ZeroDivisionError):
                problems.append(
                    f"field {name!r} holds counts ({fld.unit!r}) but the header has no valid "
                    "gyro.lsb_per_dps (or gyro.full_scale_dps) to convert them"
                )
                continue
        scale[name] = factor
    for name in REQUIRED_STATICS:
        if not reader.has_static(name):
            problems.append(f"static array {name!r} is missing (/static/{name})")
    g = reader.fields.get("gyro_raw")
    c = reader.fields.get("gyro_counter")
    b = reader.fields.get("gyro_block_host_time_s")
    if g is not None and c is not None and b is not None and g.shape and c.shape and b.shape:
        try:
            block = int(gyro.get("block_samples", 0))
        except (TypeError, ValueError):
            block = 0
        if g.shape[0] != c.shape[0]:
            problems.append(
                f"gyro_counter holds {c.shape[0]} samples per trial, gyro_raw {g.shape[0]}"
            )
        if block > 0 and g.shape[0] // block != b.shape[0]:
            problems.append(
                f"gyro_block_host_time_s holds {b.shape[0]} blocks per trial; gyro_raw's "
                f"{g.shape[0]} samples in blocks of {block} make {g.shape[0] // block}"
            )
        if len(g.shape) == 2 and g.shape[1] != 3:
            problems.append(f"gyro_raw must hold 3 axes per sample, not {g.shape[1]}")
    if reader.n_trials == 0:
        problems.append("the recording holds no trials (an empty sweep)")
    if problems:
        return problems, None
    prof = header["profile"]
    return problems, Contract(
        robot=str(header["robot"]["name"]),
        vendor=str(header["robot"].get("vendor", "")),
        period_s=float(header["controller_period_s"]),
        profile={
            k: float(prof[k]) for k in ("speed_rad_s", "acceleration_rad_s2", "hold_s", "pause_s")
        },
        fs_hz=float(gyro["nominal_rate_hz"]),
        block=int(gyro["block_samples"]),
        group_delay_s=float(gyro["group_delay_s"]),
        transport_latency_s=float(gyro["transport_latency_s"]),
        scale=scale,
    )


def read_contract(reader: RecordingReader) -> Contract:
    """The contract values of an open recording.

    Raises
    ------
    ConfigError
        The sweep holds no trial.
    RecordingError
        Naming every missing field, attribute or header key and every unit that cannot be
        converted (the CLI maps it to exit code 2).
    """
    if reader.n_trials == 0:
        raise ConfigError(f"{reader.path}: the recording holds no trials (an empty sweep)")
    problems, contract = _problems(reader)
    if contract is None:
        raise RecordingError(
            f"{reader.path}: not a recording extraction can read (docs/recording-format.md, "
            "'What extraction needs'):\n  " + "\n  ".join(problems)
        )
    return contract


def check_recording(path: str | os.PathLike[str], *, deep: bool = True) -> list[str]:
    """Every way a recording departs from the documented contract; [] if none.

    Never raises for a bad file: a file that cannot be opened is one problem.

    Parameters
    ----------
    path : path
        The recording (HDF5).
    deep : bool
        Also read the data: counters, times and rates that extraction cannot use (NaN or
        non-increasing times, all-zero gyro windows, truncated streams).

    Returns
    -------
    list of str
        One message per problem, each naming the field, attribute or key.
    """
    try:
        reader = RecordingReader(path)
    except (TimedExecError, OSError) as exc:
        return [str(exc)]
    try:
        with reader:
            problems, contract = _problems(reader)
            if contract is None or not deep:
                return problems
            try:
                return problems + _deep_problems(reader, contract)
            except DamagedChunkError:
                return problems + _damage_problems(reader, path)
    except (TimedExecError, OSError, KeyError, ValueError, TypeError) as exc:
        return [f"{os.fspath(path)}: cannot be read ({type(exc).__name__}: {exc})"]


def _damage_problems(reader: RecordingReader, path: str | os.PathLike[str]) -> list[str]:
    """The damaged chunks, in the words every command uses (:func:`damage_note`), and per
    field the rows that fail."""
    total = np.zeros(reader.n_trials, dtype=bool)
    per_field: list[str] = []
    for name in reader.fields:
        bad = reader.damaged_rows([name])
        if bad.any():
            total |= bad
            rows = np.flatnonzero(bad)
            per_field.append(
                f"field {name!r}: rows {int(rows[0])}..{int(rows[-1])} ({rows.size} rows) "
                "fail their checksum or do not decompress"
            )
    return [damage_note(path, int(total.sum()), reader.n_trials), *per_field]


def _deep_problems(reader: RecordingReader, contract: Contract) -> list[str]:
    out: list[str] = []
    for name in ("t0_s", "cmd_send_time_s"):
        v = reader.read(name)
        if not np.all(np.isfinite(v)):
            out.append(f"field {name!r}: {int(np.sum(~np.isfinite(v)))} trial(s) are not finite")
    still = reader.static("still_gyro_raw")
    if still.ndim != 2 or still.shape[1] != 3 or still.shape[0] < contract.block * 4:
        out.append(f"static 'still_gyro_raw' has shape {still.shape}; expected (n >= "
                   f"{contract.block * 4}, 3)")  # fmt: skip
    sc = reader.static("still_gyro_counter")
    sb = reader.static("still_gyro_block_host_time_s")
    if sc.shape[:1] != still.shape[:1]:
        out.append("static 'still_gyro_counter' must hold one counter per still sample")
    if sb.shape[0] != still.shape[0] // contract.block:
        out.append(f"static 'still_gyro_block_host_time_s' holds {sb.shape[0]} blocks; "
                   f"{still.shape[0]} samples in blocks of {contract.block} make "
                   f"{still.shape[0] // contract.block}")  # fmt: skip
    trial = np.asarray(reader.read("trial"))
    n_plan = min(
        len(reader.static(name)) for name in ("plan_q_start_rad", "plan_joint", "plan_direction")
    )
    outside = int(np.sum((trial < 0) | (trial >= n_plan)))
    if outside:
        out.append(
            f"field 'trial': {outside} trial(s) index no row of the plan arrays "
            f"(plan_q_start_rad, plan_joint, plan_direction hold {n_plan} rows)"
        )
    repeated = int(trial.size - np.unique(trial).size)
    if repeated:
        out.append(
            f"field 'trial': {repeated} plan index(es) recorded more than once; each "
            "trial is one row"
        )
    bad_blocks = bad_counters = flat = 0
    for chunk in reader.iter_chunks(1024, names=["gyro_block_host_time_s", "gyro_counter",
                                                 "gyro_raw"]):  # fmt: skip
        bt = chunk["gyro_block_host_time_s"].astype(np.float64)
        bad_blocks += int(np.sum(~np.all(np.isfinite(bt), axis=1)))
        c = chunk["gyro_counter"].astype(np.int64)
        steps = (np.diff(c, axis=1) + 32768) % 65536 - 32768
        # A window whose counter mostly does not advance by one is not a sample counter.
        bad_counters += int(np.sum(np.mean(steps == 1, axis=1) < 0.5))
        raw = chunk["gyro_raw"]
        flat += int(np.sum(np.all(raw == raw[:, :1], axis=(1, 2))))
    if bad_blocks:
        out.append(f"field 'gyro_block_host_time_s': {bad_blocks} trial(s) hold NaN/inf times "
                   "(a truncated stream); record only complete windows")  # fmt: skip
    if bad_counters:
        out.append(f"field 'gyro_counter': in {bad_counters} trial(s) fewer than half the "
                   "samples advance the counter by one (not a per-sample counter?)")  # fmt: skip
    if flat:
        out.append(f"field 'gyro_raw': {flat} trial(s) hold a constant value (no data)")
    return out
