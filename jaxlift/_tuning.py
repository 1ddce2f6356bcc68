"""Gain tuning by gradient through the closed-loop simulation, robustness over
parameter draws, and closed-loop stability from eigenvalues.

Tuning (:func:`tune_gains`): the cost of :func:`jaxlift._performance.cost_from_figures`
summed over the references (loads), minimised with Adam (optax) in the log of the
gains. A plain :class:`~jaxlift.PID` is tuned in ``log P, log I, log D, log N,
log K_aw`` (any subset); a :class:`~jaxlift.ScheduledPID` in the log of its per-stage
gains at the two scheduling loads 500 and 1500 kg (``log G_i(500), log G_i(1500)``,
``G`` in ``P, I, D``, stage ``i``: 18 numbers, positive at both loads and linear in
between, written back as ``G_b,i, G_m,i``), plus ``log N`` (and ``log K_aw``). A gain
that starts at 0 is started at a small floor instead (``D``: 0.05, ``K_aw``: ``I/P``).

Robust tuning: a batch of plants (posterior draws), evaluated with ``vmap``; the
objective is ``mean + tail_weight * CVaR_alpha`` of the per-draw costs (CVaR: the mean
of the worst ``ceil(alpha B)`` draws). A failed solve (solver failure, fork out of
range, non-finite figure) costs ``FAILED_COST`` (finite, gradient 0) and is counted.

Stability (:func:`stability_table`): the closed loop (continuous form) is linearised
with ``jax.jacfwd`` at operating points -- height ``x`` frozen, steady motion at the
reference speed (``v = v_ref``, force balance, ``q_I`` = the duty that delivers the
flow, ``eta = 0``; found by Newton's method on the full vector field with ``x``
frozen). The eigenvalues of the Jacobian of all states but ``x`` give the local
stability (max real part < 0). "With noise": the sensor noise drives ``u_raw``
through ``P`` and the derivative path; the saturation then passes small signals only
while the noisy ``u_raw`` stays inside (0, 1). Its incremental (describing) gain
``g = P(0 < u_ss + xi < 1)`` (Booton), estimated from the noise component ``xi`` of
``u_raw`` on a fine time grid (2000 noise samples, fixed seed; continuous or sampled
law), replaces the saturation's slope 1 in the linearisation.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Mapping, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from ._closed_loop import (
    NOISE_POWER,
    NOISE_TS,
    OUTPUT_DT,
    ClosedLoopSolution,
    Reference,
    simulate_closed_loop,
)
from ._control import SCHEDULE_MASSES, AbstractController, ScheduledPID
from ._effects import AbstractEffect
from ._model import all_param_infos, with_params
from ._params import ParameterError, from_unconstrained, to_unconstrained
from ._performance import (
    CostWeights,
    Figures,
    _ref_masks,
    bandpass,
    cost_from_figures,
    figures,
    noise_amplification,
)
from ._plant import Plant
from ._simulate import Inputs, _canonical, _split, initial_state, plant_signals_and_derivative

__all__ = [
    "GainSpace",
    "TuneResult",
    "DrawSet",
    "FAILED_COST",
    "OSC_FREE_MPS",
    "tune_gains",
    "tune_multistart",
    "tuning_cost",
    "tuning_residuals",
    "stage_noise_amplification",
    "draw_weights",
    "closed_loop_costs",
    "robust_objective",
    "parameter_draws",
    "batch_models",
    "evaluate_draws",
    "closed_loop_eigenvalues",
    "noise_describing_gain",
    "stability_table",
    "operating_points",
]

#: Cost of a run whose simulation failed (finite: no NaN in a batch; gradient 0).
FAILED_COST = 1e6
#: A run is "oscillation-free" when its sustained oscillation RMS is below this [m/s].
OSC_FREE_MPS = 0.5e-3

_FLOORS = {"D": 0.05, "K_aw": None, "N": 10.0, "P": 1.0, "I": 10.0}


# ------------------------------------------------------------------ gain coordinates
class GainSpace(eqx.Module):
    """Log coordinates of the tuned gains of a controller (see the module docstring).

    Attributes:
        template: the controller whose untuned gains are kept.
        names: coordinate names (``P``, ``I``, ... for a PID; ``P1@500``, ``P1@1500``,
            ..., ``N``, ``K_aw`` for a scheduled PID).
    """

    template: AbstractController
    names: tuple[str, ...] = eqx.field(static=True)

    @classmethod
    def for_controller(
        cls, controller: AbstractController, names: Sequence[str] | None = None
    ) -> GainSpace:
        """Coordinates for ``controller``: ``names`` of the gains to tune (default: all
        of P, I, D, N, K_aw for a PID; the 18 stage gains, N and K_aw for a scheduled
        PID; give a subset to keep some fixed, e.g. without ``K_aw``)."""
        if isinstance(controller, ScheduledPID):
            stage = [f"{k}{i}@{m:g}" for i in (1, 2, 3) for k in "PID" for m in SCHEDULE_MASSES]
            allowed = stage + ["N", "K_aw"]
        else:
            allowed = ["P", "I", "D", "N", "K_aw"]
        names = tuple(allowed if names is None else names)
        bad = [n for n in names if n not in allowed]
        if bad:
            raise ParameterError(f"cannot tune {bad}; tunable gains: {allowed}")
        return cls(template=controller, names=names)

    def _values(self, ctrl: AbstractController) -> dict[str, Array]:
        out = {}
        if isinstance(ctrl, ScheduledPID):
            for m in SCHEDULE_MASSES:
                g = ctrl.stage_gains(m)
                for i in range(3):
                    for j, k in enumerate("PID"):
                        out[f"{k}{i + 1}@{m:g}"] = g[i, j]
            out["N"], out["K_aw"] = ctrl.N, ctrl.K_aw
        else:
            out = {k: getattr(ctrl, k) for k in ("P", "I", "D", "N", "K_aw")}
        return out

    def to_theta(self, ctrl: AbstractController) -> Float[np.ndarray, " n"]:
        """Log coordinates of ``ctrl``'s tuned gains (zeros raised to a floor)."""
        vals = {k: float(np.asarray(v)) for k, v in self._values(ctrl).items()}
        out = []
        for n in self.names:
            v = vals[n]
            if v <= 0:
                base = n.split("@")[0].rstrip("123")
                if base == "K_aw":
                    v = max(vals.get("I", 300.0) / max(vals.get("P", 20.0), 1e-3), 1.0)
                else:
                    v = _FLOORS[base]
            out.append(math.log(v))
        return np.asarray(out)

    def from_theta(self, theta: Float[Array, " n"]) -> AbstractController:
        """The controller with the tuned gains ``exp(theta)`` (jit/grad-safe)."""
        vals = dict(self._values(self.template))
        for i, n in enumerate(self.names):
            vals[n] = jnp.exp(theta[i])
        if isinstance(self.template, ScheduledPID):
            g = [
                jnp.asarray(
                    [[vals[f"{k}{i}@{m:g}"] for k in "PID"] for i in (1, 2, 3)], dtype=jnp.float64
                )
                for m in SCHEDULE_MASSES
            ]
            return ScheduledPID.from_stage_gains(g[0], g[1], vals["N"], vals["K_aw"])
        return self.template.with_gains({k: vals[k] for k in ("P", "I", "D", "N", "K_aw")})

    def local_values(self, theta: Float[Array, " n"], m_load) -> Float[Array, " 11"]:
        """Scheduled PID: what the loop at load ``m_load`` sees of ``theta`` -- the nine
        stage gains at that load, ``N`` and ``K_aw`` (11 numbers, linear units). A run
        at one load depends on the 18 + 2 coordinates only through these, so its
        Jacobian needs 11 forward-mode tangents instead of one per coordinate."""
        ctrl = self.from_theta(theta)
        f64 = lambda a: jnp.asarray(a, dtype=jnp.float64)  # noqa: E731
        return jnp.concatenate(
            [f64(ctrl.stage_gains(m_load)).ravel(), jnp.stack([f64(ctrl.N), f64(ctrl.K_aw)])]
        )

    @staticmethod
    def local_controller(values: Float[Array, " 11"]) -> ScheduledPID:
        """The scheduled PID with the gains ``values`` (:meth:`local_values`) at every
        load: the same loop as the full controller at that load."""
        g = values[:9].reshape(3, 3)
        return ScheduledPID.from_stage_gains(g, g, values[9], values[10])


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
    :func:`~jaxlift._performance.noise_amplification`. For a plain PID it is the same
    number at every height; a scheduled PID has its own gains per stage, and each
    stage's gains must pay for the noise they amplify (measured: with the middle
    height alone, stage 3's ``P`` ran to 480 when tuned)."""
    xs = (0.5 * plant.x_s1, 0.5 * (plant.x_s1 + plant.x_s2), 0.5 * (plant.x_s2 + plant.x_max))
    amps = jnp.stack([noise_amplification(ctrl, plant, x, m_load, T_c) for x in xs])
    return jnp.sqrt(jnp.mean(amps**2))


