"""The fit report: before/after overlays, zooms, error per regime and stage,
oscillations, residual diagnostics, and the parameter table with standard errors.
"""

from __future__ import annotations

import json
import math
import pathlib
from collections.abc import Sequence

import numpy as np

from ..analysis.oscillation import oscillation_table, zoom_windows
from ..analysis.regimes import error_table, segment_log
from ..calibrate.result import FitResult
from ..model.log import Log
from ..model.params import save_params_json
from .analysis_plots import plot_error_bars, plot_oscillations_vs_height, plot_residuals
from .document import Report, json_safe
from .figures import new_figure
from .plots import plot_overlay


def fit_report(
    result: FitResult,
    metrics: dict,
    fit_logs: Sequence[Log],
    validate_logs: Sequence[Log],
    before_all,
    after_all,
    out_dir: str | pathlib.Path,
) -> tuple[pathlib.Path, pathlib.Path]:
    """Write params.json, metrics.json, figures and report.{md,html} into ``out_dir``."""

    out = pathlib.Path(out_dir)
    figs = out / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    save_params_json(
        out / "params.json",
        result.params,
        comment=f"calibrated by jaxlift fit; effects: {', '.join(result.effects) or 'none'}",
    )
    infos = result.model.param_infos()
    logs = [*fit_logs, *validate_logs]
    rep = Report("jaxlift calibration report")
    rep.text(
        f"Model: baseline{' + ' + ', '.join(result.effects) if result.effects else ''}. "
        f"Fitted logs: {', '.join(f'`{lg.name}`' for lg in fit_logs)}. Held-out logs: "
        f"{', '.join(f'`{lg.name}`' for lg in validate_logs) or 'none'}. "
        f"Free parameters: {', '.join(result.free)}. "
        f"Converged: **{'yes' if result.converged else 'NO'}**."
        + "".join(
            f" Stage {k + 1}: {s.failed_starts} of {len(s.start_chi2)} starts failed "
            "(their simulations did not solve) and were dropped."
            for k, s in enumerate(result.stages)
            if s.failed_starts
        )
    )
    rep.heading("Error before and after estimation")
    rows = []
    for name, lm in metrics["logs"].items():
        for when in ("before", "after"):
            rows.append({"log": name, "role": lm["role"], "model": when, **lm[when]})
    rep.table(
        rows,
        caption="chi2 per sample = mean squared residual in units of the sensor noise "
        "(1 = as good as the sensors allow). Held-out logs were not used in the fit.",
    )
    rep.heading("Parameters (thesis Table 3.1)")
    prow = []
    for name in result.params:
        info = infos[name]
        free = name in result.free
        se = result.stderr.get(name, float("nan"))
        prow.append(
            {
                "parameter": name,
                "unit": info.unit,
                "before": result.initial[name],
                "after": result.params[name],
                "std. error": se if free else None,
                "rel. error": abs(se / result.params[name])
                if free and result.params[name] != 0
                else None,
                "determined": ("no: " + result.undetermined[name])
                if name in result.undetermined
                else ("yes" if free else "fixed"),
            }
        )
    rep.table(
        prow,
        floatfmt=".4g",
        caption=f"Standard errors from the Jacobian at the optimum, inflated by "
        f"{result.inflation:.2f} for the residuals' lag-1 autocorrelation "
        f"({result.rho1:.2f}).",
    )
    if result.undetermined:
        rep.text(
            "Parameters the data cannot determine (do not trust their values): "
            + ", ".join(f"`{k}` ({v})" for k, v in result.undetermined.items())
            + ". Note that the baseline friction law depends on `cf_in` and `cf_out` only "
            "through `cf_out * cf_in^5` at these speeds."
        )
    k = len(result.free)
    corr_rows = [
        {"": result.free[i], **{result.free[j]: float(result.corr[i, j]) for j in range(k)}}
        for i in range(k)
    ]
    rep.table(corr_rows, floatfmt=".2f", caption="Correlation of the estimates.")

    rep.heading("Where the model fails")
    osc_by_label: dict[str, list[dict]] = {"before": [], "after": []}
    err_before, err_after = {}, {}
    for i, log in enumerate(logs):
        b, a = before_all[i], after_all[i]
        role = "fitted" if i < len(fit_logs) else "held-out"
        rep.heading(f"{log.name} ({role})", level=3)
        p = plot_overlay(
            log,
            [("before", b["height"], b["speed"], None), ("after", a["height"], a["speed"], None)],
            figs / f"{log.name}_overlay.png",
            title=f"{log.name} ({role}): model before and after estimation vs measured",
        )
        rep.figure(p, f"{log.name}: whole run (thesis figures 3.5-3.8).")
        segs = segment_log(log)
        for w, (t0, t1) in enumerate(zoom_windows(log, segs)):
            p = plot_overlay(
                log,
                [
                    ("before", b["height"], b["speed"], None),
                    ("after", a["height"], a["speed"], None),
                ],
                figs / f"{log.name}_zoom{w + 1}.png",
                window=(t0, t1),
                title=f"{log.name}: {t0:.0f}-{t1:.0f} s",
            )
            rep.figure(p, f"{log.name}: zoom {t0:.0f}-{t1:.0f} s.")
        tb = error_table(log, b["height"], b["speed"], segments=segs)
        ta = error_table(log, a["height"], a["speed"], segments=segs)
        err_before[log.name], err_after[log.name] = tb, ta
        rep.table(
            [
                {
                    "group": rb["group"],
                    "n": rb["n"],
                    "rms height before [mm]": rb["rms_height_mm"],
                    "rms height after [mm]": ra["rms_height_mm"],
                    "rms speed before [mm/s]": rb["rms_speed_mmps"],
                    "rms speed after [mm/s]": ra["rms_speed_mmps"],
                    "speed bias after [mm/s]": ra["bias_speed_mmps"],
                }
                for rb, ra in zip(tb, ta)
            ],
            caption=f"{log.name}: error per regime and stage (model - measured).",
        )
        if log.speed_mps is not None:
            ob = oscillation_table(log, b["speed"], segs)
            oa = oscillation_table(log, a["speed"], segs)
            osc_by_label["before"].extend(ob)
            osc_by_label["after"].extend(oa)
            rep.table(
                [
                    {
                        "t0 [s]": r["t0"],
                        "regime": r["regime"],
                        "stage": r["stage"],
                        "height [m]": r["height_m"],
                        "f meas [Hz]": r["meas_freq_hz"],
                        "f model [Hz]": r["model_freq_hz"],
                        "amp meas [mm/s]": r["meas_amp_mps"] * 1e3,
                        "amp model [mm/s]": r["model_amp_mps"] * 1e3,
                        "decay meas [1/s]": r["meas_decay_per_s"],
                        "decay model [1/s]": r["model_decay_per_s"],
                    }
                    for r in oa
                ],
                caption=f"{log.name}: oscillations per steady segment, measured vs the "
                "calibrated model (– = no oscillation above the sensor noise).",
            )
            p = plot_residuals(log, a["height"], a["speed"], figs / f"{log.name}_residuals.png")
            rep.figure(
                p,
                f"{log.name}: residuals of the calibrated model: spectrum, autocorrelation, "
                "and against speed, height and pressure. Structure here is what the model "
                "misses.",
            )
    if osc_by_label["after"]:
        p = plot_oscillations_vs_height(osc_by_label, figs / "oscillations_vs_height.png")
        rep.heading("Oscillation frequency and amplitude against height")
        rep.figure(
            p,
            "Measured (black) and model oscillations per steady segment against height. The "
            "thesis saw its model's frequency change with height more than the vehicle's.",
        )
    p = plot_error_bars(
        {"before": _pool(err_before), "after": _pool(err_after)}, figs / "errors.png"
    )
    rep.heading("Errors by regime, all logs")
    rep.figure(p, "RMS error per regime and stage, before and after estimation.")
    with open(out / "metrics.json", "w", encoding="utf-8") as fh:
        json.dump(json_safe(metrics), fh, indent=2)
        fh.write("\n")
    return rep.write(out)


