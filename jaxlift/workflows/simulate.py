"""``jaxlift simulate`` as a function: the model on one log's input, written as CSV
with a figure of model against measurement."""

from __future__ import annotations

import os
import pathlib
from collections.abc import Sequence

import numpy as np

from ..model.effects import AbstractEffect
from ..model.inputs import Inputs
from ..model.log import Log
from ..model.plant import Plant
from ..model.simulate import simulate
from ..model.solution import Solution
from ..report.plots import plot_overlay


def run_simulate(
    log: Log,
    plant: Plant,
    effects: Sequence[AbstractEffect],
    out_csv: str | os.PathLike,
) -> tuple[Solution, dict[str, float]]:
    """Simulate ``plant`` + ``effects`` on ``log``'s input and load; write
    ``time_s,height_m,speed_mps,pressure_pa`` (SI units) to ``out_csv`` and the overlay
    figure beside it (same name, ``.png``).

    Returns the solution and the RMS errors against the log (``height_m`` [m], and
    ``speed_mps`` [m/s] where the log has speed). Raises
    :class:`~jaxlift.SimulationError` if the simulation fails.
    """
    sol = simulate(plant, effects, Inputs.from_log(log)).check(f"simulating {log.path}")
    out = pathlib.Path(out_csv)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = np.column_stack([np.asarray(a) for a in (sol.ts, sol.height, sol.speed, sol.pressure)])
    np.savetxt(
        out,
        data,
        delimiter=",",
        header="time_s,height_m,speed_mps,pressure_pa",
        comments="",
        fmt="%.9g",
    )
    label = "model" + (f" + {', '.join(e.name for e in effects)}" if effects else " (baseline)")
    plot_overlay(
        log,
        [(label, sol.height, sol.speed, sol.pressure if log.pressure_pa is not None else None)],
        out.with_suffix(".png"),
        title=f"{log.name}: model vs measurement",
    )
    rms = {"height_m": float(np.sqrt(np.mean((np.asarray(sol.height) - log.height_m) ** 2)))}
    if log.speed_mps is not None:
        rms["speed_mps"] = float(np.sqrt(np.mean((np.asarray(sol.speed) - log.speed_mps) ** 2)))
    return sol, rms
