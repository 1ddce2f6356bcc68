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


#: The state each library term is read against (for the figures).
_TERM_STATE = {"1": "t", "sign(v)": "v", "v": "v", "v|v|": "v", "v^3": "v", "v^5": "v",
               "p": "p", "p sign(v)": "p", "sqrt(p)": "p", "x": "x", "x sign(v)": "x",
               "u": "u", "a": "a", "t": "t"}  # fmt: skip


def plot_shape_vs_state(shape: MissingShape, signal: str, law: Law, path) -> str:
    """``signal`` against each state (scatter, lifting in blue, the rest in grey), with
    the law's prediction (red); the leading term's state first. Each panel's title
    gives the share of the signal's variance that state's binned mean explains alone
    (on a trajectory, a state that changes slowly also stands for time)."""
    dep = shape.dependence(signal)
    y, _, st = shape.pooled(signal)
    pred = law.predict(st)
    k = _SCALE[signal]
    first = _TERM_STATE.get(law.leading, "t")
    order = [first] + [n for n in ("v", "p", "x", "u", "a", "t") if n != first]
    fig, axes = new_figure(2, 3, figsize=(12, 6.5))
    moving = np.abs(st["v"]) > 2e-3
    for ax, name in zip(axes.ravel(), order):
        ks = _STATE_SCALE.get(name, 1.0)
        xs = st[name] * ks
        ax.scatter(xs[~moving], y[~moving] * k, s=2, color="0.6", alpha=0.4, label="at rest")
        ax.scatter(xs[moving], y[moving] * k, s=2, color="C0", alpha=0.4, label="moving")
        ax.scatter(xs, pred * k, s=1, color="C3", alpha=0.5, label="law")
        r2 = dep.get(name, {}).get("r2", float("nan"))
        lead = " (leading term)" if name == first else ""
        ax.set_title(f"{name}{lead}: binned mean explains {r2:.0%}", fontsize=9)
        ax.set_xlabel(_STATE_LABEL.get(name, name))
        ax.set_ylabel(_LABEL[signal])
    axes[0, 0].legend(fontsize=7, markerscale=4)
    fig.suptitle(f"missing {signal} against the states; law: R² {law.r2:.2f}", fontsize=10)
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
        "docs/statistics.md). Where the duty changes, both may also step: "
        + (
            "the marginal likelihood chose no steps"
            if not np.isfinite(shape.log10_q_jump)
            else f"the marginal likelihood chose steps of log10 q_J = {shape.log10_q_jump:.0f}"
        )
        + ". Evidence = log-likelihood gain of each signal over a "
        f"straight line in time without steps (needed above {shape.EVIDENCE_THRESHOLD:g}). "
        "chi2/N "
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
            "candidate law": laws[sig].describe() if shape.needed[sig] else "(not needed)",
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
            f"Missing {sig} against each state (the law's leading term's first), with "
            "the law's prediction in red.",
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
