"""``jaxlift tune`` and ``jaxlift control simulate`` as functions.

:func:`run_tune` tunes the lift controller's gains on the calibrated model (nominal,
then robust over parameter draws), writes ``gains.json`` (and the nominal and robust
sets), ``summary.json``, figures and a report, and returns a :class:`TuneRun`.
:func:`run_control_simulate` runs any gains along the thesis-like reference and writes
``response.csv``, ``response.png`` and ``figures.json``. Neither prints: messages go to
``progress``.
"""

from __future__ import annotations

import dataclasses
import html
import json
import os
import pathlib
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from ..control.closed_loop import ClosedLoopSolution, simulate_closed_loop
from ..control.controller import PID, THESIS_PID, AbstractController, ScheduledPID, save_gains
from ..control.cost import tuning_cost
from ..control.draws import DrawSet, batch_models, parameter_draws
from ..control.performance import figures
from ..control.reference import thesis_reference
from ..control.tune import TuneResult, tune_gains, tune_multistart
from ..model.build import load_model, make_effects, model_params
from ..model.effects import AbstractEffect
from ..model.log import Log
from ..model.plant import Plant
from ..report.document import Report
from ..report.tuning import plot_response, robustness_report
from ._scratch import output_folder
from .fit import run_fit

#: Noise seeds of ``jaxlift tune``'s cost (the mean over them): four realisations
#: of the speed sensor's noise per load.
DEFAULT_NOISE_SEEDS = (0, 1, 2, 3)
#: Improvement of the held-out worst case that issue #18 asks of robust tuning.
ROBUST_TARGET = 0.15


def _quiet(_: str) -> None:
    pass


def calibrated_model(
    params: str | os.PathLike | None,
    effects: Sequence[str] | str | None,
    *,
    posterior_dir: str | os.PathLike | None = None,
    logs: Sequence[Log] = (),
    out_dir: str | os.PathLike | None = None,
    progress: Callable[[str], None] = _quiet,
) -> tuple[Plant, tuple[AbstractEffect, ...], str | None]:
    """``(plant, effects, parameter file)`` for tuning: from ``params``, else the
    calibrated model of a posterior directory (its ``params.json``), else a
    least-squares fit of ``logs`` (written to ``out_dir/fit``), else nominal."""
    if not params and posterior_dir and (pathlib.Path(posterior_dir) / "params.json").exists():
        params = str(pathlib.Path(posterior_dir) / "params.json")
        progress(f"no --params: the posterior's calibrated model {params}")
    if params:
        plant, effs = load_model(params, effects)
        return plant, effs, str(params)
    if not logs:
        plant, effs = load_model(None, effects)
        return plant, effs, None
    fit_dir = pathlib.Path(out_dir if out_dir is not None else ".") / "fit"
    names = [e.name for e in make_effects(effects)]
    progress(
        "no --params: fitting the model to the logs first (jaxlift fit; this takes "
        f"minutes) into {fit_dir}"
    )
    run_fit(logs, (), effects=names, out_dir=fit_dir, progress=progress)
    params = fit_dir / "params.json"
    plant, effs = load_model(params, names or None)
    return plant, effs, str(params)


@dataclasses.dataclass
class TuneRun:
    """What :func:`run_tune` found: the gains it recommends (``chosen``, named
    ``chosen_name``), the nominal and robust tunings, every gain set compared (thesis,
    nominal-tuned, robust-tuned), their nominal cost per set, the parameter draws used
    and the robustness summary over the held-out draws."""

    chosen: AbstractController
    chosen_name: str
    nominal: TuneResult
    robust: TuneResult | None
    gain_sets: dict[str, AbstractController]
    rows: list[dict]
    draws: DrawSet | None
    robustness: dict
    notes: list[str]

    def table(self):
        """Every gain set compared, as a :class:`pandas.DataFrame` indexed by name:
        the tuning cost on the nominal model (mean over the loads and noise seeds) and
        the gains (P [V/(m/s)], I [V/m], D [V s²/m], N [1/s], K_aw [1/s]; scheduled
        PID: per stage)."""
        return pd.DataFrame(self.rows).set_index("gains")

    def _repr_html_(self) -> str:
        head = (
            f"<p><b>Tuned gains</b>: recommended <b>{self.chosen_name}</b>"
            + "".join(f"<br>note: {html.escape(n)}" for n in self.notes)
            + "</p>"
        )
        verdict = self.robustness.get("robust_vs_nominal")
        tail = f"<p>{html.escape(verdict['text'])}</p>" if verdict else ""
        return head + self.table().to_html(float_format=lambda x: f"{x:.4g}") + tail


