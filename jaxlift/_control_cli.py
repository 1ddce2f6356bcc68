"""Command line: ``jaxlift tune`` and ``jaxlift control simulate``.

``jaxlift tune LOG.csv ... [--params params.json] [--posterior DIR] --out DIR`` tunes
the PID gains by gradient through the closed-loop simulation of the calibrated model
(nominal, and robust over parameter draws) and writes ``gains.json``, figures and a
report. ``jaxlift control simulate --gains gains.json --out DIR`` runs any gains on the
model along the thesis-like reference and reports the figures of "good".
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys


def _model(args, logs=None, out=None):
    """(plant, effects, params path): from --params, else the calibrated model of
    --posterior DIR (its ``params.json``), else a least-squares fit of the logs."""
    import jaxlift as jl

    posterior = getattr(args, "posterior", None)
    if not args.params and posterior and (pathlib.Path(posterior) / "params.json").exists():
        args.params = str(pathlib.Path(posterior) / "params.json")
        print(f"no --params: the posterior's calibrated model {args.params}", flush=True)
    if args.params:
        plant, effects = jl.load_model(args.params, args.effects)
        return plant, effects, args.params
    if not logs:
        plant, effects = jl.load_model(None, args.effects)
        return plant, effects, None
    from jaxlift._workflows import run_fit

    fit_dir = pathlib.Path(out) / "fit"
    effects = [e for e in (args.effects or "").split(",") if e.strip()]
    print(
        "no --params: fitting the model to the logs first (jaxlift fit; this takes "
        f"minutes) into {fit_dir}",
        flush=True,
    )
    run_fit(logs, (), effects=effects, out_dir=fit_dir, progress=lambda s: print(s, flush=True))
    params = fit_dir / "params.json"
    plant, effects = jl.load_model(params, effects or None)
    return plant, effects, str(params)


def _sim_kw(args) -> dict:
    return dict(sampled=args.sampled, T_c=args.Tc)


def cmd_tune(args) -> int:
    import numpy as np

    from jaxlift._cli import _read_logs
    from jaxlift._closed_loop import simulate_closed_loop, thesis_reference
    from jaxlift._control import PID, THESIS_PID, ScheduledPID, save_gains
    from jaxlift._report import Report
    from jaxlift._tuning import (
        batch_models,
        parameter_draws,
        plot_response,
        robustness_report,
        tune_gains,
        tune_multistart,
        tuning_cost,
    )

    out = pathlib.Path(args.out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    logs = _read_logs(args.logs)
    loads = sorted({round(float(np.median(lg.load_kg)), 0) for lg in logs})
    plant, effects, params_path = _model(args, logs, out)
    print(
        f"model: {params_path or 'nominal'}; effects: "
        f"{[e.name for e in effects] or 'none (baseline)'}; tuning loads: {loads} kg",
        flush=True,
    )
    refs = [thesis_reference(m, time_scale=args.time_scale) for m in loads]
    sim = _sim_kw(args)
    if args.noise_seed is not None:
        sim["noise_seed"] = args.noise_seed
    start = PID().with_gains({**THESIS_PID, "K_aw": THESIS_PID["I"] / THESIS_PID["P"]})
    thesis = PID().with_gains(THESIS_PID)
    if args.scheduled:
        start = ScheduledPID.from_pid(start)

    print(f"nominal tuning: at most {args.steps} LM evaluations ...", flush=True)
    nominal = tune_gains(
        start, plant, effects, refs, steps=args.steps, progress=True, rtol=args.rtol, **sim
    )
    print(
        f"  cost {nominal.initial_cost:.4g} -> {nominal.best_cost:.4g} ({nominal.wall_s:.0f} s)",
        flush=True,
    )
    gain_sets = {"thesis PID": thesis, "nominal-tuned": nominal.controller}
    chosen, chosen_name = nominal.controller, "nominal-tuned"

    draws = None
    fit_dir = os.path.dirname(os.path.abspath(params_path)) if params_path else None
    n_all = args.robust_draws + args.eval_draws
    try:
        draws = parameter_draws(n_all, args.seed, posterior_dir=args.posterior, fit_dir=fit_dir)
    except Exception as err:  # noqa: BLE001 -- no draws: nominal only, and say so
        print(f"no parameter draws ({err}): robust tuning and report skipped", flush=True)
    robust = None
    notes = []
    if draws is not None:
        print(f"parameter draws: {draws.source}", flush=True)
        model_effects = sorted(e.name for e in effects)
        if sorted(draws.effects) != model_effects:
            notes.append(
                f"the draws are of a model with effects {sorted(draws.effects) or 'none'}, "
                f"the tuned model has {model_effects or 'none'}: only the parameters the "
                "tuned model has are drawn, the others are ignored"
            )
            print(f"warning: {notes[-1]}", flush=True)
        tune_draws, eval_draws = draws.split(args.robust_draws)
        if args.robust_draws > 0:
            plants, effs = batch_models(plant, effects, tune_draws.draws)
            print(
                f"robust tuning over {args.robust_draws} draws (mean + CVaR20), from the "
                f"nominal-tuned and from the starting gains: at most {args.steps} LM "
                "evaluations each ...",
                flush=True,
            )
            robust = tune_multistart(
                [nominal.controller, start],
                plants,
                effs,
                refs,
                batched_plants=True,
                robust=True,
                steps=args.steps,
                progress=True,
                rtol=args.rtol,
                **sim,
            )
            print(
                f"  objective {robust.initial_cost:.4g} -> {robust.best_cost:.4g} "
                f"({robust.wall_s:.0f} s; {robust.message})",
                flush=True,
            )
            gain_sets["robust-tuned"] = robust.controller
            chosen, chosen_name = robust.controller, "robust-tuned"

    comment = (
        f"jaxlift tune ({chosen_name}) on {params_path or 'nominal model'}; effects "
        f"{[e.name for e in effects]}; loads {loads} kg; "
        + (f"sampled, T_c = {args.Tc:g} s" if args.sampled else "continuous controller")
    )
    save_gains(out / "gains.json", chosen, comment=comment)
    save_gains(out / "gains_nominal.json", nominal.controller, comment="nominal-tuned")
    if robust is not None:
        save_gains(out / "gains_robust.json", robust.controller, comment="robust-tuned")

    form = f"sampled at T_c = {args.Tc:g} s" if args.sampled else "continuous"
    noise = f"seed {args.noise_seed}" if args.noise_seed is not None else "off"
    rep = Report("Gain tuning of the lift controller")
    rep.text(
        f"Model: `{params_path or 'nominal'}`, effects: "
        f"{', '.join(e.name for e in effects) or 'none'}. Tuning loads: {loads} kg; "
        f"reference: the thesis-like sequence (time scale {args.time_scale:g}). "
        f"Controller: {'scheduled' if args.scheduled else 'plain'} PID, "
        f"{form}; noise: {noise}. "
        "Levenberg-Marquardt on the log gains (the cost as a sum of squares, its "
        "forward-mode Jacobian through the closed loop), at most "
        f"{args.steps} evaluations per tuning"
        + (
            "; robust tuning from the nominal-tuned and from the starting gains, the better "
            f"kept ({robust.message})"
            if robust is not None
            else ""
        )
        + f". Parameter draws: {draws.source if draws is not None else 'none'}. "
        + "".join(f"Note: {n}. " for n in notes)
        + f"Written gains: **{chosen_name}** (`gains.json`)."
    )
    rows = []
    for name, ctrl in gain_sets.items():
        costs = []
        for ref in refs:
            sol = simulate_closed_loop(plant, effects, ctrl, ref, **sim)
            costs.append(float(tuning_cost(ctrl, plant, sol)) if bool(sol.ok) else float("inf"))
        rows.append(dict(gains=name, nominal_cost=float(np.mean(costs)), **ctrl.gain_values()))
    rep.heading("Gains and nominal cost")
    rep.table(rows, floatfmt=".4g")
    runs = [
        (name, simulate_closed_loop(plant, effects, ctrl, refs[0], **sim))
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
    if draws is not None and args.eval_draws > 0:
        _, eval_draws = draws.split(args.robust_draws)
        print(f"robustness report over {args.eval_draws} held-out draws ...", flush=True)
        rep, summary = robustness_report(
            gain_sets,
            plant,
            effects,
            eval_draws,
            refs[0],
            out,
            noise_seed=None if args.no_report_noise else args.report_noise_seed,
            report=rep,
            **_sim_kw(args),
        )
    md, html = rep.write(out)
    with open(out / "summary.json", "w", encoding="utf-8") as fh:
        json.dump({"gains": rows, "robustness": summary}, fh, indent=1, default=str)
    print(f"wrote {out / 'gains.json'} ({chosen_name}), {md}, {html}, figures/")
    return 0


def cmd_control_simulate(args) -> int:
    import numpy as np

    from jaxlift._closed_loop import simulate_closed_loop, thesis_reference
    from jaxlift._control import PID, THESIS_PID, load_gains
    from jaxlift._performance import figures
    from jaxlift._tuning import plot_response, tuning_cost

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ctrl = load_gains(args.gains) if args.gains else PID().with_gains(THESIS_PID)
    plant, effects, params_path = _model(args)
    ref = thesis_reference(args.load, time_scale=args.time_scale)
    sol = simulate_closed_loop(
        plant, effects, ctrl, ref, noise_seed=args.noise_seed, **_sim_kw(args)
    ).check("closed-loop simulation")
    fig = figures(sol)
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
    label = f"{ctrl.kind} ({args.gains or 'thesis gains'})"
    plot_response([(label, sol)], out / "response.png", f"{args.load:g} kg, {params_path}")
    figs = fig.as_dict()
    figs["cost"] = float(tuning_cost(ctrl, plant, sol))
    with open(out / "figures.json", "w", encoding="utf-8") as fh:
        json.dump(figs, fh, indent=1)
    print(f"gains: {ctrl.gain_values()}")
    for k, v in figs.items():
        print(f"  {k:22s} {v:10.4g}")
    print(f"wrote {out / 'response.csv'}, response.png, figures.json")
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--params", help="parameter file (JSON, from jaxlift fit)")
    p.add_argument("--effects", default=None, help="effects (a,b); default: those in --params")
    p.add_argument("--sampled", action="store_true", help="controller on a clock (ZOH on u)")
    p.add_argument("--Tc", type=float, default=0.01, help="controller period [s] (10 ms)")
    p.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        help="shorten the thesis-like reference (1 = 110 s, whole lift)",
    )


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add this module's sub-commands to ``jaxlift``'s parser."""
    p = sub.add_parser(
        "tune",
        help="tune the PID gains by gradient through the closed-loop simulation",
        description="Tune the lift controller's gains (CONTROL.md) on the calibrated model: "
        "nominal, and robust over parameter draws (posterior, or the least-squares "
        "covariance of the fit); writes gains.json, figures and a report.",
    )
    p.add_argument("logs", nargs="+", help="logs (CSV): their loads are the tuning loads")
    _common(p)
    p.add_argument("--posterior", help="posterior directory (jaxlift posterior)")
    p.add_argument("--scheduled", action="store_true", help="tune the scheduled PID (18 + N)")
    p.add_argument("--steps", type=int, default=30, help="evaluations per tuning (LM; at most)")
    p.add_argument("--robust-draws", type=int, default=16, help="draws for robust tuning")
    p.add_argument("--eval-draws", type=int, default=100, help="held-out draws for the report")
    p.add_argument("--noise-seed", type=int, default=None, help="tune with sensor noise")
    p.add_argument(
        "--report-noise-seed", type=int, default=0, help="noise seed of the report's noisy case"
    )
    p.add_argument(
        "--no-report-noise", action="store_true", help="leave the noisy case out of the report"
    )
    p.add_argument("--rtol", type=float, default=1e-5, help="solver tolerance while tuning")
    p.add_argument("--seed", type=int, default=0, help="seed of the parameter draws")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_tune)

    p = sub.add_parser("control", help="closed-loop tools")
    csub = p.add_subparsers(dest="control_command", required=True)
    q = csub.add_parser("simulate", help="run gains on the model along the thesis-like reference")
    q.add_argument("--gains", help="gains file (JSON, CONTROL.md names); default thesis PID")
    _common(q)
    q.add_argument("--load", type=float, default=1000.0, help="load on the forks [kg]")
    q.add_argument("--noise-seed", type=int, default=None, help="sensor noise seed (off)")
    q.add_argument("--out", required=True, help="output directory")
    q.set_defaults(func=cmd_control_simulate)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(0)