def tuning_cost(ctrl, plant, sol: ClosedLoopSolution, weights=None) -> Float[Array, ""]:
    """The tuning cost of a run: :func:`~jaxlift._performance.cost_from_figures` with
    the controller's noise amplification over the stages
    (:func:`stage_noise_amplification`; the same function in tuning and reports)."""
    amp = stage_noise_amplification(ctrl, plant, sol.reference.m_load, sol.T_c)
    return cost_from_figures(figures(sol), weights, amp)


def tuning_residuals(ctrl, plant, sol: ClosedLoopSolution, weights=None) -> Float[Array, " m"]:
    """The tuning cost of a run as a sum of squares: ``sum(r**2) == tuning_cost``
    (up to rounding). Every term of :func:`~jaxlift._performance.cost_from_figures` is
    the square of an RMS or of a mean, i.e. a sum of squares of (weighted) samples:
    the error (tracking), its band-passed part (oscillation, and again on the steady
    samples), the 10 ms duty rate on the moving samples (effort), plus the two
    post-shift offsets and the noise amplification. This is what Gauss--Newton /
    Levenberg--Marquardt tuning (:func:`tune_gains` ``method="lm"``) works on."""
    w = CostWeights() if weights is None else weights
    fig = figures(sol)
    err = sol.v_ref - sol.speed
    steady, _ = _ref_masks(sol)
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


def _run_residuals(ctrl, plant, effects, ref, sim_kw, weights):
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


# ------------------------------------------------------------------ tuning
@dataclasses.dataclass
class TuneResult:
    """Result of :func:`tune_gains`.

    Attributes:
        controller: the best controller seen (lowest objective).
        initial: the starting controller.
        initial_cost, best_cost: objective at the start and at the best step.
        history: objective per step (before the step).
        history_s: wall time [s] since the start when each ``history`` entry was known.
        n_failed: failed runs in the batch at the best step.
        n_evaluations: evaluations of the objective (with or without derivatives).
        wall_s: wall time including compilation [s].
        names: the tuned coordinates.
        message: why the optimiser stopped (LM, L-BFGS).
        n_with_derivatives: evaluations that computed derivatives (Jacobian or
            gradient; the rest, LM's trial points with ``trials="residuals"``, were
            plain simulations); None: all of them.
    """

    controller: AbstractController
    initial: AbstractController
    initial_cost: float
    best_cost: float
    history: list[float]
    history_s: list[float]
    n_failed: int
    n_evaluations: int
    wall_s: float
    names: tuple[str, ...]
    message: str = ""
    n_with_derivatives: int | None = None


