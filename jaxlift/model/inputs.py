"""The inputs of one test run: the log's time grid, PWM duty and load, and the initial
height estimated from the log's initial hold.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .log import Log

#: Initial hold used to estimate the starting height (s).
INITIAL_HOLD_MAX_S = 2.0


class Inputs(eqx.Module):
    """The input of one test run, as the plant sees it.

    Attributes:
        ts: sample times [s], shape (N,).
        pwm: duty cycle in [0, 1], held from each sample to the next (zero-order hold).
        load_kg: load mass [kg], held likewise.
        jump_ts: times [s] where ``pwm`` or ``load_kg`` change (the solver steps onto
            them; only true changes: a jump time at every sample costs a step each,
            measured 13 k steps instead of ~3 k on a 130 s staircase input).
        x0: initial height [m].
    """

    ts: Float[Array, " N"]
    pwm: Float[Array, " N"]
    load_kg: Float[Array, " N"]
    jump_ts: Float[Array, " J"]
    x0: Float[Array, ""]

    @classmethod
    def from_arrays(
        cls,
        ts: ArrayLike,
        pwm: ArrayLike,
        load_kg: ArrayLike,
        x0: float | ArrayLike,
    ) -> Inputs:
        ts, pwm, load = (np.asarray(a, dtype=np.float64) for a in (ts, pwm, load_kg))
        if not (ts.shape == pwm.shape == load.shape and ts.ndim == 1 and ts.size >= 2):
            raise ValueError("ts, pwm and load_kg must be 1-D arrays of the same length >= 2")
        change = (np.diff(pwm) != 0) | (np.diff(load) != 0)
        jump_ts = ts[1:][change]
        if jump_ts.size == 0:  # diffrax wants at least one; a jump at the end is harmless
            jump_ts = ts[-1:]
        return cls(
            ts=jnp.asarray(ts),
            pwm=jnp.asarray(pwm),
            load_kg=jnp.asarray(load),
            jump_ts=jnp.asarray(jump_ts),
            x0=jnp.asarray(x0, dtype=jnp.float64),
        )

    @classmethod
    def from_log(cls, log: Log) -> Inputs:
        """Inputs of a log; the initial height is the mean height over the initial hold
        (the leading samples with ``pwm = 0``, at most ``INITIAL_HOLD_MAX_S``), or the
        first sample if the log does not start with a hold (docs/model.md)."""
        return cls.from_arrays(log.time_s, log.pwm, log.load_kg, initial_height(log))

    def at(self, t: Float[ArrayLike, ""]) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """Zero-order-held ``(pwm, load_kg)`` at time ``t`` (first sample before start)."""
        i = jnp.clip(jnp.searchsorted(self.ts, t, side="right") - 1, 0, self.ts.shape[0] - 1)
        return self.pwm[i], self.load_kg[i]


def initial_height(log: Log) -> float:
    """Mean height over the initial hold (``pwm == 0`` from the start, at most 2 s), never
    below the bottom end stop at 0 m: a fork resting on the stop reads 0 plus noise, and
    the mean of that noise can be slightly negative (docs/model.md)."""
    moving = np.nonzero(log.pwm != 0)[0]
    n_hold = moving[0] if moving.size else log.n
    n_max = int(round(INITIAL_HOLD_MAX_S / log.sample_period)) + 1
    n = max(1, min(n_hold, n_max))
    return max(float(np.mean(log.height_m[:n])), 0.0)
