"""What a per-trial dataset of a recording is: :class:`Field`, the storable dtypes, batch checks.

A field is stored as ``/trials/<name>`` with shape ``(n, *shape)``: numeric, bool and
fixed-length bytes dtypes only (text belongs in the JSON header). The writer checks each
appended batch against its fields with :func:`coerce`: shapes must match exactly, dtypes
are converted only when that loses nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec.errors import ConfigError

__all__ = [
    "TRIAL_FIELD",
    "Field",
    "canonical_dtype",
    "check_name",
    "coerce",
    "dtype_name",
    "normalise_fields",
]

_DTYPE_KINDS = "biufcS"  # bool, signed, unsigned, float, complex, fixed-length bytes


def canonical_dtype(dtype: Any, what: str) -> np.dtype[Any]:
    """Validate a dtype for storage and return it in native byte order."""
    try:
        dt = np.dtype(dtype)
    except TypeError as exc:
        raise ConfigError(f"{what}: {dtype!r} is not a numpy dtype; use e.g. 'int16'") from exc
    if dt.kind not in _DTYPE_KINDS or dt.fields is not None or dt.subdtype is not None:
        raise ConfigError(
            f"{what}: dtype {dt} cannot be stored; use a numeric, bool or fixed-length bytes "
            "dtype ('int16', 'float64', 'bool', 'S16'); put text into the header instead"
        )
    native: np.dtype[Any] = dt.newbyteorder("=")
    return native


def dtype_name(dt: np.dtype[Any]) -> str:
    """Canonical name of a storable dtype (``"int16"``, ``"S16"``)."""
    return f"S{dt.itemsize}" if dt.kind == "S" else dt.name


def check_name(name: Any, what: str) -> str:
    """Return ``name`` if it can name an HDF5 dataset; ``what`` ("field", "static") names it."""
    if not isinstance(name, str) or not name or "/" in name or name in (".", ".."):
        raise ConfigError(f"{what} name {name!r} is invalid; use a non-empty name without '/'")
    return name


@dataclass(frozen=True)
class Field:
    """One per-trial dataset of a recording.

    Parameters
    ----------
    name : str
        Dataset name, stored as ``/trials/<name>``, e.g. ``"gyro"``, ``"state_host_time_s"``.
    shape : tuple of int
        Shape of one trial's value, e.g. ``(4800, 3)``; ``()`` for a scalar per trial.
    dtype : str
        numpy dtype of the stored values, e.g. ``"int16"``, ``"float64"``; normalised to
        its canonical name.
    unit : str, optional
        Unit of the values (SI), stored as the dataset attribute ``unit``.
    doc : str, optional
        One-line description, stored as the dataset attribute ``doc``.
    """

    name: str
    shape: tuple[int, ...]
    dtype: str
    unit: str = ""
    doc: str = ""

    def __post_init__(self) -> None:
        check_name(self.name, "field")
        try:
            shape = tuple(int(s) for s in self.shape)
        except (TypeError, ValueError) as exc:
            raise ConfigError(
                f"field {self.name!r}: shape {self.shape!r} must be a tuple of ints"
            ) from exc
        if any(s < 1 for s in shape):
            raise ConfigError(
                f"field {self.name!r}: shape {shape} has a dimension < 1; every per-trial "
                "dimension must be at least 1"
            )
        dt = canonical_dtype(self.dtype, f"field {self.name!r}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "dtype", dtype_name(dt))
        object.__setattr__(self, "unit", str(self.unit))
        object.__setattr__(self, "doc", str(self.doc))

    @property
    def np_dtype(self) -> np.dtype[Any]:
        """The numpy dtype (native byte order)."""
        return np.dtype(self.dtype)

    @property
    def row_nbytes(self) -> int:
        """Bytes of one trial's value."""
        return self.np_dtype.itemsize * math.prod(self.shape)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form (``shape`` as a list)."""
        return {
            "name": self.name,
            "shape": list(self.shape),
            "dtype": self.dtype,
            "unit": self.unit,
            "doc": self.doc,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Field:
        """Inverse of :meth:`to_dict`."""
        unknown = set(data) - {"name", "shape", "dtype", "unit", "doc"}
        if unknown:
            raise ConfigError(f"Field.from_dict: unknown keys {sorted(unknown)}")
        return cls(
            name=data["name"],
            shape=tuple(data["shape"]),
            dtype=data["dtype"],
            unit=data.get("unit", ""),
            doc=data.get("doc", ""),
        )


#: The plan-index field every recording has (added first when a writer's fields lack it).
TRIAL_FIELD = Field("trial", (), "int64", doc="sweep plan index of the trial")


def normalise_fields(fields: Sequence[Field]) -> list[Field]:
    """Check a writer's fields (unique names, a valid ``trial``) and put ``trial`` first if absent."""
    out: list[Field] = []
    seen: set[str] = set()
    for f in fields:
        if not isinstance(f, Field):
            raise ConfigError(f"fields must be Field objects, got {type(f).__name__}")
        if f.name in seen:
            raise ConfigError(f"field {f.name!r} is listed twice; field names must be unique")
        seen.add(f.name)
        out.append(f)
    if "trial" in seen:
        trial = next(f for f in out if f.name == "trial")
        if trial.shape != () or trial.dtype != "int64":
            raise ConfigError(
                f"field 'trial' must have shape () and dtype int64 (the plan index), got "
                f"shape {trial.shape} and dtype {trial.dtype}; drop it to get the default"
            )
    else:
        out.insert(0, TRIAL_FIELD)
    return out


def coerce(
    name: str,
    value: ArrayLike,
    dt: np.dtype[Any],
    expected: tuple[int, ...],
    k: int,
    per_trial: tuple[int, ...],
) -> NDArray[Any]:
    """Check one batch field's shape and convert it to the field dtype if lossless."""
    arr = np.asarray(value)
    if arr.shape != expected:
        raise ConfigError(
            f"batch field {name!r}: expected shape {expected} ({k} trials x per-trial shape "
            f"{per_trial}), got {arr.shape}"
        )
    if arr.dtype == dt:
        return arr
    if np.can_cast(arr.dtype, dt, "safe"):
        return arr.astype(dt)
    if arr.dtype.kind in "iu" and dt.kind in "iu":
        info = np.iinfo(dt)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            raise ConfigError(
                f"batch field {name!r}: values {arr.min()}..{arr.max()} do not fit dtype "
                f"{dtype_name(dt)} (range {info.min}..{info.max}); check the scaling"
            )
        return arr.astype(dt)
    if arr.dtype.kind == "f" and dt.kind == "f":
        return arr.astype(dt)
    raise ConfigError(
        f"batch field {name!r}: expected dtype {dtype_name(dt)} (or one that converts to it "
        f"without loss), got {arr.dtype}; convert it explicitly"
    )
