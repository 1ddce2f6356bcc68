"""Laws outside the eight candidate effects, for the tests and the study of the
shape of what is missing (``tests/test_shape.py``, ``studies/outside_the_eight.py``): a
force law, a flow law and an input nonlinearity, written as a user writes an effect.
"""

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

import jaxlift as jl
from jaxlift.model.build import all_param_infos, make_effects, with_params
from jaxlift.model.vector_field import signals_and_derivative


class SealFriction(jl.AbstractStatelessEffect):
    """Seal friction that grows with the pressure on the seal (a force law)."""

    mu: float = 6e-5  # N/Pa
    name: ClassVar[str] = "test_seal_friction"

    def extra_friction(self, plant, z, sig):
        return self.mu * sig.p * jnp.tanh(sig.v / plant.v_eps)


class EarlyRelief(jl.AbstractStatelessEffect):
    """A pressure relief valve that cracks early and bleeds flow above p_c (a flow law)."""

    k: float = 1.5e-12  # m^3/s/Pa
    p_c: float = 13e6  # Pa
    name: ClassVar[str] = "test_early_relief"

    def extra_flow(self, plant, z, sig):
        dp = sig.p - self.p_c
        return -self.k * jnp.where(dp > 0, dp, 0.0)


class DutySaturation(jl.AbstractStatelessEffect):
    """The motor drive saturates at a duty of u_sat (an input nonlinearity)."""

    u_sat: float = 0.45
    name: ClassVar[str] = "test_duty_saturation"

    def motor_offset(self, plant, z, sig):
        capped = plant.motor_map(sig.x, plant.voltage(jnp.minimum(sig.u, self.u_sat)))
        return capped - plant.motor_map(sig.x, plant.voltage(sig.u))


LAWS = {
    "seal_friction": SealFriction,
    "early_relief": EarlyRelief,
    "duty_saturation": DutySaturation,
}


def missing_targets(law, params, effects, inputs, t, x, v, p, *, true_plant=None, base_effects=()):
    """What a fitted model (``params``, ``effects``) lacks along a trajectory (``t, x,
    v, p``): the force [N] and flow [m^3/s] that make its derivatives those of the true
    model (``true_plant``, default nominal, + ``base_effects`` + ``law``), from the two
    vector fields alone (not from the shape estimate under test): the difference of
    the accelerations divided by the fitted model's acceleration per newton, and of the
    pressure rates divided by its pressure rate per m^3/s (the inverse mass and
    capacitance, effects such as entrained air or a mast mode included)."""
    true_plant = jl.Plant() if true_plant is None else true_plant
    effs = make_effects(effects)
    own = {k: val for k, val in params.items() if k in all_param_infos(effs)}
    pf, ef = with_params(jl.Plant(), effs, own)
    true_effects = (*base_effects, law)
    n_base = 3 + sum(e.n_states for e in ef)

    def one(tk, xk, vk, pk):
        y = jnp.stack([xk, vk, pk])
        _, d_true = signals_and_derivative(tk, y, true_plant, true_effects, inputs)

        def fitted(w):
            extra = jl.MissingTerms(jnp.stack([tk - 1.0, tk + 1.0]), jnp.stack([w[0], w[0]]),
                                    jnp.stack([w[1], w[1]]))  # fmt: skip
            yy = jnp.concatenate([y, jnp.zeros(n_base - 3)])
            d = signals_and_derivative(tk, yy, pf, (*ef, extra), inputs)[1]
            return jnp.stack([d[1], d[2]])

        d_fit, per_unit = jax.jvp(fitted, (jnp.zeros(2),), (jnp.ones(2),))
        # the force moves only the acceleration, the flow only the pressure rate
        return (d_true[1] - d_fit[0]) / per_unit[0], (d_true[2] - d_fit[1]) / per_unit[1]

    F, Q = jax.vmap(one)(*(jnp.asarray(a) for a in (t, x, v, p)))
    return np.asarray(F), np.asarray(Q)
