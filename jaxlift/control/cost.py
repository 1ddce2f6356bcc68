"""The tuning cost: the figures of "good" of a closed-loop run written as a sum of
squares, per-draw costs over batches of plants, and the robust objective (mean + CVaR).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

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
from .reference import Reference

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
    moving = (sol.v_ref != 0.0).astype(err.dtype)[1:-1]
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
    **sim_kw,
) -> tuple[Float[Array, "B L"], Float[Array, "B L"], Figures]:
    """Costs of ``controller`` on plants x references (loads): arrays ``(B, L)`` of
    costs (``FAILED_COST`` for failed runs), success flags, and the figures.

    ``references``: a stacked :class:`Reference` (leading axis ``L``, e.g. loads);
    ``plants``/``effects``: one model, or stacked draws (leading axis ``B``) with
    ``batched_plants=True``. ``batch``: ``"map"`` (``lax.map``, one draw after the
    other) or ``"vmap"`` (a batched adaptive solve runs every member until the slowest
    finishes). Measured for 32 draws of the 110 s run on 2 CPU cores (benchmark):
    ``lax.map`` 0.40-0.56 s against ``vmap`` 1.45-2.4 s on a moderately loaded machine,
    about equal (1.6 s) under heavy load. ``sim_kw`` go to :func:`simulate_closed_loop`."""
    run_ref = eqx.filter_vmap(
        lambda p, e, r: _run(controller, p, e, r, sim_kw, weights), in_axes=(None, None, 0)
    )
    if batched_plants:
        if batch == "vmap":
            return eqx.filter_vmap(lambda p, e: run_ref(p, e, references))(plants, effects)
        return jax.lax.map(lambda pe: run_ref(pe[0], pe[1], references), (plants, effects))
    c, ok, fig = run_ref(plants, effects, references)
    return c[None], ok[None], jax.tree.map(lambda a: a[None], fig)


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
