"""Simulation: one entry point, ``simulate(plant, effects, inputs, ...)``.

Like ``diffrax.diffeqsolve(terms, solver, ...)``, the parts are separate objects:
the :class:`~jaxlift.Plant` (baseline parameters and laws), a sequence of effects
(:mod:`jaxlift._effects`), and the :class:`Inputs` of one test run (the log's time
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
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._effects import EFFECTS, AbstractEffect, Signals, rigid_acceleration
from ._plant import Plant

if TYPE_CHECKING:
    from ._log import Log

__all__ = ["Inputs", "Solution", "SimulationError", "simulate", "make_effects", "x64_check"]

#: Initial hold used to estimate the starting height (s).
INITIAL_HOLD_MAX_S = 2.0
#: How far (m) the fork may leave [0, x_max] before the run is declared out of range.
RANGE_TOLERANCE_M = 0.01
#: Largest solver step (s): keeps trial steps from overflowing the stiff friction law.
DTMAX = 0.05


class SimulationError(RuntimeError):
    """A simulation that did not produce a valid trajectory (solver failure, or the
    fork left the mast's range)."""


def x64_check() -> None:
    """Raise if JAX runs in float32: jaxlift's gradients and likelihoods need float64."""
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "jaxlift needs float64: call jax.config.update('jax_enable_x64', True) at the "
            "start of your program (before creating any arrays). The library does not flip "
            "this global flag for you."
        )


class Inputs(eqx.Module):
    """The input of one test run, as the plant sees it.

    Attributes:
        ts: sample times [s], shape (N,).
        pwm: duty cycle in [0, 1], held from each sample to the next (zero-order hold).
        load_kg: load mass [kg], held likewise.
        jump_ts: times [s] where ``pwm`` or ``load_kg`` change (the solver steps onto
            them; only true changes, see STACK-NOTES).
        x0: initial height [m].
    """

    ts: Float[Array, " N"]
    pwm: Float[Array, " N"]
    load_kg: Float[Array, " N"]
    jump_ts: Float[Array, " J"]
    x0: Float[Array, ""]

    @classmethod
    def from_arrays(
        cls,
        ts: ArrayLike,
        pwm: ArrayLike,
        load_kg: ArrayLike,
        x0: float | ArrayLike,
    ) -> Inputs:
        ts, pwm, load = (np.asarray(a, dtype=np.float64) for a in (ts, pwm, load_kg))
        if not (ts.shape == pwm.shape == load.shape and ts.ndim == 1 and ts.size >= 2):
            raise ValueError("ts, pwm and load_kg must be 1-D arrays of the same length >= 2")
        change = (np.diff(pwm) != 0) | (np.diff(load) != 0)
        jump_ts = ts[1:][change]
        if jump_ts.size == 0:  # diffrax wants at least one; a jump at the end is harmless
            jump_ts = ts[-1:]
        return cls(
            ts=jnp.asarray(ts),
            pwm=jnp.asarray(pwm),
            load_kg=jnp.asarray(load),
            jump_ts=jnp.asarray(jump_ts),
            x0=jnp.asarray(x0, dtype=jnp.float64),
        )

    @classmethod
    def from_log(cls, log: Log) -> Inputs:
        """Inputs of a log; the initial height is the mean height over the initial hold
        (the leading samples with ``pwm = 0``, at most ``INITIAL_HOLD_MAX_S``), or the
        first sample if the log does not start with a hold (MODEL.md)."""
        return cls.from_arrays(log.time_s, log.pwm, log.load_kg, initial_height(log))

    def at(self, t: Float[ArrayLike, ""]) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """Zero-order-held ``(pwm, load_kg)`` at time ``t`` (first sample before start)."""
        i = jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0, self.ts.shape[0] - 1)
        return self.pwm[i], self.load_kg[i]


def initial_height(log: Log) -> float:
    """Mean height over the initial hold (``pwm == 0`` from the start, at most 2 s)."""
    moving = np.nonzero(log.pwm != 0)[0]
    n_hold = moving[0] if moving.size else log.n
    n_max = int(round(INITIAL_HOLD_MAX_S / log.sample_period)) + 1
    n = max(1, min(n_hold, n_max))
    return float(np.mean(log.height_m[:n]))


