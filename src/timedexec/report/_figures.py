"""Figures in the published layout (matplotlib, headless): PNG files with units on every axis.

* Fig. 3 — gyro PSD of the still recording before and after the low-pass filter;
* Fig. 5 — one trial: commanded, measured (gyro) and reported speed, both delays marked;
* Fig. 6 — a model's delay against the joint 2 and joint 3 angles with its ±2σ band;
* Figs. 7 and 9 — actuation and response delay histograms;
* Figs. 8 and 10 — per-joint boxplots of both delays;
* the conveyor (seam-tracking) run with and without compensation;
* the welder's figure: a weld on a straight belt, torch over the seam for each strategy.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from timedexec._files import write_atomic
from timedexec._plot import subplots
from timedexec._signal import ONSET_FRACTION
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError
from timedexec.sim import pulse_profile

__all__ = [
    "fig_boxplots",
    "fig_histograms",
    "fig_model",
    "fig_psd",
    "fig_seam",
    "fig_trial",
    "fig_welding",
]

_DELAY_LABEL = {"actuation_delay": "actuation delay", "response_delay": "response delay"}


def _save(fig: Any, path: Path) -> Path:
    """Render to PNG in memory, then write atomically (never over an input, a symlink or a
    device: :func:`timedexec._files.write_atomic`)."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return write_atomic(path, buf.getvalue())


