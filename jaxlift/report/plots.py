"""Figures: model against measurement, saved as PNG (no pyplot state, see :mod:`.figures`)."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..model.log import Log
from .figures import new_figure


def plot_overlay(
    log: Log,
    sims: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]],
    path: str | os.PathLike,
    *,
    window: tuple[float, float] | None = None,
    title: str | None = None,
) -> str:
    """Height, speed (and pressure, where logged or simulated) of a log with one or more
    simulations on top, against time. ``sims`` holds ``(label, height_m, speed_mps,
    pressure_pa or None)`` at the log's time stamps. Returns the PNG path."""
    t = log.time_s
    has_p = log.pressure_pa is not None or any(s[3] is not None for s in sims)
    nrows = 4 if has_p else 3
    fig, axes = new_figure(nrows, 1, figsize=(11, 2.4 * nrows), sharex=True)
    m = slice(None)
    if window is not None:
        m = (t >= window[0]) & (t <= window[1])
    axes[0].plot(t[m], log.height_m[m], "k.", ms=1.5, label="measured")
    if log.speed_mps is not None:
        axes[1].plot(t[m], log.speed_mps[m], color="0.55", lw=0.6, label="measured")
    if log.pressure_pa is not None:
        axes[2].plot(t[m], log.pressure_pa[m] / 1e6, color="0.55", lw=0.6, label="measured")
    for i, (label, h, v, p) in enumerate(sims):
        color = f"C{i}"
        axes[0].plot(t[m], np.asarray(h)[m], color=color, lw=1.0, label=label)
        axes[1].plot(t[m], np.asarray(v)[m], color=color, lw=0.9, label=label)
        if p is not None and has_p:
            axes[2].plot(t[m], np.asarray(p)[m] / 1e6, color=color, lw=0.9, label=label)
    axes[-1].plot(t[m], log.pwm[m], color="C3", lw=0.9)
    axes[0].set_ylabel("height [m]")
    axes[1].set_ylabel("speed [m/s]")
    if has_p:
        axes[2].set_ylabel("pressure [MPa]")
    axes[-1].set_ylabel("pwm [-]")
    axes[-1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[1].legend(loc="upper left", fontsize=8)
    fig.suptitle(title or log.name)
    fig.align_ylabels(axes)  # tick labels of different widths left the labels ragged
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return os.fspath(path)
