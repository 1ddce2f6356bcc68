"""Figures and report section of the shape of what is missing
(:func:`jaxlift.estimate_missing_shape`): each signal against time with its band,
against its best explanatory state with the fitted law, and its one-state dependence
curves.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np

from ..analysis.laws import Law
from ..calibrate.shape import MissingShape
from .document import Report
from .figures import new_figure

_LABEL = {"force": "missing force [N]", "flow": "missing flow [cm³/s]"}
_SCALE = {"force": 1.0, "flow": 1e6}  # display units: N, cm^3/s
_STATE_LABEL = {"t": "time [s]", "x": "height [m]", "v": "speed [m/s]",
                "p": "pressure [MPa]", "a": "acceleration [m/s²]", "u": "duty [-]"}  # fmt: skip
_STATE_SCALE = {"p": 1e-6}


def _save(fig, path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return os.fspath(path)


def plot_shape_vs_time(shape: MissingShape, signal: str, path) -> str:
    """``signal`` of every log against time, with its ±2 standard-deviation band."""
    n = len(shape.logs)
    fig, axes = new_figure(n, 1, figsize=(9, 2.4 * n), squeeze=False)
    k = _SCALE[signal]
    for ax, lg in zip(axes[:, 0], shape.logs):
        y, sd = getattr(lg, signal) * k, getattr(lg, signal + "_sd") * k
        ax.fill_between(lg.t, y - 2 * sd, y + 2 * sd, color="C0", alpha=0.25, lw=0,
                        label="±2 sd")  # fmt: skip
        ax.plot(lg.t, y, color="C0", lw=1, label="estimate")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(_LABEL[signal])
        ax.set_title(f"{lg.name}", fontsize=9)
        ax2 = ax.twinx()
        ax2.plot(lg.t, lg.v, color="0.6", lw=0.6)
        ax2.set_ylabel("speed [m/s]", color="0.5")
    axes[0, 0].legend(loc="upper left", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    return _save(fig, path)


def plot_shape_vs_state(shape: MissingShape, signal: str, law: Law, path) -> str:
    """Left: ``signal`` against the state its one-state dependence explains best, with
    the law's prediction. Right: the one-state dependence curves of every state."""
    dep = shape.dependence(signal)
    best = max(dep, key=lambda s: dep[s]["r2"])
    y, sd, st = shape.pooled(signal)
    pred = law.predict(st)
    k = _SCALE[signal]
    fig, axes = new_figure(1, 2, figsize=(11, 4))
    ax = axes[0]
    ks = _STATE_SCALE.get(best, 1.0)
    ax.scatter(st[best] * ks, y * k, s=3, alpha=0.3, color="C0", label="estimate")
    order = np.argsort(st[best])
    ax.scatter(st[best][order] * ks, pred[order] * k, s=2, color="C3", alpha=0.5,
               label=f"law (R² {law.r2:.2f})")  # fmt: skip
    ax.set_xlabel(_STATE_LABEL.get(best, best))
    ax.set_ylabel(_LABEL[signal])
    ax.set_title(f"against {best} (explains {dep[best]['r2']:.0%} alone)", fontsize=9)
    ax.legend(fontsize=8, markerscale=4)
    ax = axes[1]
    for name, d in sorted(dep.items(), key=lambda kv: -kv[1]["r2"]):
        c = np.asarray(d["centers"], float)
        rng = np.ptp(c) or 1.0
        ax.plot((c - c.min()) / rng, np.asarray(d["mean"]) * k, marker=".",
                label=f"{name} (R² {d['r2']:.2f})")  # fmt: skip
    ax.set_xlabel("state, scaled to its range [0, 1]")
    ax.set_ylabel(_LABEL[signal] + ", binned mean")
    ax.set_title("one-state dependence", fontsize=9)
    ax.legend(fontsize=8)
    return _save(fig, path)


def shape_section(rep: Report, shape: MissingShape, figs: pathlib.Path) -> dict:
    """Add "The shape of what is missing" to ``rep`` (figures into ``figs``); returns
    the JSON-ready summary (signals, evidence, laws)."""
    figs.mkdir(parents=True, exist_ok=True)
    laws = shape.laws()
    rep.heading("The shape of what is missing")
    rep.text(
        "The model was given an unknown smooth force on the fork and an unknown smooth "
        "flow into the cylinder, per log, estimated with the fitted parameters held "
        "(iterated Kalman smoother; smoothness chosen by the marginal likelihood; "
        "docs/statistics.md). Evidence = log-likelihood gain of each signal over a "
        f"straight line in time (needed above {shape.EVIDENCE_THRESHOLD:g}). chi2/N "
        "with the signals: "
        + ", ".join(
            f"`{lg.name}` {lg.chi2n_before:.3g} → {lg.chi2n_after:.3g}" for lg in shape.logs
        )  # fmt: skip
        + "."
        + (
            ""
            if shape.with_pressure
            else " The logs carry no pressure: a slowly varying force is seen only through "
            "the dynamics it changes, and its band is wide."
        )  # fmt: skip
    )
    rows = []
    for sig in ("force", "flow"):
        y, _, _ = shape.pooled(sig)
        rows.append({
            "signal": sig, "evidence": shape.evidence[sig],
            "needed": "yes" if shape.needed[sig] else "no",
            "rms": f"{np.sqrt(np.mean(y**2)) * _SCALE[sig]:.3g} "
                   f"{'N' if sig == 'force' else 'cm³/s'}",
            "candidate law": laws[sig].describe(),
        })  # fmt: skip
    rep.table(rows, caption="The two missing signals. The law is a sparse regression over "
              "a library of terms (best subset; a term is kept if it adds at least "
              f"{laws['force'].min_gain:.0%} to R²); terms the model already has are "
              "shifts of its parameters.")  # fmt: skip
    order = [shape.dominant] + [s for s in ("force", "flow") if s != shape.dominant]
    for sig in order:
        if not shape.needed[sig]:
            continue
        rep.figure(plot_shape_vs_time(shape, sig, figs / f"missing_{sig}_time.png"),
                   f"Estimated missing {sig} against time (grey: speed).")  # fmt: skip
        rep.figure(
            plot_shape_vs_state(shape, sig, laws[sig], figs / f"missing_{sig}_state.png"),
            f"Missing {sig} against its best explanatory state, with the law; right: "
            "its binned mean against each state.",
        )
    return {**shape.as_dict(), "dominant": shape.dominant,
            "laws": {k: v.as_dict() for k, v in laws.items()}}  # fmt: skip


def write_shape_csv(shape: MissingShape, path) -> str:
    """The estimated signals and the states they act on, every sample of every log:
    ``log, time_s, force_N, force_sd_N, flow_m3s, flow_sd_m3s, height_m, speed_mps,
    pressure_pa, accel_mps2, pwm``."""
    cols = ("force", "force_sd", "flow", "flow_sd", "x", "v", "p", "a", "u")
    head = ("log,time_s,force_N,force_sd_N,flow_m3s,flow_sd_m3s,height_m,speed_mps,"
            "pressure_pa,accel_mps2,pwm")  # fmt: skip
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(head + "\n")
        for lg in shape.logs:
            arr = np.stack([lg.t, *(getattr(lg, c) for c in cols)], axis=1)
            for row in arr:
                fh.write(lg.name + "," + ",".join(f"{v:.9g}" for v in row) + "\n")
    return os.fspath(path)