def tune_gains(
    controller: AbstractController,
    plant: Plant,
    effects: Sequence[AbstractEffect],
    references: Sequence[Reference],
    *,
    names: Sequence[str] | None = None,
    batched_plants: bool = False,
    robust: bool = False,
    alpha: float = 0.2,
    tail_weight: float = 1.0,
    steps: int = 30,
    learning_rate: float = 0.08,
    weights: CostWeights | None = None,
    progress: bool = False,
    rtol: float = 1e-5,
    method: str = "lm",
    gradient: str = "auto",
    ftol: float = 1e-3,
    trials: str = "auto",
    **sim_kw,
) -> TuneResult:
    """Tune the gains of ``controller`` on the log gains, derivatives through the
    closed-loop simulation.

    The cost is a sum of squares (:func:`tuning_residuals`; the robust objective too,
    with the worst draws' weights held at each point: :func:`draw_weights`), so the
    default is Levenberg--Marquardt on the residual vector with its forward-mode
    Jacobian (one tangent per gain; :func:`jaxlift._lm.levenberg_marquardt`). Measured
    on the 110 s reference (benchmarks/results_tune.txt): LM converges in about 10
    evaluations where L-BFGS on the same cost and gradient stalls (the curvature of
    the log-gain cost spans orders of magnitude, and L-BFGS's line search spends the
    budget finding the scale that Gauss--Newton gets from ``JᵀJ``). Also available:
    L-BFGS (``scipy.optimize.minimize(method="L-BFGS-B", jac=True)`` driven by the JAX
    value and gradient) and Adam (optax).

    Args:
        controller: starting gains (:class:`~jaxlift.PID` or :class:`~jaxlift.ScheduledPID`).
        plant, effects: the model; with ``batched_plants=True`` stacked draws (see
            :func:`batch_models`).
        references: one reference per load (same length), e.g. at 500 and 1500 kg.
        names: which gains to tune (see :meth:`GainSpace.for_controller`).
        robust: objective ``mean + tail_weight * CVaR_alpha`` over the draws (else the
            mean over the draws; with one plant: the nominal cost).
        steps: budget: at most ``steps`` evaluations with derivatives (LM: residuals
            and Jacobian, at the start and at every trial point; L-BFGS: function
            evaluations incl. line search; Adam: steps, plus one at the end).
        learning_rate: Adam step in log-gain units.
        method: ``"lm"`` (default), ``"lbfgs"`` or ``"adam"``.
        ftol: LM stops when a full Gauss--Newton step would lower the objective by
            less than this fraction of it.
        trials: how LM evaluates a trial point: ``"jacobian"`` (with the Jacobian: one
            compiled function, and an accepted trial needs no second simulation; best
            when compilation dominates, few gains), ``"residuals"`` (a plain simulation,
            the Jacobian only where a step is accepted: a rejected trial then costs one
            simulation instead of ``1 + n_gains`` tangents, for a second compilation) or
            ``"auto"``: ``"jacobian"`` up to 8 gains, else ``"residuals"``.
        gradient: L-BFGS and Adam only (LM is always forward mode): ``"forward"``
            (``jax.jacfwd`` with ``diffrax.ForwardMode``; one tangent per gain:
            measured 4.5x a simulation for the plain PID's 5 gains),
            ``"reverse"`` (``RecursiveCheckpointAdjoint``; cost independent of the number
            of gains, more to compile) or ``"auto"``: forward up to 8 gains, else reverse.
        weights: cost scales (:class:`~jaxlift._performance.CostWeights`).
        progress: tqdm progress bar (stderr).
        rtol: solver tolerance during tuning; ``sim_kw``: ``sampled``, ``T_c``,
            ``noise_seed`` of :func:`simulate_closed_loop`.

    Deterministic: the same inputs give the same gains.
    """
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    effects = _canonical(effects) if not batched_plants else tuple(effects)
    space = GainSpace.for_controller(controller, names)
    refs = stack_references(list(references))
    sim_kw = dict(sim_kw, rtol=rtol)

    cfg = dict(batched=batched_plants, robust=robust, alpha=alpha, tail_weight=tail_weight)

    if gradient == "auto":
        gradient = "forward" if len(space.names) <= 8 else "reverse"
    if gradient not in ("forward", "reverse") or method not in ("adam", "lbfgs", "lm"):
        raise ValueError(
            f"gradient must be forward/reverse, method lm/adam/lbfgs: {gradient}, {method}"
        )
    if method == "lm":
        args = (space, plant, effects, refs, weights, cfg, sim_kw)
        if trials == "auto":
            trials = "jacobian" if len(space.names) <= 8 else "residuals"
        if trials not in ("jacobian", "residuals"):
            raise ValueError(f"trials must be auto/jacobian/residuals, not {trials!r}")
        r_only = (lambda th: _residuals_only(th, *args)) if trials == "residuals" else None
        return _tune_lm(
            lambda th: _residuals_and_jacobian(th, *args),
            r_only,
            space,
            controller,
            steps,
            progress,
            t_start,
            ftol,
        )

    def vg(theta):
        return _objective_value_and_grad(
            theta, space, plant, effects, refs, weights, cfg, sim_kw, gradient
        )

    if method == "lbfgs":
        return _tune_lbfgs(vg, space, controller, steps, progress, t_start)
    opt = optax.apply_if_finite(optax.adam(learning_rate), max_consecutive_errors=5)
    theta = jnp.asarray(space.to_theta(controller))
    state = opt.init(theta)
    history: list[float] = []
    history_s: list[float] = []
    best = (math.inf, theta, 0)
    bar = tqdm(range(steps), desc="tuning", disable=not progress, leave=False)
    for _ in bar:
        (val, n_bad), grad = vg(theta)
        val = float(val)
        history.append(val)
        history_s.append(time.perf_counter() - t_start)
        if val < best[0]:
            best = (val, theta, int(n_bad))
        bar.set_postfix(cost=f"{val:.4g}", best=f"{best[0]:.4g}")
        updates, state = opt.update(grad, state, theta)
        theta = optax.apply_updates(theta, updates)
    (val, n_bad), _ = vg(theta)  # the last point
    history.append(float(val))
    history_s.append(time.perf_counter() - t_start)
    if float(val) < best[0]:
        best = (float(val), theta, int(n_bad))
    return TuneResult(
        controller=space.from_theta(best[1]),
        initial=controller,
        initial_cost=history[0],
        best_cost=best[0],
        history=history,
        history_s=history_s,
        n_failed=best[2],
        n_evaluations=steps + 1,
        wall_s=time.perf_counter() - t_start,
        names=space.names,
    )


def tune_multistart(
    starts: Sequence[AbstractController], plant, effects, references, **kw
) -> TuneResult:
    """:func:`tune_gains` from each of ``starts`` (same keyword arguments); returns the
    result with the lowest objective, with ``wall_s`` and ``n_evaluations`` summed over
    all starts (the whole cost of the search) and ``message`` saying which start won.

    Why: the cost is not convex in the gains. Measured on the tests' plant with wide
    parameter draws, tuned at rtol 1e-5: robust tuning started from the nominal-tuned
    gains stayed in their basin (objective 11.2 -> 11.0, no better worst case over 200
    held-out draws), started from the thesis gains it reached 7.5 (worst case 25 %
    lower). Tuned at rtol 1e-6 both starts reached 7.5: which start wins depends on
    the case, so `jaxlift tune` runs both."""
    results = [tune_gains(c, plant, effects, references, **kw) for c in starts]
    i = int(np.argmin([r.best_cost for r in results]))
    best = results[i]
    return dataclasses.replace(
        best,
        wall_s=sum(r.wall_s for r in results),
        n_evaluations=sum(r.n_evaluations for r in results),
        message=f"start {i + 1} of {len(results)} "
        f"(objectives {', '.join(format(r.best_cost, '.4g') for r in results)}): {best.message}",
    )


