"""The monitor figure: each joint's CUSUM over its moves, the threshold, and the alarm."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["monitor_figure"]


def monitor_figure(monitor: Any, path: str | os.PathLike[str] | None = None) -> Any:
    """Draw the upper and lower CUSUMs of every joint (level, and dotted the contrast with
    the joints moved with it) against its moves.

    One panel per joint: the two statistics (warm-up moves shaded), the threshold, and a
    marker where an alarm fired. matplotlib is imported here, never at import time, and
    pyplot is not used (``timedexec._plot``).

    Parameters
    ----------
    monitor : DelayMonitor or dict
        The monitor after its updates, or its :meth:`DelayMonitor.summary` (as
        ``timedexec monitor --json`` writes it; ``timedexec report`` draws it from there).
    path : path, optional
        Where to save it (the type from the suffix, e.g. .png, .pdf).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from timedexec._plot import subplots

    summary = monitor if isinstance(monitor, dict) else monitor.summary()
    joints = summary["joints"]
    h = float(summary["threshold"])
    warmup = int(summary["warmup_moves"])
    n = max(1, len(joints))
    fig, axes = subplots(n, 1, figsize=(7.0, 1.8 * n + 0.6), sharex=False, squeeze=False)
    for ax, row in zip(axes[:, 0], joints, strict=False):
        upper = np.asarray(row["history"]["upper"], dtype=np.float64)
        lower = np.asarray(row["history"]["lower"], dtype=np.float64)
        x = np.arange(1, len(upper) + 1)
        ax.plot(x, upper, lw=1.0, color="C3", label="upper (later)")
        ax.plot(x, lower, lw=1.0, color="C0", label="lower (earlier)")
        hist = row["history"]
        cx = np.asarray(hist.get("contrast_move", []), dtype=np.float64)
        if len(cx):
            c_up = np.asarray(hist["contrast_upper"], dtype=np.float64)
            c_down = np.asarray(hist["contrast_lower"], dtype=np.float64)
            ax.plot(cx, c_up, lw=0.8, ls=":", color="C3", label="contrast upper")
            ax.plot(cx, c_down, lw=0.8, ls=":", color="C0", label="contrast lower")
            upper = np.concatenate((upper, c_up))
            lower = np.concatenate((lower, c_down))
        ax.axhline(h, color="k", lw=0.8, ls="--", label=f"threshold {h:.1f}")
        ax.axvspan(0.5, min(warmup, len(x)) + 0.5, color="0.9", label="warm-up")
        common = [
            a
            for a in summary.get("alerts", [])
            if a.get("test") == "common" and a["joint"] == row["joint"]
        ]
        if common:
            ax.plot([a["move"] for a in common], [a["statistic"] for a in common], "^",
                    color="0.4", ms=6, label="common shift (all joints)")  # fmt: skip
        alert = row.get("alert")
        if alert is not None:
            ax.plot([alert["move"]], [alert["statistic"]], "kv", ms=7, label="alarm")
            ax.set_title(f"joint {row['joint']}: {alert['shift_ms']:+.2f} ms", fontsize=9)
        else:
            ax.set_title(f"joint {row['joint']}: {row['status']}", fontsize=9)
        ax.set_ylabel("CUSUM")
        top = max(float(np.max(upper, initial=0)), float(np.max(lower, initial=0)))
        ax.set_ylim(0, max(1.3 * h, 1.05 * top))
    axes[0, 0].legend(fontsize=7, loc="upper left", ncol=3)
    axes[-1, 0].set_xlabel("moves of the joint")
    fig.suptitle(
        f"delay monitor: 1 false alarm per {summary['arl0_moves']:,.0f} moves per joint",
        fontsize=10,
    )
    fig.tight_layout()
    if path is not None:
        fig.savefig(Path(path), dpi=110)
    return fig
