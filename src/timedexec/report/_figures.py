"""Figures in the published layout (matplotlib, headless): PNG files with units on every axis.

* Fig. 3 — gyro PSD of the still recording before and after the low-pass filter;
* Fig. 5 — one trial: commanded, measured (gyro) and reported speed, both delays marked;
* Figs. 7 and 9 — actuation and response delay histograms;
* Figs. 8 and 10 — per-joint boxplots of both delays.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy import signal

from timedexec._signal import ONSET_FRACTION
from timedexec.delays import DelayTable
from timedexec.sim import pulse_profile

__all__ = ["fig_boxplots", "fig_histograms", "fig_psd", "fig_trial"]

_DELAY_LABEL = {"actuation_delay": "actuation delay", "response_delay": "response delay"}


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def fig_psd(traces: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """Fig. 3: Welch PSD of the still gyro recording and the same after the FIR filter."""
    still = traces["still"]
    fs = traces["fs_hz"]
    w, h = signal.freqz(traces["taps"], worN=len(still.freq_hz), fs=fs)
    gain2 = np.interp(still.freq_hz, w, np.abs(h) ** 2)
    fig, ax = plt.subplots(figsize=(7, 4))
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
    fig, ax = plt.subplots(figsize=(8, 4.5))
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
    ax.text((t_cmd_level + t_onset) / 2 * ms, y * 1.02, f"actuation {act * ms:.1f} ms",
            ha="center", color="C2")  # fmt: skip
    ax.annotate("", ((t_onset + resp) * ms, 0.6 * speed), (t_onset * ms, 0.6 * speed),
                arrowprops={"arrowstyle": "<->", "color": "C1"})  # fmt: skip
    ax.text((t_onset + resp) * ms + 3, 0.6 * speed, f"response {resp * ms:.1f} ms", ha="left",
            va="center", color="C1")  # fmt: skip
    ax.axvline(t_send * ms, color="k", ls="--", lw=0.8, label="command sent")
    end = t_send + prof["speed_rad_s"] / prof["acceleration_rad_s2"] * 2 + prof["hold_s"] + 0.15
    ax.set_xlim(-10, end * ms)
    ax.set_xlabel("time since the trigger package arrived (ms)")
    ax.set_ylabel("joint speed along the command (rad/s)")
    ax.set_title(f"One trial of the {traces['robot']}: commanded, measured, reported (Fig. 5)")
    ax.legend(loc="upper right", fontsize=8)
    return _save(fig, Path(path))


def fig_histograms(table: DelayTable, path: str | os.PathLike[str], column: str) -> Path:
    """Figs. 7 (actuation) and 9 (response): histogram per joint, ms."""
    values = table[column] * 1e3
    fig, ax = plt.subplots(figsize=(7, 4))
    joints = sorted(set(table["joint"].tolist()))
    ok = np.isfinite(values)
    bins = np.linspace(np.nanpercentile(values, 0.5), np.nanpercentile(values, 99.5), 50)
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
    joints = sorted(set(table["joint"].tolist()))
    data = []
    for j in joints:
        v = table[column][table["joint"] == j] * 1e3
        data.append(v[np.isfinite(v)])
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.boxplot(
        data, tick_labels=[f"joint {j}" for j in joints], showfliers=True, flierprops={"ms": 2}
    )
    ax.set_ylabel(f"{_DELAY_LABEL[column]} (ms)")
    fig_no = 8 if column == "actuation_delay" else 10
    ax.set_title(
        f"{_DELAY_LABEL[column].capitalize()} per joint, {', '.join(table.robots)} (Fig. {fig_no})"
    )
    return _save(fig, Path(path))
