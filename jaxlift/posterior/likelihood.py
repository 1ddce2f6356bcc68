"""The log-posterior: the AR(1) likelihood per log and signal plus the priors, jitted,
batched over walkers and split across CPU devices.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import ArrayLike, Float

from ..model.build import all_param_infos, make_effects, with_params
from ..model.params import from_unconstrained
from ..model.simulate import simulate
from .priors import log_abs_det_jac
from .problem import (
    NOISE_NAMES,
    SIM_MAX_STEPS,
    PosteriorProblem,
    noise_info,
    nuisance_step,
)


# ------------------------------------------------------------------ log-probability
def _ar1_loglik(r, rho, s):
    """Exact log-likelihood of a zero-mean stationary Gaussian AR(1) with innovation
    standard deviation ``s``: ``r_0 ~ N(0, s^2 / (1 - rho^2))``, then innovations."""
    n = r.shape[0]
    e = jnp.concatenate([r[:1] * jnp.sqrt(1.0 - rho**2), r[1:] - rho * r[:-1]])
    return (
        -0.5 * jnp.sum(e**2) / s**2
        - n * jnp.log(s)
        + 0.5 * jnp.log(1.0 - rho**2)
        - 0.5 * n * math.log(2 * math.pi)
    )


def _log_prob_args(problem: PosteriorProblem):
    """The arguments of the jitted log-probability (arrays passed, not closed over:
    13 k closed-over constants made XLA constant-fold for a long time)."""
    plant0, effs0 = problem.model.plant, problem.model.effects
    return (
        plant0,
        effs0,
        problem.experiments,
        jnp.asarray(problem.rho),
        jnp.asarray(problem.scale),
        jnp.asarray(problem.theta_opt),
        problem.nuisance_args(),
    )


def _prior_key(problem: PosteriorProblem) -> tuple:
    return tuple((n, problem.priors[n]) for n in problem.names)


@functools.lru_cache(maxsize=32)
def _single_fn(names: tuple[str, ...], effects: tuple[str, ...], prior_key: tuple,
               max_steps: int, nuisance: tuple[str, ...] = ()):  # fmt: skip
    """The log-probability of one walker, ``f(theta, args)`` (not jitted); cached by
    configuration so that a resumed run in the same process compiles nothing new.
    ``nuisance``: the motor parameters and ``x0@<log>`` offsets that move with the
    sampled coordinates (:attr:`PosteriorProblem.nuisance_map`, the marginal
    posterior, with :attr:`PosteriorProblem.nuisance_steps` Gauss--Newton steps:
    :func:`~jaxlift.posterior.problem.nuisance_step`); the offsets in the order of the
    experiments."""
    infos_all = all_param_infos(make_effects(effects))
    infos = [infos_all[n] if n in infos_all else noise_info(n) for n in names]
    priors = [p for _, p in prior_key]
    phys = [k for k, n in enumerate(names) if n not in NOISE_NAMES]
    noise_idx = {NOISE_NAMES.index(n): k for k, n in enumerate(names) if n in NOISE_NAMES}

    def f(theta, args):
        plant0, effs0, experiments, rho, scale, ref, nuis_args = args
        xs = [from_unconstrained(info, theta[k]) for k, info in enumerate(infos)]
        inside = jnp.all(jnp.isfinite(theta))
        log_prior = jnp.zeros(())
        for k, info in enumerate(infos):
            inside = inside & (xs[k] >= info.lower) & (xs[k] <= info.upper)
            log_prior = log_prior + priors[k].log_pdf(xs[k]) + log_abs_det_jac(info, theta[k])
        inside = inside & jnp.isfinite(log_prior)
        # out of support: simulate at the optimum instead (cheap, then masked to -inf)
        safe = jnp.where(inside, theta, ref)
        values = {names[k]: from_unconstrained(infos[k], safe[k]) for k in phys}
        d_theta = safe[jnp.asarray(phys)] - ref[jnp.asarray(phys)]
        values, experiments = nuisance_step(
            plant0, effs0, values, experiments, d_theta, nuis_args, nuisance, infos_all,
            max_steps,
        )  # fmt: skip
        plant, effs = with_params(plant0, effs0, values)
        fac = [noise_idx.get(j) for j in range(3)]
        fac = [jnp.ones(()) if k is None else from_unconstrained(infos[k], safe[k]) for k in fac]
        ll = jnp.zeros(())
        ok = inside
        for i, exp in enumerate(experiments):
            sol = simulate(plant, effs, exp.inputs, max_steps=max_steps, stability_limit=False)
            r = exp.scaled_residuals(sol)
            ok = ok & (sol.result == diffrax.RESULTS.successful) & sol.in_range
            for k in exp.signals:
                ll = ll + _ar1_loglik(r[k], rho[i, k], scale[i, k] * fac[k])
        lp = log_prior + ll
        ok = ok & jnp.isfinite(lp)
        return jnp.where(ok, lp, -jnp.inf)

    return f


@functools.lru_cache(maxsize=32)
def _batched_fn(names, effects, prior_key, max_steps, batch, devices=None, nuisance=()):
    """The jitted batch function ``core(thetas, args)``. With ``devices`` (a tuple of
    several devices) the batch is split evenly across them with ``shard_map``, each
    device running ``batch`` over its share (the batch size must be a multiple of the
    number of devices: :func:`make_log_prob` pads)."""
    single = _single_fn(names, effects, prior_key, max_steps, nuisance)
    if batch == "vmap":
        inner = jax.vmap(single, in_axes=(0, None))
    elif batch == "map":

        def inner(th, a):
            return jax.lax.map(lambda t: single(t, a), th)

    elif batch == "single":
        one = jax.jit(single)

        def core(th, a):
            return jnp.stack([one(t, a) for t in th])

        return core
    else:
        raise ValueError(f"batch must be 'vmap', 'map' or 'single', not {batch!r}")
    if devices is None or len(devices) < 2:
        return jax.jit(inner)

    mesh = Mesh(np.asarray(devices), ("walkers",))
    return jax.jit(
        jax.shard_map(
            inner,
            mesh=mesh,
            in_specs=(PartitionSpec("walkers"), PartitionSpec()),
            out_specs=PartitionSpec("walkers"),
            check_vma=False,
        )
    )


def cpu_devices(devices: int | None) -> tuple | None:
    """The devices a batch is split across: the first ``devices`` local devices of
    the default backend (all of them for ``None``); ``None`` for one."""
    avail = jax.local_devices()
    n = len(avail) if devices is None else int(devices)
    if n < 1 or n > len(avail):
        raise ValueError(f"devices must be 1 ... {len(avail)} (local devices), not {devices}")
    return tuple(avail[:n]) if n > 1 else None


def make_log_prob(
    problem: PosteriorProblem,
    *,
    batch: str = "map",
    max_steps: int = SIM_MAX_STEPS,
    devices: int | None = None,
) -> Callable[[Float[ArrayLike, "B P"]], Float[np.ndarray, " B"]]:
    """The log-posterior density (up to a constant) in unconstrained coordinates.

    Args:
        problem: from :func:`prepare_posterior`.
        batch: ``"vmap"``: one jitted ``vmap`` over the batch of walkers; ``"map"``:
            one jitted ``jax.lax.map`` (walkers one after the other inside the compiled
            function); ``"single"``: a jitted function of one walker, called in a Python
            loop (for comparison only).
        max_steps: solver step limit of each simulation.
        devices: split the batch across this many local devices (``"map"`` and
            ``"vmap"``; ``shard_map``, one compiled call). ``None``: all local devices
            of the default backend. On a CPU JAX has one device unless the program
            asked for more before its first JAX operation, e.g.
            ``jax.config.update("jax_num_cpu_devices", 2)`` (what ``jaxlift
            posterior`` does, one per core): each device then runs its share of the
            walkers on its own core. The values do not depend on the split.

    Returns:
        ``f(thetas)`` with ``thetas`` of shape ``(B, P)`` -> ``(B,)`` float64 numpy array
        (``-inf`` for failed solves / outside the prior support, never NaN). The jitted
        core is ``f.jitted(thetas, f.args)`` (its batch a multiple of ``f.n_devices``).
    """
    devs = None if batch == "single" else cpu_devices(devices)
    nd = 1 if devs is None else len(devs)
    key = (problem.names, problem.effects, _prior_key(problem), int(max_steps))
    core = _batched_fn(*key, batch, devs, problem.nuisance)
    args = _log_prob_args(problem)

    def f(thetas):
        th = np.atleast_2d(np.asarray(thetas, dtype=np.float64))
        m = th.shape[0]
        if m % nd:  # pad to a multiple of the number of devices
            th = np.concatenate([th, np.repeat(th[-1:], nd - m % nd, axis=0)])
        out = np.asarray(core(jnp.asarray(th), args), dtype=np.float64)[:m]
        return np.where(np.isnan(out), -np.inf, out)  # belt and braces: never NaN

    f.jitted = core
    f.args = args
    f.n_devices = nd
    return f


class EmceeLogProb:
    """emcee's ``vectorize=True`` callable: evaluates in batches of a fixed size (half
    the walkers, as the stretch move asks), so the jitted function compiles once."""

    def __init__(self, f, batch_size: int):
        self.f = f
        self.batch_size = batch_size
        self.n_evals = 0

    def __call__(self, coords):
        coords = np.atleast_2d(np.asarray(coords, dtype=np.float64))
        n, b = coords.shape[0], self.batch_size
        out = []
        for i in range(0, n, b):
            blk = coords[i : i + b]
            m = blk.shape[0]
            if m < b:
                blk = np.concatenate([blk, np.repeat(blk[-1:], b - m, axis=0)])
            out.append(self.f(blk)[:m])
        self.n_evals += n
        return np.concatenate(out)
