"""``motor_droop``: a series-wound motor slows under load torque, which is
proportional to pressure (thesis 2.2.2).

``omega = max(k U + z - kappa p, 0)``. Nesting value ``kappa = 0``.
"""

from __future__ import annotations

from typing import ClassVar

from ..params import param
from .base import AbstractStatelessEffect, Scalar, Signals


class MotorDroop(AbstractStatelessEffect):
    """Motor speed falling linearly with line pressure."""

    kappa: Scalar = param(
        0.0, "rad/(s Pa)", 0.0, 1e-5, "motor speed droop per pressure", nesting=0.0, scale=3e-7,
        typical=(3e-8, 6e-7),
        typical_why="a series-wound motor slowing by 2-30 % of its ~18 rad/s at 10 MPa",
    )  # fmt: skip

    name: ClassVar[str] = "motor_droop"

    def motor_offset(self, plant, z, sig: Signals):
        return -self.kappa * sig.p