class Solution(eqx.Module):
    """A simulated test run.

    Attributes:
        ts: output times [s] (the log's).
        ys: all states at ``ts``, shape (N, 3 + extra): ``x`` [m], ``v`` [m/s],
            ``p`` [Pa], then the effects' own states in registry order.
        state_names: names of the columns of ``ys``.
        result: diffrax result code (``diffrax.RESULTS``).
        in_range: whether the fork stayed within ``[0, x_max]`` (± 1 cm).
        num_steps: accepted + rejected solver steps.
    """

    ts: Float[Array, " N"]
    ys: Float[Array, "N S"]
    result: diffrax.RESULTS
    in_range: Bool[Array, ""]
    num_steps: Int[Array, ""]
    state_names: tuple[str, ...] = eqx.field(static=True)
    x_max: float = eqx.field(static=True, default=4.5)

    @property
    def height(self) -> Float[Array, " N"]:
        """Fork (carriage) height [m]."""
        return self.ys[..., 0]

    @property
    def speed(self) -> Float[Array, " N"]:
        """Fork speed [m/s]."""
        return self.ys[..., 1]

    @property
    def pressure(self) -> Float[Array, " N"]:
        """Line pressure (gauge) [Pa]."""
        return self.ys[..., 2]

    @property
    def ok(self) -> Bool[Array, ""]:
        """True when the solver succeeded and the fork stayed in range (jit-safe)."""
        return (self.result == diffrax.RESULTS.successful) & self.in_range

    def check(self, what: str = "simulation") -> Solution:
        """Return ``self`` if :attr:`ok`, else raise :class:`SimulationError` saying why.
        Not for use under ``jit``."""
        if not bool(self.result == diffrax.RESULTS.successful):
            msg = diffrax.RESULTS[self.result] if np.ndim(self.result._value) == 0 else ""
            raise SimulationError(f"{what}: the ODE solver failed: {msg}")
        if not bool(self.in_range):
            h = np.asarray(self.height)
            x_max = self.x_max + RANGE_TOLERANCE_M
            bad = np.nonzero(~np.isfinite(h) | (h < -RANGE_TOLERANCE_M) | (h > x_max))[0]
            t = float(self.ts[bad[0]]) if bad.size else float("nan")
            raise SimulationError(
                f"{what}: the fork left the mast's range [0, x_max] at t = {t:.2f} s "
                f"(height {h[bad[0]] if bad.size else float('nan'):.3f} m); the end stops are "
                "not modelled -- check the parameters or the input"
            )
        return self


def make_effects(
    names: Sequence[str] | str | None, values: dict[str, float] | None = None
) -> tuple[AbstractEffect, ...]:
    """Effects by name (comma-separated string or sequence), in registry order, with
    their parameters taken from ``values`` where given (else their defaults)."""
    from ._params import replace_params

    if names is None:
        names = []
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known effects: {list(EFFECTS)}")
    values = dict(values or {})
    chosen = [EFFECTS[n] for n in names]
    stray = sorted(k for k in values if not any(k in c.param_infos() for c in chosen))
    if stray:
        raise ValueError(
            f"parameter(s) {stray} belong to none of the effects {list(names)}; their "
            f"parameters are {sorted(k for c in chosen for k in c.param_infos())}"
        )
    out = []
    for name, cls in EFFECTS.items():
        if name in names:
            eff = cls()
            own = {k: v for k, v in values.items() if k in cls.param_infos()}
            out.append(replace_params(eff, own))
    return tuple(out)


def _canonical(effects: Sequence[AbstractEffect]) -> tuple[AbstractEffect, ...]:
    order = {name: i for i, name in enumerate(EFFECTS)}
    effects = tuple(effects)
    names = [e.name for e in effects]
    if len(set(names)) != len(names):
        raise ValueError(f"an effect appears twice in {names}")
    for e in effects:
        if not isinstance(e, AbstractEffect):
            raise TypeError(f"{e!r} is not an effect (subclass of AbstractEffect)")
    if sum(bool(e.overrides_acceleration) for e in effects) > 1:
        raise ValueError("at most one effect may replace the fork-and-load law")
    return tuple(sorted(effects, key=lambda e: order.get(e.name, len(order))))


def _split(y, effects):
    base = y[:3]
    zs, i = [], 3
    for e in effects:
        zs.append(y[i : i + e.n_states])
        i += e.n_states
    return base, zs


def signals_and_derivative(
    t, y, plant: Plant, effects: tuple[AbstractEffect, ...], inputs: Inputs
) -> tuple[Signals, Float[Array, " S"]]:
    """Evaluate the chain of MODEL.md at ``(t, y)``: the signals and ``dy/dt``."""
    delay = sum((e.delay() for e in effects), jnp.zeros(()))
    u, m_load = inputs.at(t - delay)
    return plant_signals_and_derivative(t, y, plant, effects, u, m_load)


