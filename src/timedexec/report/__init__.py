"""timedexec.report: tables and figures in the published layout (Tables I-II, Figs. 3, 5-10)."""

from __future__ import annotations

from timedexec.report._figures import fig_boxplots, fig_histograms, fig_psd, fig_trial
from timedexec.report._report import (
    PUBLISHED_TABLES,
    build_report,
    delay_summary,
    published_table_markdown,
)

__all__ = [
    "PUBLISHED_TABLES",
    "build_report",
    "delay_summary",
    "fig_boxplots",
    "fig_histograms",
    "fig_psd",
    "fig_trial",
    "published_table_markdown",
]
