"""The delay table: the interchange format between extraction, learning and discrepancy.

A CSV with one row per trial (DESIGN.md, "Delay table"):

========================  ==================================================================
column                    meaning
========================  ==================================================================
trial                     int, unique within a sweep
robot                     str, ``ur10``, ``ur10e``, ``kr5``
joint                     int, actuated joint, 1-based
direction                 int, +1 or -1
q1 ... q6                 float, start configuration, rad
t_start                   float, s since the sweep started
actuation_delay           float, s
response_delay            float, s
true_actuation_delay      optional, simulated sweeps only, s
true_response_delay       optional, simulated sweeps only, s
flag                      optional str: why a trial could not be measured ("" when fine);
                          its delays are NaN
response_flag             optional str: why the trial's response delay is not to be used
                          although its actuation delay is ("" when fine; see below)
t_since_power_on          optional float, s since the robot was powered on (its thermal
                          clock), where the recorder knows it (the simulators do)
========================  ==================================================================

Extra columns are kept as they are. Delays are in seconds; human-facing tables show ms.

``response_flag`` says that a trial's response delay is not trustworthy while its
actuation delay is: extraction writes ``deflection`` where the reported angle is a
motor-side encoder's and the age of the state could not be separated from the gear's
deflection to within the table's response accuracy, ``deflection_joint`` on every trial of
a joint whose lag is mostly the gear's play, so that the age its trials share depends on
a law the recording cannot pin down, ``deflection_noise`` on every trial of a joint whose
age the gyro's noise pulled short through the deflection terms (``docs/architecture.md``).
The value
stays in ``response_delay`` (with its standard error) for diagnosis; everything that uses
response delays takes the rows :meth:`DelayTable.usable` gives (learning trains the
response models without them, and still trains actuation on them; a joint flagged
``deflection_joint`` or ``deflection_noise`` on every trial is trained on its own
responses, with a warning, as its only measurement). A table without the
column (older extractions, other recorders) has no response flags.

A table is refused (:class:`~timedexec.errors.ConfigError`) when a trial id occurs twice:
a duplicated row would count twice in training and in every statistic, so the message
names the ids and their rows (drop the copies, or renumber a merged table). A UTF-8
byte-order mark at the start of a CSV file (as Excel writes) is ignored. Joint angles are
checked against the robot's limits where the robot is known: when training
(:func:`timedexec.learning.train_delay_models`).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._files import write_atomic
from timedexec.errors import ConfigError, RecordingError

__all__ = [
    "DELAY_COLUMNS",
    "FLAG_COLUMNS",
    "JOINT_RESPONSE_FLAGS",
    "OPTIONAL_COLUMNS",
    "REQUIRED_COLUMNS",
    "RESPONSE_FLAG_WHY",
    "DelayTable",
]

CONFIG_COLUMNS = tuple(f"q{i}" for i in range(1, 7))
REQUIRED_COLUMNS: tuple[str, ...] = (
    "trial",
    "robot",
    "joint",
    "direction",
    *CONFIG_COLUMNS,
    "t_start",
    "actuation_delay",
    "response_delay",
)
OPTIONAL_COLUMNS: tuple[str, ...] = (
    "true_actuation_delay",
    "true_response_delay",
    "flag",
    "response_flag",
)
DELAY_COLUMNS: tuple[str, ...] = ("actuation_delay", "response_delay")
_INT_COLUMNS = ("trial", "joint", "direction")
_STR_COLUMNS = ("robot", "flag", "response_flag")
#: The flag columns that rule out each delay of a row (a non-empty text: the reason).
FLAG_COLUMNS: dict[str, tuple[str, ...]] = {
    "actuation_delay": ("flag",),
    "response_delay": ("flag", "response_flag"),
}
#: What each ``response_flag`` that extraction writes means, and what removes it (for the
#: messages that name them: the extraction summary, training's warnings).
RESPONSE_FLAG_WHY: dict[str, str] = {
    "deflection": "the gear's deflection could not be separated from the state's age",
    "deflection_joint": "the joint's lag is mostly the gear's play, so the age its trials "
    "share is known to about 0.15 ms only",
    "deflection_noise": "the gyro's noise hid the gear's deflection, so the age reads short "
    "(by up to about 0.1 ms); a quieter gyro or mount removes it",
}
#: The response flags extraction puts on every trial of a joint (not per trial): a joint
#: with nothing else is trained on them with a warning rather than left without a model.
JOINT_RESPONSE_FLAGS = ("deflection_joint", "deflection_noise")


class DelayTable:
    """Columns of equal length, validated against the contract.

    Parameters
    ----------
    columns : mapping of str to array
        At least :data:`REQUIRED_COLUMNS`. ``robot`` may be a single string.
    source : str
        Where the table came from, for error messages.
    allow_nan : bool
        Whether NaN delays are allowed (they are for flagged trials; a table for training
        is checked with :meth:`validated_for_training`).
    """

    def __init__(
        self,
        columns: Mapping[str, ArrayLike | str],
        *,
        source: str = "<table>",
        allow_nan: bool = True,
    ) -> None:
        self.source = source
        missing = [c for c in REQUIRED_COLUMNS if c not in columns]
        if missing:
            raise ConfigError(
                f"{source}: missing column(s) {', '.join(missing)}; a delay table needs "
                f"{', '.join(REQUIRED_COLUMNS)}"
            )
        lengths = {
            len(np.atleast_1d(np.asarray(v)))
            for k, v in columns.items()
            if k != "robot" or not isinstance(v, str)
        }
        n = max(lengths) if lengths else 0
        cols: dict[str, NDArray[Any]] = {}
        for name, value in columns.items():
            if name == "robot" and isinstance(value, str):
                arr: NDArray[Any] = np.full(n, value, dtype=object)
            elif name in _STR_COLUMNS:
                arr = np.asarray(value, dtype=object)
            elif name in _INT_COLUMNS:
                raw = np.asarray(value)
                arr = self._as_int(name, raw)
            else:
                arr = self._as_float(name, np.asarray(value))
            if arr.shape != (n,):
                raise ConfigError(
                    f"{source}: column {name!r} has {arr.shape[0]} rows, expected {n}"
                )
            cols[name] = arr
        self.columns = cols
        if n == 0:
            raise ConfigError(f"{source}: the delay table is empty (no rows)")
        self._check_values(allow_nan)
        self._check_unique_trials()

    def _as_int(self, name: str, raw: NDArray[Any]) -> NDArray[np.int64]:
        try:
            as_float = raw.astype(float)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{self.source}: column {name!r} must hold integers ({exc})") from exc
        bad = ~np.isfinite(as_float) | (as_float != np.round(as_float))
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                f"{self.source}: column {name!r} row {row} holds {raw[row]!r}; it must be an integer"
            )
        return as_float.astype(np.int64)

    def _as_float(self, name: str, raw: NDArray[Any]) -> NDArray[np.float64]:
        try:
            return raw.astype(float)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{self.source}: column {name!r} must hold numbers ({exc})") from exc

    def _check_values(self, allow_nan: bool) -> None:
        c = self.columns
        bad = ~np.isin(c["joint"], np.arange(1, 7))
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ConfigError(f"{self.source}: row {row}: joint {c['joint'][row]} outside 1..6")
        bad = ~np.isin(c["direction"], (-1, 1))
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                f"{self.source}: row {row}: direction {c['direction'][row]} must be +1 or -1"
            )
        for name in (*CONFIG_COLUMNS, "t_start"):
            bad = ~np.isfinite(c[name])
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise ConfigError(
                    f"{self.source}: column {name!r} row {row} is {c[name][row]}; it must be finite"
                )
        for name in DELAY_COLUMNS:
            values = c[name]
            bad = np.isinf(values) if allow_nan else ~np.isfinite(values)
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise ConfigError(
                    f"{self.source}: column {name!r} row {row} is {values[row]}; delays must be "
                    "finite seconds (flag unmeasurable trials and drop them before training)"
                )

    def _check_unique_trials(self) -> None:
        trial = self.columns["trial"]
        ids, counts = np.unique(trial, return_counts=True)
        if (counts == 1).all():
            return
        dup = ids[counts > 1]
        shown = []
        for t in dup[:5]:
            rows = np.flatnonzero(trial == t)
            shown.append(f"{int(t)} (rows {', '.join(str(int(r)) for r in rows[:4])}"
                         + (", ..." if len(rows) > 4 else "") + ")")  # fmt: skip
        more = f" and {len(dup) - 5} more" if len(dup) > 5 else ""
        raise ConfigError(
            f"{self.source}: trial id(s) {'; '.join(shown)}{more} occur more than once; a "
            "trial id is unique within a sweep (a duplicated row would count twice): drop the "
            "copies, or renumber the trials of a merged table"
        )

    # ---------------------------------------------------------------- access
    def __len__(self) -> int:
        return len(self.columns["trial"])

    def __getitem__(self, name: str) -> NDArray[Any]:
        try:
            return self.columns[name]
        except KeyError:
            raise ConfigError(
                f"{self.source}: no column {name!r}; it has {', '.join(self.columns)}"
            ) from None

    def __contains__(self, name: object) -> bool:
        return name in self.columns

    def __iter__(self) -> Iterator[str]:
        return iter(self.columns)

    @property
    def q(self) -> NDArray[np.float64]:
        """Start configurations, shape (n, 6), rad."""
        return np.column_stack([self.columns[c] for c in CONFIG_COLUMNS])

    @property
    def robots(self) -> tuple[str, ...]:
        """Distinct robot names in the table."""
        return tuple(sorted({str(r) for r in self.columns["robot"]}))

    def select(self, mask: ArrayLike) -> DelayTable:
        """Rows where ``mask`` is true (or at the given indices)."""
        idx = np.asarray(mask)
        return DelayTable(
            {k: v[idx] for k, v in self.columns.items()}, source=self.source, allow_nan=True
        )

    def usable(self, delay: str) -> NDArray[np.bool_]:
        """Rows whose ``delay`` (a :data:`DELAY_COLUMNS` name) may be used: no reason in
        any of its :data:`FLAG_COLUMNS` (a missing column flags nothing), shape (n,)."""
        if delay not in FLAG_COLUMNS:
            raise ConfigError(f"unknown delay {delay!r}; choose one of {', '.join(DELAY_COLUMNS)}")
        keep = np.ones(len(self), dtype=bool)
        for name in FLAG_COLUMNS[delay]:
            if name in self.columns:
                keep &= np.array([not f for f in self.columns[name]], dtype=bool)
        return keep

    def reason_counts(self, column: str = "flag") -> dict[str, int]:
        """How many rows give each reason in a flag column (``flag``, ``response_flag``),
        most frequent first; empty when the table has no such column."""
        counts: dict[str, int] = {}
        for f in self.columns.get(column, ()):
            if f:
                counts[str(f)] = counts.get(str(f), 0) + 1
        return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))

    def validated_for_training(self) -> DelayTable:
        """Rows that carry no ``flag``, checked to hold only finite delays (a row with a
        ``response_flag`` is kept: its actuation delay is sound; see :meth:`usable`)."""
        table = self.select(self.usable("actuation_delay"))
        table._check_values(allow_nan=False)
        return table

    # ---------------------------------------------------------------- files
    def to_csv(self, path: str | os.PathLike[str]) -> Path:
        """Write atomically (a temporary file renamed into place): never half-written."""
        out = Path(path)
        names = list(REQUIRED_COLUMNS) + [c for c in self.columns if c not in REQUIRED_COLUMNS]
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(names)
        cols = []
        for name in names:
            col = self.columns[name]
            if col.dtype == object:
                cols.append([str(x) for x in col])
            elif np.issubdtype(col.dtype, np.integer):
                cols.append([str(int(x)) for x in col])
            else:
                cols.append([repr(float(x)) if np.isfinite(x) else "nan" for x in col])
        writer.writerows(zip(*cols, strict=True))
        return write_atomic(out, buf.getvalue())

    @classmethod
    def read_csv(cls, path: str | os.PathLike[str], *, allow_nan: bool = True) -> DelayTable:
        """Read and validate a delay table; errors name the column and row."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8-sig")  # -sig: a BOM (Excel) is not a name
        except FileNotFoundError:
            raise RecordingError(f"delay table {p} does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise RecordingError(f"cannot read delay table {p}: {exc}") from exc
        rows = list(csv.reader(io.StringIO(text)))
        if not rows:
            raise ConfigError(f"{p}: the delay table is empty (no header, no rows)")
        header = [h.strip() for h in rows[0]]
        body = rows[1:]
        for i, row in enumerate(body):
            if len(row) != len(header):
                raise ConfigError(
                    f"{p}: row {i} has {len(row)} fields, the header has {len(header)}"
                )
        columns: dict[str, Any] = {}
        for j, name in enumerate(header):
            values = [row[j].strip() for row in body]
            if name in _STR_COLUMNS:
                columns[name] = np.asarray(values, dtype=object)
                continue
            out = np.empty(len(values))
            for i, v in enumerate(values):
                try:
                    out[i] = float(v)
                except ValueError:
                    raise ConfigError(
                        f"{p}: column {name!r} row {i} holds {v!r}, which is not a number"
                    ) from None
            columns[name] = out
        return cls(columns, source=str(p), allow_nan=allow_nan)
