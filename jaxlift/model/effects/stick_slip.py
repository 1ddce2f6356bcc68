"""``stick_slip``: static (breakaway) friction in the cylinders (thesis 3.1, 4.1.1).

``F_f += dFs * exp(-(v / v_s)^2) * tanh(v / v_eps)``: an extra friction that is
there only near zero speed, so the fork sticks at low speed and slips when the
pressure has built up -- sustained oscillations at low speed that touch zero speed.
Nesting value: ``dFs = 0``.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp

from ..params import param
from .base import AbstractStatelessEffect, Scalar, Signals


class StickSlip(AbstractStatelessEffect):
    """Stribeck-like breakaway friction near zero speed."""

    dFs: Scalar = param(
        0.0, "N", 0.0, 1e5, "breakaway friction above Coulomb", nesting=0.0, scale=100.0,
        typical=(20.0, 2000.0),
        typical_why="cylinder seals: tens of N for new, lubricated seals to a few kN for "
        "dry or worn ones",
    )  # fmt: skip
    v_s: Scalar = param(
        0.01, "m/s", 1e-4, 0.2, "Stribeck speed of the breakaway term",
        typical=(0.002, 0.03),
        typical_why="Stribeck speeds of lubricated seals: a few mm/s to a few cm/s",
    )  # fmt: skip

    name: ClassVar[str] = "stick_slip"

    def extra_friction(self, plant, z, sig: Signals):
        v = sig.v
        return self.dFs * jnp.exp(-((v / self.v_s) ** 2)) * jnp.tanh(v / plant.v_eps)
