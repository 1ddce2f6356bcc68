"""The solution of one open-loop simulation: time series of height, speed and pressure
(SI units), the solver's result code, and the failure exception.
"""

from __future__ import annotations

from typing import ClassVar, Self

import diffrax
import equinox as eqx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .constants import MAST_HEIGHT_M

#: How far (m) the fork may leave [0, x_max] before the run is declared out of range.
RANGE_TOLERANCE_M = 0.01


class SimulationError(RuntimeError):
    """A simulation that did not produce a valid trajectory (solver failure, or the
    fork left the mast's range)."""


class AbstractSolution(eqx.Module):
    """What every simulated run has, open- or closed-loop: the output times, the states,
    the solver's result, and whether the fork stayed on the mast.

    Attributes:
        ts: output times [s].
        ys: states at ``ts``, shape (N, 3 + extra): ``x`` [m], ``v`` [m/s], ``p`` [Pa]
            (gauge), then the effects' own states in registry order.
        result: diffrax result code (``diffrax.RESULTS``).
        in_range: whether the fork stayed within ``[0, x_max]`` (± 1 cm) and finite.
        num_steps: solver steps.
        state_names: names of the columns of ``ys``.
        x_max: full height [m].
    """

    ts: eqx.AbstractVar[Float[Array, " N"]]
    ys: eqx.AbstractVar[Float[Array, "N S"]]
    result: eqx.AbstractVar[diffrax.RESULTS]
    in_range: eqx.AbstractVar[Bool[Array, ""]]
    num_steps: eqx.AbstractVar[Int[Array, ""]]
    state_names: eqx.AbstractVar[tuple[str, ...]]
    x_max: eqx.AbstractVar[float]
    #: what to check when the fork leaves the mast (ends the error message)
    out_of_range_hint: ClassVar[str] = "check the parameters or the input"
    #: what a run is called in error messages
    kind: ClassVar[str] = "simulation"

    @property
    def height(self) -> Float[Array, " N"]:
        """Fork (carriage) height [m]."""
        return self.ys[..., 0]

    @property
    def speed(self) -> Float[Array, " N"]:
        """Fork speed [m/s]."""
        return self.ys[..., 1]

    @property
    def pressure(self) -> Float[Array, " N"]:
        """Line pressure (gauge) [Pa]."""
        return self.ys[..., 2]

    @property
    def ok(self) -> Bool[Array, ""]:
        """True when the solver succeeded and the fork stayed in range (jit-safe)."""
        return (self.result == diffrax.RESULTS.successful) & self.in_range

    def check(self, what: str | None = None) -> Self:
        """Return ``self`` if :attr:`ok`, else raise :class:`SimulationError` saying why.
        Not for use under ``jit``."""
        what = self.kind if what is None else what
        if not bool(self.result == diffrax.RESULTS.successful):
            msg = diffrax.RESULTS[self.result] if np.ndim(self.result._value) == 0 else ""
            raise SimulationError(f"{what}: the ODE solver failed: {msg}")
        if not bool(self.in_range):
            h = np.asarray(self.height)
            x_max = self.x_max + RANGE_TOLERANCE_M
            bad = np.nonzero(~np.isfinite(h) | (h < -RANGE_TOLERANCE_M) | (h > x_max))[0]
            t = float(self.ts[bad[0]]) if bad.size else float("nan")
            raise SimulationError(
                f"{what}: the fork left the mast's range [0, x_max] at t = {t:.2f} s "
                f"(height {h[bad[0]] if bad.size else float('nan'):.3f} m); the top of the mast "
                f"has no end stop in the model -- {self.out_of_range_hint}"
            )
        return self


class Solution(AbstractSolution):
    """A simulated test run (open loop: the log's input).

    Attributes:
        ts: output times [s] (the log's).
        ys: all states at ``ts``, shape (N, 3 + extra): ``x`` [m], ``v`` [m/s],
            ``p`` [Pa], then the effects' own states in registry order.
        state_names: names of the columns of ``ys``.
        result: diffrax result code (``diffrax.RESULTS``).
        in_range: whether the fork stayed within ``[0, x_max]`` (± 1 cm).
        num_steps: accepted + rejected solver steps.
    """

    ts: Float[Array, " N"]
    ys: Float[Array, "N S"]
    result: diffrax.RESULTS
    in_range: Bool[Array, ""]
    num_steps: Int[Array, ""]
    state_names: tuple[str, ...] = eqx.field(static=True)
    x_max: float = eqx.field(static=True, default=MAST_HEIGHT_M, kw_only=True)