def plant_signals_and_derivative(
    t: Float[ArrayLike, ""],
    y: Float[Array, " S"],
    plant: Plant,
    effects: tuple[AbstractEffect, ...],
    u: Float[ArrayLike, ""],
    m_load: Float[ArrayLike, ""],
) -> tuple[Signals, Float[Array, " S"]]:
    """The chain of MODEL.md at ``(t, y)`` for a given duty ``u`` [-] (as the motor sees
    it, i.e. already delayed) and load ``m_load`` [kg]: the signals and ``dy/dt``.

    ``effects`` must be in registry order (see ``_canonical``). This is the building
    block of closed-loop simulation, where ``u`` comes from a controller."""
    (x, v, p), zs = _split(y, effects)
    zero = jnp.zeros(())
    sig = Signals(t=t, x=x, v=v, p=p, u=u, m_load=m_load, omega_ss=zero, a=zero, forces=zero)

    # motor (static map + effects' offsets), check valve logic on the motor command
    omega_cmd = plant.motor_map(x, plant.voltage(u))
    omega_cmd = omega_cmd + sum((e.motor_offset(plant, z, sig) for e, z in zip(effects, zs)), 0.0)
    valve_open = u > 0.0
    sig = sig._replace(omega_ss=jnp.where(valve_open, jnp.maximum(omega_cmd, 0.0), 0.0))
    omega = sig.omega_ss
    for e, z in zip(effects, zs):  # pass-through unless the effect has motor states
        omega = e.motor_speed(plant, z, sig._replace(omega_ss=omega))
    # pump, check valve, cylinder
    q_valve = jnp.where(valve_open, plant.pump_flow(omega), 0.0)
    flow = q_valve - plant.area(x) * v / plant.ratio
    flow = flow + sum((e.extra_flow(plant, z, sig) for e, z in zip(effects, zs)), 0.0)
    volume = plant.volume(x)
    cap = volume / plant.beta
    cap = cap + sum((e.extra_capacitance(plant, z, sig, volume) for e, z in zip(effects, zs)), 0.0)
    dp = flow / cap
    # friction, fork and load
    f_fric = plant.friction(v)
    f_fric = f_fric + sum((e.extra_friction(plant, z, sig) for e, z in zip(effects, zs)), 0.0)
    forces = plant.area(x) * p / plant.ratio - f_fric - plant.d * v
    sig = sig._replace(forces=forces)
    a = rigid_acceleration(plant, sig)
    for e, z in zip(effects, zs):
        if e.overrides_acceleration:
            a = e.acceleration(plant, z, sig)
    sig = sig._replace(a=a)
    dzs = [e.state_derivative(plant, z, sig) for e, z in zip(effects, zs)]
    return sig, jnp.concatenate([jnp.stack([v, a, dp]), *dzs])


def _vector_field(t, y, args):
    plant, effects, inputs = args
    return signals_and_derivative(t, y, plant, effects, inputs)[1]


def initial_state(
    plant: Plant, effects: tuple[AbstractEffect, ...], inputs: Inputs
) -> Float[Array, " S"]:
    """At rest at ``inputs.x0``, pressure at static equilibrium (MODEL.md)."""
    x0 = inputs.x0
    u0, m0 = inputs.at(inputs.ts[0])
    p0 = plant.static_pressure(x0, m0)
    y_base = jnp.stack([x0, jnp.zeros(()), p0])
    # the static motor speed at the start, for effects whose states start there
    sig, _ = signals_and_derivative(inputs.ts[0], y_base, plant, (), inputs)
    sig = sig._replace(v=jnp.zeros(()), a=jnp.zeros(()))
    zs = [e.initial_state(plant, sig) for e in effects]
    return jnp.concatenate([y_base, *zs])


def _error_norm(scaled_error):
    """Step-size error norm: the larger of the RMS over the three baseline states and the
    largest scaled error of the effects' own states. An effect whose states are frozen
    (at its nesting value) then leaves the baseline's step sequence unchanged, so the
    trajectory is exactly the baseline's (diffrax's default RMS over all states would
    dilute the error by the extra zero entries)."""
    base = jnp.sqrt(jnp.mean(scaled_error[:3] ** 2))
    if scaled_error.shape[0] == 3:
        return base
    return jnp.maximum(base, jnp.max(jnp.abs(scaled_error[3:])))


@eqx.filter_jit
def _solve(plant, effects, inputs, solver, rtol, atol_base, max_steps, adjoint, stability_limit):
    y0 = initial_state(plant, effects, inputs)
    scales = [jnp.asarray(e.state_scales, dtype=jnp.float64) for e in effects]
    atol = jnp.concatenate([atol_base, *[s * 1.0 for s in scales]]) if effects else atol_base
    delay = sum((e.delay() for e in effects), jnp.zeros(()))
    # steps end just before and restart just after each input jump, as with
    # diffrax.ClipStepSizeController(..., jump_ts=...), at a cost per step independent
    # of the number of jumps (see _stepping.py)
    from ._stepping import JumpStepSizeController, StabilityLimitedController

    # steps also kept inside Tsit5's stability region: at rest the solution has no
    # error to control, but its forward-mode sensitivities do (see _stepping.py)
    inner = diffrax.PIDController(rtol=rtol, atol=atol, dtmax=DTMAX, norm=_error_norm)
    if stability_limit:
        inner = StabilityLimitedController(inner, _vector_field, atol)
    controller = JumpStepSizeController(inner, inputs.jump_ts + delay)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field),
        solver,
        t0=inputs.ts[0],
        t1=inputs.ts[-1],
        dt0=None,
        y0=y0,
        args=(plant, effects, inputs),
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

    Returns:
        A :class:`Solution`; it never raises on solver failure -- check ``sol.ok``
        (jit-safe) or call ``sol.check()``.

    Jitted (through ``eqx.filter_jit``); ``eqx.filter_vmap`` over a batch of plants
    (or effects) works, and so do ``jax.grad`` and (with ``ForwardMode``) ``jax.jacfwd``.
    """
    x64_check()
    solver = diffrax.Tsit5() if solver is None else solver
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    effects = _canonical(effects)
    atol_base = jnp.asarray(atol, dtype=jnp.float64)
    return _solve(
        plant, effects, inputs, solver, rtol, atol_base, max_steps, adjoint, stability_limit
    )
