"""Resampling a log with jittered time stamps onto a uniform clock, only when asked
(``read_log(..., resample=dt)``, ``--resample DT`` on the command line; docs/data.md).

Without it a log whose time steps deviate more than 1 % from the sample period is refused
(:data:`~jaxlift.model.log_validation.JITTER`). With it, the samples as logged are first
checked with a looser tolerance (:data:`~jaxlift.model.log_validation.RESAMPLE_JITTER`:
a step may deviate up to 50 % from the median step; a longer one is a missing sample, a
gap, still an error: nothing is interpolated across a gap), then every column is carried
onto the clock ``t0 + k dt``, ``k = 0, 1, ...`` up to the last logged time:

* ``height_m``, ``speed_mps``, ``pressure_pa``: **linear interpolation** between the two
  logged samples around each new instant. They are samples of continuous physical
  signals (position, velocity, pressure of a mechanical and hydraulic system); without a
  model of the lift, the straight line between neighbours is the estimate that adds no
  overshoot and no new extremes, and its error (of order ``dt^2`` times the curvature)
  is far below the sensors' noise at jitter of a few percent of the period.
* ``pwm``, ``load_kg``: **zero-order hold**, the last logged value at or before the new
  instant. ``pwm`` is the controller's command, piecewise constant between its updates
  (the voltage unit holds it); interpolating would invent duty cycles that were never
  commanded and move the command's steps in time. ``load_kg`` changes in steps (a pallet
  picked up): a mass between two pallets never was on the forks.
* unused (extra) columns: zero-order hold too (their meaning is unknown, and text cannot
  be interpolated).
"""

import math
from collections.abc import Mapping

import numpy as np

from .log_validation import LogError

#: Interpolated linearly: samples of continuous physical signals.
LINEAR_COLUMNS: tuple[str, ...] = ("height_m", "speed_mps", "pressure_pa")
#: Held (previous value): commands and piecewise-constant quantities.
HOLD_COLUMNS: tuple[str, ...] = ("pwm", "load_kg")

# Round-off allowance [fraction of dt] when a new instant falls on a logged one.
_ROUND_OFF = 1e-9


def resample_period(dt: object) -> float:
    """``dt`` as a sample period [s] to resample onto; ValueError unless it is a finite
    number > 0."""
    if isinstance(dt, bool) or not isinstance(dt, int | float | np.integer | np.floating):
        raise ValueError(f"resample: expected a sample period in seconds, got {dt!r}")
    value = float(dt)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"resample: expected a sample period > 0 s, got {value!r}")
    return value


def uniform_clock(t0: float, t_end: float, dt: float) -> np.ndarray:
    """``t0 + k dt`` for ``k = 0, 1, ...`` while ``<= t_end`` (with a round-off allowance
    of 1e-9 dt) [s]."""
    n = int(math.floor((t_end - t0) / dt + _ROUND_OFF)) + 1
    return t0 + dt * np.arange(n, dtype=np.float64)


def resample_columns(
    arrays: Mapping[str, np.ndarray],
    extra: Mapping[str, np.ndarray],
    dt: float,
    *,
    path: str | None = None,
    name: str | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The checked columns of a log (``time_s`` strictly increasing) and its extra columns,
    carried onto the uniform clock of period ``dt`` [s] from the first logged time (see the
    module docstring for which column is interpolated and which held, and why).

    Raises :class:`LogError` (naming ``path`` or ``name``) when the log is shorter than one
    period, which leaves fewer than 2 samples.
    """
    t = np.asarray(arrays["time_s"], dtype=np.float64)
    if t[-1] - t[0] < dt * (1.0 - _ROUND_OFF):
        raise LogError(
            f"a log at least one resampling period ({dt:.6g} s) long", path=path,
            column="time_s", got=f"{t[-1] - t[0]:.6g} s from the first to the last sample",
            name=name,
        )  # fmt: skip
    t_new = uniform_clock(float(t[0]), float(t[-1]), dt)
    # index of the last logged sample at or before each new instant
    held = np.searchsorted(t, t_new + _ROUND_OFF * dt, side="right") - 1
    held = np.clip(held, 0, t.size - 1)
    out: dict[str, np.ndarray] = {"time_s": t_new}
    for c, a in arrays.items():
        if c == "time_s":
            continue
        if c in LINEAR_COLUMNS:
            out[c] = np.interp(t_new, t, a)
        elif c in HOLD_COLUMNS:
            out[c] = np.asarray(a)[held]
        else:
            raise ValueError(f"resample: no rule for column {c!r}")
    return out, {c: np.asarray(a)[held] for c, a in extra.items()}
