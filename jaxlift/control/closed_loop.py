"""Closed-loop simulation: controller + plant (+ effects) following a speed reference.

One entry point, :func:`simulate_closed_loop`. Two forms of the controller:

- **continuous** (default, the thesis's): the controller states ``q_I, eta`` are
  appended to the plant's state and the whole loop is one ``diffeqsolve``. The
  reference is piecewise linear; its knots (where the slope jumps, and where the
  stop logic ``v_ref == 0`` switches) are the solver's jump times. With sensor noise
  the noise is a zero-order-held input (one value per ``T_s = 0.01 s``) and every
  hold instant is a jump time too (≈ 100 per second of run: measured cost in the
  benchmark notes).
- **sampled** (``sampled=True``, clock ``T_c``, zero-order hold on ``u``,
  docs/control.md): a ``lax.scan`` over controller periods; each period updates the
  controller from the state at the sample instant (filter discretised exactly,
  integral by forward Euler) and integrates the plant over the period with ``u`` held
  (one short adaptive ``diffeqsolve`` per period). Reverse-mode and forward-mode
  differentiable like the continuous form. ``T_c`` must divide the output period
  (10 ms).

Input delay (``input_delay`` effect) in closed loop: the plant must see
``u(t - tau_d)``, which is not known in advance. In the sampled form the delay is
exact: the held duties are kept in a buffer (``MAX_DELAY_S``), and within a period
the plant sees the duty of period ``k - d - 1`` until ``t_k + frac`` and that of
period ``k - d`` afterwards (``tau_d = d T_c + frac``; the switch is a jump time).
The continuous form refuses ``input_delay`` with a clear error (a Padé stand-in would
let ``u`` leave [0, 1] and open the check valve on an undershoot).

Extra integrated outputs (not used for step-size control): ``∫u dt`` (for 10 ms
averages of ``u``: actuator effort) and the time with the valve shut while moving.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..model.constants import (
    MAST_HEIGHT_M,
    OUTPUT_DT,
    SAMPLE_PERIOD_S,
    SPEED_NOISE_POWER,
    STAGE_BOUNDARIES_M,
)
from ..model.effects import AbstractEffect
from ..model.inputs import Inputs
from ..model.plant import Plant
from ..model.simulate import DEFAULT_ATOL, DTMAX, error_norm, x64_check
from ..model.solution import RANGE_TOLERANCE_M, AbstractSolution
from ..model.stepping import JumpStepSizeController, StabilityLimitedController
from ..model.vector_field import canonical_effects, initial_state, plant_signals_and_derivative
from .controller import DEFAULT_TC, AbstractController
from .reference import Reference, is_moving

#: Sensor-noise power [(m/s)^2 s] and hold time [s] (docs/control.md, thesis 2.4.4).
NOISE_POWER = SPEED_NOISE_POWER
NOISE_TS = SAMPLE_PERIOD_S
#: Output sample period [s] of closed-loop solutions.
#: Longest input delay the sampled form's duty buffer holds [s].
MAX_DELAY_S = 0.5
#: ``N T_c`` above which a sampled filter is meaningless (docs/control.md: "say so").
NTC_WARN = 5.0


class SampledFilterWarning(UserWarning):
    """A derivative filter faster than the controller clock (``N T_c >> 1``)."""


class ClosedLoopSolution(AbstractSolution):
    """A closed-loop run, sampled every 10 ms.

    Attributes:
        ts: output times [s].
        ys: plant states at ``ts`` (``x`` m, ``v`` m/s, ``p`` Pa, effect states).
        q_I, eta: controller states at ``ts`` (integral [-], filter [m/s]).
        u: duty at ``ts`` (the held value in the sampled form) [-].
        u_int: ``∫_0^t u dt`` at ``ts`` [s] (10 ms averages of ``u`` are its differences).
        shut_int: time with the valve shut (``u_raw <= 0``) while ``v_ref != 0`` [s].
        v_ref: reference speed at ``ts`` [m/s].
        v_meas: measured speed at ``ts`` (with noise) [m/s].
        reference: the :class:`Reference`.
        result: diffrax result code (worst over the periods of a sampled run).
        in_range: whether the fork stayed within ``[0, x_max]`` (± 1 cm) and finite.
        num_steps: solver steps (summed over periods).
        T_c: controller clock [s], or None for the continuous form.
    """

    ts: Float[Array, " n"]
    ys: Float[Array, "n S"]
    q_I: Float[Array, " n"]
    eta: Float[Array, " n"]
    u: Float[Array, " n"]
    u_int: Float[Array, " n"]
    shut_int: Float[Array, " n"]
    v_ref: Float[Array, " n"]
    v_meas: Float[Array, " n"]
    reference: Reference
    result: diffrax.RESULTS
    in_range: Bool[Array, ""]
    num_steps: Int[Array, ""]
    state_names: tuple[str, ...] = eqx.field(static=True)
    T_c: float | None = eqx.field(static=True, default=None, kw_only=True)
    x_s: tuple[float, float] = eqx.field(static=True, default=STAGE_BOUNDARIES_M, kw_only=True)
    x_max: float = eqx.field(static=True, default=MAST_HEIGHT_M, kw_only=True)
    out_of_range_hint: ClassVar[str] = "check the gains, the reference or the parameters"
    kind: ClassVar[str] = "closed-loop simulation"


# ------------------------------------------------------------------ helpers
def _noise(seed, n: int) -> Float[Array, " n"]:
    """Band-limited white noise held for ``NOISE_TS``: ``n`` values [m/s]."""
    sigma = math.sqrt(NOISE_POWER / NOISE_TS)
    return sigma * jax.random.normal(jax.random.key(seed), (n,), dtype=jnp.float64)


def _noise_at(noise, t, *, at_sample: bool = False):
    """The held noise at ``t``: sample ``floor(t / T_s)``. In the continuous form the
    index comes from a binary search on the hold instants -- the same numbers as the
    solver's jump times, so that a step ending just before a jump sees the old value;
    at controller sample instants (``at_sample``) a floor with a guard."""
    if noise is None:
        return jnp.zeros(())
    n = noise.shape[0]
    if at_sample:
        i = jnp.floor(t / NOISE_TS + 1e-6).astype(jnp.int32)
    else:
        i = jnp.searchsorted(_noise_ts(n), t, side="right") - 1
    return noise[jnp.clip(i, 0, n - 1)]


def _noise_ts(n: int) -> Float[Array, " n"]:
    """Hold instants of the noise [s] (the continuous form's extra jump times)."""
    return jnp.arange(n, dtype=jnp.float64) * NOISE_TS


def _start(plant, effects, ref):
    """Plant state at rest at ``ref.x0`` (pressure at equilibrium, effects' states)."""
    inputs = Inputs(
        ts=jnp.asarray([0.0, 1.0]),
        pwm=jnp.zeros(2),
        load_kg=jnp.stack([ref.m_load, ref.m_load]),
        jump_ts=jnp.asarray([1.0]),
        x0=ref.x0,
    )
    return initial_state(plant, effects, inputs)


def _atol(effects, atol_base, extra):
    scales = [jnp.asarray(e.state_scales, dtype=jnp.float64) for e in effects]
    return jnp.concatenate([atol_base, *scales, jnp.asarray(extra, dtype=jnp.float64)])


def _in_range(x, x_max):
    return jnp.all(jnp.isfinite(x) & (x >= -RANGE_TOLERANCE_M) & (x <= x_max + RANGE_TOLERANCE_M))


def _names(effects):
    return ("height_m", "speed_mps", "pressure_pa") + tuple(
        f"{e.name}.{s}" for e in effects for s in e.state_names
    )


# ------------------------------------------------------------------ continuous form
def _cl_vector_field(t, y, args):
    plant, effects, ctrl, ref, noise, n_plant = args
    yp = y[:n_plant]
    q_I, eta = y[n_plant], y[n_plant + 1]
    v_ref = ref.v(t)
    moving = is_moving(v_ref)
    e = v_ref - (yp[1] + _noise_at(noise, t))
    out = ctrl.output(plant, yp[0], ref.m_load, e, q_I, eta, moving)
    _, dyp = plant_signals_and_derivative(t, yp, plant, effects, out.u, ref.m_load)
    shut = (moving & (out.u_raw <= 0.0)).astype(yp.dtype)
    return jnp.concatenate([dyp, jnp.stack([out.dq_I, out.deta, out.u, shut])])


@eqx.filter_jit
def _solve_continuous(plant, effects, ctrl, ref, seed, noise_on, rtol, atol_base, max_steps, adj):
    yp0 = _start(plant, effects, ref)
    n_plant = yp0.shape[0]
    n_core = n_plant + 2
    y0 = jnp.concatenate([yp0, jnp.zeros(4)])
    atol = _atol(effects, atol_base, [1e-7, 1e-7, 1.0, 1.0])
    noise = _noise(seed, ref.n_out) if noise_on else None
    jumps = ref.knots_t
    if noise_on:
        jumps = jnp.concatenate([jumps, _noise_ts(ref.n_out)[1:]])
    norm = lambda err: error_norm(err[:n_core])  # the integrated outputs do not steer
    # inside the solver's stability region too, as in jl.simulate (see _stepping.py):
    # the forks held at rest have no error to control, their sensitivities do
    controller = JumpStepSizeController(
        StabilityLimitedController(
            diffrax.PIDController(rtol=rtol, atol=atol, dtmax=DTMAX, norm=norm),
            _cl_vector_field,
            atol,
        ),
        jumps,
    )
    ts = ref.ts
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_cl_vector_field),
        diffrax.Tsit5(),
        t0=ts[0],
        t1=ts[-1],
        dt0=None,
        y0=y0,
        args=(plant, effects, ctrl, ref, noise, n_plant),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=adj,
        throw=False,
    )
    ys = sol.ys
    v_ref = ref.v(ts)
    n_at = jax.vmap(lambda t: _noise_at(noise, t))(ts) if noise_on else jnp.zeros_like(ts)
    v_meas = ys[:, 1] + n_at

    def law(y, vr, vm):
        return ctrl.output(
            plant, y[0], ref.m_load, vr - vm, y[n_plant], y[n_plant + 1], is_moving(vr)
        ).u

    u = jax.vmap(law)(ys, v_ref, v_meas)
    return ClosedLoopSolution(
        ts=ts,
        ys=ys[:, :n_plant],
        q_I=ys[:, n_plant],
        eta=ys[:, n_plant + 1],
        u=u,
        u_int=ys[:, n_plant + 2],
        shut_int=ys[:, n_plant + 3],
        v_ref=v_ref,
        v_meas=v_meas,
        reference=ref,
        result=sol.result,
        in_range=_in_range(ys[:, 0], plant.x_max),
        num_steps=sol.stats["num_steps"],
        state_names=_names(effects),
        T_c=None,
        x_s=(plant.x_s1, plant.x_s2),
        x_max=plant.x_max,
    )


