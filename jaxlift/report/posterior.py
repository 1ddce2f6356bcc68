"""Outputs of ``jaxlift posterior``: the ArviZ DataTree, the summary, figures and the
uncertainty report (Markdown + HTML). Nothing here prints."""

from __future__ import annotations

import json
import math
import pathlib
from collections.abc import Sequence

import arviz as az
import numpy as np
import xarray as xr

from ..analysis.oscillation import zoom_windows
from ..analysis.regimes import segment_log
from ..model.constants import BETA_OIL
from ..model.log import Log
from ..model.params import to_unconstrained
from ..posterior.air import AIR_THRESHOLD, air_content, air_verdict, mean_working_pressure
from ..posterior.pointwise import pointwise_groups
from ..posterior.predictive import MOTOR_DRAWS_GROUP, motor_draws_dataset, predictive_with_motor
from ..posterior.problem import (
    NOISE_NAMES,
    NUISANCE_RCOND,
    NUISANCE_STEP_GAIN,
    PosteriorProblem,
    largest_step_gain,
)
from ..posterior.sampler import SamplerRun, posterior_samples
from .document import Report
from .figures import new_figure, with_pyplot_figures


def build_datatree(problem: PosteriorProblem, samples: dict, lp: np.ndarray, extra: dict,
                   attrs: dict, seed: int = 0):  # fmt: skip
    """The posterior (walkers as chains; physical units; derived quantities) and prior
    draws as an ArviZ ``DataTree``."""

    post = {k: np.asarray(v) for k, v in samples.items()}
    post.update(extra)
    rng = np.random.default_rng(seed + 1)
    prior = {}
    for n in problem.names:
        info, pr = problem.infos[n], problem.priors[n]
        d = pr.sample(rng, 8000)
        d = d[(d >= info.lower) & (d <= info.upper)][:4000]
        prior[n] = d[None, :]
    return az.from_dict(
        {"posterior": post, "sample_stats": {"lp": lp}, "prior": prior},
        attrs={"posterior": attrs},
    )


def _summary(dt, names, tau_by_name):

    s = az.summary(dt, var_names=names, ci_prob=0.9, ci_kind="hdi", round_to="none")
    s = s.astype(float)
    s.insert(0, "tau_steps", [tau_by_name.get(n, float("nan")) for n in s.index])
    return s


