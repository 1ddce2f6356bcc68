"""Whole jobs behind the command line (and the notebooks): fit-and-report.

Each job writes into one output directory: ``params.json`` (MODEL.md names),
``metrics.json`` (machine-readable), ``figures/*.png`` and ``report.md`` +
``report.html``.
"""

from __future__ import annotations

import json
import math
import pathlib
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import numpy as np

from . import _analysis as an
from ._fit import FitResult, estimate_x0_offsets, fit
from ._log import Log
from ._model import all_param_infos, with_params
from ._plant import Plant
from ._plots import plot_overlay
from ._report import Report
from ._simulate import Inputs, make_effects, simulate

__all__ = ["simulate_logs", "run_fit", "fit_report"]


def simulate_logs(
    params: Mapping[str, float],
    effects: Sequence[str],
    logs: Sequence[Log],
    x0_offsets: Mapping[str, float] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Simulate every log's input with the given model; arrays at the log's times.
    ``x0_offsets`` [m] shift the initial height of the named logs (a fit's estimates).
    Raises :class:`~jaxlift.SimulationError` if a simulation fails."""
    effs = make_effects(effects)
    own = {k: v for k, v in params.items() if k in all_param_infos(effs)}
    plant, effs = with_params(Plant(), effs, own)
    out = []
    for log in logs:
        inputs = Inputs.from_log(log)
        off = (x0_offsets or {}).get(log.name, 0.0)
        inputs = eqx.tree_at(lambda i: i.x0, inputs, inputs.x0 + off)
        sol = simulate(plant, effs, inputs)
        sol.check(f"simulating {log.path or log.name}")
        out.append(
            {
                "height": np.asarray(sol.height),
                "speed": np.asarray(sol.speed),
                "pressure": np.asarray(sol.pressure),
            }
        )
    return out


def _chi2n(log: Log, sim: dict[str, np.ndarray]) -> float:
    from ._measurement import MeasurementModel

    s = MeasurementModel().sigmas(log.sample_period)
    parts = [((sim["height"] - log.height_m) / s["height_m"]) ** 2]
    if log.speed_mps is not None:
        parts.append(((sim["speed"] - log.speed_mps) / s["speed_mps"]) ** 2)
    if log.pressure_pa is not None:
        parts.append(((sim["pressure"] - log.pressure_pa) / s["pressure_pa"]) ** 2)
    return float(np.mean(np.concatenate(parts)))


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def _log_metrics(log: Log, sim: dict[str, np.ndarray]) -> dict[str, float]:
    m = {
        "chi2_per_sample": _chi2n(log, sim),
        "rms_height_mm": _rms(sim["height"] - log.height_m) * 1e3,
    }
    if log.speed_mps is not None:
        m["rms_speed_mmps"] = _rms(sim["speed"] - log.speed_mps) * 1e3
    if log.pressure_pa is not None:
        m["rms_pressure_MPa"] = _rms(sim["pressure"] - log.pressure_pa) / 1e6
    return m


def run_fit(
    fit_logs: Sequence[Log],
    validate_logs: Sequence[Log] = (),
    *,
    effects: Sequence[str] = (),
    free: str | Sequence[str] = "all",
    init: Mapping[str, float] | None = None,
    staged: bool = True,
    n_starts: int = 4,
    seed: int = 0,
    out_dir: str | pathlib.Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> tuple[FitResult, dict]:
    """Fit, compare before/after on fitted and held-out logs, and (if ``out_dir``)
    write params.json, metrics.json, figures and the report. Returns the fit and the
    metrics dictionary."""
    result = fit(
        fit_logs,
        effects=effects,
        free=free,
        init=init,
        staged=staged,
        n_starts=n_starts,
        seed=seed,
        progress=progress,
    )
    metrics = {
        "effects": result.effects,
        "free": result.free,
        "converged": result.converged,
        "chi2": result.chi2,
        "n_residuals": result.n_residuals,
        "residual_lag1_autocorrelation": result.rho1,
        "stderr_inflation": result.inflation,
        "params": result.params,
        "stderr": result.stderr,
        "correlation": {
            "names": result.free,
            "matrix": [[_finite(c) for c in row] for row in np.asarray(result.corr)],
        },
        "undetermined": result.undetermined,
        "stages": [
            {
                "free": s.free,
                "chi2": s.chi2,
                "converged": s.converged,
                "message": s.message,
                "num_steps": s.num_steps,
                "wall_s": s.wall_s,
                "start_chi2": s.start_chi2,
            }
            for s in result.stages
        ],
        "logs": {},
    }
    before_all = simulate_logs(result.initial, result.effects, [*fit_logs, *validate_logs])
    # held-out logs: their initial-height offsets estimated under the fitted model
    # (a nuisance, as for the fitted logs; see estimate_x0_offsets)
    offsets = {
        **estimate_x0_offsets(result.params, result.effects, validate_logs),
        **result.x0_offsets,
    }
    after_all = simulate_logs(result.params, result.effects, [*fit_logs, *validate_logs], offsets)
    for i, log in enumerate([*fit_logs, *validate_logs]):
        role = "fitted" if i < len(fit_logs) else "held_out"
        metrics["logs"][log.name] = {
            "role": role,
            "before": _log_metrics(log, before_all[i]),
            "after": _log_metrics(log, after_all[i]),
        }
    if out_dir is not None:
        fit_report(result, metrics, fit_logs, validate_logs, before_all, after_all, out_dir)
    return result, metrics


def _finite(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return _finite(x.item())
    return x


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
    from ._params import save_params_json

    out = pathlib.Path(out_dir)
    figs = out / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    save_params_json(
        out / "params.json",
        result.params,
        comment=f"calibrated by jaxlift fit; effects: {', '.join(result.effects) or 'none'}",
    )
    infos = all_param_infos(make_effects(result.effects))
    logs = [*fit_logs, *validate_logs]
    rep = Report("jaxlift calibration report")
    rep.text(
        f"Model: baseline{' + ' + ', '.join(result.effects) if result.effects else ''}. "
        f"Fitted logs: {', '.join(f'`{lg.name}`' for lg in fit_logs)}. Held-out logs: "
        f"{', '.join(f'`{lg.name}`' for lg in validate_logs) or 'none'}. "
        f"Free parameters: {', '.join(result.free)}. "
        f"Converged: **{'yes' if result.converged else 'NO'}**."
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
        segs = an.segment_log(log)
        for w, (t0, t1) in enumerate(an.zoom_windows(log, segs)):
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
        tb = an.error_table(log, b["height"], b["speed"], segments=segs)
        ta = an.error_table(log, a["height"], a["speed"], segments=segs)
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
            ob = an.oscillation_table(log, b["speed"], segs)
            oa = an.oscillation_table(log, a["speed"], segs)
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
            p = an.plot_residuals(log, a["height"], a["speed"], figs / f"{log.name}_residuals.png")
            rep.figure(
                p,
                f"{log.name}: residuals of the calibrated model: spectrum, autocorrelation, "
                "and against speed, height and pressure. Structure here is what the model "
                "misses.",
            )
    if osc_by_label["after"]:
        p = an.plot_oscillations_vs_height(osc_by_label, figs / "oscillations_vs_height.png")
        rep.heading("Oscillation frequency and amplitude against height")
        rep.figure(
            p,
            "Measured (black) and model oscillations per steady segment against height. The "
            "thesis saw its model's frequency change with height more than the vehicle's.",
        )
    p = an.plot_error_bars(
        {"before": _pool(err_before), "after": _pool(err_after)}, figs / "errors.png"
    )
    rep.heading("Errors by regime, all logs")
    rep.figure(p, "RMS error per regime and stage, before and after estimation.")
    with open(out / "metrics.json", "w", encoding="utf-8") as fh:
        json.dump(_finite(metrics), fh, indent=2)
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


# ------------------------------------------------------------------ diagnose
#: What each effect looks like in a log: the physical signature a service engineer
#: can check on their own data.
SIGNATURES = {
    "stick_slip": "sustained oscillations at low speed whose speed touches zero",
    "motor_inertia": "the speed lags the input after every step of the duty cycle",
    "motor_droop": "the lifting speed falls as the load (pressure) grows",
    "leakage": "the fork sinks while the valve is closed (holds)",
    "entrained_air": "the oscillation frequency depends on pressure (load)",
    "hose_compliance": "the oscillation frequency varies less with height than the model's",
    "mast_compliance": "a second, higher peak in the speed spectrum",
    "input_delay": "motion starts a fixed time after each input change",
}


def _signature_metrics(log: Log, sim: dict[str, np.ndarray]) -> dict[str, float]:
    """Numbers behind the signatures, measured vs model."""
    segs = an.segment_log(log)
    out: dict[str, float] = {}
    holds = [s for s in segs if s.regime == "hold" and s.duration > 1.5]
    if holds:

        def slope(h):
            return float(
                np.mean([np.polyfit(log.time_s[s.slice], h[s.slice], 1)[0] for s in holds])
            )

        out["hold_sink_meas_mmps"] = slope(log.height_m) * 1e3
        out["hold_sink_model_mmps"] = slope(sim["height"]) * 1e3
    slow = [s for s in segs if s.regime == "slow"]
    if slow and log.speed_mps is not None:
        k = max(1, int(round(0.1 / log.sample_period)))
        kern = np.ones(k) / k
        idx = np.concatenate([np.arange(s.start, s.stop) for s in slow])
        vm = np.convolve(log.speed_mps, kern, mode="same")[idx]
        vs = sim["speed"][idx]
        out["slow_share_near_zero_meas"] = float(np.mean(vm < 0.003))
        out["slow_share_near_zero_model"] = float(np.mean(vs < 0.003))
    return out


def run_diagnose(
    logs: Sequence[Log],
    validate_logs: Sequence[Log] = (),
    *,
    out_dir: str | pathlib.Path,
    iterate: bool = True,
    n_starts: int = 2,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list:
    """Diagnose (iteratively: add the winner and diagnose again until ``none``), write
    ``diagnosis.json``, figures and the report. Returns the list of diagnoses."""
    from ._diagnose import diagnose, diagnose_iteratively

    if iterate:
        steps = diagnose_iteratively(
            logs, validate_logs, n_starts=n_starts, seed=seed, progress=progress
        )
    else:
        steps = [diagnose(logs, validate_logs, n_starts=n_starts, seed=seed, progress=progress)]
    out = pathlib.Path(out_dir)
    figs = out / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    all_logs = [*logs, *validate_logs]
    # the models of each step: baseline, +effect 1, +effect 2, ...
    models = [(d.base_effects, d.base_fit.params) for d in steps]
    if steps[-1].winner_fit is not None:
        wf = steps[-1].winner_fit
        models.append((wf.effects, wf.params))
    # each model's own initial-height offsets: the fit's for the fitted logs, estimated
    # under the model for the held-out ones (see estimate_x0_offsets)
    x0s = [d.base_fit.x0_offsets for d in steps]
    if steps[-1].winner_fit is not None:
        x0s.append(steps[-1].winner_fit.x0_offsets)
    sims = {
        tuple(e): simulate_logs(p, e, all_logs, {**estimate_x0_offsets(p, e, validate_logs), **x0})
        for (e, p), x0 in zip(models, x0s)
    }
    labels = ["baseline" + "".join(f" + {x}" for x in e) for e, _ in models]
    error_rows = []
    for (e, _p), label in zip(models, labels):
        row = {"model": label}
        for i, lg in enumerate(all_logs):
            role = "fit" if i < len(logs) else "held-out"
            row[f"{lg.name} ({role}) chi2/N"] = _chi2n(lg, sims[tuple(e)][i])
        error_rows.append(row)
    _plot_error_steps(error_rows, figs / "error_by_step.png")
    first = steps[0]
    verdicts = [d.verdict for d in steps if d.verdict != "none"]
    dropped = [name for d in steps for name in d.dropped]
    data = {
        "verdict": first.verdict,
        "verdicts": verdicts,
        "dropped": dropped,
        "ranking": first.as_dict()["ranking"],
        "steps": [d.as_dict() for d in steps],
        "errors_by_step": error_rows,
        "final_effects": list(models[-1][0]),
        "final_params": {k: float(v) for k, v in models[-1][1].items()},
        "signatures": {},
    }
    rep = Report("jaxlift diagnosis: which physical effect is missing?")
    missing = ", ".join(f"**{v}**" for v in verdicts if v not in dropped) or "**none**"
    rep.text(
        f"Fitted logs: {', '.join(f'`{lg.name}`' for lg in logs)}; held out: "
        f"{', '.join(f'`{lg.name}`' for lg in validate_logs) or 'none'}. "
        f"Missing from the baseline model: {missing}."
    )
    rep.heading("The error falling, step by step")
    rep.table(error_rows, caption="chi2 per sample (1 = sensor noise level) of each model.")
    rep.figure(figs / "error_by_step.png", "Error of each model on fitted and held-out logs.")
    for k, d in enumerate(steps):
        rep.heading(
            f"Step {k + 1}: model = baseline{''.join(' + ' + x for x in d.base_effects)}; "
            f"verdict: {d.verdict}"
        )
        for name, dbic in d.dropped.items():
            rep.text(
                f"Backward check after adding {d.verdict}: without **{name}** the BIC "
                f"changes by only {dbic:+.1f} (< 10): {d.verdict} explains what {name} "
                f"did, so {name} is dropped again."
            )
        rep.text(
            f"chi2/N of the fitted model {d.base_chi2 / d.n_residuals:.3g}; residual "
            f"autocorrelation inflates variances by {d.inflation:.1f} (so the tests count "
            f"{d.n_residuals / d.inflation:.0f} effective samples, not {d.n_residuals})."
        )
        rep.table(
            [
                {
                    "effect": s.effect,
                    "score z": s.z,
                    "p (screen)": s.p_value,
                    "dBIC (refit)": s.delta_bic,
                    "held-out chi2/N before": s.heldout_chi2_before,
                    "after": s.heldout_chi2_after,
                    "signature": SIGNATURES.get(s.effect, ""),
                }
                for s in d.ranking
            ],
            caption="Ranking: confirmed candidates by BIC change (negative = better), then "
            "the others by score. Verdict = largest BIC drop beyond 10 whose held-out "
            "chi2 also falls by more than 10 (effective samples).",
        )
    # the signature, on the user's own data, before and after adding the effects
    rep.heading("The physical signature on your data")
    base_sims = sims[tuple(models[0][0])]
    final_sims = sims[tuple(models[-1][0])]
    osc = {"baseline": [], labels[-1]: []}
    for i, lg in enumerate(all_logs):
        sig_b = _signature_metrics(lg, base_sims[i])
        sig_f = _signature_metrics(lg, final_sims[i])
        data["signatures"][lg.name] = {"baseline": sig_b, "final": sig_f}
        if lg.speed_mps is not None:
            segs = an.segment_log(lg)
            osc["baseline"].extend(an.oscillation_table(lg, base_sims[i]["speed"], segs))
            osc[labels[-1]].extend(an.oscillation_table(lg, final_sims[i]["speed"], segs))
        if i == 0:
            segs = an.segment_log(lg)
            for w, (t0, t1) in enumerate(an.zoom_windows(lg, segs, n=2)):
                p = plot_overlay(
                    lg,
                    [
                        ("baseline", base_sims[i]["height"], base_sims[i]["speed"], None),
                        (labels[-1], final_sims[i]["height"], final_sims[i]["speed"], None),
                    ],
                    figs / f"{lg.name}_signature{w + 1}.png",
                    window=(t0, t1),
                    title=f"{lg.name}: {t0:.0f}-{t1:.0f} s",
                )
                rep.figure(p, f"{lg.name}, {t0:.0f}-{t1:.0f} s: measured, baseline, final model.")
    if any(osc.values()):
        p = an.plot_oscillations_vs_height(osc, figs / "oscillations_vs_height.png")
        rep.figure(
            p,
            "Oscillation frequency and amplitude per steady segment against height: "
            "measured (black), baseline and final model.",
        )
    sig_rows = [
        {"log": name, "model": which, **vals}
        for name, v in data["signatures"].items()
        for which, vals in v.items()
    ]
    rep.table(
        sig_rows,
        caption="Signature numbers: sinking speed in holds (leakage), share of slow "
        "motion with speed near zero (stick-slip); measured vs model.",
    )
    with open(out / "diagnosis.json", "w", encoding="utf-8") as fh:
        json.dump(_finite(data), fh, indent=2)
        fh.write("\n")
    rep.write(out)
    return steps


def _plot_error_steps(rows: list[dict], path) -> str:
    import matplotlib.pyplot as plt

    keys = [k for k in rows[0] if k != "model"]
    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(rows))
    for j, k in enumerate(keys):
        ax.plot(x, [r[k] for r in rows], "o-", label=k, color=f"C{j}")
    ax.set_xticks(x, [r["model"].replace("baseline + ", "+") for r in rows], rotation=15)
    ax.set_yscale("log")
    ax.axhline(1.0, color="0.5", ls="--", lw=0.8)
    ax.set_ylabel("chi2 per sample")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)
