"""Command-line interface: ``jaxlift COMMAND ...`` (see ``jaxlift --help``)."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from importlib.metadata import version

from .common import add_log_options, log_options, read_logs, setup_jax


def cmd_simulate(args) -> int:
    import jaxlift as jl
    from jaxlift.workflows.simulate import run_simulate

    (log,) = read_logs([args.log], args)
    plant, effects = jl.load_model(args.params, args.effects)
    out = pathlib.Path(args.out)
    _, rms = run_simulate(log, plant, effects, out)
    print(f"wrote {out} ({log.n} samples) and {out.with_suffix('.png')}")
    print(f"effects: {[e.name for e in effects] or 'none (baseline)'}")
    print(f"RMS height error against the log: {rms['height_m'] * 1e3:.2f} mm")
    if "speed_mps" in rms:
        print(f"RMS speed error against the log: {rms['speed_mps'] * 1e3:.2f} mm/s")
    return 0


def cmd_fit(args) -> int:
    import jaxlift as jl
    from jaxlift.workflows.fit import misfit_hint, run_fit

    fit_logs = read_logs(args.logs, args)
    val_logs = read_logs(args.validate or [], args)
    init = None
    if args.params:
        init = jl.load_params_json(args.params, jl.all_param_infos("all"))
    effects = [e for e in (args.effects or "").split(",") if e.strip()]
    print(
        f"fitting {len(fit_logs)} log(s) ({', '.join(lg.name for lg in fit_logs)}), "
        f"held out: {', '.join(lg.name for lg in val_logs) or 'none'}; "
        f"effects: {', '.join(effects) or 'none (baseline)'}; free: {args.free}",
        flush=True,
    )
    result, metrics = run_fit(
        fit_logs,
        val_logs,
        effects=effects,
        free=args.free,
        init=init,
        staged=not args.joint,
        n_starts=args.starts,
        seed=args.seed,
        out_dir=args.out,
        progress=lambda line: print(line, flush=True),
    )
    print(f"converged: {result.converged}")
    for name, lm in metrics["logs"].items():
        print(fit_log_line(name, lm))
    if result.undetermined:
        print(f"not determined by these data: {', '.join(result.undetermined)}")
    hint = misfit_hint(result.chi2_per_log, result.undetermined) if result.converged else None
    if hint:
        print(hint)
    print(f"wrote {args.out}/params.json, metrics.json, report.md, report.html, figures/")
    return 0 if result.converged else 1


def fit_log_line(name: str, lm: dict) -> str:
    """One log's line of ``jaxlift fit``'s summary from its ``metrics.json`` entry
    (``before``: nominal values, ``after``: fitted): chi2/N and RMS speed error before ->
    after, and a simulation that failed named on its side (a log whose nominal values
    leave the mast can still be fitted well: the fitted value is shown)."""
    b, a = lm["before"], lm["after"]
    head = f"  {name:24s} {lm['role']:9s}"
    if "failed" in a:
        return f"{head} not simulated with the fitted values ({a['failed']})"
    chi2_b = "    failed" if "failed" in b else f"{b['chi2_per_sample']:10.3g}"
    rms_b = "failed" if "failed" in b else f"{b.get('rms_speed_mmps', float('nan')):6.2f}"
    line = (
        f"{head} chi2/N {chi2_b} -> {a['chi2_per_sample']:8.3g}   RMS speed {rms_b}"
        f" -> {a.get('rms_speed_mmps', float('nan')):6.2f} mm/s"
    )
    if "failed" in b:
        line += f"\n  {'':24s} {'':9s} (nominal values not simulated: {b['failed']})"
    return line


def cmd_diagnose(args) -> int:
    from jaxlift.workflows.diagnose import run_diagnose

    logs = read_logs(args.logs, args)
    val = read_logs(args.validate or [], args)
    print(
        f"diagnosing {len(logs)} log(s); held out: {', '.join(lg.name for lg in val) or 'none'}",
        flush=True,
    )
    steps = run_diagnose(
        logs,
        val,
        out_dir=args.out,
        iterate=not args.once,
        max_effects=args.max_effects,
        n_starts=args.starts,
        seed=args.seed,
        shape=args.shape,
        progress=lambda line: print(line, flush=True),
    )
    from jaxlift.calibrate.diagnose import final_verdict, found_effects, kept_effects

    found, kept = found_effects(steps), kept_effects(steps)
    print(f"verdict: {steps[0].verdict}")
    if len(steps) > 1:
        print(f"missing effects, in order: {', '.join(kept) or 'none'}")
        if dropped := [e for e in found if e not in kept]:
            print(f"named on the way and dropped again (backward check): {', '.join(dropped)}")
        print(f"final verdict: {final_verdict(steps)}")
    if final_verdict(steps) in ("undecided", "unexplained"):
        print(f"{final_verdict(steps)}: " + "; ".join(steps[-1].reasons))
    with open(pathlib.Path(args.out) / "diagnosis.json", encoding="utf-8") as fh:
        shape = json.load(fh).get("missing_shape")
    if shape and "laws" in shape:
        for sig in ("force", "flow"):
            share = shape["shares"][sig]
            ev = f"evidence {shape['evidence'][sig]:.0f}, share " + (
                "n/a" if share is None else f"{share:.0%}"
            )
            if shape["needed"][sig]:
                print(f"missing {sig} (needed, {ev}): {shape['laws'][sig]['law']}")
            else:  # a law fitted to a signal the data do not need would be read as one
                print(f"missing {sig}: not needed ({ev})")
    elif shape:
        print(f"shape of what is missing: {shape['failed']}")
    print(f"wrote {args.out}/diagnosis.json, report.md, report.html, figures/")
    return 0


def cmd_report(args) -> int:
    from jaxlift.calibrate.parallel import cpu_cores
    from jaxlift.cli.posterior import split_cpu

    split_cpu(cpu_cores())  # the posterior stage's walkers on every core (before any JAX)
    from jaxlift.workflows.report import gain_order, run_report

    logs = read_logs(args.logs, args)
    val = read_logs(args.validate or [], args)
    print(
        f"report on {len(logs)} log(s); held out: {', '.join(lg.name for lg in val) or 'none'}"
        f"{' (quick)' if args.quick else ''}",
        flush=True,
    )
    s = run_report(
        logs, val, out_dir=args.out, quick=args.quick, seed=args.seed,
        progress=lambda line: print(line, flush=True), progress_bar=True,
    )  # fmt: skip
    if s["missing_effects"]:
        print(f"missing effects, in order: {', '.join(s['missing_effects'])}")
    print(f"final verdict: {s['verdict']}")
    if s["air"]:
        print(f"air: {s['air']['text']}")
    order = sorted(s["gains"], key=gain_order)
    print("recommended gains: " + ", ".join(f"{k} = {s['gains'][k]:.4g}" for k in order))
    print(f"stage times [s]: {', '.join(f'{k} {v:.0f}' for k, v in s['stage_wall_s'].items())}")
    return 0


def cmd_fleet(args) -> int:
    from jaxlift.fleet import run_fleet

    settings = {
        "job": args.job,
        "search": args.search,
        "max_effects": args.max_effects,
        "n_starts": args.starts,
        "seed": args.seed,
        "posterior": args.posterior,
        "posterior_max_steps": args.posterior_steps,
        # the workers register the user's effects themselves (their own processes)
        "effect_files": [str(pathlib.Path(f).resolve()) for f in args.effect_file],
        **log_options(args),  # channel_map, resample: how every job reads its logs
    }
    summary = run_fleet(
        args.fleet_dir,
        args.out,
        settings=settings,
        workers=args.workers,
        scheduler=args.scheduler,
        retries=args.retries,
        progress=lambda line: print(line, flush=True),
        progress_bar=True,
    )
    print(
        f"{summary['jobs']} job(s): {summary['ran']} run, {summary['skipped']} finished "
        f"before, {summary['failed']} failed"
    )
    for v, flags in summary["flagged"].items():
        print(f"{v}: " + "; ".join(flags))
    print(f"wrote {args.out}/fleet.parquet, fleet.csv, flags.json, report.md, report.html")
    return 1 if summary["failed"] else 0


def build_parser() -> argparse.ArgumentParser:
    from jaxlift.model.effects import EFFECTS

    parser = argparse.ArgumentParser(
        prog="jaxlift",
        description="Differentiable digital twin of an AGV's hydraulic lift.",
    )
    parser.add_argument("--version", action="version", version=f"jaxlift {version('jaxlift')}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("simulate", help="simulate a log's input and compare with the log")
    p.add_argument("log", help="test-run log (CSV, Parquet or MDF 4; docs/data.md)")
    p.add_argument("--params", help="parameter file (JSON, docs/model.md names); default nominal")
    p.add_argument(
        "--effects",
        default=None,
        help=f"comma-separated effects to switch on ({', '.join(EFFECTS)}); default: "
        "those whose parameters appear in --params",
    )
    p.add_argument("--out", required=True, help="output CSV (a PNG plot is written beside it)")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "fit",
        help="calibrate the model on logs (Levenberg-Marquardt) and report where it fails",
    )
    p.add_argument("logs", nargs="+", help="logs to fit (CSV, Parquet or MDF 4)")
    p.add_argument("--validate", nargs="*", default=[], help="held-out logs (not fitted)")
    p.add_argument("--effects", default="", help="effects to add to the baseline (a,b)")
    p.add_argument(
        "--free",
        default="all",
        help="free parameters: sets motor, dynamic, effects, all, and/or names (a,b)",
    )
    p.add_argument("--params", help="starting values (JSON, docs/model.md names); default nominal")
    p.add_argument("--starts", type=int, default=4, help="starting points per stage")
    p.add_argument("--seed", type=int, default=0, help="seed of the starting points")
    p.add_argument(
        "--joint", action="store_true", help="fit all free parameters at once (default: staged)"
    )
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser(
        "diagnose",
        help="fit the baseline, test every candidate effect, name the missing one(s)",
    )
    p.add_argument("logs", nargs="+", help="logs to fit (CSV, Parquet or MDF 4)")
    p.add_argument("--validate", nargs="*", default=[], help="held-out logs (not fitted)")
    p.add_argument(
        "--once",
        action="store_true",
        help="one diagnosis only (default: add the winner and "
        "diagnose again until none is missing)",
    )
    p.add_argument("--starts", type=int, default=2, help="starting points of each fit")
    p.add_argument("--max-effects", type=int, default=3, help="at most this many effects added (3)")
    p.add_argument(
        "--shape", choices=("auto", "always", "never"), default="auto",
        help="estimate the shape of what the final model misses (a force on the fork, a "
        "flow into the cylinder, and a law for each): when the verdict is unexplained "
        "(auto), always, or never",
    )  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser(
        "report",
        help="the whole story in one report: fit, diagnosis, posterior, tuned gains",
    )
    p.add_argument("logs", nargs="+", help="logs to fit (CSV, Parquet or MDF 4)")
    p.add_argument("--validate", nargs="*", default=[], help="held-out logs (not fitted)")
    p.add_argument(
        "--quick", action="store_true",
        help="small budget (~3 min): candidates screened, not confirmed; Laplace instead of "
        "MCMC; nominal tuning only",
    )  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="seed of fits, posterior and draws")
    p.add_argument(
        "--out", required=True,
        help="output directory (a second run reuses the stages whose inputs did not change)",
    )  # fmt: skip
    p.set_defaults(func=cmd_report)

    p = sub.add_parser(
        "fleet",
        help="diagnose every vehicle's logs (vehicle/date folders) on Dask; trends and flags",
    )
    p.add_argument("fleet_dir", help="folder of <vehicle>/<date>/ run folders (docs/fleet.md)")
    p.add_argument("--out", required=True, help="output directory (re-runs skip finished jobs)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument(
        "--scheduler", default=None,
        help="address of a running Dask scheduler (tcp://host:8786): run there instead",
    )  # fmt: skip
    p.add_argument("--retries", type=int, default=2, help="retries of a failed job (default 2)")
    p.add_argument(
        "--job", choices=["diagnose", "fit"], default="diagnose",
        help="per job: fit and diagnose (default), or the baseline fit only",
    )  # fmt: skip
    p.add_argument(
        "--search", choices=["on-misfit", "always"], default="on-misfit",
        help="search the candidate effects only where the baseline fit leaves a "
        "significant error (default), or on every job",
    )  # fmt: skip
    p.add_argument("--max-effects", type=int, default=2, help="effects added per job (default 2)")
    p.add_argument("--starts", type=int, default=2, help="starts per fit (default 2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fits' random starts")
    p.add_argument(
        "--posterior", choices=["laplace", "mcmc"], default="laplace",
        help="the intervals per job: the fit's standard errors (default, seconds) or "
        "the sampled posterior of the final model (minutes per job)",
    )  # fmt: skip
    p.add_argument(
        "--posterior-steps", type=int, default=5000,
        help="with --posterior mcmc: at most this many sampler steps per job",
    )  # fmt: skip
    p.set_defaults(func=cmd_fleet)

    from jaxlift.cli.control import add_parsers as add_control_parsers
    from jaxlift.cli.posterior import add_parsers as add_posterior_parsers

    add_posterior_parsers(sub)  # jaxlift posterior
    add_control_parsers(sub)  # jaxlift tune, jaxlift control simulate
    for leaf in _leaf_parsers(parser):
        if {a.dest for a in leaf._actions} & {"log", "logs", "fleet_dir"}:  # reads logs
            add_log_options(leaf)
        leaf.add_argument(
            "--effect-file",
            action="append",
            default=[],
            metavar="PATH",
            help="a Python file defining your own effect(s) (subclasses of "
            "jaxlift.AbstractEffect; docs/effects.md): used like the built-in ones. "
            "Repeatable",
        )
    return parser


def _leaf_parsers(parser: argparse.ArgumentParser):
    """Every (sub)command's parser that has no subcommands of its own."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield parser
    for action in subs:
        for child in dict.fromkeys(action.choices.values()):  # aliases: once
            yield from _leaf_parsers(child)


