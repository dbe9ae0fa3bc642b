"""One markdown report from results: recordings, delay tables, CV and evaluation JSON."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from timedexec._files import check_input_kind, check_paths, make_dir, write_atomic
from timedexec.delays import DelayTable
from timedexec.errors import ConfigError, RecordingError, TimedExecError

__all__ = ["build_report", "delay_summary", "published_table_markdown"]


def _paper_row(delay: str, family: str | None, method: str) -> tuple[float, ...] | None:
    """The paper's Table I/II row for a robot family (``paper_family``), or None."""
    from timedexec.learning import PAPER_TABLES

    return PAPER_TABLES.get(family or "", {}).get(delay, {}).get(method)


def delay_summary(table: DelayTable) -> dict[str, Any]:
    """Per-joint medians and spreads (ms), the flagged count and the valid counts.

    ``valid`` (overall and per joint and delay) counts the trials with a finite delay;
    where it is 0 the statistics are NaN and the report says "no valid trials" instead.
    ``flag_reasons`` counts the trials per flag text.
    """
    out: dict[str, Any] = {"robots": list(table.robots), "trials": len(table), "joints": {}}
    flags = table["flag"] if "flag" in table else np.full(len(table), "", dtype=object)
    out["flagged"] = int(sum(1 for f in flags if f))
    reasons: dict[str, int] = {}
    for f in flags:
        if f:
            reasons[str(f)] = reasons.get(str(f), 0) + 1
    out["flag_reasons"] = dict(sorted(reasons.items(), key=lambda kv: -kv[1]))
    finite = np.isfinite(table["actuation_delay"]) | np.isfinite(table["response_delay"])
    out["valid"] = int(np.sum(finite))
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
                "valid": len(v),
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
    from timedexec.learning import paper_family

    family = paper_family(robot)
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
            pub = _paper_row(delay, family, method)
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
        if delay == "response_delay" and family == "ur":
            lines += ["", "(the paper's UR response table has joint 4 in the joint 5 column)"]
        lines.append("")
    return "\n".join(lines)


def _kind(path: Path) -> tuple[str, Any]:
    """What the result at ``path`` is, and its JSON document for ``.json`` files."""
    if path.is_dir():
        if (path / "manifest.json").exists():
            return "model", None
        raise ConfigError(f"{path}: a folder without manifest.json is not a model bundle")
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return "recording", None
    if suffix == ".csv":
        return "table", None
    if suffix == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{path}: not a UTF-8 text file ({exc}); give the .json a "
                              "timedexec command wrote") from None  # fmt: skip
        except json.JSONDecodeError as exc:
            raise ConfigError(
                f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno}); "
                "give the .json a timedexec command wrote (train/evaluate/discrepancy --json, "
                "the demo's evaluation.json or conveyor.json)"
            ) from None
        if not isinstance(data, dict):
            return "json", data
        if data.get("kind") == "conveyor":
            return "conveyor", data
        if "strategies" in data:
            return "evaluation", data
        if "actuation_delay" in data:
            return "cv", data
        if "added_effects" in data:
            return "discrepancy", data
        if "arl0_moves" in data and "joints" in data:
            return "monitor", data
        return "json", data
    raise ConfigError(
        f"{path}: cannot tell what this result is (expected .h5 recording, .csv delay table or "
        ".json from train/evaluate/discrepancy/demo, or a model bundle folder)"
    )


def _unique_stem(path: Path, kind: str, used: set[str]) -> str:
    """A figure-name stem of its own for every input: the file's stem (a bundle: its folder
    name), else prefixed with its folder's name, else numbered (``a/delays.csv`` and
    ``b/delays.csv`` give ``delays`` and ``b-delays``)."""
    base = path.name if kind == "model" else path.stem
    candidates = [base]
    parent = path.absolute().parent.name
    if parent:
        candidates.append(f"{parent}-{base}")
    candidates += [f"{base}-{k}" for k in range(2, len(used) + 3)]
    stem = next(c for c in candidates if c not in used)
    used.add(stem)
    return stem


#: The figures drawn for each kind of result: (key, file-name suffix).
_FIGURES = {
    "recording": (("f3", "fig3-psd"), ("f5", "fig5-trial")),
    "table": (
        ("f7", "fig7-hist"),
        ("f8", "fig8-box"),
        ("f9", "fig9-hist"),
        ("f10", "fig10-box"),
    ),
    "model": (("f6", "fig6-model"),),
    "conveyor": (("seam", "seam"),),
    "monitor": (("monitor", "monitor"),),
}


