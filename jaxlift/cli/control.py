"""Command line: ``jaxlift tune`` and ``jaxlift control simulate``.

``jaxlift tune LOG.csv ... [--params params.json] [--posterior DIR] --out DIR`` tunes
the PID gains by gradient through the closed-loop simulation of the calibrated model
(nominal, and robust over parameter draws) and writes ``gains.json``, figures and a
report. ``jaxlift control simulate --gains gains.json --out DIR`` runs any gains on the
model along the thesis-like reference and reports the figures of "good".
"""

from __future__ import annotations

import argparse
import pathlib
import sys


def _progress(line: str) -> None:
    print(line, flush=True)


def cmd_tune(args) -> int:
    from jaxlift.cli.common import read_logs
    from jaxlift.workflows.tune import calibrated_model, run_tune

    logs = read_logs(args.logs, args)
    plant, effects, params_path = calibrated_model(
        args.params,
        args.effects,
        posterior_dir=args.posterior,
        logs=logs,
        out_dir=args.out,
        progress=_progress,
    )
    run_tune(
        logs,
        plant,
        effects,
        args.out,
        params_path=params_path,
        posterior_dir=args.posterior,
        scheduled=args.scheduled,
        sampled=not args.continuous,
        T_c=args.Tc,
        noise_seeds=None if args.noise_seeds == 0 else range(args.noise_seeds),
        steps=args.steps,
        rtol=args.rtol,
        robust_draws=args.robust_draws,
        eval_draws=args.eval_draws,
        seed=args.seed,
        time_scale=args.time_scale,
        report_noise_seed=None if args.no_report_noise else args.report_noise_seed,
        progress=_progress,
    )
    return 0


def cmd_control_simulate(args) -> int:
    from jaxlift.control.controller import PID, THESIS_PID, load_gains
    from jaxlift.workflows.tune import calibrated_model, run_control_simulate

    ctrl = load_gains(args.gains) if args.gains else PID().with_gains(THESIS_PID)
    plant, effects, params_path = calibrated_model(args.params, args.effects)
    _, figs = run_control_simulate(
        ctrl,
        plant,
        effects,
        args.out,
        load=args.load,
        noise_seed=args.noise_seed,
        sampled=args.sampled,
        T_c=args.Tc,
        time_scale=args.time_scale,
        label=f"{ctrl.kind} ({args.gains or 'thesis gains'})",
        model_label=str(params_path),
    )
    print(f"gains: {ctrl.gain_values()}")
    for k, v in figs.items():
        print(f"  {k:22s} {v:10.4g}")
    out = pathlib.Path(args.out)
    print(f"wrote {out / 'response.csv'}, response.png, figures.json")
    return 0


def _common(p: argparse.ArgumentParser, *, tune: bool = False) -> None:
    p.add_argument("--params", help="parameter file (JSON, from jaxlift fit)")
    p.add_argument("--effects", default=None, help="effects (a,b); default: those in --params")
    if tune:  # tuning is of the loop as deployed unless told otherwise
        p.add_argument(
            "--continuous",
            action="store_true",
            help="tune the continuous-time controller (default: sampled every --Tc, duty held)",
        )
        p.add_argument(
            "--noise-seeds",
            type=int,
            default=4,
            help="tune with the speed sensor's noise, cost averaged over this many seeds "
            "(0: no noise; default 4)",
        )
    else:
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
        description="Tune the lift controller's gains (docs/control.md) on the calibrated model, "
        "as deployed (sampled every --Tc with the duty held, the speed sensor's noise "
        "averaged over --noise-seeds seeds): nominal, and robust over parameter draws "
        "(posterior, the least-squares covariance of the fit, or stated spreads); writes "
        "gains.json, figures and a report.",
    )
    p.add_argument("logs", nargs="+", help="logs (docs/data.md): their loads are the tuning loads")
    _common(p, tune=True)
    p.add_argument("--posterior", help="posterior directory (jaxlift posterior)")
    p.add_argument("--scheduled", action="store_true", help="tune the scheduled PID (18 + N)")
    p.add_argument("--steps", type=int, default=30, help="evaluations per tuning (LM; at most)")
    p.add_argument("--robust-draws", type=int, default=16, help="draws for robust tuning")
    p.add_argument("--eval-draws", type=int, default=100, help="held-out draws for the report")
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
    q.add_argument("--gains", help="gains file (JSON, docs/control.md names); default thesis PID")
    _common(q)
    q.add_argument("--load", type=float, default=1000.0, help="load on the forks [kg]")
    q.add_argument("--noise-seed", type=int, default=None, help="sensor noise seed (off)")
    q.add_argument("--out", required=True, help="output directory")
    q.set_defaults(func=cmd_control_simulate)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(0)
