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
# # 02 — Which physical effect is missing? Add it and watch the error fall
#
# Notebook 01 showed that the calibrated baseline model misses the shipped logs by
# far more than the sensor noise (chi2 per sample ≈ 5 instead of 1) and where:
# sustained low-speed oscillations at height. Here the diagnosis names the missing
# effect, adds it, and diagnoses again until nothing is missing. The shipped logs hide
# **two** effects (their truth is in `data/README.md`; the diagnosis does not read it).
#
# The same job from the command line:
#
# ```
# jaxlift diagnose data/lift_500kg.csv data/lift_1500kg.csv \
#     --validate data/validation_1000kg.csv --out runs/diagnose
# ```
#
# `JAXLIFT_NOTEBOOK_BUDGET=small` (used by the tests) uses one starting point per fit
# instead of two.

# %%
import json
import os
import pathlib

import jax

jax.config.update("jax_enable_x64", True)  # jaxlift needs float64; set it at the start

import jaxlift as jl  # noqa: E402

SMALL = os.environ.get("JAXLIFT_NOTEBOOK_BUDGET") == "small"
ROOT = pathlib.Path(os.environ.get("JAXLIFT_ROOT", pathlib.Path.cwd().parent))
DATA = ROOT / "data"
OUT = pathlib.Path(os.environ.get("JAXLIFT_NOTEBOOK_OUT", ROOT / "runs" / "02_diagnose"))


def load(name: str) -> jl.Log:
    return jl.read_log(DATA / name)


fit_logs = [load("lift_500kg.csv"), load("lift_1500kg.csv")]
held_out = [load("validation_1000kg.csv")]

# %% [markdown]
# ## How the diagnosis decides
# For every candidate effect of docs/model.md (stick-slip, motor inertia, motor droop,
# leakage, entrained air, hose compliance, mast compliance, input delay):
#
# 1. **screen** without refitting: the score test — how strongly the residuals of the
#    fitted model point towards switching the effect on, after removing what the
#    model's own parameters can already explain, corrected for the residuals'
#    autocorrelation (thousands of correlated samples are not thousands of independent
#    ones);
# 2. **confirm** every significant candidate by refitting the model with it: the drop
#    of the information criterion (BIC on the effective sample size) and the error on
#    the held-out log;
# 3. **verdict**: the effect with the largest BIC drop (if "very strong", ΔBIC < −10,
#    and the held-out error does not grow), or `none`.
#
# Then the winner is added and the whole thing runs again.

# %%
steps = jl.run_diagnose(fit_logs, held_out, out_dir=OUT, n_starts=1 if SMALL else 2, progress=print)

# %% [markdown]
# ## The verdicts, step by step

# %%
for k, d in enumerate(steps):
    model = " + ".join(["baseline", *d.base_effects])
    print(f"step {k + 1}: model = {model}: verdict {d.verdict!r}")
    for s in d.ranking:
        conf = (
            f"dBIC {s.delta_bic:9.1f}, held-out chi2/N {s.heldout_chi2_before:.3g} -> "
            f"{s.heldout_chi2_after:.3g}"
            if s.delta_bic is not None
            else "not confirmed (screen below threshold)"
        )
        print(f"    {s.effect:16s} z = {s.z:6.1f}   {conf}")

# %% [markdown]
# ## The error falling
# chi2 per sample (1 = as good as the sensors allow) on the fitted and held-out logs,
# for the baseline and after each added effect. The same table and figure are in the
# report.

# %%
diag = json.loads((OUT / "diagnosis.json").read_text())
for row in diag["errors_by_step"]:
    print(row)

# %% [markdown]
# ## The physical signature on the user's own data
# The report shows, for the winning effects, the signature that backs them (e.g.
# stick-slip: sustained oscillations at low speed touching zero speed; hose
# compliance: an oscillation frequency that varies less with height than the baseline
# predicts). The numbers:

# %%
print(json.dumps(diag.get("signatures", {}), indent=1)[:3000])
print("verdict:", diag["verdict"])
print("report:", OUT / "report.html")

# %% [markdown]
# ## The first step's candidates as a table
# Every result is an object a notebook can show: a diagnosis renders its candidates
# (score, BIC change, held-out error, fitted size ± standard error) as a table.

# %%
steps[0]  # noqa: B018  (a notebook shows it)

# %% [markdown]
# ## A second opinion: leave-one-out cross-validation
# ΔBIC counts parameters; ArviZ's PSIS-LOO instead asks how well each model predicts
# data it was not given, from its posterior. `jaxlift posterior` stores the pointwise
# log-likelihood (summed over blocks of one second of each log and signal, because the
# residuals are correlated in time) beside the posterior, so `az.compare` can weigh the
# baseline against the diagnosed model. The chains here are short (a second opinion,
# not the posterior to report); a model clearly better by LOO agrees with the ΔBIC
# verdict above.

# %%
import arviz as az  # noqa: E402
import xarray as xr  # noqa: E402

post_steps = 300 if SMALL else 1500
models = {
    "baseline": ([], steps[0].base_fit.params),
    "diagnosed": (diag["final_effects"], diag["final_params"]),
}
trees = {}
for label, (effects, params) in models.items():
    folder = OUT / f"posterior_{label}"
    jl.run_posterior(fit_logs, folder, effects=effects, params=params, max_steps=post_steps,
                     n_predictive=8, seed=0)  # fmt: skip
    trees[f"{label} ({', '.join(effects) or 'no effects'})"] = xr.open_datatree(
        folder / "posterior.nc", engine="h5netcdf"
    )
comparison = az.compare(trees)
comparison  # noqa: B018  (a notebook shows it)
