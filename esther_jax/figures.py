"""Figures on their own canvas, written atomically: the one way the library draws.

`figure` makes a `matplotlib.figure.Figure` and its axes without pyplot, so the library
never selects matplotlib's backend (Jupyter's inline backend stays) nor keeps figures
in pyplot's registry; `save_figure` writes it as a PNG through a temporary file, so a
reader never sees half a file.
"""

import pathlib

from matplotlib.figure import Figure

from .files import atomic_output


def figure(*grid: int, figsize: tuple[float, float], **subplots):
    """A figure of `figsize` inches and its axes (`Figure.subplots(*grid, **subplots)`)."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*grid, **subplots)


def save_figure(fig: Figure, path: str | pathlib.Path, dpi: int = 110) -> pathlib.Path:
    """Write `fig` to `path` (PNG, tight bounding box) atomically; returns the path."""
    path = pathlib.Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    return path
