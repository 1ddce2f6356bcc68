"""Posterior predictive: model outputs over posterior draws, highest-density intervals,
and complete parameter sets drawn from a posterior directory.
"""

from __future__ import annotations

import functools
import json
import math
import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr
from jaxtyping import ArrayLike, Float

from ..model.build import all_param_infos, make_effects, with_params
from ..model.params import from_unconstrained, to_unconstrained
from ..model.simulate import simulate
from .problem import (
    NOISE_NAMES,
    SETTINGS_FILE,
    SIM_MAX_STEPS,
    PosteriorProblem,
    noise_info,
    nuisance_step,
    nuisance_values,
)


def hdi(x: np.ndarray, prob: float = 0.9) -> tuple[float, float]:
    """Shortest interval holding ``prob`` of the samples."""
    x = np.sort(np.asarray(x, dtype=float).ravel())
    n = x.size
    k = max(1, int(math.ceil(prob * n)))
    if k >= n:
        return float(x[0]), float(x[-1])
    w = x[k - 1 :] - x[: n - k + 1]
    i = int(np.argmin(w))
    return float(x[i]), float(x[i + k - 1])


# ------------------------------------------------------------------ predictive
def predictive(
    problem: PosteriorProblem, thetas: Float[ArrayLike, "D P"], batch_size: int = 16
) -> list[dict[str, np.ndarray]]:
    """Simulated height [m], speed [m/s] and gauge pressure [Pa] of every log for each
    draw (unconstrained coordinates), ``[{"height": (D, N), "speed": (D, N),
    "pressure": (D, N), "ok": (D,)}]`` per log."""
    plant0, effs0 = problem.model.plant, problem.model.effects
    bs = max(1, min(batch_size, int(np.shape(thetas)[0])))
    fn = _predictive_fn(problem.names, problem.effects, bs, problem.nuisance)
    args = (
        plant0,
        effs0,
        problem.experiments,
        jnp.asarray(problem.theta_opt),
        problem.nuisance_args(),
    )
    res = fn(jnp.asarray(thetas), args)
    return [{"height": np.asarray(h), "speed": np.asarray(v), "pressure": np.asarray(p),
             "ok": np.asarray(ok)} for h, v, p, ok in res]  # fmt: skip


@functools.lru_cache(maxsize=16)
def _predictive_fn(
    names: tuple[str, ...], effects: tuple[str, ...], batch_size: int, nuisance: tuple = ()
):
    infos_all = all_param_infos(make_effects(effects))
    infos = [infos_all[n] if n in infos_all else noise_info(n) for n in names]
    phys = [k for k, n in enumerate(names) if n not in NOISE_NAMES]

    def one(theta, args):
        plant0, effs0, experiments, ref, nuis_args = args
        values = {names[k]: from_unconstrained(infos[k], theta[k]) for k in phys}
        d_theta = theta[jnp.asarray(phys)] - ref[jnp.asarray(phys)]
        values, experiments = nuisance_step(
            plant0, effs0, values, experiments, d_theta, nuis_args, nuisance, infos_all,
            SIM_MAX_STEPS,
        )  # fmt: skip
        plant, effs = with_params(plant0, effs0, values)
        outs = []
        for exp in experiments:
            sol = simulate(plant, effs, exp.inputs, max_steps=SIM_MAX_STEPS, stability_limit=False)
            outs.append((sol.height, sol.speed, sol.pressure, sol.ok))
        return outs

    return jax.jit(lambda th, a: jax.lax.map(lambda t: one(t, a), th, batch_size=batch_size))


def as_list(sample) -> list[str]:
    if isinstance(sample, str):
        return [s.strip() for s in sample.split(",") if s.strip()]
    return list(sample)


def posterior_draws(
    out_dir: str | os.PathLike, n: int, seed: int
) -> tuple[list[str], list[dict[str, float]]]:
    """``n`` posterior draws of the full parameter set from a ``jaxlift posterior`` run.

    Args:
        out_dir: the output directory of :func:`run_posterior` / ``jaxlift posterior``.
        n: number of draws (without replacement while the stored draws suffice).
        seed: seed of the selection (numpy ``Generator``).

    Returns:
        ``(effects, draws)``: the names of the switched-on effects, and ``n`` dicts
        ``{name: value}`` with every model parameter (docs/model.md names, physical units):
        the sampled ones from the posterior, the others at their calibrated values;
        for a marginal posterior the motor set that goes with each draw, on the
        nuisances' linearised conditional optimum (without the Gauss--Newton step a
        posterior with ``nuisance_steps`` took: that step simulates the logs, which a
        posterior directory does not hold).
    """

    out = pathlib.Path(out_dir)
    settings_path = out / SETTINGS_FILE
    nc = out / "posterior.nc"
    for p in (settings_path, nc):
        if not p.exists():
            raise FileNotFoundError(f"{p}: not found; run `jaxlift posterior ... --out {out}`")
    with open(settings_path, encoding="utf-8") as fh:
        settings = json.load(fh)["problem"]
    names = [n for n in settings["names"] if n not in NOISE_NAMES]
    with xr.open_datatree(nc, engine="h5netcdf") as tree:
        post = tree["posterior"].to_dataset()
        flat = {k: np.asarray(post[k]).ravel() for k in names}
    m = next(iter(flat.values())).size
    rng = np.random.default_rng(seed)
    idx = rng.choice(m, size=n, replace=n > m)
    values = {k: float(v) for k, v in settings["values"].items()}
    draws = [{**values, **{k: float(flat[k][i]) for k in names}} for i in idx]
    if settings.get("nuisance"):  # the motor set that goes with each draw (marginal)
        infos = all_param_infos(make_effects(settings["effects"]))
        for d in draws:
            theta = [
                float(to_unconstrained(infos[n], d[n])) if n in infos else 0.0
                for n in settings["names"]
            ]  # noise factors (not in infos) do not enter the map
            d.update({k: v for k, v in nuisance_values(settings, theta).items() if k[:3] != "x0@"})
    return list(settings["effects"]), draws
