"""Simulation: one entry point, ``simulate(plant, effects, inputs, ...)``.

Like ``diffrax.diffeqsolve(terms, solver, ...)``, the parts are separate objects:
the :class:`~jaxlift.Plant` (baseline parameters and laws), a sequence of effects
(:mod:`jaxlift.model.effects`), and the :class:`Inputs` of one test run (the log's time
stamps, zero-order-held ``pwm`` and ``load_kg``, the initial height). The result is
a :class:`Solution` with the trajectory at the log's time stamps and a result code.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .effects import AbstractEffect
from .inputs import Inputs
from .nudging import Nudging
from .plant import Plant
from .solution import RANGE_TOLERANCE_M, Solution
from .stepping import JumpStepSizeController, StabilityLimitedController
from .vector_field import canonical_effects, initial_state, lift_vector_field

if TYPE_CHECKING:
    pass

#: Largest solver step (s): keeps trial steps from overflowing the stiff friction law.
DTMAX = 0.05


def x64_check() -> None:
    """Raise if JAX runs in float32: jaxlift's gradients and likelihoods need float64."""
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "jaxlift needs float64: call jax.config.update('jax_enable_x64', True) at the "
            "start of your program (before creating any arrays). The library does not flip "
            "this global flag for you."
        )


def error_norm(scaled_error):
    """Step-size error norm: the larger of the RMS over the three baseline states and the
    largest scaled error of the effects' own states. An effect whose states are frozen
    (at its nesting value) then leaves the baseline's step sequence unchanged, so the
    trajectory is exactly the baseline's (diffrax's default RMS over all states would
    dilute the error by the extra zero entries).

    A trial step whose error is NaN counts as infinitely wrong: the controller then
    shrinks the step as for any large error. (A NaN error would make the next step
    NaN and the solve spin to ``max_steps``: measured on a leaking fork hitting the
    bottom stop, where a 10 ms trial step sent the speed past 1 m/s and the
    fifth-power friction term to infinity.)"""
    base = jnp.sqrt(jnp.mean(scaled_error[:3] ** 2))
    if scaled_error.shape[0] > 3:
        base = jnp.maximum(base, jnp.max(jnp.abs(scaled_error[3:])))
    return jnp.where(jnp.isnan(base), jnp.inf, base)


def nudged_vector_field(t, y, args):
    """The vector field plus a :class:`~jaxlift.model.nudging.Nudging` term."""
    plant, effects, inputs, nudging = args
    return lift_vector_field(t, y, (plant, effects, inputs)) + nudging.correction(t, y)


@eqx.filter_jit
def _solve(
    plant, effects, inputs, solver, rtol, atol_base, max_steps, adjoint, stability_limit, nudging
):
    y0 = initial_state(plant, effects, inputs)
    if nudging is None:
        field, args = lift_vector_field, (plant, effects, inputs)
    else:
        field, args = nudged_vector_field, (plant, effects, inputs, nudging)
    scales = [jnp.asarray(e.state_scales, dtype=jnp.float64) for e in effects]
    atol = jnp.concatenate([atol_base, *[s * 1.0 for s in scales]]) if effects else atol_base
    delay = sum((e.delay() for e in effects), jnp.zeros(()))
    # steps end just before and restart just after each input jump, as with
    # diffrax.ClipStepSizeController(..., jump_ts=...), at a cost per step independent
    # of the number of jumps (see _stepping.py)

    # steps also kept inside Tsit5's stability region: at rest the solution has no
    # error to control, but its forward-mode sensitivities do (see _stepping.py)
    inner = diffrax.PIDController(rtol=rtol, atol=atol, dtmax=DTMAX, norm=error_norm)
    if stability_limit:
        inner = StabilityLimitedController(inner, field, atol)
    controller = JumpStepSizeController(inner, inputs.jump_ts + delay)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=inputs.ts[0],
        t1=inputs.ts[-1],
        dt0=None,
        y0=y0,
        args=args,
        saveat=diffrax.SaveAt(ts=inputs.ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    x = sol.ys[:, 0]
    in_range = jnp.all(
        jnp.isfinite(x) & (x >= -RANGE_TOLERANCE_M) & (x <= plant.x_max + RANGE_TOLERANCE_M)
    )
    names = ("height_m", "speed_mps", "pressure_pa") + tuple(
        f"{e.name}.{s}" for e in effects for s in e.state_names
    )
    return Solution(
        ts=inputs.ts,
        ys=sol.ys,
        result=sol.result,
        in_range=in_range,
        num_steps=sol.stats["num_steps"],
        state_names=names,
        x_max=plant.x_max,
    )


#: Default absolute tolerances of the baseline states: height [m], speed [m/s], p [Pa].
DEFAULT_ATOL = (1e-7, 1e-7, 1.0)


def simulate(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    inputs: Inputs,
    *,
    solver: diffrax.AbstractSolver | None = None,
    rtol: float = 1e-6,
    atol: tuple[float, float, float] = DEFAULT_ATOL,
    max_steps: int = 200_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    stability_limit: bool = True,
    nudging: Nudging | None = None,
) -> Solution:
    """Simulate one test run of the lift.

    Args:
        plant: baseline parameters and laws.
        effects: candidate effects to switch on (any order; applied in registry order).
        inputs: the run's input (see :meth:`Inputs.from_log`).
        solver: diffrax solver (default ``Tsit5``; the plant is mildly stiff).
        rtol, atol: step-size control; ``atol`` for (height m, speed m/s, pressure Pa);
            effects bring scales for their own states.
        max_steps: solver step limit; exceeding it gives ``result != successful``.
        adjoint: diffrax adjoint; ``diffrax.ForwardMode()`` for ``jax.jacfwd``
            (Levenberg--Marquardt), default ``RecursiveCheckpointAdjoint`` (reverse mode).
        stability_limit: keep every step inside Tsit5's stability region (one extra
            Jacobian-vector product per step, ~15 % of the cost). Needed wherever
            derivatives are taken: where the lift rests, the error control lets the step
            grow past that region, which the solution tolerates but its sensitivities do
            not (they explode; see ``_stepping.py``). ``False`` is for value-only work
            (posterior sampling, predictive bands, plots); the solution then still meets
            ``rtol``/``atol``.
        nudging: pull the simulation towards a log's measurements (an observer term, not
            physics: a device for fitting on rough least-squares surfaces, see
            :mod:`jaxlift.model.nudging`); None (default) is the model itself.

    Returns:
        A :class:`Solution`; it never raises on solver failure -- check ``sol.ok``
        (jit-safe) or call ``sol.check()``.

    Jitted (through ``eqx.filter_jit``); ``eqx.filter_vmap`` over a batch of plants
    (or effects) works, and so do ``jax.grad`` and (with ``ForwardMode``) ``jax.jacfwd``.
    """
    x64_check()
    solver = diffrax.Tsit5() if solver is None else solver
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    effects = canonical_effects(effects)
    atol_base = jnp.asarray(atol, dtype=jnp.float64)
    return _solve(
        plant, effects, inputs, solver, rtol, atol_base, max_steps, adjoint, stability_limit,
        nudging,
    )  # fmt: skip
