# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 03 — How sure are we? The posterior of the bulk modulus and the friction
#
# The least-squares fit (notebook 01) gives one value per parameter. Here an ensemble
# MCMC sampler (emcee) gives the distribution of the bulk modulus `beta` and the
# friction parameters `cf_con, cf_in, cf_out, d` that is compatible with the logs, and
# from it the **air content** of the oil with its uncertainty: what a service engineer
# needs before bleeding the hydraulic system.
#
# The same job from the command line:
#
# ```
# jaxlift fit data/lift_500kg.csv data/lift_1500kg.csv --out runs/fit
# jaxlift posterior data/lift_500kg.csv data/lift_1500kg.csv \
#     --params runs/fit/params.json --out runs/posterior
# ```
#
# Run it again with the same arguments and it resumes the chain where it stopped.
# `JAXLIFT_NOTEBOOK_BUDGET=small` makes this notebook quick (a short chain that has not
# converged: the numbers are then only a demonstration; used by the tests).

# %%
import json
import os
import pathlib

import jax

jax.config.update("jax_enable_x64", True)  # jaxlift needs float64; set it at the start
# one XLA CPU device per core: the sampler splits each batch of walkers across them
# (as `jaxlift posterior` does); like float64, this must come before any JAX operation
jax.config.update("jax_num_cpu_devices", os.cpu_count() or 1)

import jaxlift as jl  # noqa: E402
from jaxlift.posterior.predictive import posterior_draws  # noqa: E402
from jaxlift.posterior.priors import DEFAULT_PRIORS  # noqa: E402
from jaxlift.workflows.posterior import run_posterior  # noqa: E402

SMALL = os.environ.get("JAXLIFT_NOTEBOOK_BUDGET") == "small"
ROOT = pathlib.Path(os.environ.get("JAXLIFT_ROOT", pathlib.Path.cwd().parent))
DATA = ROOT / "data"
OUT = pathlib.Path(os.environ.get("JAXLIFT_NOTEBOOK_OUT", ROOT / "runs" / "03_posterior"))

# %% [markdown]
# ## The logs and the starting point
# Two thesis-like runs at 500 kg and 1500 kg. The posterior starts from a least-squares
# calibration. With the small budget we take the baseline part of the known truth of
# the shipped (simulated) logs as the starting point and let the least squares re-fit
# the sampled parameters from there; with the full budget the whole staged
# least-squares fit runs first, as `jaxlift posterior` does without `--params`.

# %%
logs = [jl.read_log(DATA / "lift_500kg.csv"), jl.read_log(DATA / "lift_1500kg.csv")]
params = None
if SMALL:
    truth = jl.load_params_json(DATA / "truth.json", jl.all_param_infos("all"))
    params = {k: v for k, v in truth.items() if k in jl.all_param_infos(())}

# %% [markdown]
# ## The statistical model
# * **Sampled**: `beta, cf_con, cf_in, cf_out, d` (the thesis's dynamic set), in
#   unconstrained coordinates (log of the distance to the lower bound) with the
#   Jacobian of that transform; reported in physical units.
# * **Marginalised** (the default): the motor set and each log's initial-height offset
#   are not held at their least-squares values; they follow the sampled parameters
#   along their conditional optimum (a Gauss-Newton profile), so their uncertainty
#   reaches `beta`'s interval (held fixed, `conditioning="conditional"`, it came out 40 %
#   narrower than the fit's own standard error). Every other parameter is fixed at its
#   least-squares value.
# * **Priors**: wide and physical (below). `beta` is log-normal around ideal oil.
# * **Likelihood**: the residuals of real logs are autocorrelated and larger than the
#   sensor noise, so a white-noise likelihood at the sensor levels would make the
#   intervals far too narrow. The default models each log's and signal's residuals as
#   an AR(1) process whose correlation and scale are estimated from the least-squares
#   residuals. On data that the model explains down to white sensor noise this is the
#   ordinary likelihood.

# %%
for name in ("beta", "cf_con", "cf_in", "cf_out", "d"):
    print(f"{name:7s} {DEFAULT_PRIORS[name].describe()}")

# %% [markdown]
# ## Sample
# 32 walkers until the chain is 50 autocorrelation times long (small budget: 12 walkers,
# 30 steps). The chain goes to `chain.h5`; a killed run resumes where it stopped.

# %%
res = run_posterior(
    logs,
    OUT,
    params=params,
    n_walkers=12 if SMALL else 32,
    max_steps=30 if SMALL else 20_000,
    n_predictive=8 if SMALL else 64,
    progress=print,
)
print("converged:", res["converged"], "after", res["steps"], "steps")

# %% [markdown]
# `res` is a `jl.PosteriorResult`: it reads like the dict of `posterior.json`, shows as
# a table here, and holds the ArviZ DataTree (`res.datatree`) with the posterior, the
# prior, the observed data, the posterior predictive and the pointwise log-likelihood
# (for `az.loo` and `az.compare`).

# %%
res  # noqa: B018 (a notebook cell shows its last value)

# %%
print("DataTree groups:", ", ".join(sorted(res.datatree.children)))

# %% [markdown]
# ## The posterior
# Mean, standard deviation, 90 % highest-density interval, the autocorrelation time
# tau and ESS. (R-hat over the walkers of one ensemble is not a valid test: they are
# not independent chains.) `cf_in` and `cf_out` enter the friction only as
# `cf_out * cf_in^5`: that product is determined, the split between them comes from
# the priors.

# %%
for row in res["summary"]:
    print(
        f"{row['parameter']:14s} {row['mean']:12.4g} ± {row['sd']:9.2g}  90 % HDI "
        f"[{row['HDI 5 %']:.4g}, {row['HDI 95 %']:.4g}] {row['unit']}"
    )

# %% [markdown]
# ## Air in the oil
# The effective bulk modulus of the baseline model lumps together everything that
# makes the oil column soft. Attributing it all to air (docs/model.md), the gas volume
# fraction at the mean working pressure is `phi = p (1/beta - 1/beta_oil)`.

# %%
print(res["air"]["text"])

# %% [markdown]
# The shipped logs were made with a soft hose (`hose_compliance`) and stiffer oil
# (0.5 GPa), not with air: the baseline's `beta` then absorbs the hose. `jaxlift
# diagnose` names the hose; re-running the posterior with `--effects hose_compliance`
# separates the hose's share from the oil's.
#
# ## For others: posterior draws of the whole parameter set
# The controller design samples plants from this posterior:

# %%
effects, draws = posterior_draws(OUT, n=3, seed=0)
print("effects:", effects)
for d in draws:
    print({k: round(d[k], 4 if k != "beta" else -6) for k in ("beta", "cf_con", "d", "k1")})

# %%
print("report:", OUT / "report.html")
print(json.dumps({k: res[k] for k in ("steps", "converged", "acceptance")}))
