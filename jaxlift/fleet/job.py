"""One fleet job, as a worker process runs it: fit → diagnose → interval summary.

The job is a program of its own (it runs in a worker process of the engine), so it
switches JAX to float64 itself, like the command line does.
"""

from __future__ import annotations

import json
import math
import pathlib
import sys
import time

import jax
import numpy as np

from ..calibrate.diagnose import (
    NOT_AN_EFFECT,
    final_verdict,
    found_effects,
    remaining_misfit,
    usable_heldout,
)
from ..calibrate.fit import fit
from ..model.effects import load_effect_file
from ..model.inputs import Inputs
from ..model.log import read_log
from ..posterior.air import air_content, mean_pressure
from ..workflows.diagnose import run_diagnose
from ..workflows.posterior import run_posterior
from .manifest import code_version

#: What a job does unless told otherwise (``jaxlift fleet --help``).
DEFAULT_SETTINGS = {
    # "diagnose": fit, then the iterative diagnosis; "fit": the baseline fit only
    "job": "diagnose",
    # "on-misfit": search the candidates only when the baseline fit leaves an error
    # significantly above the sensor noise (remaining_misfit on fitted and held-out
    # logs); "always": search them on every job
    "search": "on-misfit",
    "max_effects": 2,
    "n_starts": 2,
    "seed": 0,
    # the intervals: "laplace" (the fit's AR(1)-inflated standard errors, normal on the
    # log scale: seconds) or "mcmc" (jaxlift posterior of the final model, its 90 % HDI;
    # minutes per job), at most posterior_max_steps sampler steps
    "posterior": "laplace",
    "posterior_max_steps": 5000,
    # how the logs are read (read_log, docs/data.md): channel map and resampling period
    "channel_map": None,
    "resample": None,
}

#: The parameters the fleet tracks: bulk modulus (air) and friction.
TRACKED = ("beta", "cf_con", "d")
#: Probability of the intervals in the fleet table.
INTERVAL = 0.9
_Z = 1.6448536269514722  # standard normal quantile of 0.95: two-sided 90 %
_MAX_EXP = math.log(sys.float_info.max)  # the largest finite exp's argument (709.78)


def write_json(path: pathlib.Path, obj) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=_jsonable) + "\n", encoding="utf-8")
    tmp.replace(path)  # atomic: a result file is complete or absent


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    return str(x)


def laplace_interval(value: float, se: float) -> tuple[float, float]:
    """90 % interval of a positive parameter from its estimate and (AR(1)-inflated)
    standard error, normal on the log scale (``value * exp(±z se/value)``): the
    Laplace approximation of the posterior around the least-squares optimum with flat
    priors on log values. NaN where the standard error is not finite; ``(0, inf)``
    where it is so large against the value that the factor overflows (measured in
    the 50 x 8 fleet study: a job failed on ``math.exp`` overflowing)."""
    if not (math.isfinite(se) and value > 0):
        return math.nan, math.nan
    x = _Z * se / value
    if x > _MAX_EXP:  # the interval spans every positive value a float holds
        return 0.0, math.inf
    f = math.exp(x)
    return value / f, value * f


def summarise(result, logs) -> dict:
    """The fleet table's numbers from the final model's fit: tracked parameters with
    90 % intervals, air content implied by the bulk modulus, fit quality."""
    row: dict = {"chi2n": result.chi2 / result.n_residuals, "rho1": result.rho1}
    for name in TRACKED:
        v = float(result.params[name])
        se = float(result.stderr.get(name, math.nan))
        lo, hi = laplace_interval(v, se)
        row.update({name: v, f"{name}_se": se, f"{name}_lo": lo, f"{name}_hi": hi})
    p_mean = mean_pressure(
        result.model.plant, result.model.effects, [Inputs.from_log(lg) for lg in logs],
        [lg.name for lg in logs],
    )  # fmt: skip
    row["p_mean_pa"] = p_mean
    row["air"] = float(air_content(row["beta"], p_mean))
    # monotone in beta: the interval's ends swap
    row["air_lo"] = float(air_content(row["beta_hi"], p_mean))
    row["air_hi"] = float(air_content(row["beta_lo"], p_mean))
    alpha0 = result.params.get("alpha0")
    row["alpha0"] = float(alpha0) if "entrained_air" in result.effects else math.nan
    row["interval"] = "laplace"
    return row


