"""``leakage``: internal leakage past piston seals and pump (thesis 4.1.3).

The numerator of ``dp/dt`` gains ``-C_L p``: the fork sinks while the valve is
closed. Nesting value ``C_L = 0``.
"""

from __future__ import annotations

from typing import ClassVar

from ..params import param
from .base import AbstractStatelessEffect, Scalar, Signals


class Leakage(AbstractStatelessEffect):
    """Laminar leakage flow proportional to pressure."""

    C_L: Scalar = param(
        0.0, "m^3/(s Pa)", 0.0, 1e-9, "laminar leakage coefficient", nesting=0.0, scale=1e-13,
        typical=(1e-14, 1.5e-12),
        typical_why="a shut valve letting the fork sink 0.1-10 mm/s at 10 MPa (stage 1)",
    )  # fmt: skip

    name: ClassVar[str] = "leakage"
    revealing_run: ClassVar[str] = (
        "a long hold (a minute) mid-mast with a heavy load and the motor off: only a "
        "leak lets the fork sink"
    )

    def extra_flow(self, plant, z, sig: Signals):
        return -self.C_L * sig.p
