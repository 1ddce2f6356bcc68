"""The fleet report: the fleet at a glance, then each vehicle's trends."""

from __future__ import annotations

import datetime
import math
import pathlib
from collections.abc import Mapping

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.patches import Rectangle

from .document import Report
from .figures import new_figure

_CATS = {"none": 0, "not searched": 0, "effect": 1, "undecided": 2, "unexplained": 3,
         "failed": 4}  # fmt: skip
_COLORS = ["#dfeee0", "#f4a259", "#f6e27f", "#c0392b", "#555555"]


def _cat(row: dict) -> str:
    if row["status"] != "ok":
        return "failed"
    v = row["verdict"]
    return v if v in _CATS else "effect"


def plot_overview(flags: dict, path: pathlib.Path) -> None:
    """Vehicles × dates, coloured by the job's verdict."""
    vehicles = list(flags)
    dates = sorted({r["date"] for f in flags.values() for r in f["rows"]})
    grid = np.full((len(vehicles), len(dates)), np.nan)
    for i, v in enumerate(vehicles):
        for r in flags[v]["rows"]:
            grid[i, dates.index(r["date"])] = _CATS[_cat(r)]
    h = max(2.5, 0.22 * len(vehicles) + 1.2)
    fig, ax = new_figure(figsize=(max(5, 0.6 * len(dates) + 3), h))
    ax.imshow(grid, cmap=ListedColormap(_COLORS), vmin=-0.5, vmax=4.5, aspect="auto")
    ax.set_yticks(range(len(vehicles)), vehicles, fontsize=7)
    ax.set_xticks(range(len(dates)), dates, rotation=60, ha="right", fontsize=7)
    for i, v in enumerate(vehicles):
        for r in flags[v]["rows"]:
            if _cat(r) == "effect":
                ax.text(dates.index(r["date"]), i, r["verdict"][:10], ha="center",
                        va="center", fontsize=5)  # fmt: skip
    handles = [Rectangle((0, 0), 1, 1, color=c) for c in _COLORS]
    ax.legend(handles, ["none", "effect", "undecided", "unexplained", "failed"],
              loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=7)  # fmt: skip
    ax.set_title("verdict per vehicle and date")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def plot_vehicle(vehicle: str, info: dict, path: pathlib.Path, tracked: Mapping) -> None:
    """Air content and the other tracked parameters of one vehicle over time, 90 %
    intervals, with the fitted trend line. ``tracked``: name -> (what, unit, scale, ...)."""
    ok = [r for r in info["rows"] if r["status"] == "ok"]
    dates = [datetime.date.fromisoformat(r["date"]) for r in ok]
    panels = [("air", "air content [% by volume]", 100.0), *[
        (n, f"{t[0]} [{t[1]}]", t[2]) for n, t in tracked.items() if n != "beta"]]  # fmt: skip
    fig, axes = new_figure(1, len(panels), figsize=(4 * len(panels), 3))
    for ax, (name, label, scale) in zip(axes, panels, strict=True):
        y = np.array([r[name] for r in ok], float) * scale
        lo = np.array([r[f"{name}_lo"] for r in ok], float) * scale
        hi = np.array([r[f"{name}_hi"] for r in ok], float) * scale
        err = np.vstack([np.clip(y - lo, 0, None), np.clip(hi - y, 0, None)])
        err = np.where(np.isfinite(err), err, 0.0)
        ax.errorbar(dates, y, yerr=err, fmt="o", capsize=3)
        test = info["tests"].get("beta" if name == "air" else name)
        if name != "air" and test and math.isfinite(test["slope"]):
            d0 = dates[0]
            t = np.array([(d - d0).days / 7 for d in dates])
            yv = np.array([r[name] for r in ok], float)
            good = np.isfinite(yv) & (yv > 0)
            if good.sum() >= 2:
                c = np.mean(np.log(yv[good]) - test["slope"] * t[good])
                ax.plot(dates, np.exp(c + test["slope"] * t) * scale, "--", lw=1,
                        label=f"trend z {test['z']:.1f}")  # fmt: skip
                ax.legend(fontsize=7)
        ax.set_ylabel(label)
        ax.tick_params(axis="x", rotation=45, labelsize=7)
    fig.suptitle(vehicle)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def fleet_report(
    flags: dict, out_dir: str | pathlib.Path, run_info: dict, tracked: Mapping, method: str
) -> Report:
    """Write the figures and ``report.md`` / ``report.html`` into ``out_dir``.
    ``flags``: :func:`jaxlift.fleet.vehicle_flags`; ``tracked``: the tracked
    parameters' descriptions; ``method``: how a vehicle is flagged (a paragraph)."""
    out = pathlib.Path(out_dir)
    figs = out / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    rep = Report("Fleet report")
    n_jobs = sum(len(f["rows"]) for f in flags.values())
    attention = {v: f for v, f in flags.items() if f["flags"]}
    rep.text(
        f"{len(flags)} vehicle(s), {n_jobs} job(s) ({run_info['ran']} run now, "
        f"{run_info['skipped']} finished before, {run_info['failed']} failed). "
        f"{len(attention)} vehicle(s) need attention."
    )
    rep.heading("The fleet at a glance")
    rows = []
    for v, f in flags.items():
        last = f["latest"] or {}
        rows.append({
            "vehicle": v,
            "latest date": last.get("date", "–"),
            "latest verdict": last.get("verdict", "failed"),
            "air [%] (90 %)": (f"{100 * last['air']:.2g} [{100 * last['air_lo']:.2g}, "
                               f"{100 * last['air_hi']:.2g}]") if last else "–",
            "attention": "; ".join(f["flags"]) or "–",
        })  # fmt: skip
    rows.sort(key=lambda r: (r["attention"] == "–", r["vehicle"]))
    rep.table(rows, caption="Vehicles needing attention first. Air content: gas volume "
              "fraction at the mean working pressure implied by the fitted bulk modulus "
              "(all softening attributed to air).")  # fmt: skip
    plot_overview(flags, figs / "overview.png")
    rep.figure(figs / "overview.png", "Verdict of every job.")
    rep.heading("How a vehicle is flagged")
    rep.text(method)
    rep.heading("Vehicles")
    for v, f in flags.items():
        if not f["latest"]:
            rep.heading(v, 3).text("every job failed: " + "; ".join(
                r.get("error", "") for r in f["rows"]))  # fmt: skip
            continue
        rep.heading(v, 3)
        for line in f["flags"] + f["notes"]:
            rep.text(f"- {line}")
        path = figs / f"vehicle_{v}.png"
        plot_vehicle(v, f, path, tracked)
        rep.figure(path, f"{v}: air content and friction over time (90 % intervals).")
    rep.write(out)
    return rep
