"""Figures without pyplot: matplotlib is imported on first use and the user's backend and
pyplot state are never touched (no ``matplotlib.use``, no global figure registry).

``subplots`` mirrors :func:`matplotlib.pyplot.subplots` on a bare
:class:`~matplotlib.figure.Figure`; saving picks the canvas from the file type (Agg for PNG),
so this works headless and inside a user's interactive session alike.
"""

from __future__ import annotations

from typing import Any

__all__ = ["subplots"]


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
