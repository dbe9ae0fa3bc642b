"""The figure of an adaptive sweep: its model's estimated error against robot time."""

from __future__ import annotations

import math
import os
from pathlib import Path

from timedexec._plot import subplots
from timedexec.calibration._adaptive import read_design_log
from timedexec.recording import RecordingReader

__all__ = ["plot_design_log"]


def plot_design_log(
    recording: str | os.PathLike[str], out: str | os.PathLike[str] | None = None
) -> Path | None:
    """Plot an adaptive recording's design log: per batch, the estimated RMS error of a new
    trial in the workspace (and after the batch), the RMS error on the newest measured batch
    predicted before the model saw it, and the noise floor, in ms, against robot time, min.

    Parameters
    ----------
    recording : path
        An adaptive sweep's recording.
    out : path, optional
        Figure to write; default ``RECORDING`` with the suffix ``.design.png``.

    Returns
    -------
    Path or None
        The figure, or None when the recording holds no batch chosen by a model (a fixed
        sweep, or an adaptive one stopped in its first two batches).
    """
    with RecordingReader(recording) as r:
        log = [n for n in read_design_log(r) if math.isfinite(n["error_s"])]
    if not log:
        return None
    path = Path(out) if out is not None else Path(recording).with_suffix(".design.png")
    t_min = [n["robot_time_s"] / 60.0 for n in log]
    fig, ax = subplots(figsize=(6.4, 3.6), constrained_layout=True)
    ax.plot(t_min, [1e3 * n["error_s"] for n in log], "o-", label="estimated error (model)")
    held = [(t, 1e3 * n["held_out_rmse_s"]) for t, n in zip(t_min, log, strict=True)
            if math.isfinite(n["held_out_rmse_s"])]  # fmt: skip
    if held:
        ax.plot(*zip(*held, strict=True), "s--", label="RMSE on the next batch, before seeing it")
    ax.plot(t_min, [1e3 * n["floor_s"] for n in log], ":", color="0.4", label="noise floor")
    ax.set_xlabel("robot time, min")
    ax.set_ylabel("actuation delay error, ms")
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("adaptive sweep: the model's error against robot time", fontsize=10)
    fig.savefig(path, dpi=120)
    return path