def write_outputs(
    problem: PosteriorProblem,
    run: SamplerRun,
    logs: Sequence[Log],
    out: pathlib.Path,
    *,
    n_predictive: int = 64,
    n_loglik: int = 128,
    seed: int = 0,
    beta_oil: float = BETA_OIL,
) -> dict:
    """Write ``posterior.nc``, ``summary.csv``, ``posterior.json``, figures and the report
    into ``out``; returns the content of ``posterior.json``.

    ``posterior.nc`` holds the groups ``posterior``, ``sample_stats``, ``prior`` and,
    from ``n_loglik`` draws (0: left out), ``observed_data``, ``posterior_predictive``
    (``n_predictive`` of them, with noise) and ``log_likelihood`` (pointwise per
    second of each log and signal: :mod:`jaxlift.posterior.pointwise`), so that
    ``az.loo`` and ``az.compare`` work on it. ``n_predictive`` draws also make the
    prediction bands. Where the problem takes the nuisances' Gauss--Newton step
    (``nuisance_steps``), the ``max(n_predictive, n_loglik)`` simulated draws and the
    motor set of each go into the group ``motor_draws`` (read by
    :func:`~jaxlift.posterior.predictive.posterior_draws`)."""
    figs = out / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    samples, lp, thin = posterior_samples(problem, run.path, run.tau)
    tau_by_name = {n: float(t) for n, t in zip(problem.names, run.tau)}
    extra = {}
    p_mean = mean_working_pressure(problem)
    air = None
    has_hose = "hose_compliance" in problem.effects
    if "beta" in samples:
        phi = air_content(samples["beta"], p_mean, beta_oil)
        extra["air_fraction"] = phi
        air = air_verdict(phi.ravel(), p_mean, has_hose)
    if "cf_in" in samples and "cf_out" in samples:
        extra["cf_out_cf_in5"] = samples["cf_out"] * samples["cf_in"] ** 5
    attrs = {
        "jaxlift_effects": ",".join(problem.effects),
        "jaxlift_likelihood": problem.likelihood,
        "jaxlift_converged": int(run.converged),
        "jaxlift_steps": run.iteration,
        "jaxlift_burn": thin["burn"],
        "jaxlift_thin": thin["thin"],
        "jaxlift_p_mean_pa_abs": p_mean,
        "jaxlift_beta_oil_pa": beta_oil,
    }
    dt = build_datatree(problem, samples, lp, extra, attrs, seed)
    # draws for the prediction bands and the pointwise log-likelihood (az.loo/compare)
    rng = np.random.default_rng(seed + 2)
    flat = np.stack([np.asarray(samples[n]).ravel() for n in problem.names], axis=-1)
    n_draws = min(max(n_predictive, n_loglik), flat.shape[0])
    idx = rng.choice(flat.shape[0], size=n_draws, replace=False)
    thetas = np.stack(
        [np.asarray(to_unconstrained(problem.infos[n], flat[idx, k]))
         for k, n in enumerate(problem.names)], axis=-1,
    )  # fmt: skip
    pred, motor = predictive_with_motor(problem, thetas)
    ok = np.all([pr["ok"] for pr in pred], axis=0)
    if problem.nuisance_steps and np.any(ok):  # the stepped motor set needs the logs
        motor_ok = {k: v[ok] for k, v in motor.items()}
        dt[MOTOR_DRAWS_GROUP] = xr.DataTree(motor_draws_dataset(problem, thetas[ok], motor_ok))
    if n_loglik > 0 and np.any(ok):
        groups = pointwise_groups(
            problem, thetas[ok], [{k: v[ok] for k, v in pr.items()} for pr in pred],
            n_predictive=n_predictive, seed=seed + 3,
        )  # fmt: skip
        for group, ds in groups.items():
            dt[group] = xr.DataTree(ds)
        dt["log_likelihood"].attrs["jaxlift_failed_draws"] = int(np.sum(~ok))
    nc = out / "posterior.nc"
    if nc.exists():
        nc.unlink()
    dt.to_netcdf(nc, engine="h5netcdf")
    names = list(problem.names) + list(extra)
    summ = _summary(dt, names, tau_by_name)
    summ.to_csv(out / "summary.csv", index_label="parameter", float_format="%.6g")

    # figures
    fig_paths = {}
    fig_paths["trace"] = _az_fig("plot_trace_dist", dt, problem.names, figs / "trace.png")
    fig_paths["pair"] = _az_fig("plot_pair", dt, problem.param_names, figs / "pair.png")
    fig_paths["posterior"] = _az_fig("plot_dist", dt, names, figs / "posterior.png")
    fig_paths["prior_posterior"] = _plot_prior_posterior(problem, samples, figs)
    fig_paths["tau"] = _plot_tau(run, figs)
    if air is not None:
        fig_paths["air"] = _plot_air(extra["air_fraction"], air, figs)
    pred_figs = []
    for log, pr in zip(logs, pred):
        band = {k: v[:n_predictive] for k, v in pr.items()}
        pred_figs.extend(_plot_bands(log, band, figs))

    rows = []
    for n in names:
        r = summ.loc[n]
        info = problem.infos.get(n)
        rows.append(
            {
                "parameter": n,
                "unit": info.unit if info else ("-" if n == "air_fraction" else "N"),
                "least squares": problem.values.get(n, float("nan")) if info else float("nan"),
                "mean": r["mean"],
                "sd": r["sd"],
                "HDI 5 %": r["hdi90_lb"],
                "HDI 95 %": r["hdi90_ub"],
                "tau [steps]": r["tau_steps"],
                "ESS bulk": r["ess_bulk"],
                "R-hat": r["r_hat"],
            }
        )
    result = {
        "converged": run.converged,
        "steps": run.iteration,
        "resumed_from": run.resumed_from,
        "tau": tau_by_name,
        "tau_factor": run.tau_factor,
        "acceptance": run.acceptance,
        "burn": thin["burn"],
        "thin": thin["thin"],
        "n_draws": int(flat.shape[0]),
        "wall_s_this_run": run.wall_s,
        "move": run.move,
        "move_settings": run.move_settings,
        "n_walkers": run.n_walkers,
        "n_devices_this_run": run.n_devices,
        "summary": rows,
        "air": air,
        "effects": list(problem.effects),
        "likelihood": problem.likelihood,
        "sampled": list(problem.names),
    }
    with open(out / "posterior.json", "w", encoding="utf-8") as fh:
        json.dump(_jsonable(result), fh, indent=2)
        fh.write("\n")
    _report(problem, run, logs, out, rows, air, fig_paths, pred_figs, thin, p_mean)
    return result


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _move_note(settings: dict) -> str:
    """The move's choices before sampling, as the report says them ('' without any)."""
    if "laplace_weight" not in settings:
        return ""
    note = f" with independence steps at {settings['laplace_weight']:.2g}"
    if settings.get("pareto_khat") is not None:
        note += (
            f", chosen from its proposal's Pareto k-hat {settings['pareto_khat']:.2f} and "
            f"relative ESS {settings['ess_fraction']:.2f}"
        )
    return note


