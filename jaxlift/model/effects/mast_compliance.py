"""``mast_compliance``: the mast and forks flex; the load rides on a spring (4.1.3).

The load mass rides on a spring-damper ``k_s = 1/ks_inv``, ``c_s`` on the carriage,
which carries the stage masses ``m_st(x)``. The wire sensor measures the carriage
(``x``). New states: the load's deflection ``delta`` relative to the carriage (m,
negative under gravity) and its rate (m/s).

    m_st(x) a   = F - m_st g + k_s delta + c_s delta'          (carriage)
    m_load (a + delta'') = -k_s delta - c_s delta' - m_load g  (load)

Nesting value ``ks_inv = 0`` (rigid): the rigid law is used and the two states stay
at zero, so the trajectory is exactly the baseline's. ``c_s`` has no effect then.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp

from ..constants import G
from ..params import param
from .base import AbstractEffect, Scalar, Signals, rigid_acceleration


class MastCompliance(AbstractEffect):
    """Load on a spring-damper on the carriage."""

    ks_inv: Scalar = param(
        0.0, "m/N", 0.0, 1e-3, "mast compliance 1/k_s", nesting=0.0, scale=1e-6,
        typical=(1e-7, 1e-5),
        typical_why="mast and forks deflecting 0.1-10 mm per kN: load modes of ~3-30 Hz "
        "at 1000 kg",
    )  # fmt: skip
    c_s: Scalar = param(
        5e3, "N s/m", 0.0, 1e6, "mast damping",
        typical=(1e3, 1e5),
        typical_why="damping ratios 0.05-0.5 of those modes at 1000 kg",
    )  # fmt: skip

    name: ClassVar[str] = "mast_compliance"
    revealing_run: ClassVar[str] = (
        "the same slow run with a light and a heavy load, low and high on the mast: the "
        "oil's spring softens as its column grows, the mast's does not, so a mode that "
        "moves with the load but not with the height is the mast"
    )
    state_names: ClassVar[tuple[str, ...]] = ("delta", "delta_rate")
    state_scales: ClassVar[tuple[float, ...]] = (1e-7, 1e-6)
    overrides_acceleration: ClassVar[bool] = True

    def initial_state(self, plant, sig: Signals):
        return jnp.stack([-sig.m_load * G * self.ks_inv, jnp.zeros(())])

    def _flex(self, sig):
        return (self.ks_inv > 0.0) & (sig.m_load > 0.0)

    def _spring(self, z, sig):
        ks_inv = jnp.where(self._flex(sig), self.ks_inv, 1.0)  # double-where: no 1/0
        return z[0] / ks_inv + self.c_s * z[1]  # force of the load on the carriage, up

    def acceleration(self, plant, z, sig: Signals):
        m_st = plant.stage_mass(sig.x)
        a_flex = (sig.forces - m_st * G + self._spring(z, sig)) / m_st
        return jnp.where(self._flex(sig), a_flex, rigid_acceleration(plant, sig))

    def state_derivative(self, plant, z, sig: Signals):
        m_load = jnp.where(self._flex(sig), sig.m_load, 1.0)
        dd = -self._spring(z, sig) / m_load - G - sig.a
        return jnp.stack([z[1], jnp.where(self._flex(sig), dd, 0.0)])
