"""Experiments (one log each: inputs, measured signals, noise levels) and the scaled
residuals ``(model - measured) / sigma`` of a model on them; the named parameter sets.
"""

from __future__ import annotations

from collections.abc import Sequence

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..model.build import all_param_infos
from ..model.effects import AbstractEffect
from ..model.inputs import Inputs
from ..model.log import Log
from ..model.measurement import MeasurementModel
from ..model.nudging import Nudging
from ..model.params import ParameterError
from ..model.plant import Plant
from ..model.simulate import simulate

#: Named parameter sets (thesis 2.3.2): the motor set and the dynamic set.
PARAMETER_SETS: dict[str, tuple[str, ...]] = {
    "motor": ("k1", "k2", "k3", "z1", "z2", "z3"),
    "dynamic": ("beta", "cf_con", "cf_in", "cf_out", "d"),
}

#: Residual (per sample) that stands for a failed simulation: large, finite, so that
#: Levenberg--Marquardt rejects the step instead of propagating inf/NaN.
FAILED_RESIDUAL = 1e3


def resolve_free(free: str | Sequence[str], effects: Sequence[AbstractEffect]) -> list[str]:
    """Expand set names into parameter names.

    ``free`` is a comma-separated string or a sequence of set names (``motor``,
    ``dynamic``, ``effects`` = the parameters of the switched-on effects, ``all`` =
    motor + dynamic + effects) and/or parameter names (docs/model.md).
    """
    if isinstance(free, str):
        free = [f.strip() for f in free.split(",") if f.strip()]
    eff_names = [n for e in effects for n in type(e).param_infos()]
    known = all_param_infos(effects)
    out: list[str] = []
    for item in free:
        if item == "all":
            names = [*PARAMETER_SETS["motor"], *PARAMETER_SETS["dynamic"], *eff_names]
        elif item == "effects":
            names = eff_names
        elif item in PARAMETER_SETS:
            names = list(PARAMETER_SETS[item])
        elif item in known:
            names = [item]
        else:
            sets = ["all", "effects", *PARAMETER_SETS]
            raise ParameterError(
                f"--free: {item!r} is neither a parameter set ({sets})"
                f" nor a parameter of this model ({sorted(known)})"
            )
        out.extend(n for n in names if n not in out)
    if not out:
        raise ParameterError("no free parameters")
    return out


class Experiment(eqx.Module):
    """One log prepared for fitting: its inputs, measurements and noise levels.

    ``signals`` lists which of (height, speed, pressure) the log has (0, 1, 2)."""

    inputs: Inputs
    y: Float[Array, "3 N"]  # measured height [m], speed [m/s], pressure [Pa] (0 if absent)
    sigma: Float[Array, " 3"]  # noise standard deviations of the three signals
    signals: tuple[int, ...] = eqx.field(static=True)
    name: str = eqx.field(static=True)

    @property
    def n_residuals(self) -> int:
        return len(self.signals) * int(self.inputs.ts.shape[0])

    def scaled_residuals(self, sol) -> Float[Array, "3 N"]:
        """``(model - measured) / sigma`` of height, speed and pressure (one row each;
        only the rows in ``signals`` are measured)."""
        model = jnp.stack([sol.height, sol.speed, sol.pressure])
        return (model - self.y) / self.sigma[:, None]


def make_experiments(
    logs: Sequence[Log], measurement: MeasurementModel | None = None
) -> list[Experiment]:
    """Experiments from logs; noise levels from the measurement model (docs/model.md)."""
    measurement = MeasurementModel() if measurement is None else measurement
    out = []
    for log in logs:
        sig = measurement.sigmas(log.sample_period)
        zeros = np.zeros(log.n)
        y = np.stack(
            [
                log.height_m,
                log.speed_mps if log.speed_mps is not None else zeros,
                log.pressure_pa if log.pressure_pa is not None else zeros,
            ]
        )
        signals = tuple(
            i
            for i, present in enumerate(
                [True, log.speed_mps is not None, log.pressure_pa is not None]
            )
            if present
        )
        out.append(
            Experiment(
                inputs=Inputs.from_log(log),
                y=jnp.asarray(y),
                sigma=jnp.asarray([sig["height_m"], sig["speed_mps"], sig["pressure_pa"]]),
                signals=signals,
                name=log.name,
            )
        )
    return out


def _solution_residuals(sol, exp: Experiment) -> Float[Array, " M"]:
    keep = np.asarray(exp.signals)
    r = exp.scaled_residuals(sol)[keep].reshape(-1)
    # Only a solver failure is a failure here: a trajectory that leaves [0, x_max] is
    # still a valid (if bad) fit candidate whose residuals carry a useful gradient.
    solved = sol.result == diffrax.RESULTS.successful
    return jnp.where(solved & jnp.all(jnp.isfinite(r)), r, FAILED_RESIDUAL)


def residuals(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    experiments: Sequence[Experiment],
    *,
    adjoint: diffrax.AbstractAdjoint | None = None,
    nudge_gain: Float[Array, ""] | float | None = None,
    **simulate_kwargs,
) -> list[Float[Array, " M"]]:
    """Scaled residuals (model - measured) / sigma, one vector per experiment.

    ``nudge_gain`` [1/s]: simulate each log pulled towards its own measurements
    (:mod:`jaxlift.model.nudging`); None: the model itself."""
    out = []
    for exp in experiments:
        nudging = None
        if nudge_gain is not None:
            speed = exp.y[1] if 1 in exp.signals else None
            nudging = Nudging.of(exp.inputs.ts, exp.y[0], speed, nudge_gain)
        sol = simulate(
            plant, effects, exp.inputs, adjoint=adjoint, nudging=nudging, **simulate_kwargs
        )
        out.append(_solution_residuals(sol, exp))
    return out
