"""The vector field of plant + effects: the signals of the chain (motor speed, flow,
forces; see ``docs/model.md``) and the state derivative, and the initial state at static
equilibrium.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .constants import START_CLEARANCE
from .effects import EFFECTS, AbstractEffect, Signals, rigid_acceleration
from .inputs import Inputs
from .plant import Plant


def canonical_effects(effects: Sequence[AbstractEffect]) -> tuple[AbstractEffect, ...]:
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


def split_state(y, effects):
    base = y[:3]
    zs, i = [], 3
    for e in effects:
        zs.append(y[i : i + e.n_states])
        i += e.n_states
    return base, zs


def signals_and_derivative(
    t, y, plant: Plant, effects: tuple[AbstractEffect, ...], inputs: Inputs
) -> tuple[Signals, Float[Array, " S"]]:
    """Evaluate the chain of docs/model.md at ``(t, y)``: the signals and ``dy/dt``."""
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
    """The chain of docs/model.md at ``(t, y)`` for a given duty ``u`` [-] (as the motor sees
    it, i.e. already delayed) and load ``m_load`` [kg]: the signals and ``dy/dt``.

    ``effects`` must be in registry order (see ``canonical_effects``). This is the building
    block of closed-loop simulation, where ``u`` comes from a controller."""
    (x, v, p), zs = split_state(y, effects)
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
    # the bottom end stop acts on the carriage (under mast_compliance too: ``forces``
    # are the forces on the carriage besides gravity and the load)
    forces = (
        plant.area(x) * p / plant.ratio - f_fric - plant.d * v + plant.end_stop_force(x, v, m_load)
    )
    sig = sig._replace(forces=forces)
    a = rigid_acceleration(plant, sig)
    for e, z in zip(effects, zs):
        if e.overrides_acceleration:
            a = e.acceleration(plant, z, sig)
    sig = sig._replace(a=a)
    dzs = [e.state_derivative(plant, z, sig) for e, z in zip(effects, zs)]
    return sig, jnp.concatenate([jnp.stack([v, a, dp]), *dzs])


def lift_vector_field(t, y, args):
    plant, effects, inputs = args
    return signals_and_derivative(t, y, plant, effects, inputs)[1]


def initial_state(
    plant: Plant, effects: tuple[AbstractEffect, ...], inputs: Inputs
) -> Float[Array, " S"]:
    """At rest at ``inputs.x0`` (never below the bottom end stop at 0 m: a fit's
    initial-height offset cannot put the start there), pressure at static equilibrium
    (docs/model.md)."""
    # where, not maximum: at the tie x0 = 0 (a log starting on the stop) the derivative
    # is that of raising the start (1), not 1/2 (see Plant.end_stop_force)
    x0 = jnp.where(inputs.x0 >= 0.0, inputs.x0, 0.0)
    # off the contact's tie (constants.START_CLEARANCE): every start 1 µm higher, so
    # that the start stays continuous with derivative 1 (a shift far below the noise)
    x0 = x0 + START_CLEARANCE
    u0, m0 = inputs.at(inputs.ts[0])
    p0 = plant.static_pressure(x0, m0)
    y_base = jnp.stack([x0, jnp.zeros(()), p0])
    # the static motor speed at the start, for effects whose states start there
    sig, _ = signals_and_derivative(inputs.ts[0], y_base, plant, (), inputs)
    sig = sig._replace(v=jnp.zeros(()), a=jnp.zeros(()))
    zs = [e.initial_state(plant, sig) for e in effects]
    return jnp.concatenate([y_base, *zs])