class _BudgetSpent(Exception):
    """Raised inside L-BFGS's objective when the evaluation budget is spent."""


class _Stalled(Exception):
    """Raised inside LM's evaluations when the best objective stopped improving."""


def _tune_lbfgs(vg, space, controller, steps, progress, t_start) -> TuneResult:
    from scipy.optimize import minimize
    from tqdm.auto import tqdm

    history: list[float] = []
    history_s: list[float] = []
    best: list = [math.inf, None, 0]
    bar = tqdm(total=steps, desc="tuning (L-BFGS)", disable=not progress, leave=False)

    def fun(th):
        if len(history) >= steps:
            raise _BudgetSpent
        (val, n_bad), grad = vg(jnp.asarray(th))
        val, grad = float(val), np.asarray(grad, dtype=float)
        history.append(val)
        history_s.append(time.perf_counter() - t_start)
        if val < best[0]:
            best[:] = [val, np.array(th), int(n_bad)]
        bar.update(1)
        bar.set_postfix(cost=f"{val:.4g}", best=f"{best[0]:.4g}")
        if not (math.isfinite(val) and np.all(np.isfinite(grad))):
            return FAILED_COST, np.zeros_like(grad)
        return val, grad

    theta0 = np.asarray(space.to_theta(controller), dtype=float)
    message = "evaluation budget spent"
    try:  # the budget is exact: scipy's maxfun is only checked between iterations
        res = minimize(fun, theta0, jac=True, method="L-BFGS-B", options=dict(maxiter=steps))
        message = str(res.message)
    except _BudgetSpent:
        pass
    bar.close()
    return TuneResult(
        controller=space.from_theta(jnp.asarray(best[1])),
        initial=controller,
        initial_cost=history[0],
        best_cost=best[0],
        history=history,
        history_s=history_s,
        n_failed=best[2],
        n_evaluations=len(history),
        wall_s=time.perf_counter() - t_start,
        names=space.names,
        message=message,
    )


def _objective(theta, space, plant, effects, refs, weights, cfg, sim_kw):
    ctrl = space.from_theta(theta)
    c, ok, _ = closed_loop_costs(
        ctrl, plant, effects, refs, batched_plants=cfg["batched"], weights=weights, **sim_kw
    )
    per_draw = jnp.mean(c, axis=1)
    w = draw_weights(per_draw, cfg["robust"], cfg["alpha"], cfg["tail_weight"])
    return jnp.sum(w * per_draw), jnp.sum(~ok)


# module level, so that repeated tunings of the same problem shape compile once
@eqx.filter_jit
def _objective_value_and_grad(theta, space, plant, effects, refs, weights, cfg, sim_kw, mode):
    if mode == "reverse":
        f = lambda th: _objective(th, space, plant, effects, refs, weights, cfg, sim_kw)
        return jax.value_and_grad(f, has_aux=True)(theta)
    kw = dict(sim_kw, adjoint=diffrax.ForwardMode())

    def f(th):
        out = _objective(th, space, plant, effects, refs, weights, cfg, kw)
        return out[0], out

    grad, out = jax.jacfwd(f, has_aux=True)(theta)
    return out, grad


def _residual_objective(theta, space, plant, effects, refs, weights, cfg, sim_kw):
    """Residual vector ``r`` with ``sum(r**2)`` = the objective (draws x loads, each
    run's residuals scaled by ``sqrt(w_b / L)``, :func:`draw_weights`), the objective,
    and the number of failed runs."""
    ctrl = space.from_theta(theta)
    run_ref = eqx.filter_vmap(
        lambda p, e, r: _run_residuals(ctrl, p, e, r, sim_kw, weights), in_axes=(None, None, 0)
    )
    if cfg["batched"]:
        r, ok, c = jax.lax.map(lambda pe: run_ref(pe[0], pe[1], refs), (plant, effects))
    else:
        r, ok, c = jax.tree.map(lambda a: a[None], run_ref(plant, effects, refs))
    per_draw = jnp.mean(c, axis=1)
    w = draw_weights(per_draw, cfg["robust"], cfg["alpha"], cfg["tail_weight"])
    scale = jnp.sqrt(w / c.shape[1])
    return (r * scale[:, None, None]).ravel(), (jnp.sum(w * per_draw), jnp.sum(~ok))


@eqx.filter_jit
def _residuals_and_jacobian(theta, space, plant, effects, refs, weights, cfg, sim_kw):
    """Residuals, their forward-mode Jacobian w.r.t. the log gains, objective, failures.
    A scheduled PID with more than 11 tuned coordinates is differentiated per load in
    its 11 :meth:`GainSpace.local_values` and chained (measured for 19 coordinates
    and two loads on 2 busy cores: 1.6 s against 2.25 s per Jacobian)."""
    kw = dict(sim_kw, adjoint=diffrax.ForwardMode())
    if isinstance(space.template, ScheduledPID) and theta.shape[0] > 11:
        return _local_residuals_and_jacobian(theta, space, plant, effects, refs, weights, cfg, kw)

    def f(th):
        r, aux = _residual_objective(th, space, plant, effects, refs, weights, cfg, kw)
        return r, (r, aux)

    J, (r, aux) = jax.jacfwd(f, has_aux=True)(theta)
    return r, J, aux


def _local_residuals_and_jacobian(theta, space, plant, effects, refs, weights, cfg, kw):
    def one(p, e, ref):
        vals = space.local_values(theta, ref.m_load)
        dvals = jax.jacfwd(space.local_values)(theta, ref.m_load)

        def f(v):
            out = _run_residuals(space.local_controller(v), p, e, ref, kw, weights)
            return out[0], out

        J_local, (r, ok, c) = jax.jacfwd(f, has_aux=True)(vals)
        return r, J_local @ dvals, ok, c

    run_ref = eqx.filter_vmap(one, in_axes=(None, None, 0))
    if cfg["batched"]:
        r, J, ok, c = jax.lax.map(lambda pe: run_ref(pe[0], pe[1], refs), (plant, effects))
    else:
        r, J, ok, c = jax.tree.map(lambda a: a[None], run_ref(plant, effects, refs))
    per_draw = jnp.mean(c, axis=1)
    w = draw_weights(per_draw, cfg["robust"], cfg["alpha"], cfg["tail_weight"])
    scale = jnp.sqrt(w / c.shape[1])
    r = (r * scale[:, None, None]).ravel()
    J = (J * scale[:, None, None, None]).reshape(r.shape[0], theta.shape[0])
    return r, J, (jnp.sum(w * per_draw), jnp.sum(~ok))


