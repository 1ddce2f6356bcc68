"""Plots of the analyses of :mod:`jaxlift.analysis`: oscillations against height,
residuals (time, spectrum, autocorrelation), error per regime and stage.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np

from ..analysis.regimes import X_S_DEFAULT, Array1, check_len
from ..analysis.residuals import residual_diagnostics
from ..model.log import Log
from .figures import new_figure

# ----------------------------------------------------------------------------------------------
# plots


def _save(fig, path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return os.fspath(path)


_REGIME_MARKER = {"slow": "o", "fast": "s"}


def plot_oscillations_vs_height(
    rows_by_label: Mapping[str, Sequence[dict]], path: str | os.PathLike
) -> str:
    """Oscillation frequency (top) and amplitude (bottom) against mean height [m].

    ``rows_by_label`` maps a model label (e.g. ``"before"``, ``"after"``) to rows of
    :func:`oscillation_table`.  Measured values are black (taken once, from the rows of all
    labels, duplicates removed), each model in its own colour; circles are slow segments,
    squares fast ones; hollow markers are amplitudes of segments below the noise floor (no
    frequency).  Frequency in Hz, amplitude in mm/s; the dashed line is the measured noise
    floor as an amplitude.  Returns the PNG path.
    """
    fig, (ax_f, ax_a) = new_figure(2, 1, figsize=(8, 7), sharex=True)

    def draw(rows, prefix, color, label):
        for regime, marker in _REGIME_MARKER.items():
            rr = [r for r in rows if r["regime"] == regime]
            if not rr:
                continue
            hgt = np.array([r["height_m"] for r in rr])
            fr = np.array([r[f"{prefix}_freq_hz"] for r in rr], dtype=float)
            am = np.array([r[f"{prefix}_amp_mps"] for r in rr], dtype=float) * 1e3
            det = np.isfinite(fr)
            lab = f"{label} ({regime})"
            ax_f.plot(hgt[det], fr[det], marker, color=color, ls="none", ms=6, label=lab)
            ax_a.plot(hgt[det], am[det], marker, color=color, ls="none", ms=6, label=lab)
            ax_a.plot(hgt[~det], am[~det], marker, mfc="none", mec=color, ls="none", ms=6)

    seen = set()
    meas = []
    for rows in rows_by_label.values():
        for r in rows:
            key = (round(r["t0"], 6), round(r["t1"], 6), round(r["height_m"], 6))
            if key not in seen:
                seen.add(key)
                meas.append(r)
    draw(meas, "meas", "k", "measured")
    for i, (label, rows) in enumerate(rows_by_label.items()):
        draw(rows, "model", f"C{i}", label)
    floors = [r["noise_floor_mps"] for r in meas if "noise_floor_mps" in r]
    if floors:
        # amplitude of a sinusoid that just reaches the floor is about sqrt(2) x floor
        ax_a.axhline(math.sqrt(2) * max(floors) * 1e3, color="0.5", ls="--", lw=0.8)
    for x in X_S_DEFAULT:
        ax_f.axvline(x, color="0.7", lw=0.8)
        ax_a.axvline(x, color="0.7", lw=0.8)
    ax_f.set_ylabel("frequency [Hz]")
    ax_a.set_ylabel("amplitude [mm/s]")
    ax_a.set_xlabel("mean height [m]")
    for ax in (ax_f, ax_a):
        ax.grid(alpha=0.3)
    handles, labels = ax_f.get_legend_handles_labels()
    if handles:
        ax_f.legend(fontsize=8, ncol=2)
    ax_f.set_title("oscillations of the speed in steady moving segments")
    return _save(fig, path)


def _binned_mean(x: np.ndarray, y: np.ndarray, nbins: int = 30) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0 or np.ptp(x) == 0:
        return np.array([]), np.array([])
    edges = np.linspace(x.min(), x.max(), nbins + 1)
    k = np.clip(np.digitize(x, edges) - 1, 0, nbins - 1)
    cnt = np.bincount(k, minlength=nbins)
    s = np.bincount(k, weights=y, minlength=nbins)
    keep = cnt >= 5
    centers = 0.5 * (edges[1:] + edges[:-1])
    return centers[keep], s[keep] / cnt[keep]


def plot_residuals(
    log: Log,
    height: Array1,
    speed: Array1,
    path: str | os.PathLike,
    pressure: Array1 | None = None,
) -> str:
    """Residual diagnostics on a 2×3 grid, residual = model − measured speed [mm/s] (the
    height residual [mm] when the log has no speed): against time; its spectrum (Welch,
    log scale); the autocorrelation of the scaled speed and height residuals; against the
    simulated speed [m/s] (not the measured one: its noise is in the residual too, which
    would draw a spurious slope of -1), the measured height [m], and the pressure [MPa]
    (simulated when given, else logged).  Scatter plots carry binned means (red).  Returns
    the PNG path."""
    h = check_len(log, "height", height)
    v = check_len(log, "speed", speed)
    diag = residual_diagnostics(log, h, v)
    t = log.time_s
    if log.speed_mps is not None:
        res = (v - log.speed_mps) * 1e3
        rname, runit, key = "speed residual", "mm/s", "speed"
    else:
        res = (h - log.height_m) * 1e3
        rname, runit, key = "height residual", "mm", "height"
    fig, axes = new_figure(2, 3, figsize=(14, 7.5))

    ax = axes[0, 0]
    ax.plot(t, res, lw=0.4, color="C0")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"{rname} [{runit}]")

    ax = axes[0, 1]
    f, p = diag[key]["freqs_hz"], diag[key]["power"]
    sig = diag[key]["sigma"] * 1e3
    ax.semilogy(f[1:], p[1:] * sig**2, lw=0.8, color="C0", label="residual")
    ax.axhline(2 * log.sample_period * sig**2, color="0.5", ls="--", lw=0.8, label="sensor noise")
    ax.set_xlim(0.0, min(f[-1], 20.0))
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"PSD [({runit})²/Hz]")
    ax.legend(fontsize=8)

    ax = axes[0, 2]
    for name, d in diag.items():
        if name == "pressure":
            continue
        ax.plot(d["lags_s"], d["acf"], lw=0.9, label=f"{name} (ρ1 = {d['rho1']:.2f})")
    bound = 2.0 / math.sqrt(log.n)
    ax.axhspan(-bound, bound, color="0.85")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("lag [s]")
    ax.set_ylabel("autocorrelation [-]")
    ax.legend(fontsize=8)

    xs = [
        (v, "simulated speed [m/s]"),
        (np.asarray(log.height_m), "measured height [m]"),
    ]
    if pressure is not None:
        xs.append((check_len(log, "pressure", pressure) * 1e-6, "simulated pressure [MPa]"))
    elif log.pressure_pa is not None:
        xs.append((np.asarray(log.pressure_pa) * 1e-6, "measured pressure [MPa]"))
    else:
        xs.append((None, "pressure"))
    for ax, (x, xl) in zip(axes[1], xs, strict=True):
        if x is None:
            ax.text(0.5, 0.5, "no pressure", ha="center", va="center", transform=ax.transAxes)
            ax.set_xticks([])
            ax.set_yticks([])
            continue
        ax.plot(x, res, ",", color="C0", alpha=0.4)
        bx, by = _binned_mean(x, res)
        ax.plot(bx, by, "-", color="C3", lw=1.2)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(xl)
        ax.set_ylabel(f"{rname} [{runit}]")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    fig.suptitle(f"{log.name}: residuals (model − measured)")
    return _save(fig, path)


def plot_error_bars(
    table_by_label: Mapping[str, Sequence[dict]],
    path: str | os.PathLike,
    *,
    noise_speed_mmps: float | None = None,
    noise_height_mm: float | None = None,
) -> str:
    """Grouped bars of the RMS speed error [mm/s] (top) and RMS height error [mm] (bottom) per
    group of :func:`error_table`, one bar colour per label (e.g. ``"before"``, ``"after"``).
    Groups are listed in the order they first appear.  ``noise_speed_mmps`` /
    ``noise_height_mm``: sensor noise σ, drawn as a dashed line (the RMS error of a perfect
    model).  Returns the PNG path."""
    groups: list[str] = []
    for rows in table_by_label.values():
        for r in rows:
            if r["group"] not in groups:
                groups.append(r["group"])
    labels = list(table_by_label)
    nl = max(1, len(labels))
    x = np.arange(len(groups))
    width = 0.8 / nl
    fig, axes = new_figure(2, 1, figsize=(max(7, 0.9 * len(groups) + 2), 6.5), sharex=True)
    for ax, key, unit, noise in (
        (axes[0], "rms_speed_mmps", "RMS speed error [mm/s]", noise_speed_mmps),
        (axes[1], "rms_height_mm", "RMS height error [mm]", noise_height_mm),
    ):
        if noise is not None:
            ax.axhline(noise, color="0.3", ls="--", lw=0.9, label="sensor noise")
        for i, label in enumerate(labels):
            by_group = {r["group"]: r.get(key, math.nan) for r in table_by_label[label]}
            vals = np.array([by_group.get(g, math.nan) for g in groups], dtype=float)
            ax.bar(x + (i - (nl - 1) / 2) * width, np.nan_to_num(vals), width, label=label)
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    axes[1].set_xticks(x, groups, rotation=30, ha="right")
    return _save(fig, path)