def conditioning_text(
    nuisance: tuple[str, ...], x0_offsets: dict, ls_info: dict, nuisance_steps: int
) -> str:
    """The report's paragraph on what the intervals are conditional on: the marginalised
    nuisances (``nuisance``, from :class:`PosteriorProblem`), what is held and why, the
    check of the linearised nuisance map with its failed points, and the step (or, with
    no nuisance, the conditional mode). ``x0_offsets`` in m."""
    offsets = ", ".join(f"`{k}` {v * 1e3:+.3f} mm" for k, v in x0_offsets.items())
    if nuisance:
        moving = ", ".join(f"`{n}`" for n in nuisance if not n.startswith("x0@"))
        held = (
            f"Marginalised, not fixed: {moving or 'no motor parameter'} and each log's "
            f"initial-height offset (least squares: {offsets}) move with the sampled "
            "parameters along their conditional optimum, linearised at the least-squares "
            "optimum (a Gauss-Newton profile; exact for a model linear in them), so that "
            "their uncertainty reaches the intervals. Fixed at the least-squares values: "
            "every other parameter not sampled."
        )
        stop = ls_info.get("offsets_held_at_stop", [])
        if stop:
            held += (
                f" Held: {', '.join(f'`{n}`' for n in stop)}, of a log that starts on the "
                "bottom stop (its likelihood is one-sided there: a lower start changes "
                "nothing, which the linearised optimum cannot follow)."
            )
        check = ls_info.get("nuisance_check")
        name, lin, stp = largest_step_gain(check) if check else ("", 0.0, 0.0)
        if name:  # (no name: no point of the check was simulated; failed says where)
            held += (
                " Checked: one standard deviation either way along each sampled parameter, "
                "one Gauss-Newton step of the nuisances from that linearisation gains at "
                f"most {lin - stp:.2f} in log-likelihood (along `{name}`: a fall of "
                f"{lin:.2f} on it, {stp:.2f} after the step; a quadratic falls 0.5)."
            )
        if check and check.get("failed"):
            held += (
                " **The simulation failed** at " + ", ".join(check["failed"]) + " (along "
                "the covariance column): the log-probability is -inf there, so the "
                "posterior ends within one standard deviation of the optimum on that "
                "side; where the model fits, that is a wall of the solver (its step "
                "limit, the mast's range), not of the data."
            )
        if nuisance_steps:
            held += (
                f" Above {NUISANCE_STEP_GAIN:g} the linearisation is not trusted: every "
                "evaluation of the posterior took that Gauss-Newton step (one more "
                "simulation of each log). The draws with their motor set "
                "(`jaxlift.posterior_draws`, for robust tuning) come from the "
                "predictive draws, which were simulated with the step (group "
                f"`{MOTOR_DRAWS_GROUP}` of posterior.nc)."
            )
        for direction in ls_info.get("nuisance_directions_held", []):
            mix = " against ".join(f"`{n}`" for n in direction["nuisances"])
            held += (
                f" Held: the direction of {mix}, which the logs barely determine (singular "
                f"value {direction['singular_value']:.1e} of the largest; below "
                f"{NUISANCE_RCOND:g} the linearised optimum is not trusted)."
            )
    else:
        held = (
            "Fixed at the least-squares values (`--conditional`): all parameters not "
            "sampled (the motor set among them: the posterior is conditional on the "
            "calibrated motor map) and each log's initial-height offset: "
            f"{offsets}. The intervals are conditional on them, and narrower than the "
            "marginal ones."
        )
    return held