def _recording_trials(path: Path, trial: int) -> None:
    """Refuse a ``trial`` that is not a row of the recording, naming the valid range."""
    from timedexec.recording import RecordingReader

    with RecordingReader(path) as reader:
        n = int(reader.n_trials)
    if n == 0:
        raise ConfigError(f"{path}: the recording holds no trial yet; nothing to show in Fig. 5")
    if not 0 <= trial < n:
        raise ConfigError(
            f"trial {trial} is not a trial of {path}: it holds {n} trials, rows 0 .. {n - 1}; "
            f"choose one in that range (report --trial)"
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
        (:func:`timedexec.tasks.compare_seam_tracking` as JSON), ``monitor --json``
        output (per-joint state, alarms and the CUSUM figure).
    out_dir : path
        Created if missing.
    trial : int
        Which recorded trial Fig. 5 shows (row index, ``0 .. n - 1``).

    Every input gets figure names of its own (two ``delays.csv`` from different folders
    give two sets of figures); every input is read and checked before anything is written,
    and no output may be an input or anything but a regular file
    (:func:`timedexec._files.check_paths`).

    Raises
    ------
    RecordingError
        A result that does not exist.
    ConfigError
        A result of unknown kind, malformed JSON, a ``trial`` outside the recordings' rows,
        or an output path the policy refuses.
    """
    if isinstance(trial, bool) or not isinstance(trial, int | np.integer):
        raise ConfigError(f"trial {trial!r} must be an integer row index (report --trial)")
    out = Path(out_dir)
    plan: list[tuple[Path, str, str, Any, dict[str, Path]]] = []
    used: set[str] = set()
    for raw in results:
        path = Path(raw)
        if not path.exists():
            raise RecordingError(f"result {path} does not exist")
        check_input_kind(path, "result")
        kind, data = _kind(path)
        if kind == "recording":
            _recording_trials(path, int(trial))
        stem = _unique_stem(path, kind, used)
        figures = {key: out / f"{stem}-{suffix}.png" for key, suffix in _FIGURES.get(kind, ())}
        # a heading as unique as the figures: the name, else the path as given
        title = path.name if stem == (path.name if kind == "model" else path.stem) else str(path)
        plan.append((path, title, kind, data, figures))
    if trial < 0 and not any(kind == "recording" for _, _, kind, *_ in plan):
        raise ConfigError(f"trial {trial} must be a row index >= 0 (report --trial)")
    outputs = {f"figure {p.name}": p for *_, figs in plan for p in figs.values()}
    check_paths(
        inputs={f"result {p}": p for p, *_ in plan},
        outputs={**outputs, "report": out / "report.md"},
        folders={"report folder": out},
    )
    out = make_dir(out, "report folder")
    md = ["# timedexec report", ""]
    state: dict[str, Any] = {"robot": "", "table": None}
    for path, title, kind, data, figures in plan:
        try:
            md += _section(path, title, kind, data, figures, int(trial), state)
        except (TimedExecError, OSError):
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise ConfigError(
                f"{path}: not a complete {kind} result ({type(exc).__name__}: {exc}); give "
                "the file as the timedexec command wrote it"
            ) from exc
    return write_atomic(out / "report.md", "\n".join(md))


def _table_lines(title: str, table: DelayTable, figures: dict[str, Path]) -> list[str]:
    """The delay table's section: per-joint statistics and Figs. 7-10, or the line that
    says no trial is valid (and no empty figure)."""
    from timedexec.report._figures import fig_boxplots, fig_histograms

    summary = delay_summary(table)
    md = [f"## Delay table `{title}` ({', '.join(table.robots)}, {len(table):,} trials, "
          f"{summary['flagged']} flagged)", ""]  # fmt: skip
    if summary["valid"] == 0:
        reasons = summary["flag_reasons"]
        why = "; ".join(f"{r} ({n})" for r, n in reasons.items()) or "no finite delays"
        return [*md, f"No valid trials: none of the {len(table):,} trials has a measured "
                f"delay (flags: {why}); nothing to summarise or plot.", ""]  # fmt: skip
    md += ["| joint | actuation median (2.5-97.5 %) ms | response median (2.5-97.5 %) ms |",
           "|---|---|---|"]  # fmt: skip
    for j, row in summary["joints"].items():
        cells = []
        for col in ("actuation_delay", "response_delay"):
            c = row[col]
            cells.append(
                f"{c['median_ms']:.1f} ({c['p2_5_ms']:.1f}-{c['p97_5_ms']:.1f})"
                if c["valid"]
                else "no valid trials"
            )
        md.append(f"| {j} | {cells[0]} | {cells[1]} |")
    md.append("")
    for col, fig in (("actuation_delay", 7), ("response_delay", 9)):
        h = fig_histograms(table, figures[f"f{fig}"], col)
        b = fig_boxplots(table, figures[f"f{fig + 1}"], col)
        md += [f"![Fig. {fig}]({h.name}) ![Fig. {fig + 1}]({b.name})", ""]
    return md


def _monitor_lines(title: str, data: dict[str, Any], figure: Path) -> list[str]:
    """The delay monitor's section (``timedexec monitor --json``): per joint its state and
    shift, the alarms, and the CUSUM figure."""
    from timedexec.monitoring import describe_alert, monitor_figure

    monitor_figure(data, figure)
    md = [f"## Delay monitor `{title}`", "",
          f"Per-joint CUSUM of each move's observed lag against the model; threshold "
          f"{data['threshold']:.2f}, set for 1 false alarm per {data['arl0_moves']:,.0f} moves "
          f"per joint; the first {data['warmup_moves']} moves of each joint are the "
          "warm-up the shift is measured from.", "",
          "| joint | state | moves | gap to model (ms) | shift since warm-up (ms) |",
          "|---|---|---|---|---|"]  # fmt: skip

    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:+.2f}"

    for j in data["joints"]:
        md.append(f"| {j['joint']} | {j['status']} | {j['moves']} | "
                  f"{ms(j.get('gap_to_model_ms'))} | {ms(j.get('shift_ms'))} |")  # fmt: skip
    md.append("")
    for a in data["alerts"]:
        kind = "Common shift" if a.get("test") == "common" else "Alarm"
        cmd = a["recalibrate"]["command"]  # as code: it holds ** and quotes
        md.append(f"- **{kind}**: {describe_alert(a).replace(cmd, f'`{cmd}`')}")
    if not data["alerts"]:
        md.append("No alarm.")
    return [*md, "", f"![delay monitor]({figure.name})", ""]


def _section(
    path: Path,
    title: str,
    kind: str,
    data: Any,
    figures: dict[str, Path],
    trial: int,
    state: dict[str, Any],
) -> list[str]:
    """The markdown (and figures) of one result; ``state`` carries the robot and the last
    delay table to the results after it."""
    from timedexec.report._figures import fig_model, fig_psd, fig_seam, fig_trial

    md: list[str] = []
    if kind == "recording":
        from timedexec.extraction import trial_traces

        traces = trial_traces(path, [trial])
        state["robot"] = traces["robot"]
        f3 = fig_psd(traces, figures["f3"])
        f5 = fig_trial(traces, figures["f5"])
        md += [
            f"## Recording `{title}` ({traces['robot']})",
            "",
            *([f"**{traces['damage_note']}.**", ""] if "damage_note" in traces else []),
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
        state["table"] = table
        state["robot"] = state["robot"] or table.robots[0]
        md += _table_lines(title, table, figures)
    elif kind == "cv":
        md += [f"## Models: cross-validation `{title}`", "",
               published_table_markdown(data, state["robot"] or "ur10"), ""]  # fmt: skip
    elif kind == "evaluation":
        md += [f"## Timed execution on the simulator `{title}` ({data.get('robot', '')})", "",
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
        state["robot"] = state["robot"] or model.robot
        table = state["table"]
        same = table if table is not None and model.robot in table.robots else None
        f6 = fig_model(model, figures["f6"], same)
        md += [f"## Model bundle `{title}` ({model.robot}, "
               f"{model.manifest['training_data']['trials']:,} training trials)", ""]  # fmt: skip
        if model.cv_scores_ms:
            md += [published_table_markdown(model.cv_scores_ms, model.robot,
                                            model.noise_floor_ms), ""]  # fmt: skip
        md += ["Joint 2's predicted delays against the joint 2 and joint 3 angles, "
               "Gaussian process mean with ±2σ band:", "", f"![Fig. 6]({f6.name})", ""]  # fmt: skip
    elif kind == "conveyor":
        fs = fig_seam(data, figures["seam"])
        md += [f"## Conveyor tracking `{title}` ({data['robot']}, seam at "
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
    elif kind == "monitor":
        md += _monitor_lines(title, data, figures["monitor"])
    else:
        text = path.read_text(encoding="utf-8", errors="replace")[:4000]
        md += [f"## `{title}`", "", "```json", text, "```", ""]
    return md
