"""The fork-speed reference the controller follows: ramped sections of constant speed,
and the thesis-like sequence of ``docs/control.md``.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..model.constants import OUTPUT_DT

#: Reference speeds below this [m/s] are "stopped" (docs/control.md: the controller
#: closes the valve and holds its states where ``v_ref = 0``). Not an exact zero: at
#: the first sample of a ramp from a hold, ``v_ref(t_k)`` is evaluated at ``t_k = k T_c``,
#: and XLA's fused multiply-add makes ``k T_c - t_knot`` 1e-17 s instead of 0, so an
#: exact test called the loop "moving" one sample early (measured: the states
#: integrated that sample's noise; found by the independent closed loop,
#: tests/scipy_closed_loop.py). A nanometre per second is far below any real reference.
STOPPED_BELOW_MPS = 1e-9


def is_moving(v_ref: Float[ArrayLike, "..."]) -> Array:
    """Whether the reference moves: ``|v_ref| >`` :data:`STOPPED_BELOW_MPS` [m/s]."""
    return jnp.abs(jnp.asarray(v_ref)) > STOPPED_BELOW_MPS


#: The thesis-like reference (docs/control.md, thesis figure 2.9): ``(v_ref [m/s],
#: duration [s])`` sections, ramped over 1 s, from 0.2 m: fast (0.09 m/s) and slow
#: (0.025 m/s) sections in every stage, holds, both stage shifts crossed (the first
#: at slow speed near 34 s, the second at fast speed near 74 s); 110 s, ends at 4.34 m.
THESIS_REFERENCE_SECTIONS: list[tuple[float, float]] = [
    (0.0, 2.0),  # initial hold at 0.2 m
    (0.09, 5.0),  # stage 1 fast
    (0.025, 14.0),  # stage 1 slow
    (0.0, 3.0),  # hold
    (0.09, 4.0),  # fast
    (0.025, 14.0),  # slow, through the first stage shift
    (0.09, 6.0),  # stage 2 fast
    (0.025, 14.0),  # stage 2 slow
    (0.0, 3.0),  # hold
    (0.025, 6.0),  # slow
    (0.09, 6.0),  # fast, through the second stage shift
    (0.025, 12.0),  # stage 3 slow
    (0.09, 5.0),  # stage 3 fast
    (0.025, 12.0),  # stage 3 slow
    (0.0, 4.0),  # final hold
]


class Reference(eqx.Module):
    """A piecewise-linear fork-speed reference with its load and starting height.

    Attributes:
        knots_t: times [s] of the knots (ascending, first 0).
        knots_v: reference speed at the knots [m/s]; linear in between.
        m_load: load on the forks [kg] (known to the controller).
        x0: starting height [m] (at rest).
        n_out: number of output samples (period ``OUTPUT_DT``).
    """

    knots_t: Float[Array, " K"]
    knots_v: Float[Array, " K"]
    m_load: Float[Array, ""]
    x0: Float[Array, ""]
    n_out: int = eqx.field(static=True)

    @classmethod
    def from_sections(
        cls,
        sections: Sequence[tuple[float, float]],
        *,
        m_load: float = 1000.0,
        x0: float = 0.2,
        ramp_s: float = 1.0,
    ) -> Reference:
        """Levels ``(v [m/s], duration [s])`` joined by linear ramps of ``ramp_s`` [s]
        (included in the next section, as in :func:`jaxlift.model.sequences.ramped_sequence`).
        Durations must be multiples of 10 ms."""
        if not sections:
            raise ValueError("a reference needs at least one section")
        kt, kv = [0.0], [float(sections[0][0])]
        t = 0.0
        for i, (level, dur) in enumerate(sections):
            if dur <= 0:
                raise ValueError(f"reference section {i}: duration must be positive, got {dur}")
            if i > 0 and ramp_s > 0 and ramp_s >= dur:
                raise ValueError(f"reference section {i}: ramp {ramp_s} s longer than it")
            if i > 0 and level != kv[-1]:
                if ramp_s > 0:
                    kt += [t, t + ramp_s]
                    kv += [kv[-1], float(level)]
                else:
                    kt += [t, t]
                    kv += [kv[-1], float(level)]
            t += dur
        kt.append(t)
        kv.append(kv[-1])
        n_out = int(round(t / OUTPUT_DT)) + 1
        if abs((n_out - 1) * OUTPUT_DT - t) > 1e-9:
            raise ValueError(f"the reference's length {t} s is not a multiple of 10 ms")
        if max(abs(v) for v in kv) > 0.15:
            raise ValueError("reference speeds beyond 0.15 m/s leave the friction law's range")
        return cls(
            knots_t=jnp.asarray(kt, dtype=jnp.float64),
            knots_v=jnp.asarray(kv, dtype=jnp.float64),
            m_load=jnp.asarray(m_load, dtype=jnp.float64),
            x0=jnp.asarray(x0, dtype=jnp.float64),
            n_out=n_out,
        )

    @property
    def t1(self) -> float:
        """End time [s]."""
        return (self.n_out - 1) * OUTPUT_DT

    @property
    def ts(self) -> Float[Array, " n"]:
        """Output times [s]."""
        return jnp.arange(self.n_out, dtype=jnp.float64) * OUTPUT_DT

    def v(self, t: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        """Reference speed [m/s] at ``t`` [s]."""
        return jnp.interp(t, self.knots_t, self.knots_v)

    def with_load(self, m_load: float | ArrayLike) -> Reference:
        """The same reference with another load [kg]."""
        return eqx.tree_at(lambda r: r.m_load, self, jnp.asarray(m_load, dtype=jnp.float64))

    def height(self) -> Float[np.ndarray, " n"]:
        """Reference height at the output times [m] (``x0 + ∫ v_ref``), numpy."""
        ts = np.asarray(self.ts)
        v = np.interp(ts, np.asarray(self.knots_t), np.asarray(self.knots_v))
        return float(self.x0) + np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]))]) * (
            OUTPUT_DT
        )


def thesis_reference(
    m_load: float = 1000.0, *, x0: float = 0.2, ramp_s: float = 1.0, time_scale: float = 1.0
) -> Reference:
    """The thesis-like reference of docs/control.md (:data:`THESIS_REFERENCE_SECTIONS`),
    110 s. ``time_scale < 1`` shortens every section (tests), keeping the speeds:
    the reference then covers a fraction of the lift."""
    secs = [(v, round(d * time_scale, 2)) for v, d in THESIS_REFERENCE_SECTIONS]
    return Reference.from_sections(secs, m_load=m_load, x0=x0, ramp_s=ramp_s * min(1, time_scale))
