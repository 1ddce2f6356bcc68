"""``entrained_air``: undissolved air makes the oil softer at low pressure
(thesis 2.2.5, 3.2).

Isothermal gas of volume fraction ``alpha0`` at atmospheric pressure:
``C = V (1/beta + alpha0 p_atm / p_abs^2)``.

Deviation from docs/model.md's reference form (which writes ``p``): ``p`` in the model is
the *gauge* pressure (``p0 = M g r / A`` balances the load against atmosphere), while
Boyle's law holds for the absolute pressure ``p_abs = p + p_atm``. We use
``p_abs``; at working pressures of 7-15 MPa the two differ by 1-3 % in this term,
and ``p_abs`` stays finite where the gauge pressure passes through zero.
Nesting value ``alpha0 = 0``.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp

from ..constants import P_ATM
from ..params import param
from .base import AbstractStatelessEffect, Scalar, Signals


class EntrainedAir(AbstractStatelessEffect):
    """Compliance of undissolved air, falling with the square of pressure."""

    alpha0: Scalar = param(
        0.0, "-", 0.0, 2.0, "gas volume per oil volume at p_atm", nesting=0.0, scale=0.01,
        typical=(0.001, 2.0),
        typical_why="from barely any air to the ~1.5 that would explain the thesis's whole "
        "softening (docs/model.md); 2 is the specification's upper bound",
    )  # fmt: skip

    name: ClassVar[str] = "entrained_air"
    revealing_run: ClassVar[str] = (
        "slow runs with a light and a heavy load: air softens the oil most at low "
        "pressure, so the light load oscillates slower, against the heavy load, than "
        "the oil's own compressibility explains"
    )

    def extra_capacitance(self, plant, z, sig: Signals, volume):
        p_abs = jnp.maximum(sig.p + P_ATM, 0.1 * P_ATM)  # no gas law below vacuum
        return volume * self.alpha0 * P_ATM / p_abs**2