@eqx.filter_jit
def _residuals_only(theta, space, plant, effects, refs, weights, cfg, sim_kw):
    """Residuals, objective and failures without derivatives (LM's trial points)."""
    return _residual_objective(theta, space, plant, effects, refs, weights, cfg, sim_kw)


def _tune_lm(
    rj, r_only, space, controller, steps, progress, t_start, ftol, patience=5
) -> TuneResult:
    """Levenberg--Marquardt (:func:`jaxlift._lm.levenberg_marquardt`) on the residuals.
    ``r_only`` None: every trial point is evaluated with the Jacobian (one compiled
    function; an accepted trial then needs no second simulation); else trial points
    are simulated without derivatives (``r_only``) and the Jacobian is computed where
    a step is accepted. ``steps``: at most this many evaluations (either kind).
    Stops when the Gauss--Newton step would gain less than ``ftol`` of the objective,
    or when the best objective has improved by less than ``ftol`` (relative) over the
    last ``patience`` evaluations: near the optimum the cost is rough at the 0.1-1 %
    level (kinks where the valve saturates, and the integrator's steps changing with
    the gains; measured: the Gauss--Newton curvature there spans 6e5, the rejected
    trials are 0.2-0.5 % above the best), and the remaining trials are wasted."""
    from tqdm.auto import tqdm

    from ._lm import levenberg_marquardt

    history: list[float] = []
    history_s: list[float] = []
    best: list = [math.inf, None, 0]
    cache: dict = {}
    n_jac = [0]
    bar = tqdm(total=steps, desc="tuning (LM)", disable=not progress, leave=False)

    def evaluate(th, with_jacobian=True):
        th = np.asarray(th, dtype=float)
        hit = "theta" in cache and np.array_equal(cache["theta"], th)
        if hit and (cache["J"] is not None or not with_jacobian):
            return cache["r"], cache["J"]
        if len(history) >= steps:
            raise _BudgetSpent
        if len(history) > patience and best[0] > (1.0 - ftol) * min(history[:-patience]):
            raise _Stalled
        if with_jacobian or r_only is None:
            r, J, (obj, n_bad) = rj(jnp.asarray(th))
            J = np.asarray(J)
            n_jac[0] += 1
        else:
            r, (obj, n_bad) = r_only(jnp.asarray(th))
            J = None
        r, obj = np.asarray(r), float(obj)
        history.append(obj)
        history_s.append(time.perf_counter() - t_start)
        if obj < best[0]:
            best[:] = [obj, th, int(n_bad)]
        bar.update(1)
        bar.set_postfix(cost=f"{obj:.4g}", best=f"{best[0]:.4g}")
        if not (np.all(np.isfinite(r)) and (J is None or np.all(np.isfinite(J)))):
            r = np.full_like(r, np.inf)
        cache.update(theta=th, r=r, J=J)
        return r, J

    theta0 = np.asarray(space.to_theta(controller), dtype=float)
    r0, _ = evaluate(theta0)
    # stop when a full Gauss--Newton step would lower the objective by less than
    # ftol of it (the LM driver's test is relative to chi2 per degree of freedom)
    gtol = ftol * max(r0.size - theta0.size, 1)
    message = "evaluation budget spent"
    try:
        res = levenberg_marquardt(
            lambda th: evaluate(th, False)[0], evaluate, theta0, max_iter=4 * steps, gtol=gtol
        )
        message = res.message
    except _BudgetSpent:
        pass
    except _Stalled:
        message = f"stalled: best improved by < {ftol:g} over the last {patience} evaluations"
    bar.close()
    return TuneResult(
        controller=space.from_theta(jnp.asarray(best[1])),
        initial=controller,
        initial_cost=history[0],
        best_cost=best[0],
        history=history,
        history_s=history_s,
        n_failed=best[2],
        n_evaluations=len(history),
        wall_s=time.perf_counter() - t_start,
        names=space.names,
        message=message,
        n_with_derivatives=n_jac[0],
    )


# ------------------------------------------------------------------ parameter draws
@dataclasses.dataclass
class DrawSet:
    """Parameter draws of the plant (+ effects).

    Attributes:
        source: where they came from (posterior, or least-squares covariance), as text.
        effects: effect names of the model.
        draws: one ``{name: value}`` per draw (physical units, MODEL.md names).
    """

    source: str
    effects: list[str]
    draws: list[dict[str, float]]

    def split(self, n_first: int) -> tuple[DrawSet, DrawSet]:
        """The first ``n_first`` draws and the rest (e.g. tuning / held-out)."""
        return (
            DrawSet(self.source, self.effects, self.draws[:n_first]),
            DrawSet(self.source, self.effects, self.draws[n_first:]),
        )