def _report(problem, run, logs, out, rows, air, figs, pred_figs, thin, p_mean):
    rep = Report("jaxlift posterior: how sure are we?")
    conv = (
        f"**converged**: {run.iteration} steps > {run.tau_factor:g} x max tau "
        f"({max(run.tau):.1f} steps), tau stable"
        if run.converged
        else f"**NOT CONVERGED**: the step limit was reached after {run.iteration} steps; "
        f"{run.tau_factor:g} x max tau = {run.tau_factor * max(run.tau):.0f} steps would be "
        "needed. The intervals below are provisional; run the same command again to go on"
    )
    rep.text(
        f"Logs: {', '.join(f'`{lg.name}`' for lg in logs)}. Model: baseline"
        f"{''.join(' + ' + e for e in problem.effects)}. Sampled (emcee ensemble sampler, "
        f"{run.move} move{_move_note(run.move_settings)}, "
        f"{run.tau.size} coordinates): {', '.join(f'`{n}`' for n in problem.names)}. "
        f"Chain: {conv}."
    )
    if air is not None:
        rep.heading("Air in the oil")
        rep.text(air["text"])
        rep.text(
            f"Gas volume fraction `phi = p * (1/beta - 1/beta_oil)` at the mean working "
            f"pressure p = {p_mean / 1e6:.2f} MPa (absolute: gauge line pressure over the "
            f"moving parts of the logs + 1 atm), `beta_oil` = {BETA_OIL:.3g} Pa (ideal oil, "
            f"docs/model.md). Mean {air['phi_mean'] * 100:.3g} %, 90 % HDI "
            f"[{air['phi_hdi90'][0] * 100:.3g}, {air['phi_hdi90'][1] * 100:.3g}] %. Bleeding "
            f"is called indicated when the whole interval lies above {AIR_THRESHOLD:.1%} "
            "gas at working pressure (about 10 % free gas at atmospheric pressure at "
            "10 MPa: visibly foamy oil), not indicated when it lies wholly below."
        )
        if "air" in figs:
            rep.figure(figs["air"], "Posterior of the gas fraction at the working pressure.")
    rep.heading("Posterior summary")
    rep.table(
        rows,
        floatfmt=".4g",
        caption="Physical units. HDI = 90 % highest-density interval. tau = integrated "
        "autocorrelation time of the ensemble (emcee); ESS from ArviZ with each walker as "
        "a chain. R-hat across the walkers of one ensemble is not a valid convergence test "
        "(the walkers are not independent chains): judge convergence by tau and ESS. "
        "`cf_out_cf_in5` = cf_out * cf_in^5, the combination the data determine.",
    )
    rep.figure(figs["posterior"], "Marginal posteriors with 90 % HDI (ArviZ).")
    rep.heading("Priors")
    rep.table(
        [
            {
                "parameter": n,
                "unit": problem.infos[n].unit,
                "prior": problem.priors[n].describe(problem.infos[n].unit),
                "bounds": f"[{problem.infos[n].lower:g}, {problem.infos[n].upper:g}]",
                "why": problem.priors[n].reason,
            }
            for n in problem.names
        ],
        caption="Priors (truncated to the bounds). Sampling is in the unconstrained "
        "coordinates of each parameter (log of the distance to the lower bound) with the "
        "Jacobian of the transform, so these are priors on the physical values.",
    )
    rep.figure(
        figs["prior_posterior"],
        "Prior (grey line) and posterior (histogram) of each sampled parameter, log axis.",
    )
    rep.heading("The statistical model")
    lik = (
        "AR(1) residuals: per log and signal, (model - measured) / sensor noise follows "
        "r_t = rho r_(t-1) + e_t with rho and the innovation scale fixed at their values "
        "in the least-squares residuals (table). Real logs' residuals are autocorrelated "
        "and larger than the sensor noise; a white-noise likelihood would make the "
        "intervals far too narrow. On white noise and a correct model this is the plain "
        "Gaussian likelihood at the sensor noise."
        if problem.likelihood == "ar1"
        else "White Gaussian noise at the sensor levels of docs/model.md (height 0.5 mm, speed "
        "sqrt(1e-7 / T_s)). Over-confident when the residuals are autocorrelated."
    )
    rep.text(f"Likelihood: {lik}")
    if any(n in NOISE_NAMES for n in problem.names):
        rep.text("Noise-scale factors per signal are sampled (`noise_*`).")
    held = conditioning_text(
        problem.nuisance, problem.x0_offsets, problem.ls_info, problem.nuisance_steps
    )
    rep.text(
        held + " What the intervals leave out: model error. They assume the model (with its "
        "effects) is right; whether it is, is the diagnosis's question (`jaxlift "
        "diagnose`), and a model that misses an effect gives intervals around the wrong "
        "values. Walkers start around the least-squares optimum, spread by its covariance "
        "(combined with the priors, so that directions the data do not determine start "
        "at the prior's width)."
    )
    misfit = problem.ls_info.get("misfit")  # chains stored before it was recorded: none
    if misfit and misfit["above_noise"]:
        rep.text(
            f"**Warning: the model does not reach the sensor noise.** The least-squares fit "
            f"leaves chi2/N {misfit['chi2n']:.3g}, {misfit['z']:.1f} standard errors above "
            "the noise floor of 1. The intervals below are conditional on this model and "
            "this optimum: if the model misses an effect, or the fit ended in another basin "
            "of a rough least-squares surface (stick-slip), they are around the wrong "
            "values. `jaxlift diagnose` says which."
        )
    sig = ("height", "speed", "pressure")
    checks = {(c["log"], c["signal"]): c for c in problem.ls_info.get("innovation_check", [])}
    rep.table(
        [
            {
                "log": e.name,
                "signal": sig[k],
                "chi2/N at LS": problem.ls_info["chi2_per_signal"][e.name][sig[k]],
                "rho": float(problem.rho[i, k]),
                "innovation scale / sensor noise": float(problem.scale[i, k]),
                "Ljung-Box p (innovations)": checks.get((e.name, sig[k]), {}).get("p"),
                "variance widened x": checks.get((e.name, sig[k]), {}).get("variance_factor"),
            }
            for i, e in enumerate(problem.experiments)
            for k in e.signals
        ],
        floatfmt=".3g",
        caption="Residual noise model per log and signal. Ljung-Box: whether the model's "
        "innovations are white up to lag 20 (0.2 s); where not (p < 0.01), the noise "
        "variance is multiplied by the innovations' long-run variance factor (last "
        "column; the innovation scale shown includes it).",
    )
    bad = [c for c in checks.values() if not c["white"]]
    if bad:
        widened = all(c.get("widened", False) for c in bad)
        rep.text(
            "**Warning: the AR(1) noise model does not hold.** The innovations of "
            + ", ".join(
                f"`{c['log']}` {c['signal']} (p {c['p']:.2g}, variance x "
                f"{c.get('variance_factor') or 1.0:.2f})"
                for c in bad
            )
            + " are autocorrelated beyond what it describes (Ljung-Box, 20 lags, p < "
            "0.01). "
            + (
                "Their noise variance was widened by the innovations' long-run variance "
                "(Bartlett-weighted autocorrelations up to lag 20), so that the likelihood "
                "counts the independent information they hold, not more. "
                if widened
                else "Not widened (`widen=False`, or a chain set up before the widening): "
                "the intervals may be too narrow. "
            )
            + "Correlation left in the residuals is often a model error: see the "
            "diagnosis."
        )
    rep.heading("Convergence")
    rep.text(
        f"{run.iteration} steps x {run.n_walkers} walkers; acceptance fraction "
        f"{run.acceptance:.2f}; burn-in {thin['burn']} steps "
        f"discarded, thinned by {thin['thin']}."
        + (f" Resumed from step {run.resumed_from}." if run.resumed_from else "")
    )
    rep.figure(figs["tau"], "Estimated max tau against chain length; converged above the line.")
    rep.figure(figs["trace"], "Traces and marginals per walker (ArviZ).")
    rep.figure(figs["pair"], "Pairs (corner plot) of the sampled parameters (ArviZ).")
    rep.heading("Posterior predictive: height and speed over each log")
    rep.text(
        "Bands: 5-95 % of the model trajectories of posterior draws (parameter "
        "uncertainty only; the sensor noise is not added), measurements on top."
    )
    for p, cap in pred_figs:
        rep.figure(p, cap)
    rep.write(out)


