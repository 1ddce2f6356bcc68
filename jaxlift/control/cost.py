"""The tuning cost: the figures of "good" of a closed-loop run written as a sum of
squares, per-draw costs over batches of plants, and the robust objective (mean + CVaR).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..model.constants import OUTPUT_DT
from ..model.effects import AbstractEffect
from ..model.plant import Plant
from .closed_loop import ClosedLoopSolution, simulate_closed_loop
from .controller import AbstractController
from .performance import (
    CostWeights,
    Figures,
    bandpass,
    cost_from_figures,
    figures,
    noise_amplification,
    ref_masks,
)
from .reference import Reference, is_moving

#: Cost of a run whose simulation failed (finite: no NaN in a batch; gradient 0).
FAILED_COST = 1e6
#: A run is "oscillation-free" when its sustained oscillation RMS is below this [m/s].
OSC_FREE_MPS = 0.5e-3


# ------------------------------------------------------------------ costs
def _sanitize(sol: ClosedLoopSolution) -> ClosedLoopSolution:
    """Non-finite entries (a failed solve) set to 0 so that the figures, and their
    gradients, stay finite; the run is then discarded by its ``ok`` flag."""
    fix = lambda a: jnp.where(jnp.isfinite(a), a, 0.0)
    return eqx.tree_at(
        lambda s: (s.ys, s.q_I, s.eta, s.u, s.u_int, s.shut_int, s.v_meas),
        sol,
        (fix(sol.ys), fix(sol.q_I), fix(sol.eta), fix(sol.u), fix(sol.u_int),
         fix(sol.shut_int), fix(sol.v_meas)),
    )  # fmt: skip


def stage_noise_amplification(ctrl, plant, m_load, T_c=None) -> Float[Array, ""]:
    """RMS over the three stages (at each stage's middle height) of the controller's
    :func:`~jaxlift.control.performance.noise_amplification`. For a plain PID it is the same
    number at every height; a scheduled PID has its own gains per stage, and each
    stage's gains must pay for the noise they amplify (measured: with the middle
    height alone, stage 3's ``P`` ran to 480 when tuned)."""
    xs = (0.5 * plant.x_s1, 0.5 * (plant.x_s1 + plant.x_s2), 0.5 * (plant.x_s2 + plant.x_max))
    amps = jnp.stack([noise_amplification(ctrl, plant, x, m_load, T_c) for x in xs])
    return jnp.sqrt(jnp.mean(amps**2))


def tuning_cost(ctrl, plant, sol: ClosedLoopSolution, weights=None) -> Float[Array, ""]:
    """The tuning cost of a run: :func:`~jaxlift.control.performance.cost_from_figures` with
    the controller's noise amplification over the stages
    (:func:`stage_noise_amplification`; the same function in tuning and reports)."""
    amp = stage_noise_amplification(ctrl, plant, sol.reference.m_load, sol.T_c)
    return cost_from_figures(figures(sol), weights, amp)


def tuning_residuals(ctrl, plant, sol: ClosedLoopSolution, weights=None) -> Float[Array, " m"]:
    """The tuning cost of a run as a sum of squares: ``sum(r**2) == tuning_cost``
    (up to rounding). Every term of :func:`~jaxlift.control.performance.cost_from_figures` is
    the square of an RMS or of a mean, i.e. a sum of squares of (weighted) samples:
    the error (tracking), its band-passed part (oscillation, and again on the steady
    samples), the 10 ms duty rate on the moving samples (effort), plus the two
    post-shift offsets and the noise amplification. This is what Gauss--Newton /
    Levenberg--Marquardt tuning (:func:`tune_gains`, the default optimiser) works on."""
    w = CostWeights() if weights is None else weights
    fig = figures(sol)
    err = sol.v_ref - sol.speed
    steady, _ = ref_masks(sol)
    steady = steady.astype(err.dtype)
    moving = is_moving(sol.v_ref).astype(err.dtype)[1:-1]
    osc = bandpass(err)
    rate = jnp.diff(jnp.diff(sol.u_int) / OUTPUT_DT) / OUTPUT_DT
    n = err.shape[0]
    # the RMS helpers add 1e-30 under the square root: one constant residual each
    tiny = jnp.full(1, 1e-15)

    def wrms_terms(x, wts, scale):
        norm = jnp.sqrt(jnp.maximum(jnp.sum(wts), 1e-12))
        return jnp.concatenate([wts * x / norm, tiny]) / scale  # wts are 0/1: sqrt(w) = w

    off = jnp.where(jnp.isnan(fig.shift_offset), 0.0, fig.shift_offset)
    amp = stage_noise_amplification(ctrl, plant, sol.reference.m_load, sol.T_c)
    return jnp.concatenate(
        [
            err / (math.sqrt(n) * w.tracking),
            osc / (math.sqrt(n) * w.oscillation),
            wrms_terms(osc, steady, w.sustained),
            off / w.offset,
            wrms_terms(rate, moving, w.effort),
            (amp / w.noise)[None],
        ]
    )


def _run(ctrl, plant, effects, ref, sim_kw, weights):
    sol = simulate_closed_loop(plant, effects, ctrl, ref, **sim_kw)
    sol = _sanitize(sol)
    fig = figures(sol)
    cost = tuning_cost(ctrl, plant, sol, weights)
    ok = sol.ok & jnp.isfinite(cost)
    return jnp.where(ok, cost, FAILED_COST), ok, fig


def run_residuals(ctrl, plant, effects, ref, sim_kw, weights):
    """Residuals (``sum(r**2)`` = the cost), success flag and cost of one run; a failed
    run has residuals ``(sqrt(FAILED_COST), 0, ...)`` (cost ``FAILED_COST``, Jacobian 0)."""
    sol = _sanitize(simulate_closed_loop(plant, effects, ctrl, ref, **sim_kw))
    r = tuning_residuals(ctrl, plant, sol, weights)
    cost = jnp.sum(r**2)
    ok = sol.ok & jnp.isfinite(cost)
    failed = jnp.zeros_like(r).at[0].set(math.sqrt(FAILED_COST))
    return jnp.where(ok, r, failed), ok, jnp.where(ok, cost, FAILED_COST)


def closed_loop_costs(
    controller: AbstractController,
    plants: Plant,
    effects: tuple[AbstractEffect, ...],
    references: Reference,
    *,
    batched_plants: bool = False,
    weights: CostWeights | None = None,
    batch: str = "map",
    noise_seeds: ArrayLike | None = None,
    **sim_kw,
) -> tuple[Float[Array, "B L"], Float[Array, "B L"], Figures]:
    """Costs of ``controller`` on plants x runs: arrays ``(B, L)`` of costs
    (``FAILED_COST`` for failed runs), success flags, and the figures.

    ``references``: a stacked :class:`Reference` (leading axis ``L``, the runs: e.g.
    loads, or loads x noise seeds, :func:`tuning_runs`); ``plants``/``effects``: one
    model, or stacked draws (leading axis ``B``) with ``batched_plants=True``.
    ``noise_seeds``: the sensor-noise seed of each run, shape ``(L,)``, or ``(B, L)``
    with a realisation of its own for every draw (None: ``sim_kw``'s ``noise_seed``,
    the same for every run, or no noise). ``batch``: ``"map"`` (``lax.map``, one draw
    after the other) or ``"vmap"`` (a batched adaptive solve runs every member until
    the slowest finishes). Measured for 32 draws of the 110 s run on 2 CPU cores
    (benchmark): ``lax.map`` 0.40-0.56 s against ``vmap`` 1.45-2.4 s on a moderately
    loaded machine, about equal (1.6 s) under heavy load. ``sim_kw`` go to
    :func:`simulate_closed_loop`."""
    one = lambda p, e, r, kw: _run(controller, p, e, r, kw, weights)
    return over_runs(one, plants, effects, references, noise_seeds, sim_kw, batched_plants, batch)


def over_runs(one, plants, effects, references, noise_seeds, sim_kw, batched_plants, batch="map"):
    """``one(plant, effects, reference, sim_kw)`` over the draws (leading axis of
    ``plants``/``effects`` when ``batched_plants``) and the runs (leading axis of
    ``references``, with ``noise_seeds`` per run or per draw and run), each output with
    leading axes ``(B, L)`` (``B = 1`` for one model). The one place where draws, runs
    and noise seeds are laid out, for costs, residuals and Jacobians alike."""

    def runs(p, e, seeds):
        if seeds is None:
            return eqx.filter_vmap(lambda r: one(p, e, r, sim_kw))(references)
        return eqx.filter_vmap(lambda r, s: one(p, e, r, dict(sim_kw, noise_seed=s)))(
            references, seeds
        )

    seeds = None if noise_seeds is None else jnp.asarray(noise_seeds, dtype=jnp.uint32)
    if not batched_plants:
        if seeds is not None and seeds.ndim == 2:
            seeds = seeds[0]
        return jax.tree.map(lambda a: a[None], runs(plants, effects, seeds))
    n_draws = jax.tree.leaves(plants)[0].shape[0]
    if seeds is not None and seeds.ndim == 1:
        seeds = jnp.broadcast_to(seeds, (n_draws, seeds.shape[0]))
    if batch == "vmap":
        return eqx.filter_vmap(runs)(plants, effects, seeds)
    return jax.lax.map(lambda pes: runs(*pes), (plants, effects, seeds))


#: Seeds of the draws' own noise realisations are ``seed + DRAW_SEED_STRIDE * b``
#: (:func:`tuning_runs`), far apart from the small seeds a user passes.
DRAW_SEED_STRIDE = 100_003


def tuning_runs(
    references: Sequence[Reference],
    noise_seeds: Sequence[int] | None,
    n_draws: int | None = None,
) -> tuple[Reference, Array | None]:
    """The runs of one cost evaluation: every reference (load) with every noise seed
    (``L x S`` runs, seed-major), stacked, and their seeds -- ``(L S,)``, or ``(B, L S)``
    with ``n_draws = B``: then draw ``b`` has noise of its own (seeds shifted by
    ``b`` :data:`DRAW_SEED_STRIDE`), so that the draws also average over the noise.
    ``noise_seeds`` None: the references alone, no seeds (no noise).

    Why several seeds: with noise the cost of one realisation is itself random, and
    its gradient is the gradient of that realisation; the mean over ``S`` seeds is an
    estimate of the expected cost whose error falls like ``1/sqrt(S)``, and the tuned
    gains stop fitting one noise sequence."""
    refs = list(references)
    if noise_seeds is None:
        return stack_references(refs), None
    seeds = [int(s) for s in noise_seeds]
    if not seeds:
        raise ValueError("noise_seeds: give at least one seed, or None for no noise")
    stacked = stack_references([r for _ in seeds for r in refs])
    per_run = np.repeat(np.asarray(seeds, dtype=np.int64), len(refs))
    if n_draws is not None:
        per_run = per_run[None, :] + DRAW_SEED_STRIDE * np.arange(n_draws)[:, None]
    return stacked, jnp.asarray(per_run % 2**32, dtype=jnp.uint32)


def robust_objective(
    costs: Float[Array, " B"], alpha: float = 0.2, tail_weight: float = 1.0
) -> Float[Array, ""]:
    """``mean + tail_weight * CVaR_alpha`` of per-draw costs (CVaR: mean of the worst
    ``ceil(alpha B)``)."""
    k = max(1, math.ceil(alpha * costs.shape[0]))
    worst = jnp.sort(costs)[-k:]
    return jnp.mean(costs) + tail_weight * jnp.mean(worst)


def draw_weights(
    costs: Float[Array, " B"], robust: bool, alpha: float = 0.2, tail_weight: float = 1.0
) -> Float[Array, " B"]:
    """Weights ``w`` with ``sum(w * costs)`` = the tuning objective: ``1/B`` each (the
    mean), plus ``tail_weight / k`` on the ``k = ceil(alpha B)`` worst draws when
    ``robust`` (:func:`robust_objective`). The worst set is taken at ``costs`` and
    held fixed for derivatives (the objective is piecewise a weighted sum of squares,
    which is what lets Levenberg--Marquardt tune it)."""
    b = costs.shape[0]
    w = jnp.full(b, 1.0 / b)
    if not robust:
        return w
    k = max(1, math.ceil(alpha * b))
    worst = jnp.argsort(jax.lax.stop_gradient(costs))[b - k :]
    return w.at[worst].add(tail_weight / k)


def stack_references(refs: Sequence[Reference]) -> Reference:
    """Stack references of equal shape (e.g. one per load) along a new leading axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *refs)
