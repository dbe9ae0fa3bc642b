"""timedexec.report: tables and figures in the published layout (Tables I-II, Figs. 3, 5-10, conveyor)."""

from __future__ import annotations

from timedexec.report._demo import DEMO_STEPS, run_demo
from timedexec.report._figures import (
    fig_boxplots,
    fig_histograms,
    fig_model,
    fig_psd,
    fig_seam,
    fig_trial,
    fig_welding,
)
from timedexec.report._report import (
    build_report,
    delay_summary,
    published_table_markdown,
)

__all__ = [
    "DEMO_STEPS",
    "build_report",
    "delay_summary",
    "fig_boxplots",
    "fig_histograms",
    "fig_model",
    "fig_psd",
    "fig_seam",
    "fig_trial",
    "fig_welding",
    "published_table_markdown",
    "run_demo",
]