# ------------------------------------------------------------------ sampled form
def _plant_field(t, y, args):
    plant, effects, u_a, u_b, t_switch, m_load = args
    u = jnp.where(t < t_switch, u_a, u_b)
    return plant_signals_and_derivative(t, y, plant, effects, u, m_load)[1]


@eqx.filter_jit
def _solve_sampled(
    plant, effects, ctrl, ref, seed, noise_on, T_c, rtol, atol_base, max_steps, adj, has_delay
):
    yp0 = _start(plant, effects, ref)
    atol = _atol(effects, atol_base, [])
    noise = _noise(seed, ref.n_out) if noise_on else None
    stride = int(round(OUTPUT_DT / T_c))
    n_per = (ref.n_out - 1) * stride
    n_buf = int(math.ceil(MAX_DELAY_S / T_c)) + 2
    tau = sum((e.delay() for e in effects), jnp.zeros(()))
    d = jnp.floor(tau / T_c + 1e-9).astype(jnp.int32)
    frac = tau - d * T_c
    m = ref.m_load
    per_max = max(16, max_steps // max(n_per, 1))

    def period(carry, k):
        y, q_I, eta, buf = carry
        t = k * T_c
        v_ref = ref.v(t)
        moving = is_moving(v_ref)
        v_meas = y[1] + _noise_at(noise, t, at_sample=True)
        u, u_raw, q1, eta1 = ctrl.sampled_update(
            plant, y[0], m, v_ref - v_meas, q_I, eta, moving, T_c
        )
        buf = jnp.concatenate([u[None], buf[:-1]])
        if has_delay:
            u_a = buf[jnp.clip(d + 1, 0, n_buf - 1)]
            u_b = buf[jnp.clip(d, 0, n_buf - 1)]
            t_sw = t + frac
            jumps = jnp.stack([t_sw])
        else:
            u_a = u_b = u
            t_sw = t
            jumps = jnp.stack([t + T_c])
        # inside the solver's stability region, as in the continuous form: without it
        # a fork at rest (the period's solution constant, nothing to control) took
        # whole-period steps across the Coulomb friction's stiff slope at v = 0, and
        # the forward-mode sensitivities grew to 1e19 (measured): the tuning's
        # Jacobian was garbage and LM stalled at its start (issue: `--sampled` "cost
        # 6.297 -> 6.297")
        controller = JumpStepSizeController(
            StabilityLimitedController(
                diffrax.PIDController(rtol=rtol, atol=atol, dtmax=DTMAX, norm=error_norm),
                _plant_field,
                atol,
            ),
            jumps,
            assume_sorted=True,
        )
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(_plant_field),
            diffrax.Tsit5(),
            t0=t,
            t1=t + T_c,
            dt0=T_c,
            y0=y,
            args=(plant, effects, u_a, u_b, t_sw, m),
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=controller,
            max_steps=per_max,
            adjoint=adj,
            throw=False,
        )
        y1 = sol.ys[-1]
        shut = (moving & (u_raw <= 0.0)).astype(y.dtype)
        bad = (sol.result != diffrax.RESULTS.successful).astype(jnp.int32)
        return (y1, q1, eta1, buf), (y1, q1, eta1, u, shut, v_meas, bad, sol.stats["num_steps"])

    carry0 = (yp0, jnp.zeros(()), jnp.zeros(()), jnp.zeros(n_buf))
    _, (ys, qs, etas, us, shuts, vms, bads, steps) = jax.lax.scan(period, carry0, jnp.arange(n_per))
    ys = jnp.concatenate([yp0[None], ys])[::stride]
    qs = jnp.concatenate([jnp.zeros(1), qs])[::stride]
    etas = jnp.concatenate([jnp.zeros(1), etas])[::stride]
    u_int = jnp.concatenate([jnp.zeros(1), jnp.cumsum(us) * T_c])[::stride]
    shut_int = jnp.concatenate([jnp.zeros(1), jnp.cumsum(shuts) * T_c])[::stride]
    u_out = jnp.concatenate([us, us[-1:]])[::stride]
    vm_out = jnp.concatenate([vms, vms[-1:]])[::stride]
    failed = jnp.any(bads > 0)
    result = diffrax.RESULTS.where(
        failed, diffrax.RESULTS.max_steps_reached, diffrax.RESULTS.successful
    )
    ts = ref.ts
    return ClosedLoopSolution(
        ts=ts,
        ys=ys,
        q_I=qs,
        eta=etas,
        u=u_out,
        u_int=u_int,
        shut_int=shut_int,
        v_ref=ref.v(ts),
        v_meas=vm_out,
        reference=ref,
        result=result,
        in_range=_in_range(ys[:, 0], plant.x_max),
        num_steps=jnp.sum(steps),
        state_names=_names(effects),
        T_c=T_c,
        x_s=(plant.x_s1, plant.x_s2),
        x_max=plant.x_max,
    )