def _az_fig(fn_name, dt, names, path):
    """An ArviZ figure of ``names`` saved to ``path``, sized for the number of
    parameters (ArviZ's default size crowded 8 parameters' titles and ticks into each
    other). ArviZ refuses more than ``plot.max_subplots`` (40) panels; a pair plot of 7
    or more parameters (e.g. the dynamic set with two effects: 8 x 8 = 64) needs more,
    and the whole posterior run ended in that error after sampling. The limit is raised
    for this figure alone."""
    n = len(names)
    n_panels = max(n**2, 40)
    cols = min(n, 4)
    size = {
        "plot_dist": dict(
            col_wrap=cols, figure_kwargs={"figsize": (3.3 * cols, 2.4 * math.ceil(n / cols))}
        ),
        "plot_pair": dict(figure_kwargs={"figsize": (1.9 * n + 1.0, 1.9 * n + 1.0)}),
        "plot_trace_dist": dict(figure_kwargs={"figsize": (12.0, 1.6 * n + 0.8)}),
    }.get(fn_name, {})

    def make():
        with az.rc_context({"plot.max_subplots": n_panels}):
            pc = getattr(az, fn_name)(dt, var_names=list(names), backend="matplotlib", **size)
        pc.savefig(path, dpi=80)

    with_pyplot_figures(make)
    return str(path)


