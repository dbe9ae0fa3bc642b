"""Array type aliases shared by every layer (layer 0: imports only numpy).

One definition, so a change of precision or shape convention is made once.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["BoolArray", "FloatArray", "IntArray"]

#: A float64 array; docstrings give its shape and unit.
FloatArray = NDArray[np.float64]
#: An int64 array (indices, counters).
IntArray = NDArray[np.int64]
#: A boolean mask.
BoolArray = NDArray[np.bool_]
