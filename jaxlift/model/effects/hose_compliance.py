"""``hose_compliance``: hoses and seals stretch with pressure (thesis 3.2).

``C = V / beta + C_h``: a compliance that does not grow with height, so the
hydraulic frequency varies less with height. Nesting value ``C_h = 0``.
"""

from __future__ import annotations

from typing import ClassVar

from ..params import param
from .base import AbstractStatelessEffect, Scalar, Signals


class HoseCompliance(AbstractStatelessEffect):
    """Constant extra hydraulic capacitance."""

    C_h: Scalar = param(
        0.0, "m^3/Pa", 0.0, 1e-9, "hose and seal compliance", nesting=0.0, scale=1e-12,
        typical=(1e-13, 1e-11),
        typical_why="hoses and seals from a tenth to ten times the oil's own capacitance "
        "V0/beta ~ 1.4e-12 m^3/Pa",
    )  # fmt: skip

    name: ClassVar[str] = "hose_compliance"
    revealing_run: ClassVar[str] = (
        "slow runs low and high on the mast: the hose's softness is the same at every "
        "height, so it matters most where the oil column is short"
    )

    def extra_capacitance(self, plant, z, sig: Signals, volume):
        return self.C_h
