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
    "pressure": (D, N), "ok": (D,)}]`` per log. The motor set that went with each
    draw: :func:`predictive_with_motor`."""
    return predictive_with_motor(problem, thetas, batch_size)[0]


def predictive_with_motor(
    problem: PosteriorProblem, thetas: Float[ArrayLike, "D P"], batch_size: int = 16
) -> tuple[list[dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """:func:`predictive`, and the motor parameters (physical units, ``{name: (D,)}``)
    each draw was simulated with: for a marginal posterior those of the nuisances'
    conditional optimum (:func:`~jaxlift.posterior.problem.nuisance_step`, with its
    Gauss--Newton step where the problem takes it), else the calibrated ones."""
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
    res, motor = fn(jnp.asarray(thetas), args)
    pred = [{"height": np.asarray(h), "speed": np.asarray(v), "pressure": np.asarray(p),
             "ok": np.asarray(ok)} for h, v, p, ok in res]  # fmt: skip
    return pred, {n: np.asarray(v) for n, v in motor.items()}


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
        motor = {n: jnp.asarray(values[n]) for n in nuisance if not n.startswith("x0@")}
        return outs, motor

    return jax.jit(lambda th, a: jax.lax.map(lambda t: one(t, a), th, batch_size=batch_size))


def as_list(sample) -> list[str]:
    if isinstance(sample, str):
        return [s.strip() for s in sample.split(",") if s.strip()]
    return list(sample)


#: Group of ``posterior.nc`` holding, for a posterior that took the nuisances'
#: Gauss--Newton step (``nuisance_steps``), the predictive draws with the motor set each
#: was simulated with (:func:`motor_draws_dataset`, read by :func:`posterior_draws`).
MOTOR_DRAWS_GROUP = "motor_draws"


def motor_draws_dataset(
    problem: PosteriorProblem, thetas: Float[ArrayLike, "D P"], motor: dict[str, np.ndarray]
) -> xr.Dataset:
    """The draws ``thetas`` (unconstrained) in physical units with the motor set that
    went with each (:func:`predictive_with_motor`), along a ``draw`` dimension: the
    group :data:`MOTOR_DRAWS_GROUP` of ``posterior.nc``."""
    phys = problem.to_physical(np.asarray(thetas))
    data = {n: ("draw", np.asarray(phys[n], dtype=float)) for n in problem.names}
    data.update({n: ("draw", np.asarray(v, dtype=float)) for n, v in motor.items()})
    ds = xr.Dataset(data)
    ds.attrs["jaxlift_note"] = (
        "posterior draws with the motor set of the nuisances' conditional optimum after "
        "one Gauss-Newton step from its linearisation (the posterior took that step)"
    )
    return ds


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
        for a marginal posterior the motor set that goes with each draw: on the
        nuisances' linearised conditional optimum, or, for a posterior that took one
        Gauss--Newton step from it (``nuisance_steps``), the stepped motor set, which
        needs the logs and was computed for the posterior predictive's draws only: the
        draws are then taken from those (group :data:`MOTOR_DRAWS_GROUP` of
        ``posterior.nc``).

    Raises:
        FileNotFoundError: ``out_dir`` lacks the settings or ``posterior.nc``.
        ValueError: a posterior that took the step has no stored motor draws (written
            before 2026-12-07, or with no predictive draws).
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
    stepped = bool(settings.get("nuisance_steps")) and bool(settings.get("nuisance"))
    with xr.open_datatree(nc, engine="h5netcdf") as tree:
        if stepped:
            if MOTOR_DRAWS_GROUP not in tree.children:
                raise ValueError(
                    f"{nc}: no group '{MOTOR_DRAWS_GROUP}'. This posterior took a "
                    "Gauss-Newton step of the motor set (nuisance_steps), whose values "
                    "need the logs and are written with the predictive draws; run "
                    f"`jaxlift posterior ... --out {out}` again (it resumes the chain "
                    "and rewrites the outputs) with --predictive or --loglik-draws above 0"
                )
            post = tree[MOTOR_DRAWS_GROUP].to_dataset()
            keys = [k for k in post.data_vars if k not in NOISE_NAMES]
            flat = {k: np.asarray(post[k]).ravel() for k in keys}
        else:
            post = tree["posterior"].to_dataset()
            flat = {k: np.asarray(post[k]).ravel() for k in names}
    m = next(iter(flat.values())).size
    rng = np.random.default_rng(seed)
    idx = rng.choice(m, size=n, replace=n > m)
    values = {k: float(v) for k, v in settings["values"].items()}
    draws = [{**values, **{k: float(flat[k][i]) for k in flat}} for i in idx]
    if settings.get("nuisance") and not stepped:  # the motor set of each draw (marginal)
        infos = all_param_infos(make_effects(settings["effects"]))
        for d in draws:
            theta = [
                float(to_unconstrained(infos[n], d[n])) if n in infos else 0.0
                for n in settings["names"]
            ]  # noise factors (not in infos) do not enter the map
            d.update({k: v for k, v in nuisance_values(settings, theta).items() if k[:3] != "x0@"})
    return list(settings["effects"]), draws