def run_tune(
    logs: Sequence[Log],
    plant: Plant,
    effects: Sequence[AbstractEffect],
    out_dir: str | os.PathLike | None = None,
    *,
    params_path: str | None = None,
    posterior_dir: str | os.PathLike | None = None,
    scheduled: bool = False,
    sampled: bool = True,
    T_c: float = 0.01,
    noise_seeds: Sequence[int] | None = DEFAULT_NOISE_SEEDS,
    steps: int = 30,
    rtol: float = 1e-5,
    robust_draws: int = 16,
    eval_draws: int = 100,
    seed: int = 0,
    time_scale: float = 1.0,
    report_noise_seed: int | None = 0,
    progress: Callable[[str], None] = _quiet,
) -> TuneRun:
    """Tune the PID gains of ``docs/control.md`` on ``plant`` + ``effects`` at the
    logs' loads (median load of each log [kg]), nominal then robust, and write the
    outputs to ``out_dir``.

    Args:
        logs: the logs whose loads are the tuning loads.
        plant, effects: the calibrated model (see :func:`calibrated_model`).
        out_dir: output directory (``gains.json``, ``gains_nominal.json``,
            ``gains_robust.json``, ``summary.json``, ``report.md/.html``, ``figures/``;
            None: a temporary folder, removed on return).
        params_path: the parameter file the model came from; its folder is searched for
            a fit's covariance when there is no posterior.
        posterior_dir: posterior directory for the parameter draws.
        scheduled: tune the gain-scheduled PID (18 stage gains + N + K_aw).
        sampled, T_c: controller on a clock of period ``T_c`` [s] with zero-order hold
            (the default: the loop as deployed; False: the thesis's continuous form).
        noise_seeds: tune with the speed sensor's noise, the cost averaged over these
            seeds (default 4 seeds; None: no noise). Robust tuning gives every draw a
            realisation of its own (the first seed, shifted per draw).
        steps: evaluations per tuning (Levenberg--Marquardt, at most).
        rtol: the solver's relative tolerance while tuning.
        robust_draws, eval_draws: parameter draws for robust tuning / the held-out report.
        seed: seed of the parameter draws.
        time_scale: shortens the thesis-like reference (1: 110 s, the whole lift).
        report_noise_seed: noise seed of the report's noisy case (None: leave it out).
        progress: receives one line per step.
    """
    out, _keeper = output_folder(out_dir, "tune")  # none: removed on return
    (out / "figures").mkdir(parents=True, exist_ok=True)
    loads = sorted({round(float(np.median(lg.load_kg)), 0) for lg in logs})
    progress(
        f"model: {params_path or 'nominal'}; effects: "
        f"{[e.name for e in effects] or 'none (baseline)'}; tuning loads: {loads} kg"
    )
    refs = [thesis_reference(m, time_scale=time_scale) for m in loads]
    sim = dict(sampled=sampled, T_c=T_c)
    noise_seeds = None if noise_seeds is None else [int(s) for s in noise_seeds]
    start = PID().with_gains({**THESIS_PID, "K_aw": THESIS_PID["I"] / THESIS_PID["P"]})
    thesis = PID().with_gains(THESIS_PID)
    if scheduled:
        start = ScheduledPID.from_pid(start)

    progress(f"nominal tuning: at most {steps} LM evaluations ...")
    nominal = tune_gains(
        start, plant, effects, refs, steps=steps, progress=True, rtol=rtol,
        noise_seeds=noise_seeds, **sim,
    )  # fmt: skip
    progress(
        f"  cost {nominal.initial_cost:.4g} -> {nominal.best_cost:.4g} ({nominal.wall_s:.0f} s)"
    )
    gain_sets = {"thesis PID": thesis, "nominal-tuned": nominal.controller}
    chosen, chosen_name = nominal.controller, "nominal-tuned"
    notes = []
    if nominal.start_note:
        notes.append(nominal.start_note)
        progress(f"note: {nominal.start_note}")

    draws = None
    fit_dir = os.path.dirname(os.path.abspath(params_path)) if params_path else None
    try:
        if robust_draws + eval_draws <= 0:  # nominal only: no draws wanted
            raise ValueError("none asked for (robust_draws = eval_draws = 0)")
        draws = parameter_draws(
            robust_draws + eval_draws,
            seed,
            posterior_dir=posterior_dir,
            fit_dir=fit_dir,
            values={k: float(v) for k, v in model_params(plant, effects).items()},
            effects=[e.name for e in effects],
        )
    except Exception as err:  # noqa: BLE001 -- no draws: nominal only, and say so
        progress(f"no parameter draws ({err}): robust tuning and report skipped")
    robust = None
    choice_note = None  # why the written gains are the ones they are, if not plain
    if draws is not None:
        progress(f"parameter draws: {draws.source}")
        model_effects = sorted(e.name for e in effects)
        if sorted(draws.effects) != model_effects:
            notes.append(
                f"the draws are of a model with effects {sorted(draws.effects) or 'none'}, "
                f"the tuned model has {model_effects or 'none'}: only the parameters the "
                "tuned model has are drawn, the others are ignored"
            )
            progress(f"warning: {notes[-1]}")
        tune_draws, _ = draws.split(robust_draws)
        if robust_draws > 0:
            plants, effs = batch_models(plant, effects, tune_draws.draws)
            progress(
                f"robust tuning over {robust_draws} draws (mean + CVaR20), from the "
                f"nominal-tuned and from the starting gains: at most {steps} LM "
                "evaluations each ..."
            )
            robust = tune_multistart(
                [nominal.controller, start],
                plants,
                effs,
                refs,
                batched_plants=True,
                robust=True,
                steps=steps,
                progress=True,
                rtol=rtol,
                noise_seeds=None if noise_seeds is None else noise_seeds[:1],
                **sim,
            )
            progress(
                f"  objective {robust.initial_cost:.4g} -> {robust.best_cost:.4g} "
                f"({robust.wall_s:.0f} s; {robust.message})"
            )
            gain_sets["robust-tuned"] = robust.controller
            chosen, chosen_name = robust.controller, "robust-tuned"

    save_gains(out / "gains_nominal.json", nominal.controller, comment="nominal-tuned")
    if robust is not None:
        save_gains(out / "gains_robust.json", robust.controller, comment="robust-tuned")

    form = f"sampled at T_c = {T_c:g} s" if sampled else "continuous"
    noise = (
        "off"
        if noise_seeds is None
        else f"the speed sensor's (docs/control.md), cost averaged over seeds {noise_seeds}"
        + (" (robust tuning: one realisation per draw)" if robust is not None else "")
    )
    rep = Report("Gain tuning of the lift controller")
    rep.text(
        f"Model: `{params_path or 'nominal'}`, effects: "
        f"{', '.join(e.name for e in effects) or 'none'}. Tuning loads: {loads} kg; "
        f"reference: the thesis-like sequence (time scale {time_scale:g}). "
        f"Controller: {'scheduled' if scheduled else 'plain'} PID, "
        f"{form}; noise: {noise}. "
        "Levenberg-Marquardt on the log gains (the cost as a sum of squares, its "
        "forward-mode Jacobian through the closed loop), at most "
        f"{steps} evaluations per tuning"
        + (
            "; robust tuning from the nominal-tuned and from the starting gains, the better "
            f"kept ({robust.message})"
            if robust is not None
            else ""
        )
        + f". Parameter draws: {draws.source if draws is not None else 'none'}. "
        + "".join(f"Note: {n}. " for n in notes)
    )
    rows = []
    for name, ctrl in gain_sets.items():
        costs = []
        for ref in refs:
            for seed in noise_seeds or [None]:
                sol = simulate_closed_loop(plant, effects, ctrl, ref, noise_seed=seed, **sim)
                ok = bool(sol.ok)
                costs.append(float(tuning_cost(ctrl, plant, sol)) if ok else float("inf"))
        rows.append(dict(gains=name, nominal_cost=float(np.mean(costs)), **ctrl.gain_values()))
    rep.heading("Gains and nominal cost")
    rep.table(rows, floatfmt=".4g")
    seed0 = None if noise_seeds is None else noise_seeds[0]
    runs = [
        (name, simulate_closed_loop(plant, effects, ctrl, refs[0], noise_seed=seed0, **sim))
        for name, ctrl in gain_sets.items()
    ]
    png = plot_response(runs, out / "figures" / "response.png", f"{refs[0].m_load:g} kg")
    rep.figure(png, "Closed-loop response on the calibrated model")
    hist = [dict(step=i, nominal=v) for i, v in enumerate(nominal.history)]
    if robust is not None:
        for i, v in enumerate(robust.history):
            if i < len(hist):
                hist[i]["robust_objective"] = v
    rep.heading("Tuning history")
    rep.table(hist[:: max(1, len(hist) // 12)], floatfmt=".4g")
    summary = {}
    if draws is not None and eval_draws > 0:
        _, held_out = draws.split(robust_draws)
        progress(f"robustness report over {eval_draws} held-out draws ...")
        rep, summary = robustness_report(
            gain_sets,
            plant,
            effects,
            held_out,
            refs,
            out,
            noise_seed=report_noise_seed,
            report=rep,
            sampled=sampled,
            T_c=T_c,
        )
        if robust is not None:
            verdict = robust_verdict(summary)
            summary["robust_vs_nominal"] = verdict
            rep.heading("Does robust tuning pay?")
            rep.text(verdict["text"])
            progress(verdict["text"])
            name, choice_note = recommended(verdict)
            if name == "nominal-tuned":
                chosen, chosen_name = nominal.controller, name
            if choice_note:
                notes.append(choice_note)
                progress(f"note: {choice_note}")
    elif robust is not None:
        choice_note = "robust-tuned gains recommended without a held-out check (eval_draws = 0)"
        notes.append(choice_note)
    comment = (
        f"jaxlift tune ({chosen_name}) on {params_path or 'nominal model'}; effects "
        f"{[e.name for e in effects]}; loads {loads} kg; "
        + (f"sampled, T_c = {T_c:g} s" if sampled else "continuous controller")
    )
    save_gains(out / "gains.json", chosen, comment=comment)
    rep.heading("Recommended gains")
    if robust is None:  # the choice rule below has nothing to choose between
        rule = "only the nominal model was tuned (no robust tuning in this run)."
    else:
        rule = (
            "the robust-tuned gains when their worst cost over the held-out draws is no "
            "higher than the nominal-tuned gains' in every case, else the nominal-tuned."
        )
    rep.text(
        f"Written gains: **{chosen_name}** (`gains.json`): {rule}"
        + (f" Note: {choice_note}." if choice_note else "")
    )
    md, html = rep.write(out)
    with open(out / "summary.json", "w", encoding="utf-8") as fh:
        json.dump({"gains": rows, "robustness": summary}, fh, indent=1, default=str)
    progress(f"wrote {out / 'gains.json'} ({chosen_name}), {md}, {html}, figures/")
    return TuneRun(chosen, chosen_name, nominal, robust, gain_sets, rows, draws, summary, notes)


def recommended(verdict: dict) -> tuple[str, str | None]:
    """Which tuned gains to recommend, from :func:`robust_verdict`'s held-out
    comparison: ``"robust-tuned"`` when their worst cost over the held-out draws is no
    higher than the nominal-tuned gains' in every case, else ``"nominal-tuned"`` (the
    robust objective was lower on the tuning draws only). Returns ``(name, note)``."""
    worse = [c["case"] for c in verdict.get("cases", []) if c["improvement"] < 0]
    if not verdict.get("cases"):
        return "robust-tuned", "robust-tuned gains recommended without a held-out comparison"
    if worse:
        return "nominal-tuned", (
            "the robust-tuned gains' held-out worst cost is higher than the nominal-tuned "
            f"gains' on {', '.join(worse)}: the nominal-tuned gains are recommended"
        )
    return "robust-tuned", None


def robust_verdict(summary: dict) -> dict:
    """Robust-tuned against nominal-tuned gains on the held-out draws of a
    :func:`~jaxlift.report.tuning.robustness_report` summary: per case, the worst
    cost of each and the improvement; and, where the improvement is below
    :data:`ROBUST_TARGET`, how wide the draws are for the nominal-tuned gains (their
    worst cost over their median): when that is close to 1 the draws are too narrow
    for any gain set to buy robustness. Returns ``{"cases": [...], "text": ...}``."""
    cases = []
    for case, rows in summary.get("cases", {}).items():
        by = {r["gains"]: r for r in rows}
        if "robust-tuned" not in by or "nominal-tuned" not in by:
            continue
        nom, rob = by["nominal-tuned"], by["robust-tuned"]
        gain = 1.0 - rob["cost_worst"] / nom["cost_worst"]
        cases.append(
            dict(
                case=case,
                nominal_worst=nom["cost_worst"],
                robust_worst=rob["cost_worst"],
                improvement=gain,
                nominal_worst_over_median=nom["cost_worst"] / nom["cost_median"],
            )
        )
    if not cases:
        return {"cases": [], "text": "No held-out comparison of robust and nominal gains."}
    lines = [
        f"{c['case']}: worst cost {c['nominal_worst']:.4g} (nominal-tuned) -> "
        f"{c['robust_worst']:.4g} (robust-tuned), {100 * c['improvement']:+.1f} %"
        for c in cases
    ]
    best = max(c["improvement"] for c in cases)
    spread = max(c["nominal_worst_over_median"] for c in cases)
    if best >= ROBUST_TARGET:
        tail = (
            f"Robust tuning lowers the held-out worst case by up to {100 * best:.0f} % "
            f"(target {100 * ROBUST_TARGET:.0f} %)."
        )
    else:
        tail = (
            f"Robust tuning lowers the held-out worst case by at most {100 * best:.1f} %, "
            f"short of {100 * ROBUST_TARGET:.0f} %. Why: over these draws the nominal-tuned "
            f"gains' worst cost is at most {spread:.3g} times their median cost -- the "
            "plants the draws describe are close to the nominal one, so no gain set can "
            "make the worst draw much better than the nominal-tuned gains already do. "
            "Robust tuning pays where the draws are wide (stated spreads, a poorly "
            "determined fit, a posterior from little data)."
        )
    short = (
        f"robust tuning lowers the held-out worst-case cost by at most {100 * best:.1f} % "
        f"over {len(cases)} case{'s' if len(cases) > 1 else ''} (target "
        f"{100 * ROBUST_TARGET:.0f} %"
        + ("; reached)." if best >= ROBUST_TARGET else "; not reached: the draws are narrow).")
    )
    return {"cases": cases, "text": "; ".join(lines) + ". " + tail, "short": short}


def run_control_simulate(
    controller: AbstractController,
    plant: Plant,
    effects: Sequence[AbstractEffect],
    out_dir: str | os.PathLike,
    *,
    load: float = 1000.0,
    noise_seed: int | None = None,
    sampled: bool = False,
    T_c: float = 0.01,
    time_scale: float = 1.0,
    label: str = "gains",
    model_label: str = "nominal",
) -> tuple[ClosedLoopSolution, dict[str, float]]:
    """Run ``controller`` on the model along the thesis-like reference at ``load`` [kg];
    write ``response.csv`` (SI units), ``response.png`` and ``figures.json`` to
    ``out_dir``. Returns the solution and the figures of "good" (plus ``cost``).
    Raises :class:`~jaxlift.SimulationError` if the simulation fails."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ref = thesis_reference(load, time_scale=time_scale)
    sol = simulate_closed_loop(
        plant, effects, controller, ref, noise_seed=noise_seed, sampled=sampled, T_c=T_c
    ).check("closed-loop simulation")
    data = np.column_stack(
        [np.asarray(a) for a in (sol.ts, sol.v_ref, sol.height, sol.speed, sol.pressure, sol.u)]
    )
    np.savetxt(
        out / "response.csv",
        data,
        delimiter=",",
        header="time_s,v_ref_mps,height_m,speed_mps,pressure_pa,u",
        comments="",
        fmt="%.9g",
    )
    plot_response([(label, sol)], out / "response.png", f"{load:g} kg, {model_label}")
    figs = figures_of(sol, controller, plant)
    with open(out / "figures.json", "w", encoding="utf-8") as fh:
        json.dump(figs, fh, indent=1)
    return sol, figs


def figures_of(
    sol: ClosedLoopSolution, controller: AbstractController, plant: Plant
) -> dict[str, float]:
    """The figures of "good" of one run as a flat dict, with the tuning ``cost``."""
    figs = figures(sol).as_dict()
    figs["cost"] = float(tuning_cost(controller, plant, sol))
    return figs
