"""Figures without pyplot's global state: jaxlift never switches matplotlib's backend.

A figure made here is a plain :class:`matplotlib.figure.Figure`, not registered with
pyplot, so it needs no closing, saves with any backend (``savefig`` picks its canvas
by the file type) and shows inline in a notebook when returned.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import matplotlib.pyplot as plt
from matplotlib.figure import Figure

_FIGURE_KEYS = ("figsize", "dpi", "layout", "constrained_layout", "tight_layout")


def new_figure(nrows: int = 1, ncols: int = 1, **kwargs: Any) -> tuple[Figure, Any]:
    """Like ``plt.subplots`` (same arguments), without pyplot: ``(figure, axes)``."""
    fig = Figure(**{k: kwargs.pop(k) for k in _FIGURE_KEYS if k in kwargs})
    return fig, fig.subplots(nrows, ncols, **kwargs)


def with_pyplot_figures[T](make: Callable[[], T]) -> T:
    """Run ``make`` (a library plot that draws through pyplot, as ArviZ's do) and close
    exactly the pyplot figures it opened, leaving the user's own figures alone."""
    before = set(plt.get_fignums())
    try:
        return make()
    finally:
        for num in set(plt.get_fignums()) - before:
            plt.close(num)
