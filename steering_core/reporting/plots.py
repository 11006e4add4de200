"""Matplotlib figures written as files only (no pyplot state, no display), shared by the phase reports."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from steering_core.storage.fileio import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DPI = 120


def figure(figsize: tuple[float, float]) -> Figure:
    """Return a new figure on the Agg canvas: files only, no pyplot state, no display."""
    # imported here: matplotlib costs most of a second, which every CLI start would pay
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: Path) -> None:
    """Save a figure atomically as PNG (no timestamp in the metadata: same figure, same bytes)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI, bbox_inches="tight")
