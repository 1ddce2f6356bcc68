"""Candidate effects of docs/model.md: one file each, one line each in ``BUILT_IN``.

To add an effect to jaxlift: write ``jaxlift/model/effects/my_effect.py`` with a
subclass of :class:`AbstractEffect`, and add one line to ``BUILT_IN`` below. Nothing
else changes. A user adds one without touching jaxlift: see :mod:`.registry`
(``register_effect``, ``--effect-file``, the entry-point group ``jaxlift.effects``).
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
from .registry import (
    EFFECTS,
    load_effect_file,
    load_entry_point_effects,
    register_effect,
    unregister_effect,
)
from .stick_slip import StickSlip

#: The eight effects of docs/model.md, in its table's order: the order in which effects
#: are applied and in which their states are stacked (user effects come after them).
BUILT_IN: tuple[type[AbstractEffect], ...] = (
    StickSlip,
    MotorInertia,
    MotorDroop,
    Leakage,
    EntrainedAir,
    HoseCompliance,
    MastCompliance,
    InputDelay,
)
for _cls in BUILT_IN:
    register_effect(_cls, builtin=True)

__all__ = [
    "AbstractEffect",
    "AbstractStatelessEffect",
    "Signals",
    "EFFECTS",
    "BUILT_IN",
    "rigid_acceleration",
    "register_effect",
    "unregister_effect",
    "load_effect_file",
    "load_entry_point_effects",
]
