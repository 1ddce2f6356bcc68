"""Measurement model (docs/model.md): what the vehicle's sensors make of the trajectory.

Height: the wire sensor, white noise ``sigma_height`` (0.5 mm). Speed: band-limited
white noise of power ``speed_noise_power`` [(m/s)^2 s] held for one sample, so
``sigma_v = sqrt(power / T_s)`` (thesis 2.4.4). Pressure (where a sensor exists):
white noise ``sigma_pressure``. Every draw comes from an explicit ``jax.random`` key.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .constants import SIGMA_HEIGHT_M, SIGMA_PRESSURE_PA, SPEED_NOISE_POWER
from .inputs import Inputs
from .log import Log
from .solution import Solution


class MeasurementModel(eqx.Module):
    """Sensor noise levels (SI units)."""

    sigma_height: float = SIGMA_HEIGHT_M  # m
    speed_noise_power: float = SPEED_NOISE_POWER  # (m/s)^2 s
    sigma_pressure: float = SIGMA_PRESSURE_PA  # Pa

    def sigma_speed(self, sample_period: float | Float[Array, ""]) -> Float[Array, ""]:
        """Standard deviation of the speed noise at sample period ``T_s`` [m/s]."""
        return jnp.sqrt(self.speed_noise_power / sample_period)

    def sigmas(self, sample_period: float) -> dict[str, float]:
        """Noise standard deviations of each logged signal, by log column name."""
        return {
            "height_m": float(self.sigma_height),
            "speed_mps": float(self.sigma_speed(sample_period)),
            "pressure_pa": float(self.sigma_pressure),
        }


def measure(
    sol: Solution, model: MeasurementModel, key: PRNGKeyArray
) -> dict[str, Float[Array, " N"]]:
    """Noisy measurements of a solution: ``{"height_m", "speed_mps", "pressure_pa"}``."""
    kh, kv, kp = jax.random.split(key, 3)
    n = sol.ts.shape[0]
    ts_period = (sol.ts[-1] - sol.ts[0]) / (n - 1)
    return {
        "height_m": sol.height + model.sigma_height * jax.random.normal(kh, (n,)),
        "speed_mps": sol.speed + model.sigma_speed(ts_period) * jax.random.normal(kv, (n,)),
        "pressure_pa": sol.pressure + model.sigma_pressure * jax.random.normal(kp, (n,)),
    }


def to_log(
    sol: Solution,
    inputs: Inputs,
    model: MeasurementModel,
    key: PRNGKeyArray,
    *,
    with_speed: bool = True,
    with_pressure: bool = False,
    name: str = "simulated",
) -> Log:
    """A :class:`~jaxlift.Log` of noisy measurements of a simulated run."""
    sol.check(name)
    meas = {k: np.asarray(v) for k, v in measure(sol, model, key).items()}
    return Log(
        time_s=np.asarray(inputs.ts),
        pwm=np.asarray(inputs.pwm),
        height_m=meas["height_m"],
        load_kg=np.asarray(inputs.load_kg),
        speed_mps=meas["speed_mps"] if with_speed else None,
        pressure_pa=meas["pressure_pa"] if with_pressure else None,
        name=name,
    )
