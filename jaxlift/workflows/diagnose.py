"""``jaxlift diagnose`` as a function: fit the baseline, screen and confirm the
candidate effects, and write ``diagnosis.json``, the figures and the report.
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Callable, Sequence

import numpy as np

from ..analysis.oscillation import oscillation_table, zoom_windows
from ..analysis.regimes import error_table, segment_log
from ..calibrate.diagnose import (
    diagnose,
    diagnose_iteratively,
    final_verdict,
    found_effects,
    kept_effects,
)
from ..calibrate.fit import estimate_x0_offsets
from ..calibrate.result import FitResult
from ..calibrate.shape import estimate_missing_shape
from ..model.log import Log
from ..model.solution import SimulationError
from ..report.analysis_plots import plot_oscillations_vs_height
from ..report.document import Report, json_safe
from ..report.fit import plot_error_steps
from ..report.plots import plot_overlay
from ..report.shape import shape_section, write_shape_csv
from ._scratch import output_folder
from .fit import chi2n, simulate_logs

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
    segs = segment_log(log)
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
    out_dir: str | pathlib.Path | None = None,
    iterate: bool = True,
    max_effects: int = 3,
    n_starts: int = 2,
    seed: int = 0,
    base: FitResult | None = None,
    shape: str = "auto",
    progress: Callable[[str], None] | None = None,
) -> list:
    """Diagnose (iteratively: add the winner and diagnose again until ``none``), write
    ``diagnosis.json``, figures and the report into ``out_dir`` (None: a temporary
    folder, removed on return). Returns the list of diagnoses.
    ``base``: a fit of the baseline (or of a starting model: its effects) to begin
    from, instead of fitting it first. ``shape``: estimate the shape of what the final
    model misses (:func:`~jaxlift.estimate_missing_shape`) when the verdict is
    ``unexplained`` (``"auto"``), always (``"always"``) or never (``"never"``)."""
    if shape not in ("auto", "always", "never"):
        raise ValueError(f"shape must be 'auto', 'always' or 'never', got {shape!r}")

    if iterate:
        steps = diagnose_iteratively(
            logs, validate_logs, max_effects=max_effects, n_starts=n_starts, seed=seed,
            base=base, progress=progress,
        )  # fmt: skip
    else:
        steps = [
            diagnose(
                logs, validate_logs, n_starts=n_starts, seed=seed, progress=progress, base=base,
                base_effects=() if base is None else base.effects,
            )
        ]  # fmt: skip
    out, _keeper = output_folder(out_dir, "diagnose")  # none: removed on return
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
    labels: list[str] = []
    for e, _ in models:
        label = "baseline" + "".join(f" + {x}" for x in e)
        while label in labels:  # the same effects refitted: a newcomer dropped again
            label += " (refitted)"
        labels.append(label)
    # a log that one of the models cannot simulate (a held-out log under the baseline,
    # say) is named with the reason and left out of the per-log sections below
    failed: dict[str, dict[str, str]] = {}
    sims = []  # per model, in the order of ``models``
    for (e, p), x0, label in zip(models, x0s, labels):
        why: dict[str, str] = {}
        x0 = {**estimate_x0_offsets(p, e, validate_logs), **x0}
        sims.append(simulate_logs(p, e, all_logs, x0, failures=why))
        for name, msg in why.items():
            failed.setdefault(name, {})[label] = msg
    error_rows = []
    for k, label in enumerate(labels):
        row = {"model": label}
        for i, lg in enumerate(all_logs):
            role = "fit" if i < len(logs) else "held-out"
            sim = sims[k][i]
            row[f"{lg.name} ({role}) chi2/N"] = (
                chi2n(lg, sim) if sim is not None else "simulation failed"
            )
        error_rows.append(row)
    shown = [i for i, lg in enumerate(all_logs) if lg.name not in failed]
    plot_error_steps(error_rows, figs / "error_by_step.png")
    first = steps[0]
    verdicts = found_effects(steps)
    dropped = [name for d in steps for name in d.dropped]
    last = steps[-1]
    data = {
        "verdict": first.verdict,
        "verdicts": verdicts,
        # how the iteration ended: "none" (nothing more is missing), "undecided" (which
        # of two) or "unexplained" (something none of the candidates describes)
        "final_verdict": final_verdict(steps),
        "remaining_misfit": None if last.misfit is None else last.misfit.as_dict(),
        "heldout_excluded": first.heldout_excluded,
        "undecided_between": last.undecided_between,
        "reasons": last.reasons,
        "dropped": dropped,
        # the effects kept, in order (an effect dropped in one step and named again
        # later counts): what the verdicts minus the dropped ones give otherwise
        "kept": kept_effects(steps),
        "ranking": first.as_dict()["ranking"],
        "steps": [d.as_dict() for d in steps],
        "errors_by_step": error_rows,
        "final_effects": list(models[-1][0]),
        "final_params": {k: float(v) for k, v in models[-1][1].items()},
        "signatures": {},
        "simulation_failures": failed,
    }
    rep = Report("jaxlift diagnosis: which physical effect is missing?")
    missing = ", ".join(f"**{v}**" for v in kept_effects(steps)) or "**none**"
    rep.text(
        f"Fitted logs: {', '.join(f'`{lg.name}`' for lg in logs)}; held out: "
        f"{', '.join(f'`{lg.name}`' for lg in validate_logs) or 'none'}. "
        f"Missing from the baseline model: {missing}."
        + (
            f" Then **undecided** between {' and '.join(last.undecided_between) or '—'}: "
            + "; ".join(last.reasons)
            + "."
            if last.verdict == "undecided"
            else ""
        )
        + (
            " Then **unexplained**: " + "; ".join(last.reasons) + "."
            if final_verdict(steps) == "unexplained"
            else ""
        )
    )
    for name, why in first.heldout_excluded.items():
        rep.text(f"Held-out log `{name}` is not used to judge the candidates: {why}.")
    for name, by_model in failed.items():
        rep.text(
            f"Log `{name}` could not be simulated by "
            + "; ".join(f"the {label} model ({msg})" for label, msg in by_model.items())
            + ": it is left out of the per-log sections below."
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
            if name == d.verdict:  # the newcomer itself (diagnose_iteratively)
                rep.text(
                    f"Backward check of **{name}** itself: refitted without it from its "
                    f"values, the model changes the BIC by only {dbic:+.1f} (< 10): the "
                    f"step's model had not reached its own optimum, and {name}'s refit "
                    "only completed that fit. It is dropped, and the step is repeated "
                    "from the better fit."
                )
                continue
            rep.text(
                f"Backward check after adding {d.verdict}: without **{name}** the BIC "
                f"changes by only {dbic:+.1f} (< 10): {d.verdict} explains what {name} "
                f"did, so {name} is dropped again."
            )
        if d.reasons and d.verdict not in ("none", "undecided", "unexplained"):
            # a winner the held-out logs decided, or one the lookahead kept: why
            rep.text(f"Why {d.verdict}: " + "; ".join(d.reasons) + ".")
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
                    "share of error removed": s.explained_share,
                    "signature": SIGNATURES.get(s.effect, ""),
                }
                for s in d.ranking
            ],
            caption="Ranking: confirmed candidates by BIC change (negative = better), then "
            "the others by score. Verdict = largest BIC drop beyond 10 whose held-out "
            "chi2 also falls by more than 10 (effective samples) and, where the error is "
            "far above the noise, that removes at least 25 % of it; two within 10 of each "
            "other on the fitted logs are decided by adding the held-out logs' evidence "
            "(their chi2 change, in effective samples), or left undecided.",
        )
    # where the final model's error remains: per regime and per stage, each log
    rep.heading("Where the error remains")
    rep.text(
        "RMS and mean error of the final model (model - measured) overall, per regime and "
        "per mast stage. The sensor noise is 0.5 mm (height) and 3.2 mm/s (speed): groups "
        "well above that hold what the model still misses."
    )
    final_sims_all = sims[-1]
    where_rows = []
    for i in shown:
        lg, sim = all_logs[i], final_sims_all[i]
        for row in error_table(lg, sim["height"], sim["speed"]):
            where_rows.append({"log": lg.name, **row})
    data["where_error_remains"] = where_rows
    rep.table(where_rows, caption="Error of the final model by log, regime and stage.")
    # the signature, on the user's own data, before and after adding the effects
    rep.heading("The physical signature on your data")
    base_sims, final_sims = sims[0], sims[-1]
    osc = {"baseline": [], labels[-1]: []}
    for i in shown:
        lg = all_logs[i]
        sig_b = _signature_metrics(lg, base_sims[i])
        sig_f = _signature_metrics(lg, final_sims[i])
        data["signatures"][lg.name] = {"baseline": sig_b, "final": sig_f}
        if lg.speed_mps is not None:
            segs = segment_log(lg)
            osc["baseline"].extend(oscillation_table(lg, base_sims[i]["speed"], segs))
            osc[labels[-1]].extend(oscillation_table(lg, final_sims[i]["speed"], segs))
        if i == shown[0]:
            segs = segment_log(lg)
            for w, (t0, t1) in enumerate(zoom_windows(lg, segs, n=2)):
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
        p = plot_oscillations_vs_height(osc, figs / "oscillations_vs_height.png")
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
    final_fit = steps[-1].winner_fit or steps[-1].base_fit
    if shape == "always" or (shape == "auto" and data["final_verdict"] == "unexplained"):
        (progress or (lambda s: None))("estimating the shape of what is missing")
        try:
            est = estimate_missing_shape(final_fit, logs, progress=progress)
        except SimulationError as err:  # reported, never fatal to the diagnosis
            data["missing_shape"] = {"failed": str(err)}
            rep.heading("The shape of what is missing")
            rep.text(f"Could not be estimated: {err}")
        else:
            data["missing_shape"] = shape_section(rep, est, figs)
            write_shape_csv(est, out / "missing_shape.csv")
    with open(out / "diagnosis.json", "w", encoding="utf-8") as fh:
        json.dump(json_safe(data), fh, indent=2)
        fh.write("\n")
    rep.write(out)
    return steps