# ------------------------------------------------------------------ entry point
def _concrete_max(x) -> float | None:
    """The largest value of a concrete array, or None for a tracer."""
    if isinstance(x, jax.core.Tracer):
        return None
    return float(np.max(np.asarray(x)))


def simulate_closed_loop(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    controller: AbstractController,
    reference: Reference,
    *,
    sampled: bool = False,
    T_c: float = DEFAULT_TC,
    noise_seed: int | ArrayLike | None = None,
    rtol: float = 1e-6,
    atol: tuple[float, float, float] = DEFAULT_ATOL,
    max_steps: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
) -> ClosedLoopSolution:
    """Simulate the controller driving the plant along ``reference``.

    Args:
        plant, effects: the plant (any effects; registry order is restored).
        controller: a :class:`~jaxlift.PID` or :class:`~jaxlift.ScheduledPID`.
        reference: speed reference, load and start height (:class:`Reference`).
        sampled: run the controller on a clock ``T_c`` [s] with zero-order hold on
            ``u`` (default: continuous time, as in the thesis).
        T_c: controller period [s] for ``sampled=True``; must divide 10 ms.
        noise_seed: seed of the speed-sensor noise (docs/control.md: power 1e-7
            (m/s)^2 s, held 10 ms); ``None``: no noise. Same seed, same noise.
        rtol, atol: step-size control (atol for height m, speed m/s, pressure Pa).
        max_steps: solver step limit (over the whole run); default ``200_000 + N t1``
            (a fast derivative filter, e.g. ``N = 1e4`` 1/s, makes the continuous loop
            stiff: Tsit5 then needs steps of ~``3/N``).
        adjoint: diffrax adjoint (default reverse mode ``RecursiveCheckpointAdjoint``;
            ``diffrax.ForwardMode()`` for ``jax.jacfwd``).

    Returns:
        A :class:`ClosedLoopSolution` (never raises on solver failure: check ``.ok``
        or call ``.check()``).

    Jitted; ``eqx.filter_vmap`` over plants, controllers, references (loads) or noise
    seeds works, and so does ``jax.grad`` w.r.t. the controller's gains.

    Raises:
        ValueError: ``input_delay`` with the continuous form; ``T_c`` not dividing 10 ms.
    Warns:
        SampledFilterWarning: sampled form with ``N T_c > 5`` (filter faster than the
            clock: the discretised filter is then a pass-through of the last sample).
    """
    x64_check()
    effects = canonical_effects(effects)
    has_delay = any(e.name == "input_delay" for e in effects)
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    atol_base = jnp.asarray(atol, dtype=jnp.float64)
    noise_on = noise_seed is not None
    if max_steps is None:
        n_filter = _concrete_max(controller.N)
        n_filter = 1000.0 if n_filter is None else n_filter
        max_steps = 200_000 + int(n_filter * reference.t1)
    seed = jnp.asarray(0 if noise_seed is None else noise_seed, dtype=jnp.uint32)
    if not sampled:
        if has_delay:
            raise ValueError(
                "input_delay in closed loop needs the sampled controller (sampled=True, "
                "--sampled): in continuous time u(t - tau_d) is not known in advance"
            )
        return _solve_continuous(
            plant,
            effects,
            controller,
            reference,
            seed,
            noise_on,
            rtol,
            atol_base,
            max_steps,
            adjoint,
        )
    T_c = float(T_c)
    ratio = OUTPUT_DT / T_c
    if T_c <= 0 or abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ValueError(f"T_c = {T_c} s: the controller period must divide 0.01 s")
    n_max = _concrete_max(controller.N)  # None if traced (e.g. under grad): not checked
    n_tc = None if n_max is None else n_max * T_c
    if n_tc is not None and n_tc > NTC_WARN:
        warnings.warn(
            f"N T_c = {n_tc:.3g} >> 1: the derivative filter (N = {n_max:g} "
            f"1/s) is faster than the controller clock (T_c = {T_c:g} s); in the sampled "
            "form it then passes the last sample through (D N (e - eta) -> D N (e_k - e_k-1)"
            " ...) and N no longer filters",
            SampledFilterWarning,
            stacklevel=2,
        )
    return _solve_sampled(
        plant,
        effects,
        controller,
        reference,
        seed,
        noise_on,
        T_c,
        rtol,
        atol_base,
        max_steps,
        adjoint,
        has_delay,
    )