def _plot_prior_posterior(problem, samples, figs):
    """Prior (line) and posterior (histogram) of each sampled parameter, each scaled to
    a peak of 1: a posterior a thousand times narrower than its prior (``beta`` on the
    shipped logs) is otherwise a spike too thin to see beside a flat prior. A vertical
    line marks the posterior median so that even a posterior narrower than one pixel is
    visible."""
    names = list(problem.names)
    cols = min(len(names), 4)
    rows = math.ceil(len(names) / cols)
    fig, axes = new_figure(rows, cols, figsize=(3.3 * cols, 2.5 * rows), squeeze=False)
    for ax, n in zip(axes.ravel(), names):
        info, pr = problem.infos[n], problem.priors[n]
        x = np.asarray(samples[n]).ravel()
        log_axis = bool((x > 0).all())
        xs = np.log10(x) if log_axis else x
        counts, edges = np.histogram(xs, bins=40)
        ax.stairs(counts / max(counts.max(), 1), edges, fill=True, color="C0", alpha=0.6,
                  label="posterior")  # fmt: skip
        ax.axvline(np.median(xs), color="C0", lw=1.0)
        if log_axis:
            q = np.concatenate([pr.quantiles([0.02, 0.98]), np.quantile(x, [0.0, 1.0])])
            q = q[q > 0]
            grid = np.geomspace(q.min(), q.max(), 400)
            dens = np.exp(np.asarray(pr.log_pdf(grid))) * grid * math.log(10)
            dens = np.where((grid >= info.lower) & (grid <= info.upper), dens, 0.0)
            if dens.max() > 0:
                ax.plot(np.log10(grid), dens / dens.max(), color="0.3", label="prior")
            ax.set_xlabel(f"log10 {n} [{info.unit}]")
        else:
            ax.set_xlabel(f"{n} [{info.unit}]")
        ax.set_yticks([])
    for ax in axes.ravel()[len(names) :]:
        ax.set_visible(False)
    axes[0][0].legend(fontsize=7)
    return _save(fig, figs / "prior_posterior.png")


def _plot_tau(run, figs):
    fig, ax = new_figure(figsize=(5, 3.2))
    if run.tau_history:
        it, tau = zip(*run.tau_history)
        ax.plot(it, tau, "o-", label="max tau")
        n = np.linspace(0, max(it), 50)
        ax.plot(n, n / run.tau_factor, "--", color="0.5", label=f"steps / {run.tau_factor:g}")
        ax.legend(fontsize=8)
    ax.set_xlabel("steps")
    ax.set_ylabel("tau [steps]")
    ax.grid(alpha=0.3)
    return _save(fig, figs / "tau.png")


