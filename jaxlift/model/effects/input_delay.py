"""``input_delay``: controller clock, I/O and voltage-unit response time (4.1.4).

The plant sees ``u(t - tau_d)`` (zero-order hold, the first sample held before the
log starts); the solver's jump times move with it. Nesting value ``tau_d = 0``.

Gradient note: with a zero-order-hold input, the trajectory depends on ``tau_d``
only through *where* the input jumps. The solver steps onto the shifted jump times,
so derivatives with respect to ``tau_d`` flow through those step ends.
"""

from __future__ import annotations

from typing import ClassVar

from ..params import param
from .base import AbstractStatelessEffect, Scalar


class InputDelay(AbstractStatelessEffect):
    """Pure time delay of the commanded duty cycle."""

    tau_d: Scalar = param(
        0.0, "s", 0.0, 2.0, "input dead time", nesting=0.0, scale=0.05,
        typical=(0.01, 0.2),
        typical_why="controller clock, I/O and voltage-unit response: 10-200 ms",
    )  # fmt: skip

    name: ClassVar[str] = "input_delay"
    revealing_run: ClassVar[str] = (
        "steps of the duty from rest, of several sizes: a delay shifts every response "
        "by the same time, whatever the step"
    )

    def delay(self):
        return self.tau_d
