"""Hypothesis strategies shared by the test suite (one place, as attrs keeps them).

Add a strategy here when more than one test module can use it; keep each one documented
with the shapes and units it generates.
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from numpy.typing import NDArray

from timedexec.robots import RobotSpec


def robot_configurations(
    spec: RobotSpec, *, margin_rad: float = 0.0
) -> st.SearchStrategy[NDArray[np.float64]]:
    """Joint configurations of ``spec`` inside its limits, shape (6,), rad.

    ``margin_rad`` keeps every joint that far inside its limits (for finite differences).
    """
    joints = [
        st.floats(
            min_value=lo + margin_rad,
            max_value=hi - margin_rad,
            allow_nan=False,
            allow_infinity=False,
        )
        for lo, hi in zip(spec.q_min_rad, spec.q_max_rad, strict=True)
    ]
    return st.tuples(*joints).map(lambda q: np.asarray(q, dtype=np.float64))
