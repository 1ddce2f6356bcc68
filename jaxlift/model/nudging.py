"""Nudging: a simulation pulled towards a log's measured height and speed.

An observer term added to the state derivative (synchronisation of the model to the
data, "nudging" in data assimilation)::

    dx/dt += g (x_meas(t) - x)          dv/dt += g (v_meas(t) - v)

with the measurements interpolated linearly between samples and ``g`` a gain [1/s].
Where the log has no speed, the height alone pulls both (a critically damped pair):
``dx/dt += 2 g (x_meas - x)``, ``dv/dt += g² (x_meas - x)``.

It is not physics. It is a device for fitting where the least-squares surface of the
ordinary simulation is rough: a strong stick-slip, whose slips each move in time with
every parameter, so that the errors of a whole log's slips add up and a local fit from
anywhere but the optimum stagnates (studies/DETECTION.md, "Seventh sitting"). Pulled
towards the data, the simulation cannot drift away from the measured trajectory, the
errors do not accumulate and the surface is smooth; fitting at decreasing gains, each
fit started where the previous one ended, and finally at ``g = 0`` (the ordinary
simulation), follows the optimum to the one of the model itself
(:func:`jaxlift.fit`'s ``synchronise``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


class Nudging(eqx.Module):
    """The pull of one log's measurements on its simulation.

    Attributes:
        ts: sample times [s].
        height: measured height [m] at ``ts``.
        speed: measured speed [m/s] at ``ts`` (ignored unless ``has_speed``).
        gain: the pull ``g`` [1/s]; 0 is the ordinary simulation.
        has_speed: whether the log has a speed signal.
    """

    ts: Float[Array, " N"]
    height: Float[Array, " N"]
    speed: Float[Array, " N"]
    gain: Float[Array, ""]
    has_speed: bool = eqx.field(static=True)

    @classmethod
    def of(
        cls,
        ts: ArrayLike,
        height: ArrayLike,
        speed: ArrayLike | None,
        gain: float | Float[ArrayLike, ""],
    ) -> Nudging:
        """From a log's time stamps [s], height [m], speed [m/s] (or None) and a gain [1/s]."""
        ts = jnp.asarray(ts, dtype=jnp.float64)
        height = jnp.asarray(height, dtype=jnp.float64)
        has_speed = speed is not None
        speed = jnp.asarray(speed, dtype=jnp.float64) if has_speed else jnp.zeros_like(height)
        return cls(ts, height, speed, jnp.asarray(gain, dtype=jnp.float64), has_speed)

    def correction(self, t: Float[ArrayLike, ""], y: Float[Array, " S"]) -> Float[Array, " S"]:
        """The term added to ``dy/dt`` at ``(t, y)`` (zero but for height and speed)."""
        ex = jnp.interp(t, self.ts, self.height) - y[0]
        g = self.gain
        if self.has_speed:
            ev = jnp.interp(t, self.ts, self.speed) - y[1]
            dx, dv = g * ex, g * ev
        else:
            dx, dv = 2.0 * g * ex, g**2 * ex
        return jnp.zeros_like(y).at[0].set(dx).at[1].set(dv)
