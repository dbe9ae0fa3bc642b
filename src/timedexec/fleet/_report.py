"""The fleet report: one row per robot, a figure comparing robots, what each robot needs.

Files (in the fleet's output folder, each written whole through a rename):

* ``fleet.csv`` — the fleet table (:data:`FLEET_COLUMNS`), one row per robot in the
  manifest's order; the same bytes for the same manifest and settings, wherever it ran;
* ``fleet.json`` — every robot's full summary (extraction, CV scores, evaluation, drift
  checks, decision) and the settings; deterministic as ``fleet.csv``;
* ``report.md`` and ``fleet.png`` — for people: the table, which robots need a new
  calibration and why, the failures, the figure;
* ``run.json`` and ``costs.csv`` — how the run went (where each robot ran; wall time, CPU
  time, peak memory and bytes read per stage): these differ from run to run.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from timedexec._files import write_atomic
from timedexec._plot import subplots
from timedexec.fleet._pipeline import STAGES, FleetSettings, RobotResult

__all__ = ["FLEET_COLUMNS", "fleet_document", "fleet_rows", "write_fleet_report"]

#: Columns of ``fleet.csv`` (delays and errors in ms).
FLEET_COLUMNS = (
    "name",
    "robot",
    "source",
    "deployed",
    "status",
    "trials",
    "flagged",
    "damaged",
    "actuation_median_ms",
    "actuation_p2_5_ms",
    "actuation_p97_5_ms",
    "response_median_ms",
    "response_p2_5_ms",
    "response_p97_5_ms",
    "model",
    "actuation_model_error_ms",
    "actuation_noise_floor_ms",
    "response_model_error_ms",
    "response_noise_floor_ms",
    "eval_none_ms",
    "eval_model_ms",
    "eval_coverage_95",
    "monitor",
    "needs_recalibration",
    "reason",
)
FORMAT = "timedexec-fleet"
FORMAT_VERSION = 1


def _get(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def fleet_rows(results: Sequence[RobotResult]) -> list[dict[str, Any]]:
    """The fleet table as dicts (keys :data:`FLEET_COLUMNS`), one per robot."""
    rows = []
    for r in results:
        s = r.summary
        ext, tr, ev = s.get("extraction"), s.get("training"), s.get("evaluation")
        row: dict[str, Any] = {
            **r.entry.to_dict(),
            "status": r.status if r.ok else f"failed ({r.failed_stage})",
            "trials": _get(ext, "trials"),
            "flagged": _get(ext, "flagged"),
            "damaged": _get(ext, "damaged_trials"),
            "model": _get(tr, "actuation_delay", "model"),
            "eval_none_ms": _get(ev, "timing_rms_ms", "none"),
            "eval_model_ms": _get(ev, "timing_rms_ms", "model"),
            "eval_coverage_95": _get(ev, "coverage_95"),
            "monitor": _get(s, "drift", "state"),
            "needs_recalibration": _get(s, "decision", "needs_recalibration"),
            "reason": _get(s, "decision", "reason"),
        }
        for d in ("actuation", "response"):
            for stat in ("median_ms", "p2_5_ms", "p97_5_ms"):
                row[f"{d}_{stat}"] = _get(ext, f"{d}_delay", stat)
            row[f"{d}_model_error_ms"] = _get(tr, f"{d}_delay", "model_error_ms")
            row[f"{d}_noise_floor_ms"] = _get(tr, f"{d}_delay", "noise_floor_ms")
        rows.append({k: row[k] for k in FLEET_COLUMNS})
    return rows


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else "nan"
    return str(value)


def _csv(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


def _ms(value: Any, digits: int = 1) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _markdown(
    results: Sequence[RobotResult], rows: Sequence[dict[str, Any]], settings: FleetSettings
) -> str:
    ok = [r for r in results if r.ok]
    failed = [r for r in results if not r.ok]
    recal = [row for row in rows if row["needs_recalibration"]]
    lines = [
        "# Fleet report",
        "",
        f"{len(results)} robots: {len(ok)} processed, {len(failed)} failed; "
        f"{len(recal)} need a new calibration. Models: {', '.join(settings.methods)} with "
        f"{settings.folds}-fold cross-validation (split by start configuration).",
        "",
        "| robot | type | status | trials (flagged) | actuation median (2.5-97.5 %), ms "
        "| response median (2.5-97.5 %), ms | model error / floor, ms (act.) "
        "| timing RMS none / model, ms | monitor | recalibrate |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        trials = "–" if row["trials"] is None else f"{row['trials']:,} ({row['flagged']})"
        act, resp = (
            "–"
            if row[f"{d}_median_ms"] is None
            else f"{_ms(row[f'{d}_median_ms'])} ({_ms(row[f'{d}_p2_5_ms'])}-"
            f"{_ms(row[f'{d}_p97_5_ms'])})"
            for d in ("actuation", "response")
        )
        err = (
            f"{_ms(row['actuation_model_error_ms'], 2)} / {_ms(row['actuation_noise_floor_ms'], 2)}"
        )
        ev = f"{_ms(row['eval_none_ms'], 2)} / {_ms(row['eval_model_ms'], 2)}"
        lines.append(
            f"| {row['name']} | {row['robot']} | {row['status']} | {trials} | {act} | {resp} "
            f"| {err} | {ev} | {row['monitor'] or '–'} | {'**yes**' if row['needs_recalibration'] else 'no'} |"
        )
    lines += ["", "![delays and model errors per robot](fleet.png)", ""]
    if recal:
        lines += ["## Robots that need a new calibration", ""]
        lines += [f"- **{row['name']}** ({row['robot']}): {row['reason']}" for row in recal]
        lines.append("")
    damaged = [r for r in results if (r.summary.get("extraction") or {}).get("damaged_trials")]
    if damaged:
        from timedexec.recording import damage_note

        lines += ["## Damaged recordings", ""]
        lines += [
            f"- **{r.name}**: "
            + damage_note(
                r.entry.source,
                r.summary["extraction"]["damaged_trials"],
                r.summary["extraction"]["trials"],
            )
            for r in damaged
        ]
        lines.append("")
    if failed:
        lines += ["## Failures", ""]
        lines += [f"- **{r.name}**: {r.failed_stage} failed: {r.error}" for r in failed]
        lines.append("")
    lines += [
        "## How to read it",
        "",
        "- Delays are the extracted ones (flagged trials left out); the spread is the "
        "2.5-97.5 % range over the sweep.",
        "- Model error is the cross-validated RMS error of the model the executor uses "
        "(the GP when trained), the floor is the replicate scatter no model can beat.",
        "- Timing RMS is the motion-onset error on held-out trials of the simulated robot "
        "of that type, without compensation and with the robot's new model.",
        f"- Monitor: the deployed model against the new sweep, per joint and delay; drift "
        f"is a shift of at least {settings.drift_ms:g} ms that is significant at "
        f"{settings.drift_alpha:g} per robot. `no reference`: no deployed model named.",
        "- Per robot: `robots/NAME/` holds the delay table, the model bundle (with cv.json), "
        "evaluation.json, drift.json and result.json; `run.json` and `costs.csv` say where "
        "and at what cost each robot ran.",
        "",
    ]
    return "\n".join(lines)


def _figure(rows: Sequence[dict[str, Any]], path: Path) -> Path:
    """Delays (median and 2.5-97.5 % range) and model error against the floor, per robot."""
    import numpy as np

    x = np.arange(len(rows))
    fig, (ax1, ax2) = subplots(2, 1, figsize=(max(6.0, 0.9 * len(rows) + 2.5), 6.5), sharex=True)

    def val(row: dict[str, Any], key: str) -> float:
        v = row[key]
        return float("nan") if v is None else float(v)

    for d, dx, color in (("actuation", -0.12, "tab:blue"), ("response", 0.12, "tab:orange")):
        med = np.array([val(r, f"{d}_median_ms") for r in rows])
        lo = np.array([val(r, f"{d}_p2_5_ms") for r in rows])
        hi = np.array([val(r, f"{d}_p97_5_ms") for r in rows])
        ax1.errorbar(
            x + dx, med, yerr=[med - lo, hi - med], fmt="o", color=color, capsize=3,
            label=f"{d} delay (median, 2.5-97.5 %)",
        )  # fmt: skip
    ax1.set_ylabel("delay, ms")
    ax1.legend(loc="best", fontsize=8)
    ax1.grid(True, axis="y", alpha=0.3)
    for d, dx, color in (("actuation", -0.18, "tab:blue"), ("response", 0.18, "tab:orange")):
        err = np.array([val(r, f"{d}_model_error_ms") for r in rows])
        floor = np.array([val(r, f"{d}_noise_floor_ms") for r in rows])
        ax2.bar(x + dx, err, width=0.34, color=color, alpha=0.7, label=f"{d}: model CV error")
        ax2.plot(x + dx, floor, "k_", markersize=14, mew=2)
    ax2.plot([], [], "k_", markersize=14, mew=2, label="noise floor (replicate scatter)")
    ax2.set_ylabel("RMS error, ms")
    ax2.legend(loc="best", fontsize=8)
    ax2.grid(True, axis="y", alpha=0.3)
    ax2.set_xticks(x)
    labels = []
    for row in rows:
        mark = " (failed)" if not str(row["status"]).startswith("ok") else ""
        labels.append(f"{row['name']}\n{row['robot']}{mark}")
    ax2.set_xticklabels(labels, rotation=30, ha="right", fontsize=8)
    for tick, row in zip(ax2.get_xticklabels(), rows, strict=True):
        if row["needs_recalibration"]:
            tick.set_color("tab:red")
    for i, row in enumerate(rows):
        if not str(row["status"]).startswith("ok"):
            ax1.text(i, 0.5, "failed", transform=ax1.get_xaxis_transform(), ha="center",
                     va="center", color="tab:red", rotation=90, fontsize=9)  # fmt: skip
    ax1.set_title("Delays and model errors per robot (red: needs a new calibration)", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return write_atomic(path, buf.getvalue())


def fleet_document(
    results: Sequence[RobotResult], settings: FleetSettings, *, manifest_name: str
) -> dict[str, Any]:
    """The document of ``fleet.json``: settings, summary and every robot's numbers
    (deterministic: no wall times, no paths of this run)."""
    rows = fleet_rows(results)
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "manifest": manifest_name,
        "settings": settings.to_dict(),
        "summary": {
            "robots": len(results),
            "ok": sum(r.ok for r in results),
            "failed": [r.name for r in results if not r.ok],
            "needs_recalibration": [row["name"] for row in rows if row["needs_recalibration"]],
        },
        "robots": [r.to_dict() for r in results],
    }


def write_fleet_report(
    out: Path,
    results: Sequence[RobotResult],
    settings: FleetSettings,
    *,
    run: dict[str, Any],
    manifest_name: str,
) -> dict[str, Path]:
    """Write the fleet's files (see the module's docstring) into ``out``; return them by name."""
    rows = fleet_rows(results)
    doc = fleet_document(results, settings, manifest_name=manifest_name)
    cost_rows = [
        {"name": r.name, "stage": stage, **r.costs[stage], "worker": r.worker}
        for r in results
        for stage in STAGES
        if stage in r.costs
    ]
    files = {
        "fleet.csv": _csv(rows, FLEET_COLUMNS),
        "fleet.json": json.dumps(doc, indent=2) + "\n",
        "report.md": _markdown(results, rows, settings),
        "costs.csv": _csv(
            cost_rows, ("name", "stage", "wall_s", "cpu_s", "peak_rss_mb", "read_mb", "worker")
        ),
        "run.json": json.dumps(
            {**run, "robots": {r.name: {"worker": r.worker, "costs": r.costs} for r in results}},
            indent=2,
        )
        + "\n",
    }
    written = {name: write_atomic(out / name, text) for name, text in files.items()}
    written["fleet.png"] = _figure(rows, out / "fleet.png")
    return written
