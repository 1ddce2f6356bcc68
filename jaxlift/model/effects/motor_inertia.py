"""``motor_inertia``: rotor and pump inertia -- the motor speed lags the voltage (4.1.1).

New state ``omega`` (rad/s): ``d omega/dt = (omega_ss - omega) / tau_m`` with
``omega_ss`` the baseline static map (0 while ``u = 0``). The pump delivers
``Q(omega)``; the check valve still closes at once when ``u = 0``.

Nesting value ``tau_m = 0``: then ``omega = omega_ss`` exactly (the state is carried
but frozen, so the trajectory is bit-for-bit the baseline's). Small positive
``tau_m`` makes the system stiff (eigenvalue ``-1/tau_m``); with the default explicit
solver keep ``tau_m`` above ~5 ms or pass an implicit solver.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp

from ..params import param
from .base import AbstractEffect, Scalar, Signals


class MotorInertia(AbstractEffect):
    """First-order lag of the motor speed behind its static map."""

    tau_m: Scalar = param(
        0.0, "s", 0.0, 5.0, "motor/pump speed time constant", nesting=0.0, scale=0.1,
        typical=(0.01, 0.5),
        typical_why="rotor and pump inertia against the motor torque: 10 ms for a small "
        "pump motor to 0.5 s for a large series-wound one",
    )  # fmt: skip

    name: ClassVar[str] = "motor_inertia"
    revealing_run: ClassVar[str] = (
        "steps of the duty from rest, of several sizes: a motor lag rounds the start "
        "of every lift with the same time constant"
    )
    state_names: ClassVar[tuple[str, ...]] = ("omega_m",)
    state_scales: ClassVar[tuple[float, ...]] = (1e-3,)
    overrides_acceleration: ClassVar[bool] = False

    def initial_state(self, plant, sig: Signals):
        return jnp.reshape(sig.omega_ss, (1,))

    def _active(self):
        return self.tau_m > 0.0

    def motor_speed(self, plant, z, sig: Signals):
        return jnp.where(self._active(), z[0], sig.omega_ss)

    def state_derivative(self, plant, z, sig: Signals):
        tau = jnp.where(self._active(), self.tau_m, 1.0)  # double-where: no 1/0
        rate = jnp.where(self._active(), (sig.omega_ss - z[0]) / tau, 0.0)
        return jnp.reshape(rate, (1,))
