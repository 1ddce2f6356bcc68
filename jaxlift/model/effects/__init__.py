"""Candidate effects of docs/model.md: one file each, one line each in ``EFFECTS``.

To add an effect: write ``jaxlift/model/effects/my_effect.py`` with a subclass of
:class:`AbstractEffect`, and add one line to ``EFFECTS`` below. Nothing else changes.
"""

from __future__ import annotations

from .base import AbstractEffect, AbstractStatelessEffect, Signals, rigid_acceleration
from .entrained_air import EntrainedAir
from .hose_compliance import HoseCompliance
from .input_delay import InputDelay
from .leakage import Leakage
from .mast_compliance import MastCompliance
from .motor_droop import MotorDroop
from .motor_inertia import MotorInertia
from .stick_slip import StickSlip

#: The registry: effect name -> class. Order = docs/model.md's table = the order in
#: which effects are applied and in which their states are stacked.
EFFECTS: dict[str, type[AbstractEffect]] = {
    cls.name: cls
    for cls in (
        StickSlip,
        MotorInertia,
        MotorDroop,
        Leakage,
        EntrainedAir,
        HoseCompliance,
        MastCompliance,
        InputDelay,
    )
}

__all__ = ["AbstractEffect", "AbstractStatelessEffect", "Signals", "EFFECTS", "rigid_acceleration"]