def parameter_draws(
    n: int,
    seed: int,
    *,
    posterior_dir: str | os.PathLike | None = None,
    fit_dir: str | os.PathLike | None = None,
) -> DrawSet:
    """``n`` draws of the model parameters from ``seed``.

    From the posterior (``jaxlift._posterior.posterior_draws(posterior_dir, n, seed)``)
    when ``posterior_dir`` is given and that works; else from the least-squares fit in
    ``fit_dir`` (``params.json`` and ``metrics.json``: standard errors and, where
    present, the correlation matrix; independent otherwise): a Gaussian in the
    unconstrained coordinate of each parameter (log/logit, delta method), except for a
    parameter whose standard error is large against its distance to the bound (>
    half of it), which is drawn in physical units and clipped to its bounds. Unfitted
    parameters are fixed. ``source`` says which was used."""
    notes = []
    if posterior_dir is not None:
        try:
            from ._posterior import posterior_draws  # written in parallel; may be absent

            eff, draws = posterior_draws(posterior_dir, n, seed)
            return DrawSet(f"posterior samples from {posterior_dir}", list(eff), list(draws))
        except (ImportError, FileNotFoundError, OSError, ValueError) as err:
            notes.append(f"posterior in {posterior_dir} not usable ({err})")
    if fit_dir is None:
        raise ParameterError(
            "no parameter draws: give a posterior directory or a fit directory "
            "(params.json + metrics.json from `jaxlift fit`)"
        )
    fit_dir = os.fspath(fit_dir)
    infos = all_param_infos("all")
    from ._params import load_params_json

    values = load_params_json(os.path.join(fit_dir, "params.json"), infos)
    mpath = os.path.join(fit_dir, "metrics.json")
    try:
        with open(mpath, encoding="utf-8") as fh:
            metrics = json.load(fh)
    except FileNotFoundError:
        raise ParameterError(f"{mpath}: not found (needed for the fit covariance)") from None
    se = {k: float(v) for k, v in (metrics.get("stderr") or {}).items() if v is not None}
    se = {k: v for k, v in se.items() if k in values and math.isfinite(v) and v > 0}
    names = sorted(se)
    corr = np.eye(len(names))
    if "correlation" in metrics:
        cn = metrics["correlation"]["names"]
        cm = np.asarray(metrics["correlation"]["matrix"], dtype=float)
        idx = {k: i for i, k in enumerate(cn)}
        for a, na in enumerate(names):
            for b, nb in enumerate(names):
                if na in idx and nb in idx:
                    corr[a, b] = cm[idx[na], idx[nb]]
    else:
        notes.append("metrics.json has no correlation matrix: parameters drawn independently")
    mean, sd, logspace = [], [], []
    for k in names:
        info, v = infos[k], values[k]
        theta = float(to_unconstrained(info, v))
        eps = 1e-6 * max(abs(v), 1e-12)
        slope = (
            float(to_unconstrained(info, v + eps)) - float(to_unconstrained(info, v - eps))
        ) / (2 * eps)
        dist = min(v - info.lower, info.upper - v)
        use_log = info.transform != "identity" and se[k] < 0.5 * dist and math.isfinite(slope)
        logspace.append(use_log)
        mean.append(theta if use_log else v)
        sd.append(se[k] * abs(slope) if use_log else se[k])
    cov = np.outer(sd, sd) * corr
    cov = 0.5 * (cov + cov.T) + 1e-12 * np.diag(np.square(sd))
    rng = np.random.default_rng(seed)
    z = rng.multivariate_normal(np.asarray(mean), cov, size=n, method="eigh")
    draws = []
    for row in z:
        d = dict(values)
        for j, k in enumerate(names):
            info = infos[k]
            x = float(from_unconstrained(info, row[j])) if logspace[j] else float(row[j])
            d[k] = float(np.clip(x, info.lower, info.upper))
        draws.append(d)
    effects = [e for e in metrics.get("effects", []) or []]
    if not effects:
        from ._effects import EFFECTS

        effects = [n_ for n_, c in EFFECTS.items() if set(c.param_infos()) & set(values)]
    notes.insert(0, f"least-squares covariance of the fit in {fit_dir} (no posterior)")
    return DrawSet("; ".join(notes), list(effects), draws)


def batch_models(
    plant: Plant, effects: Sequence[AbstractEffect], draws: Sequence[Mapping[str, float]]
) -> tuple[Plant, tuple[AbstractEffect, ...]]:
    """Stack ``(plant, effects)`` with each draw's values (names the model does not
    have, e.g. effect parameters when the effects are off, are ignored)."""
    effects = _canonical(effects)
    known = set(all_param_infos(effects))
    models = [
        with_params(plant, effects, {k: v for k, v in d.items() if k in known}) for d in draws
    ]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *models)


def evaluate_draws(
    controller: AbstractController,
    plants: Plant,
    effects: tuple[AbstractEffect, ...],
    reference: Reference,
    *,
    weights: CostWeights | None = None,
    **sim_kw,
) -> tuple[np.ndarray, np.ndarray, Figures]:
    """Costs, success flags and figures of one controller over stacked draws on one
    reference (``vmap``)."""
    c, ok, fig = closed_loop_costs(
        controller,
        plants,
        effects,
        stack_references([reference]),
        batched_plants=True,
        weights=weights,
        **sim_kw,
    )
    return np.asarray(c[:, 0]), np.asarray(ok[:, 0]), jax.tree.map(lambda a: a[:, 0], fig)


# ------------------------------------------------------------------ stability
def operating_points(plant: Plant) -> list[tuple[str, float]]:
    """Heights [m] along the lift: the middle and both ends of every stage."""
    x1, x2, xm = plant.x_s1, plant.x_s2, plant.x_max
    return [
        ("stage 1 low", 0.3),
        ("stage 1 mid", 0.75),
        ("stage 1 top", x1 - 0.1),
        ("stage 2 low", x1 + 0.1),
        ("stage 2 mid", 0.5 * (x1 + x2)),
        ("stage 2 top", x2 - 0.1),
        ("stage 3 low", x2 + 0.1),
        ("stage 3 mid", 0.5 * (x2 + xm)),
        ("stage 3 top", xm - 0.2),
    ]


def _cl_field_frozen(z, x, v_ref, plant, effects, ctrl, m_load, sat_gain):
    """Closed-loop derivative of all states but ``x`` (``x`` frozen), no noise."""
    n_plant = 3 + sum(e.n_states for e in effects)
    yp = jnp.concatenate([x[None], z[: n_plant - 1]])
    q_I, eta = z[n_plant - 1], z[n_plant]
    out = ctrl.output(plant, x, m_load, v_ref - yp[1], q_I, eta, True, sat_gain=sat_gain)
    _, dyp = plant_signals_and_derivative(0.0, yp, plant, effects, out.u, m_load)
    return jnp.concatenate([dyp[1:], jnp.stack([out.dq_I, out.deta])])


@eqx.filter_jit
def _equilibrium_and_jacobian(plant, effects, ctrl, m_load, x, v_ref, sat_gain):
    # first guess: force balance at v_ref, the duty that delivers the flow
    inputs = Inputs(
        ts=jnp.asarray([0.0, 1.0]),
        pwm=jnp.zeros(2),
        load_kg=jnp.stack([m_load, m_load]),
        jump_ts=jnp.asarray([1.0]),
        x0=x,
    )
    y0 = initial_state(plant, effects, inputs)
    area, r = plant.area(x), plant.ratio
    p = ((m_load + plant.stage_mass(x)) * 9.81 + plant.friction(v_ref) + plant.d * v_ref) * r / area
    omega = area * v_ref / r * 2 * jnp.pi / (plant.eta_v * plant.disp)
    k = plant.staged(x, plant.k1, plant.k2, plant.k3)
    zz = plant.staged(x, plant.z1, plant.z2, plant.z3)
    u = (omega - zz) / k / plant.u_batt
    (_, _, _), zs = _split(y0, effects)
    z = jnp.concatenate([jnp.stack([v_ref, p]), *zs, jnp.stack([u, 0.0])])
    f = lambda z: _cl_field_frozen(z, x, v_ref, plant, effects, ctrl, m_load, sat_gain)

    def newton(z, _):
        J = jax.jacfwd(f)(z)
        dz = jnp.linalg.solve(J, -f(z))
        return z + dz, None

    z, _ = jax.lax.scan(newton, z, None, length=12)
    J = jax.jacfwd(f)(z)
    resid = f(z)
    return z, J, resid


