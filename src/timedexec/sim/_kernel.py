"""The compiled step of :class:`timedexec.sim.JointBank`: :func:`timedexec.sim._drive._drive_step`
(written once, in plain floats) compiled by Numba and looped over the bank's elements.

Why compiled: a bank steps a few hundred to a few thousand drives per physics step, and the
numpy version spent ~60 µs per step in the ~40 array operations' call overhead whatever
the size (a six-element bank cost as much as a 100-element one); the discrepancy analysis
runs tens of thousands of such steps per case. Compiled, one loop over the elements: 8 /
25 / 96 µs per step for 6 / 600 / 4,000 elements (numpy: 59 / ~75 / 223 µs), the same
bits (no fast-math: no reassociation, no fused multiply-add; ``math.cos`` and ``math.sin``
are the C library's, as numpy's are). Imported on first use (:func:`_physics._bank_step`);
the machine code is cached in the user's cache directory (:func:`_cache_dir`).
"""

from __future__ import annotations

import os
from pathlib import Path


def _cache_dir() -> str | None:
    """Where Numba keeps the compiled code unless the user says (``NUMBA_CACHE_DIR``): the
    user's cache directory, not beside the source. Beside the source it lands in
    site-packages for an installed copy, where pip's uninstall leaves it behind and the
    leftover ``timedexec/sim`` folder then shadows a later editable install (seen in the
    fresh-checkout check: every test module failed to import ``timedexec.sim``). None when
    that directory cannot be made or written (Numba then uses its own default)."""
    try:
        base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        path = Path(base) / "timedexec" / "numba"
        path.mkdir(parents=True, exist_ok=True)
    except (OSError, RuntimeError):  # no home, read-only file system
        return None
    return str(path) if os.access(path, os.W_OK) else None


# Read by Numba when it is first imported (a process that imported it before keeps its own
# setting).
if "NUMBA_CACHE_DIR" not in os.environ and (_dir := _cache_dir()) is not None:
    os.environ["NUMBA_CACHE_DIR"] = _dir

import numba  # noqa: E402
import numpy as np  # noqa: E402

from timedexec.sim._drive import _drive_step  # noqa: E402

__all__ = ["bank_step"]

_step = numba.njit(cache=True)(_drive_step)


@numba.njit(cache=True)
def bank_step(c, dt, q, v, tau_m, integ, stuck, v_ref):  # type: ignore[no-untyped-def]
    """:func:`_drive_step` for every element of a bank (arrays of shape (n,); ``c`` the
    coefficients, (12, n) in ``_Coefficients`` order). Returns new arrays
    ``(q, v, tau_m, integ, stuck)``."""
    n = q.shape[0]
    q_out, v_out = np.empty(n), np.empty(n)
    tau_out, integ_out = np.empty(n), np.empty(n)
    stuck_out = np.empty(n, dtype=np.bool_)
    for i in range(n):
        q_out[i], v_out[i], tau_out[i], integ_out[i], stuck_out[i] = _step(
            c[0, i], c[1, i], c[2, i], c[3, i], c[4, i], c[5, i], c[6, i], c[7, i],
            c[8, i], c[9, i], c[10, i], c[11, i], dt, q[i], v[i], tau_m[i], integ[i],
            stuck[i], v_ref[i],
        )  # fmt: skip
    return q_out, v_out, tau_out, integ_out, stuck_out