def _pool(tables: dict[str, list[dict]]) -> list[dict]:
    """Pool per-log error tables into one (RMS over samples)."""
    acc: dict[str, dict] = {}
    for rows in tables.values():
        for r in rows:
            a = acc.setdefault(r["group"], {"group": r["group"], "n": 0, "_h": 0.0, "_v": 0.0})
            n = r["n"]
            a["n"] += n
            a["_h"] += n * r["rms_height_mm"] ** 2
            a["_v"] += n * (r["rms_speed_mmps"] ** 2 if np.isfinite(r["rms_speed_mmps"]) else 0)
    out = []
    for a in acc.values():
        n = max(a["n"], 1)
        out.append(
            {
                "group": a["group"],
                "n": a["n"],
                "rms_height_mm": math.sqrt(a["_h"] / n),
                "bias_height_mm": float("nan"),
                "rms_speed_mmps": math.sqrt(a["_v"] / n),
                "bias_speed_mmps": float("nan"),
            }
        )
    return out


def plot_error_steps(rows: list[dict], path) -> str:

    keys = [k for k in rows[0] if k != "model"]
    fig, ax = new_figure(figsize=(8, 4))
    x = np.arange(len(rows))
    for j, k in enumerate(keys):
        y = [r[k] if isinstance(r[k], (int, float)) else np.nan for r in rows]  # failed
        ax.plot(x, y, "o-", label=k, color=f"C{j}")
    ax.set_xticks(x, [r["model"].replace("baseline + ", "+") for r in rows], rotation=15)
    ax.set_yscale("log")
    ax.axhline(1.0, color="0.5", ls="--", lw=0.8)
    ax.set_ylabel("chi2 per sample")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return str(path)