def air_axis(x_pct: np.ndarray, threshold_pct: float) -> tuple[float, float, bool]:
    """x-limits [%] of the gas-fraction histogram, and whether the bleeding threshold
    is inside them: zoomed on the posterior (0.1-99.9 % quantiles, 25 % margins),
    widened to the threshold only where the posterior then keeps at least a quarter
    of the width (a posterior 0.01 % wide beside a 1 % threshold was a sliver)."""
    q0, q1 = np.quantile(x_pct, [0.001, 0.999])
    pad = max(q1 - q0, 1e-9) * 0.25
    x0, x1 = q0 - pad, q1 + pad
    if x0 - 3 * (x1 - x0) <= threshold_pct <= x1 + 3 * (x1 - x0):
        x0, x1 = min(x0, threshold_pct - pad), max(x1, threshold_pct + pad)
    return float(x0), float(x1), bool(x0 <= threshold_pct <= x1)


def _plot_air(phi, air, figs):
    fig, ax = new_figure(figsize=(5.5, 3.2))
    x = np.asarray(phi).ravel() * 100
    x = x[np.isfinite(x)]
    lo, hi = air["phi_hdi90"]
    thr = air["threshold"] * 100
    x0, x1, shown = air_axis(x if x.size else np.array([lo, hi]) * 100, thr)
    ax.hist(x, bins=50, density=True, color="C1", alpha=0.7)
    ax.axvspan(lo * 100, hi * 100, color="C1", alpha=0.15, label="90 % HDI")
    if shown:
        ax.axvline(thr, color="k", ls="--", label=f"bleeding threshold {thr:.3g} %")
    else:  # an arrow at the edge says where the threshold is
        right = thr > x1
        ax.annotate(
            f"bleeding threshold {thr:.3g} % {'→' if right else '←'}",
            xy=(0.98 if right else 0.02, 0.9), xycoords="axes fraction",
            ha="right" if right else "left", fontsize=8,
        )  # fmt: skip
    ax.set_xlim(x0, x1)
    ax.set_xlabel(f"gas volume fraction at {air['p_mean_pa_abs'] / 1e6:.1f} MPa [%]")
    ax.set_yticks([])
    ax.legend(fontsize=8, loc="upper left")
    return _save(fig, figs / "air_fraction.png")


def _save(fig, path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    return str(path)


def _plot_bands(log: Log, pr: dict, figs) -> list[tuple[str, str]]:

    ok = pr["ok"]
    h, v = pr["height"][ok], pr["speed"][ok]
    t = log.time_s
    windows = [None]
    try:
        windows += list(zoom_windows(log, segment_log(log), n=1))
    except Exception:  # noqa: BLE001 - a zoom is a nicety; short logs may have none
        pass
    out = []
    for win in windows:
        fig, (a1, a2) = new_figure(2, 1, figsize=(10, 5.5), sharex=True)
        sl = slice(None) if win is None else (t >= win[0]) & (t <= win[1])
        for ax, data, meas, unit, scale in (
            (a1, h, log.height_m, "height [m]", 1.0),
            (a2, v, log.speed_mps, "speed [m/s]", 1.0),
        ):
            if meas is not None:
                ax.plot(t[sl], meas[sl], ".", ms=1.5, color="k", alpha=0.5, label="measured")
            if data.size:
                lo, mid, hi = np.quantile(data[:, sl] * scale, [0.05, 0.5, 0.95], axis=0)
                ax.fill_between(t[sl], lo, hi, color="C0", alpha=0.4, label="model 5-95 %")
                ax.plot(t[sl], mid, color="C0", lw=0.8)
            ax.set_ylabel(unit)
            ax.grid(alpha=0.3)
        a1.legend(fontsize=8, loc="upper left")
        a2.set_xlabel("time [s]")
        title = log.name if win is None else f"{log.name}: {win[0]:.0f}-{win[1]:.0f} s"
        a1.set_title(f"{title}: posterior predictive ({int(ok.sum())} draws)")
        fig.tight_layout()
        p = figs / (f"{log.name}_predictive.png" if win is None else
                    f"{log.name}_predictive_zoom.png")  # fmt: skip
        fig.savefig(p, dpi=90)
        out.append((str(p), f"{title}: 5-95 % band of the posterior predictive."))
    return out