def closed_loop_eigenvalues(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    controller: AbstractController,
    m_load: float,
    x: float,
    v_ref: float,
    sat_gain: float | None = None,
) -> tuple[np.ndarray, float, bool]:
    """Eigenvalues [1/s] of the closed loop linearised at height ``x`` [m] (frozen),
    steady motion at ``v_ref`` [m/s], load ``m_load`` [kg]; ``sat_gain``: slope of the
    saturation (None: 1, the noise-free interior). Returns ``(eigenvalues, duty at the
    operating point, whether the operating point was found with 0 < u < 1)``."""
    effects = _canonical(effects)
    z, J, resid = _equilibrium_and_jacobian(
        plant,
        effects,
        controller,
        jnp.asarray(m_load, dtype=jnp.float64),
        jnp.asarray(x, dtype=jnp.float64),
        jnp.asarray(v_ref, dtype=jnp.float64),
        None if sat_gain is None else jnp.asarray(sat_gain, dtype=jnp.float64),
    )
    n_plant = 3 + sum(e.n_states for e in effects)
    u = float(z[n_plant - 1])
    scale = np.abs(np.asarray(J)).max(axis=1) * np.maximum(np.abs(np.asarray(z)), 1e-6) + 1e-12
    found = bool(np.all(np.abs(np.asarray(resid)) <= 1e-6 * scale)) and 0.0 < u < 1.0
    return np.linalg.eigvals(np.asarray(J)), u, found


def noise_describing_gain(
    controller: AbstractController,
    plant: Plant,
    x: float,
    m_load: float,
    u_op: float,
    *,
    sampled: bool = False,
    T_c: float = 0.01,
    seed: int = 0,
    n_samples: int = 2000,
    sub: int = 64,
) -> float:
    """Incremental gain of the saturation ``clip(., 0, 1)`` for a small signal on top of
    the sensor noise's part of ``u_raw`` around the duty ``u_op``: the probability
    that ``u_op + xi`` is inside (0, 1) (Booton), over time. ``xi = P n + D N (n - eta_n)``
    with ``eta_n`` the filtered noise (the slow integral path is left out); continuous
    form on ``sub`` points per noise hold, sampled form at the clock instants."""
    P, _, D = (float(g) for g in controller.gains(plant, jnp.asarray(x), jnp.asarray(m_load)))
    N = float(controller.N)
    rng = np.random.default_rng(seed)
    n = rng.normal(0.0, math.sqrt(NOISE_POWER / NOISE_TS), n_samples)
    if sampled:
        reps = max(1, int(round(NOISE_TS / T_c)))
        nk = np.repeat(n, reps)
        a = 1.0 - math.exp(-N * T_c)
        eta, xi = 0.0, np.empty(nk.size)
        for i, v in enumerate(nk):
            xi[i] = P * v + D * N * (v - eta)
            eta += a * (v - eta)
    else:
        tau = (np.arange(sub) + 0.5) / sub * NOISE_TS
        eta, xs = 0.0, []
        for v in n:
            dev = (v - eta) * np.exp(-N * tau)  # n - eta_n within the hold
            xs.append(P * v + D * N * dev)
            eta = v - (v - eta) * math.exp(-N * NOISE_TS)
        xi = np.concatenate(xs)
    inside = (u_op + xi > 0.0) & (u_op + xi < 1.0)
    return float(np.mean(inside))


def stability_table(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    controller: AbstractController,
    m_load: float,
    *,
    speeds: Sequence[float] = (0.025, 0.09),
    noise: bool = False,
    sampled: bool = False,
    T_c: float = 0.01,
) -> list[dict]:
    """Max real part of the closed-loop eigenvalues at :func:`operating_points` and
    ``speeds`` [m/s]; with ``noise`` the saturation's slope is the noise describing
    gain (:func:`noise_describing_gain`). Rows: point, x, v_ref, u, gain, max_real,
    the eigenvalue's frequency [Hz], stable."""
    rows = []
    for label, x in operating_points(plant):
        for v in speeds:
            eig, u, found = closed_loop_eigenvalues(plant, effects, controller, m_load, x, v)
            g = 1.0
            if noise and found:
                g = noise_describing_gain(controller, plant, x, m_load, u, sampled=sampled, T_c=T_c)
                eig, _, _ = closed_loop_eigenvalues(
                    plant, effects, controller, m_load, x, v, sat_gain=g
                )
            i = int(np.argmax(eig.real))
            rows.append(
                dict(
                    point=label,
                    x_m=x,
                    v_ref_mps=v,
                    u=u,
                    sat_gain=g,
                    max_real_per_s=float(eig.real[i]) if found else float("nan"),
                    freq_hz=abs(float(eig.imag[i])) / (2 * math.pi) if found else float("nan"),
                    stable=bool(found and eig.real[i] < 0),
                )
            )
    return rows


