"""Input sequences for test runs: levels joined by linear ramps, sampled uniformly.

A sequence is a list of ``(level, duration_s)`` sections; between consecutive
sections the level is ramped linearly over ``ramp_s`` seconds (ramps included in
the next section's duration). The result is what a vehicle logs: a value per sample.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float


def ramped_sequence(
    sections: Sequence[tuple[float, float]], *, ramp_s: float = 1.0, dt: float = 0.01
) -> tuple[Float[np.ndarray, " N"], Float[np.ndarray, " N"]]:
    """Sample times [s] and values of a ramped piecewise-constant sequence.

    Args:
        sections: ``(level, duration_s)`` pairs; the first starts at t = 0 without ramp.
        ramp_s: ramp time between levels [s] (0: steps).
        dt: sample period [s].
    """
    if not sections:
        raise ValueError("a sequence needs at least one section")
    total = sum(d for _, d in sections)
    n = int(round(total / dt)) + 1
    ts = np.round(np.arange(n) * dt, 9)
    values = np.empty(n)
    t_start, prev = 0.0, sections[0][0]
    for i, (level, dur) in enumerate(sections):
        if dur <= 0:
            raise ValueError(f"section {i}: duration must be positive, got {dur}")
        mask = (ts >= t_start - 1e-9) & (ts < t_start + dur - 1e-9)
        if i == len(sections) - 1:
            mask |= ts >= t_start + dur - 1e-9
        frac = (
            np.ones(mask.sum())
            if ramp_s <= 0 or i == 0
            else np.clip((ts[mask] - t_start) / ramp_s, 0.0, 1.0)
        )
        values[mask] = prev + (level - prev) * frac
        t_start, prev = t_start + dur, level
    return ts, values


#: A test run like the thesis's figure 2.1: fast and slow sections in every stage,
#: ramped, with holds (pwm = 0); ~130 s. The duty levels give ~0.09 m/s (fast) and
#: ~0.02-0.03 m/s (slow) on the nominal plant at 500-1500 kg.
THESIS_LIKE_SECTIONS: list[tuple[float, float]] = [
    (0.0, 2.0),  # initial hold
    (0.45, 5.0),  # stage 1 fast
    (0.17, 16.0),  # stage 1 slow
    (0.0, 4.0),  # hold
    (0.44, 5.0),  # fast
    (0.18, 14.0),  # slow, through the first stage shift (~40 s)
    (0.42, 6.0),  # stage 2 fast
    (0.17, 21.0),  # stage 2 slow
    (0.0, 4.0),  # hold
    (0.17, 6.0),  # slow
    (0.43, 6.0),  # fast, through the second stage shift (~85 s)
    (0.17, 16.0),  # stage 3 slow
    (0.41, 5.0),  # stage 3 fast
    (0.16, 14.0),  # stage 3 slow
    (0.0, 5.0),  # final hold
]

#: A different input for validation: other levels and order (used with 0.5 s ramps).
VALIDATION_SECTIONS: list[tuple[float, float]] = [
    (0.0, 2.0),
    (0.30, 6.0),
    (0.22, 9.0),
    (0.55, 5.0),
    (0.0, 3.0),
    (0.20, 14.0),  # slow, through the first stage shift
    (0.38, 8.0),
    (0.0, 3.0),
    (0.50, 7.0),  # fast, through the second stage shift
    (0.21, 15.0),
    (0.36, 9.0),
    (0.19, 12.0),
    (0.0, 4.0),
]
