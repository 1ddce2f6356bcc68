"""Whole jobs behind the command line (and the notebooks): fit-and-report.

Each job writes into one output directory: ``params.json`` (docs/model.md names),
``metrics.json`` (machine-readable), ``figures/*.png`` and ``report.md`` +
``report.html``.
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import numpy as np
import xarray as xr

from ..calibrate.fit import estimate_x0_offsets, fit
from ..calibrate.result import FitResult
from ..model.build import all_param_infos, make_effects, with_params
from ..model.inputs import Inputs
from ..model.log import Log
from ..model.measurement import MeasurementModel
from ..model.plant import Plant
from ..model.simulate import simulate
from ..model.solution import SimulationError
from ..report.document import json_safe
from ..report.fit import fit_report


def simulate_logs(
    params: Mapping[str, float],
    effects: Sequence[str],
    logs: Sequence[Log],
    x0_offsets: Mapping[str, float] | None = None,
    failures: dict[str, str] | None = None,
) -> list[dict[str, np.ndarray] | None]:
    """Simulate every log's input with the given model; arrays at the log's times.
    ``x0_offsets`` [m] shift the initial height of the named logs (a fit's estimates).
    Raises :class:`~jaxlift.SimulationError` if a simulation fails, unless a dict
    ``failures`` is given: then a failed log's entry is ``None`` and the reason is
    stored under the log's name (a report goes on without that log)."""
    effs = make_effects(effects)
    own = {k: v for k, v in params.items() if k in all_param_infos(effs)}
    plant, effs = with_params(Plant(), effs, own)
    out = []
    for log in logs:
        inputs = Inputs.from_log(log)
        off = (x0_offsets or {}).get(log.name, 0.0)
        inputs = eqx.tree_at(lambda i: i.x0, inputs, inputs.x0 + off)
        sol = simulate(plant, effs, inputs)
        try:
            sol.check(f"simulating {log.path or log.name}")
        except SimulationError as err:
            if failures is None:
                raise
            failures[log.name] = str(err)
            out.append(None)
            continue
        out.append(
            {
                "height": np.asarray(sol.height),
                "speed": np.asarray(sol.speed),
                "pressure": np.asarray(sol.pressure),
            }
        )
    return out


def model_vs_measurement(result: FitResult, logs: Sequence[Log]) -> xr.Dataset:
    """Model against measurement on ``logs`` (fitted or held out), as an
    :class:`xarray.Dataset` over one ``sample`` dimension with the coordinates ``log``
    (name) and ``time_s`` [s]: ``height_m`` [m], ``speed_mps`` [m/s] and
    ``pressure_pa`` [Pa, gauge] as measured (NaN where a log has no such column) and
    ``*_model`` as simulated with the fit's parameters (the fitted logs' initial-height
    offsets from the fit; other logs' estimated under the fitted model). One log:
    ``ds.where(ds.log == name, drop=True)``; per log: ``ds.groupby("log")``.
    Raises :class:`~jaxlift.SimulationError` if a simulation fails."""
    logs = list(logs)
    others = [lg for lg in logs if lg.name not in result.x0_offsets]
    offsets = {**estimate_x0_offsets(result.params, result.effects, others), **result.x0_offsets}
    sims = simulate_logs(result.params, result.effects, logs, offsets)
    cols: dict[str, list] = {"log": [], "time_s": []}
    for lg, sim in zip(logs, sims, strict=True):
        cols["log"].append(np.full(lg.n, lg.name))
        cols["time_s"].append(np.asarray(lg.time_s))
        for col, key in (("height_m", "height"), ("speed_mps", "speed"),
                         ("pressure_pa", "pressure")):  # fmt: skip
            meas = getattr(lg, col)
            cols.setdefault(col, []).append(
                np.full(lg.n, np.nan) if meas is None else np.asarray(meas, float)
            )
            cols.setdefault(col + "_model", []).append(np.asarray(sim[key], float))
    units = {"height_m": "m", "speed_mps": "m/s", "pressure_pa": "Pa (gauge)"}
    data = {
        k: ("sample", np.concatenate(v), {"units": units[k.removesuffix("_model")]})
        for k, v in cols.items()
        if k not in ("log", "time_s")
    }
    coords = {
        "log": ("sample", np.concatenate(cols["log"])),
        "time_s": ("sample", np.concatenate(cols["time_s"]), {"units": "s"}),
    }
    return xr.Dataset(data, coords=coords, attrs={"effects": ", ".join(result.effects)})


def chi2n(log: Log, sim: dict[str, np.ndarray]) -> float:

    s = MeasurementModel().sigmas(log.sample_period)
    parts = [((sim["height"] - log.height_m) / s["height_m"]) ** 2]
    if log.speed_mps is not None:
        parts.append(((sim["speed"] - log.speed_mps) / s["speed_mps"]) ** 2)
    if log.pressure_pa is not None:
        parts.append(((sim["pressure"] - log.pressure_pa) / s["pressure_pa"]) ** 2)
    return float(np.mean(np.concatenate(parts)))


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def _log_metrics(log: Log, sim: dict[str, np.ndarray] | None, failed: str | None = None):
    if sim is None:
        return {"failed": failed}
    m = {
        "chi2_per_sample": chi2n(log, sim),
        "rms_height_mm": _rms(sim["height"] - log.height_m) * 1e3,
    }
    if log.speed_mps is not None:
        m["rms_speed_mmps"] = _rms(sim["speed"] - log.speed_mps) * 1e3
    if log.pressure_pa is not None:
        m["rms_pressure_MPa"] = _rms(sim["pressure"] - log.pressure_pa) / 1e6
    return m


#: chi2/N of a fitted log above which the fit's end is called out: 1.5 times what the
#: sensor noise explains (the detection study's "baseline misfit" threshold).
MISFIT_HINT_CHI2N = 1.5


def misfit_hint(chi2_per_log: Mapping[str, float], undetermined: Mapping[str, str]) -> str | None:
    """A line for the user when a fit converged but some fitted log stays well above the
    sensor-noise floor (chi2/N >= :data:`MISFIT_HINT_CHI2N`): the model lacks an effect,
    or the fit ended in a false minimum (a parameter at one of its bounds points there).
    ``None`` when every fitted log is below the threshold."""
    high = {k: v for k, v in chi2_per_log.items() if v >= MISFIT_HINT_CHI2N}
    if not high:
        return None
    logs = ", ".join(f"{k} {v:.3g}" for k, v in high.items())
    line = (
        f"misfit above the sensor noise (chi2/N >= {MISFIT_HINT_CHI2N:g}: {logs}): the model"
        " lacks an effect (`jaxlift diagnose` tests the candidates) or the fit ended in a"
        " false minimum"
    )
    bound = [k for k, why in undetermined.items() if "bound" in why]
    if bound:
        line += (
            f"; {', '.join(bound)} at a bound points to the second: try more starts"
            " (--starts 8) or a start from an earlier calibration (--params)"
        )
    return line


def run_fit(
    fit_logs: Sequence[Log],
    validate_logs: Sequence[Log] = (),
    *,
    effects: Sequence[str] = (),
    free: str | Sequence[str] = "all",
    init: Mapping[str, float] | None = None,
    staged: bool = True,
    n_starts: int = 4,
    seed: int = 0,
    out_dir: str | pathlib.Path | None = None,
    progress: Callable[[str], None] | None = None,
    starts_from_logs: bool = True,
) -> tuple[FitResult, dict]:
    """Fit, compare before/after on fitted and held-out logs, and (if ``out_dir``)
    write params.json, metrics.json, figures and the report. Returns the fit and the
    metrics dictionary. ``starts_from_logs``: the last stage also starts from what the
    effects read from the logs (:func:`~jaxlift.fit`; stick-slip's slip statistics)."""
    result = fit(
        fit_logs,
        effects=effects,
        free=free,
        init=init,
        staged=staged,
        n_starts=n_starts,
        seed=seed,
        progress=progress,
        starts_from_logs=starts_from_logs,
    )
    metrics = {
        "effects": result.effects,
        "free": result.free,
        "converged": result.converged,
        "chi2": result.chi2,
        "n_residuals": result.n_residuals,
        "residual_lag1_autocorrelation": result.rho1,
        "stderr_inflation": result.inflation,
        "params": result.params,
        "stderr": result.stderr,
        "correlation": {
            "names": result.free,
            "matrix": [[json_safe(c) for c in row] for row in np.asarray(result.corr)],
        },
        "undetermined": result.undetermined,
        "stages": [
            {
                "free": s.free,
                "chi2": s.chi2,
                "converged": s.converged,
                "message": s.message,
                "num_steps": s.num_steps,
                "wall_s": s.wall_s,
                "start_chi2": s.start_chi2,
                "failed_starts": s.failed_starts,
            }
            for s in result.stages
        ],
        "logs": {},
    }
    # a log the model cannot simulate (the nominal start, or a held-out log under the
    # fitted model) is reported as failed, not a crash, and left out of the figures
    failed_before: dict[str, str] = {}
    failed_after: dict[str, str] = {}
    before_all = simulate_logs(
        result.initial, result.effects, [*fit_logs, *validate_logs], failures=failed_before
    )
    # held-out logs: their initial-height offsets estimated under the fitted model
    # (a nuisance, as for the fitted logs; see estimate_x0_offsets)
    offsets = {
        **estimate_x0_offsets(result.params, result.effects, validate_logs),
        **result.x0_offsets,
    }
    after_all = simulate_logs(
        result.params, result.effects, [*fit_logs, *validate_logs], offsets, failed_after
    )
    for i, log in enumerate([*fit_logs, *validate_logs]):
        role = "fitted" if i < len(fit_logs) else "held_out"
        metrics["logs"][log.name] = {
            "role": role,
            "before": _log_metrics(log, before_all[i], failed_before.get(log.name)),
            "after": _log_metrics(log, after_all[i], failed_after.get(log.name)),
        }
    if out_dir is not None:
        shown = [
            i for i in range(len(fit_logs) + len(validate_logs))
            if before_all[i] is not None and after_all[i] is not None
        ]  # fmt: skip
        fit_report(
            result,
            metrics,
            [fit_logs[i] for i in shown if i < len(fit_logs)],
            [validate_logs[i - len(fit_logs)] for i in shown if i >= len(fit_logs)],
            [before_all[i] for i in shown],
            [after_all[i] for i in shown],
            out_dir,
        )
    return result, metrics
