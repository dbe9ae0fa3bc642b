"""Figures without pyplot: matplotlib is imported on first use and the user's backend and
pyplot state are never touched (no ``matplotlib.use``, no global figure registry).

``subplots`` mirrors :func:`matplotlib.pyplot.subplots` on a bare
:class:`~matplotlib.figure.Figure`; saving picks the canvas from the file type (Agg for PNG),
so this works headless and inside a user's interactive session alike.
"""

from __future__ import annotations

import os
from typing import Any

from timedexec.errors import ConfigError

__all__ = ["check_figure_format", "subplots"]


def check_figure_format(path: str | os.PathLike[str], label: str = "figure") -> None:
    """Refuse a figure path whose suffix matplotlib cannot write, before any work.

    Raises
    ------
    ConfigError
        Naming ``label``, the path, the suffix and the formats matplotlib writes.
    """
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = os.path.splitext(os.fspath(path))[1].lstrip(".").lower()
    if suffix not in formats:
        raise ConfigError(
            f"{label} {os.fspath(path)}: {('.' + suffix) if suffix else 'no suffix'} is not a "
            f"figure format matplotlib writes; end the name with one of "
            f"{', '.join('.' + f for f in sorted(formats))} (e.g. .png)"
        )


def subplots(*args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """A new figure and its axes: ``subplots(nrows, ncols, figsize=..., sharex=...)``.

    ``figsize`` and ``constrained_layout`` go to the figure, the rest to
    :meth:`matplotlib.figure.Figure.subplots`.
    """
    from matplotlib.figure import Figure

    figsize = kwargs.pop("figsize", None)
    constrained = bool(kwargs.pop("constrained_layout", False))
    fig = Figure(figsize=figsize, layout="constrained" if constrained else None)
    return fig, fig.subplots(*args, **kwargs)