def fig_psd(traces: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """Fig. 3: Welch PSD of the still gyro recording and the same after the FIR filter."""
    still = traces["still"]
    fs = traces["fs_hz"]
    w, h = signal.freqz(traces["taps"], worN=len(still.freq_hz), fs=fs)
    gain2 = np.interp(still.freq_hz, w, np.abs(h) ** 2)
    fig, ax = subplots(figsize=(7, 4))
    to_dps2 = np.rad2deg(1.0) ** 2
    ax.semilogy(still.freq_hz, still.psd * to_dps2, label="still recording (raw)", lw=1)
    ax.semilogy(
        still.freq_hz, still.psd * gain2 * to_dps2 + 1e-30, label="after the low-pass FIR", lw=1
    )
    ax.axvline(traces["cutoff_hz"], color="k", ls=":", label=f"cutoff {traces['cutoff_hz']:.0f} Hz")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("PSD ((°/s)²/Hz)")
    ax.set_xscale("log")
    ax.set_xlim(2.0, fs / 2)
    ax.set_ylim(bottom=max(1e-14, float((still.psd * gain2 * to_dps2).min()) + 1e-16))
    ax.set_title("Gyro noise spectrum while still (Fig. 3)")
    ax.legend()
    return _save(fig, Path(path))


def fig_trial(traces: dict[str, Any], path: str | os.PathLike[str], i: int = 0) -> Path:
    """Fig. 5: commanded, measured and reported speed of one trial with both delays."""
    prof = traces["profile"]
    t_g = traces["gyro_time_s"][i]
    t_send = float(traces["send_time_s"][i])
    speed = float(traces["speed_rad_s"][i])
    act = float(traces["actuation_delay"][i])
    resp = float(traces["response_delay"][i])
    cmd = pulse_profile(t_g - t_send, **prof)
    fig, ax = subplots(figsize=(8, 4.5))
    ms = 1e3
    ax.plot(t_g * ms, cmd, label="commanded", color="k", lw=1.5)
    ax.plot(
        t_g * ms, traces["gyro_speed_rad_s"][i], label="measured (gyro, raw)", color="0.75", lw=0.6
    )
    ax.plot(
        t_g * ms, traces["gyro_filtered_rad_s"][i], label="measured (gyro, filtered)", color="C0"
    )
    ax.step(traces["state_time_s"][i] * ms, traces["state_speed_rad_s"][i], where="post",
            label="reported (at arrival)", color="C3")  # fmt: skip
    level = ONSET_FRACTION * speed
    t_cmd_level = t_send + level / prof["acceleration_rad_s2"]
    t_onset = t_cmd_level + act
    ax.axhline(level, color="0.5", ls=":", lw=0.8)
    y = 1.08 * speed
    ax.annotate("", (t_onset * ms, y), (t_cmd_level * ms, y),
                arrowprops={"arrowstyle": "<->", "color": "C2"})  # fmt: skip
    ax.text(t_cmd_level * ms, 1.16 * speed, f"actuation {act * ms:.1f} ms", ha="left",
            va="center", color="C2")  # fmt: skip
    # The response delay is the age of the reported state: the gap between the measured
    # speed crossing half the commanded speed and the same instant in the reported stream.
    half = 0.5 * speed
    filt = np.asarray(traces["gyro_filtered_rad_s"][i])
    rising = np.flatnonzero((filt >= half) & (t_g >= t_send))
    if len(rising):
        t_half = float(t_g[rising[0]])
        ax.annotate("", ((t_half + resp) * ms, half), (t_half * ms, half),
                    arrowprops={"arrowstyle": "<->", "color": "C1"})  # fmt: skip
        ax.text((t_half + resp) * ms + 3, half, f"response {resp * ms:.1f} ms", ha="left",
                va="center", color="C1")  # fmt: skip
    ax.axvline(t_send * ms, color="k", ls="--", lw=0.8, label="command sent")
    end = t_send + prof["speed_rad_s"] / prof["acceleration_rad_s2"] * 2 + prof["hold_s"] + 0.15
    ax.set_xlim(-10, end * ms)
    ax.set_ylim(-0.15 * speed, 1.3 * speed)
    ax.set_xlabel("time since the trigger package arrived (ms)")
    ax.set_ylabel("joint speed along the command (rad/s)")
    ax.set_title(f"One trial of the {traces['robot']}: commanded, measured, reported (Fig. 5)")
    ax.legend(loc="upper right", fontsize=8)
    return _save(fig, Path(path))


def fig_histograms(table: DelayTable, path: str | os.PathLike[str], column: str) -> Path:
    """Figs. 7 (actuation) and 9 (response): histogram per joint, ms."""
    values = table[column] * 1e3
    ok = np.isfinite(values)
    if not ok.any():
        raise ConfigError(
            f"{table.source}: no finite {_DELAY_LABEL[column]} to plot (every trial flagged)"
        )
    fig, ax = subplots(figsize=(7, 4))
    joints = [j for j in sorted(set(table["joint"].tolist())) if (ok & (table["joint"] == j)).any()]
    bins = np.linspace(np.percentile(values[ok], 0.5), np.percentile(values[ok], 99.5), 50)
    for j in joints:
        m = ok & (table["joint"] == j)
        ax.hist(values[m], bins=bins.tolist(), histtype="step", lw=1.3, label=f"joint {j}")
    ax.set_xlabel(f"{_DELAY_LABEL[column]} (ms)")
    ax.set_ylabel("trials")
    fig_no = 7 if column == "actuation_delay" else 9
    ax.set_title(
        f"{_DELAY_LABEL[column].capitalize()} of {', '.join(table.robots)} (Fig. {fig_no})"
    )
    ax.legend()
    return _save(fig, Path(path))


def fig_boxplots(table: DelayTable, path: str | os.PathLike[str], column: str) -> Path:
    """Figs. 8 (actuation) and 10 (response): per-joint boxplots, ms."""
    joints = []
    data = []
    for j in sorted(set(table["joint"].tolist())):
        v = table[column][table["joint"] == j] * 1e3
        v = v[np.isfinite(v)]
        if len(v):  # a joint without a valid trial gets no empty box
            joints.append(j)
            data.append(v)
    if not data:
        raise ConfigError(
            f"{table.source}: no finite {_DELAY_LABEL[column]} to plot (every trial flagged)"
        )
    fig, ax = subplots(figsize=(6, 4))
    ax.boxplot(
        data, tick_labels=[f"joint {j}" for j in joints], showfliers=True, flierprops={"ms": 2}
    )
    ax.set_ylabel(f"{_DELAY_LABEL[column]} (ms)")
    fig_no = 8 if column == "actuation_delay" else 10
    ax.set_title(
        f"{_DELAY_LABEL[column].capitalize()} per joint, {', '.join(table.robots)} (Fig. {fig_no})"
    )
    return _save(fig, Path(path))


def fig_model(
    model: Any,
    path: str | os.PathLike[str],
    table: DelayTable | None = None,
    *,
    joint: int = 2,
    method: str | None = None,
    points: int = 200,
) -> Path:
    """Fig. 6: the model's delays of ``joint`` against the joint 2 and joint 3 angles.

    Each panel sweeps one angle through the range the table covers (or ±1 rad around the
    home pose without a table) with the other joints at the table's median start pose,
    for both directions: the mean with a band of ±2 single-trial standard deviations
    (where about 95 % of trials should fall), clipped at 0 ms below (a delay is never
    negative; the Gaussian band of a short delay would dip under 0). The table's trials of ``joint`` are shown
    as dots; they differ in the other joints too, so they scatter around the slice.

    Parameters
    ----------
    model : timedexec.learning.DelayModel
    table : DelayTable, optional
        Measured trials of the same robot: the reference pose, the angle ranges, the dots.
    joint : int
        Actuated joint whose delays are shown (the paper's Fig. 6: joint 2).
    method : str, optional
        The model's method drawn; default the bundle's ``default_method`` (the GP where it
        has one).
    """
    from timedexec.robots import get_robot

    spec = get_robot(model.robot, period_s=model.period_s)
    qcols = [f"q{k}" for k in range(1, 7)]
    sel = None
    if table is not None:
        sel = table["joint"] == joint
        if not sel.any():
            sel = None
    if sel is not None and table is not None:
        q_tab = np.column_stack([table[c][sel] for c in qcols])
        q_ref = np.median(q_tab, axis=0)
        lo, hi = q_tab.min(axis=0), q_tab.max(axis=0)
    else:
        q_ref = np.asarray(spec.home_q_rad, dtype=float)
        lo = np.maximum(q_ref - 1.0, spec.q_min_rad)
        hi = np.minimum(q_ref + 1.0, spec.q_max_rad)
    fig, axes = subplots(2, 2, figsize=(10, 7), sharex="col", squeeze=False)
    colors = {1: "tab:blue", -1: "tab:orange"}
    for col, angle in enumerate((2, 3)):
        k = angle - 1
        grid = np.linspace(lo[k], hi[k], points)
        q = np.tile(q_ref, (points, 1))
        q[:, k] = grid
        for direction in (1, -1):
            pred = model.predict_many(joint, direction, q, method=method)
            for row, name in enumerate(("actuation", "response")):
                ax = axes[row, col]
                mean = np.asarray(getattr(pred, f"{name}_mean")) * 1e3
                std = np.asarray(getattr(pred, f"{name}_std")) * 1e3
                label = f"direction {direction:+d}"
                ax.plot(np.rad2deg(grid), mean, color=colors[direction], lw=1.5, label=label)
                # A delay is never negative: the band stops at 0 ms.
                ax.fill_between(
                    np.rad2deg(grid),
                    np.maximum(mean - 2 * std, 0.0),
                    mean + 2 * std,
                    color=colors[direction],
                    alpha=0.15,
                    label=f"±2σ, direction {direction:+d}",
                )
                if sel is not None and table is not None:
                    m = sel & (table["direction"] == direction)
                    ax.plot(
                        np.rad2deg(table[f"q{angle}"][m]),
                        table[f"{name}_delay"][m] * 1e3,
                        ".",
                        ms=2,
                        color=colors[direction],
                        alpha=0.35,
                    )
                ax.set_ylabel(f"joint {joint} {name} delay (ms)")
        axes[1, col].set_xlabel(f"joint {angle} angle q{angle} (°)")
    ref = ", ".join(f"{np.rad2deg(v):.0f}" for v in q_ref)
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.suptitle(
        f"{spec.name}: {method} model of joint {joint}, other joints at ({ref})° (Fig. 6); "
        "dots: measured trials",
        fontsize=10,
    )
    return _save(fig, Path(path))


def fig_seam(result: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """The conveyor runs: tool-to-seam distance over the cruise, without compensation, with
    it, and with it plus position feedback.

    ``result`` is :func:`timedexec.tasks.compare_seam_tracking`'s output (or its JSON).
    Solid: the physical distance (simulator truth); dashed: what the executor believes from
    its back-dated state.
    """
    fig, ax = subplots(figsize=(7, 4))
    colors = {
        "uncompensated": "tab:red",
        "compensated": "tab:green",
        "compensated + feedback": "tab:blue",
    }
    for name, run in result["runs"].items():
        t = np.asarray(run["times_s"]) * 1e3
        c = colors.get(name)
        ax.plot(t, run["lag_cm"], color=c, lw=1.5,
                label=f"{name}: mean {run['mean_lag_cm']:+.2f} cm")  # fmt: skip
        ax.plot(t, run["estimated_lag_cm"], color=c, lw=1, ls="--",
                label=f"{name}, believed (back-dated state)")  # fmt: skip
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel("time after the planned meeting with the seam (ms)")
    ax.set_ylabel("tool behind the seam along the belt (cm)")
    ax.set_title(
        f"{result['robot']}: following a seam at {result['speed_m_s']:g} m/s (positive: late)"
    )
    ax.legend(fontsize=8)
    return _save(fig, Path(path))


#: Colours of the welding strategies (fixed, so figures of different runs compare).
_WELD_COLORS = {
    "none": "tab:red",
    "constant": "tab:orange",
    "median": "tab:olive",
    "model": "tab:green",
    "oracle": "tab:blue",
    "model + feedback": "tab:purple",
}


def fig_welding(data: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """The welder's figure: the torch over the seam on a straight conveyor, per strategy.

    ``data`` is :meth:`timedexec.evaluation.ConveyorEvaluation.figure_data` (or its JSON): one
    run per strategy. Left: top view *on the part* (the belt's motion removed, so the seam
    stands still): the seam and each strategy's torch tip, in mm from the seam start.
    Right: the torch's error across the seam (top) and along it (bottom) over time, mm;
    the shaded span is the cruise window the tables average over. Physical torch (the
    simulator's joint angles), not what the robot reports.
    """
    fig, axes = subplots(1, 2, figsize=(12, 4.8))
    top, right = axes
    right.axis("off")
    grid = right.get_gridspec()
    sub = grid[0, 1].subgridspec(2, 1, hspace=0.08)
    ax_across = fig.add_subplot(sub[0])
    ax_along = fig.add_subplot(sub[1], sharex=ax_across)
    runs = data["runs"]
    speed = float(data["speed_m_s"])
    seam_drawn = False
    for name, run in runs.items():
        t = np.asarray(run["times_s"], dtype=float)
        if not len(t):
            continue
        shift = np.outer(t, [0.0, speed])  # belt along +y of the part view
        torch = np.asarray(run["torch_xy_m"]) - shift
        seam = np.asarray(run["seam_xy_m"]) - shift
        origin = seam[0]
        color = _WELD_COLORS.get(name)
        if not seam_drawn:
            top.plot(*((seam - origin) * 1e3).T, color="k", lw=3, alpha=0.35, label="seam")
            seam_drawn = True
        top.plot(*((torch - origin) * 1e3).T, color=color, lw=1.2, label=name)
        ax_across.plot(t * 1e3, run["across_mm"], color=color, lw=1.2, label=name)
        ax_along.plot(t * 1e3, run["along_mm"], color=color, lw=1.2)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("on the part, across the belt (mm)")
    top.set_ylabel("on the part, along the belt (mm)")
    top.set_title(
        f"{data['robot']}: {data['seam']} seam, belt {speed:g} m/s (top view on the part)"
    )
    top.legend(fontsize=8)
    settle, cruise = float(data.get("settle_s", np.nan)), float(data.get("cruise_s", np.nan))
    for ax in (ax_across, ax_along):
        ax.axhline(0.0, color="k", lw=0.8)
        if np.isfinite(settle) and np.isfinite(cruise):
            ax.axvspan(settle * 1e3, (settle + cruise) * 1e3, color="0.9", zorder=0)
    ax_across.set_ylabel("across the seam (mm)")
    ax_along.set_ylabel("along the seam (mm)")
    ax_along.set_xlabel("time after meeting the seam (ms)")
    ax_across.legend(fontsize=7, ncol=3)
    ax_across.tick_params(labelbottom=False)
    return _save(fig, Path(path))
