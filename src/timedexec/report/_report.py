"""One markdown report from results: recordings, delay tables, CV and evaluation JSON."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._files import make_dir
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, RecordingError

__all__ = ["build_report", "delay_summary", "published_table_markdown"]


def _paper_row(delay: str, robot: str, method: str) -> tuple[float, ...] | None:
    """The paper's Table I/II row for this robot's family, or None."""
    from timedexec.learning import PAPER_TABLES

    family = "kuka" if robot.startswith("kr") else "ur"
    return PAPER_TABLES.get(family, {}).get(delay, {}).get(method)


def delay_summary(table: DelayTable) -> dict[str, Any]:
    """Per-joint medians and spreads (ms) and the flagged count."""
    out: dict[str, Any] = {"robots": list(table.robots), "trials": len(table), "joints": {}}
    flags = table["flag"] if "flag" in table else np.full(len(table), "", dtype=object)
    out["flagged"] = int(sum(1 for f in flags if f))
    for j in sorted(set(table["joint"].tolist())):
        m = table["joint"] == j
        row = {}
        for col in ("actuation_delay", "response_delay"):
            v = table[col][m] * 1e3
            v = v[np.isfinite(v)]
            row[col] = {
                "median_ms": float(np.median(v)) if len(v) else float("nan"),
                "p2_5_ms": float(np.percentile(v, 2.5)) if len(v) else float("nan"),
                "p97_5_ms": float(np.percentile(v, 97.5)) if len(v) else float("nan"),
            }
        out["joints"][str(j)] = row
    return out


def published_table_markdown(
    cv: dict[str, Any], robot: str, floor: dict[str, Any] | None = None
) -> str:
    """Table I/II layout: our CV errors (ms) with the published value in parentheses.

    ``floor`` (``{delay: {column: ms}}``, a bundle's ``noise_floor_ms``) adds the replicate
    scatter as a last row: the error no model can beat.
    """
    lines = []
    for delay, title in (
        ("actuation_delay", "Table I — actuation"),
        ("response_delay", "Table II — response"),
    ):
        if delay not in cv:
            continue
        methods = cv[delay]
        first = next(iter(methods.values()))
        cols = list(first)
        lines += [f"**{title} delay: 10-fold CV error (ms), published in parentheses**", ""]
        lines.append(
            "| method | " + " | ".join(f"joint {c}" if c.isdigit() else c for c in cols) + " |"
        )
        lines.append("|---" * (len(cols) + 1) + "|")
        for method, row in methods.items():
            pub = _paper_row(delay, robot, method)
            cells = []
            for k, c in enumerate(cols):
                value = row.get(c)
                cell = "-" if value is None else f"{value:.2f}"
                if pub is not None and k < len(pub):
                    cell += f" ({pub[k]:.2f})"
                cells.append(cell)
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        if floor and delay in floor:
            cells = [f"{floor[delay][c]:.2f}" if c in floor[delay] else "-" for c in cols]
            lines.append("| *noise floor* | " + " | ".join(cells) + " |")
        if delay == "response_delay" and not robot.startswith("kr"):
            lines += ["", "(the paper's UR response table has joint 4 in the joint 5 column)"]
        lines.append("")
    return "\n".join(lines)


def _kind(path: Path) -> str:
    if path.is_dir():
        if (path / "manifest.json").exists():
            return "model"
        raise ConfigError(f"{path}: a folder without manifest.json is not a model bundle")
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return "recording"
    if suffix == ".csv":
        return "table"
    if suffix == ".json":
        data = json.loads(path.read_text())
        if data.get("kind") == "conveyor":
            return "conveyor"
        if "strategies" in data:
            return "evaluation"
        if "actuation_delay" in data:
            return "cv"
        if "added_effects" in data:
            return "discrepancy"
        return "json"
    raise ConfigError(
        f"{path}: cannot tell what this result is (expected .h5 recording, .csv delay table or "
        ".json from train/evaluate/discrepancy/demo, or a model bundle folder)"
    )


def build_report(
    results: Sequence[str | os.PathLike[str]], out_dir: str | os.PathLike[str], *, trial: int = 0
) -> Path:
    """Write ``out_dir/report.md`` with figures (PNG) for the given results.

    Parameters
    ----------
    results : paths
        Any of: recordings (``.h5``: Figs. 3 and 5), delay tables (``.csv``: Figs. 7-10 and
        per-joint statistics), ``train --json`` output (Tables I-II beside the paper),
        ``evaluate --json`` output (strategy table), model bundle folders (Fig. 6, with the
        dots from the last delay table given before it), conveyor results
        (:func:`timedexec.execution.compare_seam_tracking` as JSON).
    out_dir : path
        Created if missing.
    trial : int
        Which recorded trial Fig. 5 shows (row index).
    """
    from timedexec.report._figures import (
        fig_boxplots,
        fig_histograms,
        fig_model,
        fig_psd,
        fig_seam,
        fig_trial,
    )

    out = make_dir(out_dir, "report folder")
    md = ["# timedexec report", ""]
    robot = ""
    table: DelayTable | None = None
    for raw in results:
        path = Path(raw)
        if not path.exists():
            raise RecordingError(f"result {path} does not exist")
        kind = _kind(path)
        stem = path.stem
        if kind == "recording":
            from timedexec.extraction import trial_traces

            traces = trial_traces(path, [trial])
            robot = traces["robot"]
            f3 = fig_psd(traces, out / f"{stem}-fig3-psd.png")
            f5 = fig_trial(traces, out / f"{stem}-fig5-trial.png")
            md += [
                f"## Recording `{path.name}` ({robot})",
                "",
                f"Gyro noise while still, before and after the {traces['cutoff_hz']:.0f} Hz "
                "low-pass filter designed from it:",
                "",
                f"![Fig. 3]({f3.name})",
                "",
                f"Trial {trial}: actuation {traces['actuation_delay'][0] * 1e3:.1f} ms, response "
                f"{traces['response_delay'][0] * 1e3:.1f} ms"
                + (
                    f" (ground truth {traces['truth']['actuation_delay'][0] * 1e3:.1f} / "
                    f"{traces['truth']['response_delay'][0] * 1e3:.1f} ms)"
                    if traces["truth"]
                    else ""
                )
                + ":",
                "",
                f"![Fig. 5]({f5.name})",
                "",
            ]
        elif kind == "table":
            table = DelayTable.read_csv(path)
            robot = robot or table.robots[0]
            summary = delay_summary(table)
            md += [f"## Delay table `{path.name}` ({', '.join(table.robots)}, {len(table):,} trials, "
                   f"{summary['flagged']} flagged)", ""]  # fmt: skip
            md += ["| joint | actuation median (2.5-97.5 %) ms | response median (2.5-97.5 %) ms |",
                   "|---|---|---|"]  # fmt: skip
            for j, row in summary["joints"].items():
                a, r = row["actuation_delay"], row["response_delay"]
                md.append(
                    f"| {j} | {a['median_ms']:.1f} ({a['p2_5_ms']:.1f}-{a['p97_5_ms']:.1f}) | "
                    f"{r['median_ms']:.1f} ({r['p2_5_ms']:.1f}-{r['p97_5_ms']:.1f}) |"
                )
            md.append("")
            for col, fig in (("actuation_delay", 7), ("response_delay", 9)):
                h = fig_histograms(table, out / f"{stem}-fig{fig}-hist.png", col)
                b = fig_boxplots(table, out / f"{stem}-fig{fig + 1}-box.png", col)
                md += [f"![Fig. {fig}]({h.name}) ![Fig. {fig + 1}]({b.name})", ""]
        elif kind == "cv":
            data = json.loads(path.read_text())
            md += [f"## Models: cross-validation `{path.name}`", "",
                   published_table_markdown(data, robot or "ur10"), ""]  # fmt: skip
        elif kind == "evaluation":
            data = json.loads(path.read_text())
            md += [f"## Timed execution on the simulator `{path.name}` ({data.get('robot', '')})", "",
                   "| strategy | onset timing RMS (ms) | seam error at 0.5 m/s (cm) |", "|---|---|---|"]  # fmt: skip
            for name, row in data["strategies"].items():
                md.append(f"| {name} | {row['timing_rms_ms']:.2f} | {row['seam_error_cm']:.3f} |")
            if "coverage_95" in data:
                md += [
                    "",
                    f"95 % bounds cover the true onset in {100 * data['coverage_95']:.1f} % of trials.",
                ]
            md.append("")
        elif kind == "model":
            from timedexec.learning import DelayModel

            model = DelayModel.load(path)
            robot = robot or model.robot
            same = table if table is not None and model.robot in table.robots else None
            f6 = fig_model(model, out / f"{path.name}-fig6-model.png", same)
            md += [f"## Model bundle `{path.name}` ({model.robot}, "
                   f"{model.manifest['training_data']['trials']:,} training trials)", ""]  # fmt: skip
            if model.cv_scores_ms:
                md += [published_table_markdown(model.cv_scores_ms, model.robot,
                                                model.noise_floor_ms), ""]  # fmt: skip
            md += ["Joint 2's predicted delays against the joint 2 and joint 3 angles, "
                   "Gaussian process mean with ±2σ band:", "", f"![Fig. 6]({f6.name})", ""]  # fmt: skip
        elif kind == "conveyor":
            data = json.loads(path.read_text())
            fs = fig_seam(data, out / f"{stem}-seam.png")
            md += [f"## Conveyor tracking `{path.name}` ({data['robot']}, seam at "
                   f"{data['speed_m_s']:g} m/s)", "",
                   "Tool behind the seam along the belt over the cruise (simulator truth; "
                   "believed: the executor's back-dated estimate; negative: ahead):", "",
                   "| run | mean lag (cm) | last 100 ms (cm) | believed (cm) | start shift (ms) |",
                   "|---|---|---|---|---|"]  # fmt: skip
            for name, run in data["runs"].items():
                md.append(
                    f"| {name} | {run['mean_lag_cm']:+.2f} | {run.get('final_lag_cm', math.nan):+.2f} "
                    f"| {run['estimated_mean_lag_cm']:+.2f} | {run['actuation_shift_ms']:.1f} |"
                )
            md += ["", f"![conveyor]({fs.name})", ""]
        else:
            md += [f"## `{path.name}`", "", "```json", path.read_text()[:4000], "```", ""]
    report = out / "report.md"
    report.write_text("\n".join(md))
    return report