def load_user_effects(paths) -> list[str]:
    """Register installed packages' effects (entry points ``jaxlift.effects``) and
    those of ``--effect-file`` files; their names."""
    import jaxlift as jl

    names = jl.load_entry_point_effects()
    for path in paths or []:
        names += jl.load_effect_file(path)
    return names


#: The packages whose versions every output folder records.
PROVENANCE_PACKAGES = (
    "jaxlift", "jax", "jaxlib", "diffrax", "optimistix", "equinox", "lineax", "emcee",
    "arviz", "numpy", "scipy", "matplotlib", "optax",
)  # fmt: skip


def write_provenance(args, argv, rc: int) -> None:
    """``provenance.json`` in the command's output folder (``--out``; beside the file
    for ``simulate``): the command line, package versions, seeds, and the SHA-256 of
    every input file (logs, parameter and effect files), so that a result can be
    traced to what made it."""
    import datetime
    import hashlib
    import json
    import platform
    from importlib.metadata import PackageNotFoundError

    out = getattr(args, "out", None)
    if not out:
        return
    folder = pathlib.Path(out)
    if not folder.is_dir():
        folder = folder.parent
    if not folder.is_dir():
        return
    inputs = []
    for key in ("log", "logs", "validate", "params", "effect_file", "gains", "channel_map"):
        value = getattr(args, key, None)
        for path in value if isinstance(value, list) else [value]:
            if path and pathlib.Path(path).is_file():
                digest = hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()
                inputs.append({"path": str(path), "sha256": digest})
    versions = {}
    for pkg in PROVENANCE_PACKAGES:
        try:
            versions[pkg] = version(pkg)
        except PackageNotFoundError:
            versions[pkg] = None
    seeds = {k: v for k, v in vars(args).items() if "seed" in k}
    record = {
        "command": ["jaxlift", *(sys.argv[1:] if argv is None else argv)],
        "exit_code": rc,
        "finished_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "versions": versions,
        "seeds": seeds,
        "inputs": inputs,
    }
    (folder / "provenance.json").write_text(json.dumps(record, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_jax()
    import jaxlift as jl

    try:
        user = load_user_effects(getattr(args, "effect_file", []))
        if user:
            print(f"user effects: {', '.join(user)}", flush=True)
        rc = args.func(args)
        write_provenance(args, argv, rc)
        return rc
    except (
        jl.LogError,
        jl.ParameterError,
        jl.SimulationError,
        jl.ChainFileLocked,
        ValueError,
    ) as err:
        print(f"jaxlift {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