# ------------------------------------------------------------------ figures and reports
def plot_response(
    runs: Sequence[tuple[str, ClosedLoopSolution]], path: str | os.PathLike, title: str = ""
) -> str:
    """Height, speed against the reference, and duty of closed-loop runs (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(11, 7.5), sharex=True)
    ref = runs[0][1]
    ax[0].plot(ref.ts, ref.reference.height(), "k--", lw=0.8, label="reference")
    ax[1].plot(ref.ts, ref.v_ref, "k--", lw=0.8, label="reference")
    for i, (label, sol) in enumerate(runs):
        ax[0].plot(sol.ts, sol.height, color=f"C{i}", lw=0.9, label=label)
        ax[1].plot(sol.ts, sol.speed, color=f"C{i}", lw=0.7, label=label)
        ax[2].plot(sol.ts, sol.u, color=f"C{i}", lw=0.5, label=label)
    ax[0].set_ylabel("height [m]")
    ax[1].set_ylabel("fork speed [m/s]")
    ax[2].set_ylabel("duty u [-]")
    ax[2].set_xlabel("time [s]")
    for a in ax:
        a.grid(alpha=0.3)
    ax[1].legend(loc="upper right", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.fspath(path)


def plot_distributions(
    table: Mapping[str, Mapping[str, np.ndarray]], keys: Sequence[str], path: str | os.PathLike
) -> str:
    """Box plots of figures (``table[gain set][key]`` arrays over draws) (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 3.6))
    for a, k in zip(np.atleast_1d(ax), keys):
        data = [np.asarray(v[k])[np.isfinite(v[k])] for v in table.values()]
        a.boxplot(data, tick_labels=list(table), whis=(0, 100))
        a.set_title(k, fontsize=9)
        a.tick_params(axis="x", labelrotation=30, labelsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.fspath(path)


def _finite(fn, a) -> float:
    """``fn`` over the finite entries of ``a``; NaN if there are none (no warning)."""
    a = np.asarray(a, dtype=float).ravel()
    a = a[np.isfinite(a)]
    return float(fn(a)) if a.size else float("nan")


def _fig_arrays(fig: Figures) -> dict[str, np.ndarray]:
    b = fig.tracking_rms.shape[0]
    rows = [jax.tree.map(lambda a, i=i: a[i], fig).as_dict() for i in range(b)]
    return {k: np.asarray([r[k] for r in rows]) for k in rows[0]}


def robustness_report(
    controllers: Mapping[str, AbstractController],
    plant: Plant,
    effects: Sequence[AbstractEffect],
    draws: DrawSet,
    reference: Reference,
    out_dir: str | os.PathLike,
    *,
    noise_seed: int | None = 0,
    sampled: bool = False,
    T_c: float = 0.01,
    weights: CostWeights | None = None,
    report=None,
) -> tuple[object, dict]:
    """Evaluate each gain set over the draws (the figures as distributions, worst
    case, share of oscillation-free draws, failures), with and without the model's
    effects, with and without noise, plus the stability tables on the nominal model.
    Adds sections to ``report`` (a :class:`~jaxlift._report.Report`, made if None)
    and writes figures under ``out_dir/figures``. Returns ``(report, summary)``."""
    from ._report import Report

    out = os.fspath(out_dir)
    figdir = os.path.join(out, "figures")
    os.makedirs(figdir, exist_ok=True)
    rep = Report("Robustness of the lift controller") if report is None else report
    effects = _canonical(effects)
    sim = dict(sampled=sampled, T_c=T_c)
    rep.heading("Robustness over parameter draws")
    rep.text(
        f"{len(draws.draws)} held-out draws of the plant parameters; source: {draws.source}. "
        f"Reference: the thesis-like sequence at {float(reference.m_load):g} kg, "
        f"{'sampled controller, T_c = ' + format(T_c, 'g') + ' s' if sampled else 'continuous controller'}. "  # noqa: E501
        f"Oscillation-free: sustained oscillation RMS below {OSC_FREE_MPS * 1e3:g} mm/s. "
        f"A failed run (solver failure or fork out of range) costs {FAILED_COST:g} and is counted."
    )
    summary: dict = {"source": draws.source, "n_draws": len(draws.draws), "cases": {}}
    cases = [("with effects" if effects else "model", effects, None)]
    if effects:
        cases.append(("without effects", (), None))
    if noise_seed is not None:
        cases.append((f"{cases[0][0]}, with noise", effects, noise_seed))
    for case, effs, seed in cases:
        plants, effs_b = batch_models(plant, effs, draws.draws)
        table, rows = {}, []
        for name, ctrl in controllers.items():
            c, ok, fig = evaluate_draws(
                ctrl, plants, effs_b, reference, weights=weights, noise_seed=seed, **sim
            )
            arr = _fig_arrays(fig)
            arr["cost"] = np.where(ok, c, np.nan)
            table[name] = arr
            osc_free = ok & (arr["osc_sustained_mmps"] < OSC_FREE_MPS * 1e3)
            rows.append(
                dict(
                    gains=name,
                    cost_median=float(np.median(c)),
                    cost_worst=float(np.max(c)),
                    tracking_p50_mmps=_finite(np.median, arr["tracking_rms_mmps"]),
                    tracking_max_mmps=_finite(np.max, arr["tracking_rms_mmps"]),
                    osc_sust_p50_mmps=_finite(np.median, arr["osc_sustained_mmps"]),
                    osc_sust_max_mmps=_finite(np.max, arr["osc_sustained_mmps"]),
                    offset_max_mmps=_finite(
                        np.max, np.abs([arr["shift1_offset_mmps"], arr["shift2_offset_mmps"]])
                    ),
                    effort_p50=_finite(np.median, arr["effort_per_s"]),
                    shut_p50_pct=_finite(np.median, arr["shut_share_pct"]),
                    osc_free_pct=100.0 * float(np.mean(osc_free)),
                    failed=int(np.sum(~ok)),
                )
            )
        summary["cases"][case] = rows
        rep.heading(f"Figures over the draws: {case}", 3)
        rep.table(rows, floatfmt=".3g", caption=f"{case}: distribution over the draws")
        slug = case.replace(" ", "_").replace(",", "")
        png = plot_distributions(
            table,
            ["cost", "tracking_rms_mmps", "osc_sustained_mmps", "effort_per_s"],
            os.path.join(figdir, f"draws_{slug}.png"),
        )
        rep.figure(png, f"{case}: figures over the draws (box: quartiles, whiskers: range)")
    rep.heading("Closed-loop stability (nominal model)")
    rep.text(
        "Max real part of the eigenvalues of the closed loop linearised with `jax.jacfwd` "
        "at steady motion (height frozen) along the lift, slow and fast reference speed. "
        "With noise: the saturation's slope replaced by its describing gain under the "
        "sensor noise (the probability that the noisy duty stays inside (0, 1)); "
        "a gain below 1 weakens the loop."
    )
    m = float(reference.m_load)
    for name, ctrl in controllers.items():
        rows = []
        for noisy in (False, True):
            for r in stability_table(
                plant, effects, ctrl, m, noise=noisy, sampled=sampled, T_c=T_c
            ):
                rows.append(dict(noise=noisy, **r))
        summary.setdefault("stability", {})[name] = rows
        n_unstable = sum(not r["stable"] for r in rows)
        rep.heading(f"Stability: {name} ({n_unstable} of {len(rows)} points unstable)", 3)
        rep.table(
            rows,
            columns=["noise", "point", "x_m", "v_ref_mps", "u", "sat_gain", "max_real_per_s",
                     "freq_hz", "stable"],
            floatfmt=".3g",
        )  # fmt: skip
    return rep, summary
