"""Command line: ``jaxlift posterior LOG.csv ... --out DIR`` (uncertainty by MCMC)."""

from __future__ import annotations

import argparse

from ..calibrate.parallel import cpu_cores


def split_cpu(n: int) -> None:
    """One XLA CPU device per core, so that the walkers run on all cores (one jitted
    batch split across the devices: ``make_log_prob(devices=...)``). Possible only
    before the process's first JAX operation; else the devices stay as they are."""
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:  # JAX already running (e.g. main() called in a test)
        pass


def cmd_posterior(args) -> int:
    import pathlib

    n_dev = cpu_cores() if args.devices is None else args.devices
    split_cpu(n_dev)

    import jax

    import jaxlift as jl
    from jaxlift.cli.common import read_logs
    from jaxlift.posterior.moves import MOVES
    from jaxlift.workflows.posterior import run_posterior

    logs = read_logs(args.logs, args)
    params = None
    if args.params:
        params = jl.load_params_json(args.params, jl.all_param_infos("all"))
    effects = [e.strip() for e in (args.effects or "").split(",") if e.strip()]
    if args.params and args.effects is None:  # effects whose parameters are in the file
        effects = [n for n, c in jl.EFFECTS.items() if set(c.param_infos()) & set(params)]
    out = pathlib.Path(args.out)
    if (out / "chain.h5").exists():
        print(f"{out} has a chain: resuming it", flush=True)
    print(
        f"posterior over {', '.join(lg.name for lg in logs)}; effects: "
        f"{', '.join(effects) or 'none (baseline)'}; calibration: "
        f"{args.params or 'least-squares fit first'}",
        flush=True,
    )
    res = run_posterior(
        logs,
        out,
        effects=effects,
        params=params,
        sample=args.sample,
        likelihood=args.likelihood,
        sample_noise=args.sample_noise,
        conditioning="conditional" if args.conditional else "marginal",
        n_walkers=args.walkers,
        max_steps=args.max_steps,
        seed=args.seed,
        n_predictive=args.predictive,
        n_loglik=args.loglik_draws,
        beta_oil=args.beta_oil,
        move=MOVES[args.move](),
        devices=None if args.devices is None else min(args.devices, len(jax.local_devices())),
        progress=lambda line: print(line, flush=True),
        progress_bar=True,
    )
    if not res["converged"]:
        print(
            f"NOT CONVERGED after {res['steps']} steps (max tau "
            f"{max(v for v in res['tau'].values()):.1f}); run the same command again to go on"
        )
    for row in res["summary"]:
        print(
            f"  {row['parameter']:14s} {row['mean']:12.5g}  90 % HDI "
            f"[{row['HDI 5 %']:.5g}, {row['HDI 95 %']:.5g}] {row['unit']}"
        )
    if res["air"] is not None:
        print(res["air"]["text"])
    print(
        f"wrote {out}/chain.h5, posterior.nc, summary.csv, posterior.json, params.json, "
        "report.md, report.html, figures/"
    )
    return 0 if res["converged"] else 1


def _walkers(text: str) -> int | str:
    """``--walkers``: ``auto`` or an even number >= 2 (the lower bound that depends on
    the number of sampled parameters is checked by the sampler, with its reason)."""
    if text == "auto":
        return text
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an even number or 'auto', not {text!r}"
        ) from None
    if n < 2 or n % 2:
        raise argparse.ArgumentTypeError(f"expected an even number >= 2 or 'auto', not {n}")
    return n


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add this module's sub-commands to ``jaxlift``'s parser."""
    from jaxlift.posterior.moves import DEFAULT_MOVE, MOVES

    p = sub.add_parser(
        "posterior",
        help="posterior uncertainty of the bulk modulus and friction (emcee), air content",
    )
    p.add_argument("logs", nargs="+", help="logs (CSV, Parquet or MDF 4; docs/data.md)")
    p.add_argument("--out", required=True, help="output directory (resumes a chain in it)")
    p.add_argument(
        "--params",
        help="calibrated parameters (params.json of `jaxlift fit`); default: a least-squares "
        "fit first",
    )
    p.add_argument(
        "--effects",
        default=None,
        help="effects switched on (a,b); default: those whose parameters are in --params",
    )
    p.add_argument(
        "--sample",
        default=None,
        help="parameters to sample (names or sets dynamic, motor, effects); default: "
        "beta, cf_con, cf_in, cf_out, d and the effects' parameters",
    )
    p.add_argument(
        "--conditional",
        action="store_true",
        help="hold the motor set and the initial-height offsets at their least-squares "
        "values (default: marginalised, so that their uncertainty reaches the intervals)",
    )
    p.add_argument(
        "--walkers",
        type=_walkers,
        default="auto",
        help="number of walkers (even, at least twice the sampled parameters), or auto "
        "(the default since 2026-12-01; 32 before): 2 x parameters + 4, at least 16, a "
        "multiple of 4, as `jaxlift report` uses (the chain is about as long in steps as "
        "with more walkers, with fewer effective samples, ~47 per walker: 680-1100 for "
        "the shipped logs' five parameters with 16). A chain started with another number "
        "resumes only with that number",
    )
    p.add_argument("--max-steps", type=int, default=20_000, help="step limit (default 20000)")
    p.add_argument("--seed", type=int, default=0, help="seed of walkers and sampler")
    p.add_argument(
        "--likelihood",
        choices=("ar1", "white"),
        default="ar1",
        help="residual model: AR(1) fitted to the least-squares residuals (default) or "
        "white noise at the sensor levels",
    )
    p.add_argument(
        "--sample-noise", action="store_true", help="also sample a noise factor per signal"
    )
    p.add_argument(
        "--predictive", type=int, default=64, help="posterior-predictive draws (default 64)"
    )
    p.add_argument(
        "--loglik-draws", type=int, default=128,
        help="draws for the pointwise log-likelihood in posterior.nc (az.loo, az.compare; "
        "default 128, 0: none)",
    )  # fmt: skip
    p.add_argument("--beta-oil", type=float, default=1.4e9, help="bulk modulus of ideal oil [Pa]")
    p.add_argument(
        "--move",
        choices=list(MOVES),
        default=DEFAULT_MOVE,
        help=f"emcee proposal (default {DEFAULT_MOVE}: differential evolution mixed with "
        "independence proposals from the Laplace approximation, about 4x shorter "
        "autocorrelation times than de-snooker where the posterior is close to Gaussian "
        "(the shipped logs' model: tau 7 against 31 steps), with the share of "
        "independence steps chosen before sampling from how well that proposal covers "
        "the posterior (0.05 where it does not); de-snooker: differential "
        "evolution with snooker updates, about 3x shorter than stretch, emcee's default; "
        "kde: can strand walkers; docs/statistics.md, Sampler); a chain resumes with the "
        "move it was started with",
    )
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        help="split each batch of walkers across this many XLA CPU devices, one per core "
        "(default: the number of cores; 1: one device)",
    )
    p.set_defaults(func=cmd_posterior)