def sampled_intervals(row: dict, post, p_mean: float) -> dict:
    """Replace ``row``'s Laplace intervals of the tracked parameters by the
    posterior's (:func:`~jaxlift.run_posterior` result ``post``): mean, sd and the 90 %
    HDI; the air content's interval from the bulk modulus's (monotone)."""
    by = {r["parameter"]: r for r in post["summary"]}
    for name in TRACKED:
        r = by.get(name)
        if r is None:  # not sampled (held): the Laplace interval stays, and says so
            continue
        row[name], row[f"{name}_se"] = float(r["mean"]), float(r["sd"])
        row[f"{name}_lo"], row[f"{name}_hi"] = float(r["HDI 5 %"]), float(r["HDI 95 %"])
    row["air"] = float(air_content(row["beta"], p_mean))
    row["air_lo"] = float(air_content(row["beta_hi"], p_mean))
    row["air_hi"] = float(air_content(row["beta_lo"], p_mean))
    row["interval"] = "mcmc"
    row["posterior_converged"] = bool(post["converged"])
    row["posterior_steps"] = int(post["steps"])
    return row


_LOADED_EFFECT_FILES: set[str] = set()


def _load_user_effects(paths) -> None:
    """Register the user's effect files (``--effect-file``) in this worker process,
    once per process."""
    for path in paths:
        if path not in _LOADED_EFFECT_FILES:
            load_effect_file(path)
            _LOADED_EFFECT_FILES.add(path)


def run_job(job, settings: dict, job_dir: str | pathlib.Path) -> dict:
    """Run one job and write ``job_dir/result.json`` (last, atomically) and the
    diagnosis report under ``job_dir/diagnosis/``. Returns the result record. Raises
    on failure (the engine retries and then records the failure)."""
    # this process's program start; modules imported above create no jax arrays
    jax.config.update("jax_enable_x64", True)
    s = {**DEFAULT_SETTINGS, **settings}
    _load_user_effects(s.get("effect_files", []))
    job_dir = pathlib.Path(job_dir)
    job_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        how = {"channel_map": s["channel_map"], "resample": s["resample"]}
        logs = [read_log(p, **how) for p in job.fit]
        val = [read_log(p, **how) for p in job.validate]
        record: dict = {"vehicle": job.vehicle, "date": job.date.isoformat()}
        base = fit(logs, staged=True, n_starts=s["n_starts"], seed=s["seed"])
        if not math.isfinite(base.chi2):
            raise RuntimeError(
                "the baseline fit failed: " + "; ".join(st.message for st in base.stages)
            )
        usable, _excluded = usable_heldout(logs, val)
        misfit = remaining_misfit(base, usable)
        record["baseline_chi2n"] = base.chi2 / base.n_residuals
        record["baseline_misfit_significant"] = misfit.significant
        final, effects, verdict, reasons = base, [], "none", []
        if s["job"] == "fit":
            verdict = "not searched"
            reasons = ["job 'fit': the candidate effects were not searched"]
        elif s["search"] == "always" or misfit.significant:
            steps = run_diagnose(
                logs, val, out_dir=job_dir / "diagnosis", max_effects=s["max_effects"],
                n_starts=s["n_starts"], seed=s["seed"],
            )  # fmt: skip
            last = steps[-1]
            final = last.base_fit if last.verdict in NOT_AN_EFFECT else last.winner_fit
            effects = [e for e in found_effects(steps) if e in final.effects]
            verdict = final_verdict(steps)
            if verdict == "none" and effects:
                verdict = "+".join(effects)
            reasons = list(last.reasons)
        else:
            reasons = [
                f"the baseline fit leaves no significant error (chi2/N "
                f"{record['baseline_chi2n']:.3g}): no effect is missing that these logs "
                "could show"
            ]
        row = summarise(final, logs)
        if s["posterior"] == "mcmc":
            post = run_posterior(
                logs, job_dir / "posterior", effects=list(final.effects),
                params=dict(final.params), max_steps=s["posterior_max_steps"],
                seed=s["seed"], n_predictive=0, n_loglik=0,
            )  # fmt: skip
            row = sampled_intervals(row, post, row["p_mean_pa"])
        record.update(status="ok", verdict=verdict, effects=effects, reasons=reasons, **row)
    finally:
        jax.clear_caches()  # a long-lived worker must not keep every shape's compilation
    record.update(
        wall_s=time.perf_counter() - t0,
        jaxlift_version=code_version(),
        settings=s,
        logs_fit=[p.name for p in job.fit],
        logs_validate=[p.name for p in job.validate],
    )
    write_json(job_dir / "result.json", record)
    return record
