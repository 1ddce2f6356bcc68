"""``jaxlift posterior`` as a function: prepare (or resume) the posterior problem, run the
sampler to convergence, and write the chain, the ArviZ file, the summary and the report.
"""

from __future__ import annotations

import html
import json
import os
import pathlib
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import pandas as pd
import xarray as xr

from ..model.build import make_effects
from ..model.constants import BETA_OIL
from ..model.log import Log
from ..model.params import save_params_json
from ..posterior.likelihood import cpu_devices
from ..posterior.moves import AbstractMove, LaplaceMove
from ..posterior.predictive import as_list
from ..posterior.problem import SETTINGS_FILE, prepare_posterior, problem_from_settings
from ..posterior.sampler import auto_walkers, sample_posterior
from ..report.posterior import write_outputs
from ._scratch import output_folder

# ------------------------------------------------------------------ whole job


class PosteriorResult(Mapping):
    """What :func:`run_posterior` found: the content of ``posterior.json`` (read it like
    a dict: ``res["converged"]``, ``res["summary"]``, ``res["air"]``, ...), the
    posterior as an ArviZ DataTree (:attr:`datatree`: ``posterior``, ``prior``,
    ``observed_data``, ``posterior_predictive``, ``log_likelihood``; ready for
    ``az.loo``/``az.compare``), the summary as a pandas table (:meth:`table`), and the
    folder it was written to (:attr:`out_dir`: a temporary one, removed with the result,
    when :func:`run_posterior` was given none)."""

    def __init__(self, data: Mapping, out_dir: str | os.PathLike):
        self._data = dict(data)
        self.out_dir = pathlib.Path(out_dir)
        self._tree = None
        self._keeper = None  # the temporary folder of a run without out_dir

    def __getitem__(self, key):
        return self._data[key]

    def __iter__(self):
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    @property
    def datatree(self) -> xr.DataTree:
        """The posterior (``posterior.nc``), loaded into memory on first use."""
        if self._tree is None:
            with xr.open_datatree(self.out_dir / "posterior.nc", engine="h5netcdf") as tree:
                self._tree = tree.load()
        return self._tree

    def table(self) -> pd.DataFrame:
        """Per parameter: mean, sd, 90 % HDI, unit, tau, ESS (pandas)."""
        return pd.DataFrame(self._data["summary"]).set_index("parameter")

    def _repr_html_(self) -> str:
        air = self._data.get("air") or {}
        head = (
            f"<p>{'converged' if self._data.get('converged') else 'NOT converged'} after "
            f"{self._data.get('steps')} steps; effects: "
            f"{', '.join(self._data.get('effects') or []) or 'none'}</p>"
        )
        text = f"<p>{html.escape(air['text'])}</p>" if air.get("text") else ""
        return head + self.table().to_html(float_format=lambda v: f"{v:.4g}") + text


def run_posterior(
    logs: Sequence[Log],
    out_dir: str | os.PathLike | None = None,
    *,
    effects: Sequence[str] | str = (),
    params: Mapping[str, float] | None = None,
    sample: Sequence[str] | str | None = None,
    likelihood: str = "ar1",
    sample_noise: bool = False,
    conditioning: str = "marginal",
    n_walkers: int | str = "auto",
    max_steps: int = 20_000,
    seed: int = 0,
    chunk: int = 50,
    tau_factor: float = 50.0,
    n_predictive: int = 64,
    n_loglik: int = 128,
    beta_oil: float = BETA_OIL,
    batch: str = "map",
    move: AbstractMove | None = None,
    devices: int | None = None,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
) -> PosteriorResult:
    """The whole job behind ``jaxlift posterior``: set up (least squares), sample (or
    resume the chain in ``out_dir``), summarise and report.

    Writes into ``out_dir`` (None: a temporary folder that lives as long as the
    returned result): ``chain.h5`` (emcee), ``posterior_settings.json`` (the
    set-up, compared on resume), ``params.json`` (the calibrated values, as ``jaxlift
    fit`` writes them), ``posterior.nc`` (ArviZ DataTree), ``summary.csv``,
    ``posterior.json``, ``figures/*.png``, ``report.md`` and ``report.html``.

    If ``out_dir`` already has a chain, the run resumes it; the requested settings must
    match the stored ones (else :class:`ValueError`; ``move`` among them: a directory
    from before the choice of move holds a stretch-move chain). ``move`` and
    ``devices``: see :func:`sample_posterior`. ``n_predictive``, ``n_loglik``: draws for
    the prediction bands and for the pointwise log-likelihood in ``posterior.nc``
    (:func:`~jaxlift.report.posterior.write_outputs`). ``conditioning``: ``"marginal"``
    (default: the motor set and the initial-height offsets move with the sampled
    parameters, :func:`~jaxlift.posterior.problem.prepare_posterior`) or
    ``"conditional"`` (held at their least-squares values). ``n_walkers``: the
    ensemble size, or ``"auto"`` (the default since 2026-12-01, 32 before:
    :func:`~jaxlift.posterior.sampler.auto_walkers` of the number of sampled parameters:
    16 for the default five, 20 for the report's eight; the chain's length in steps
    does not depend on it, its number of effective samples does). Returns a
    :class:`PosteriorResult` (the content of ``posterior.json``, read like a dict, and
    the ArviZ DataTree)."""

    say = progress or (lambda _line: None)
    out, keeper = output_folder(out_dir, "posterior")
    out.mkdir(parents=True, exist_ok=True)
    chain = out / "chain.h5"
    settings_path = out / SETTINGS_FILE
    move = LaplaceMove() if move is None else move
    if not isinstance(move, AbstractMove):  # fails here, before the least squares
        raise TypeError(f"move must be a jaxlift move (jaxlift.posterior.moves), not {move!r}")
    if isinstance(n_walkers, str) and n_walkers != "auto":
        raise ValueError(f"n_walkers must be a number or 'auto', not {n_walkers!r}")
    requested = {
        "effects": sorted(e.name for e in make_effects(effects)),
        "sample": None if sample is None else as_list(sample),
        "likelihood": likelihood,
        "sample_noise": bool(sample_noise),
        "conditioning": conditioning,
        "n_walkers": n_walkers if n_walkers == "auto" else int(n_walkers),
        "seed": int(seed),
        "move": move.name,
        "params": None if params is None else {k: float(v) for k, v in params.items()},
    }
    if settings_path.exists():
        with open(settings_path, encoding="utf-8") as fh:
            stored = json.load(fh)
        stored["requested"].setdefault("move", "stretch")  # the only one before
        stored["requested"].setdefault("conditioning", "conditional")  # before issue #17
        diff = {
            k: (stored["requested"].get(k), v)
            for k, v in requested.items()
            if stored["requested"].get(k) != v and not (k == "params" and v is None)
        }
        if diff:
            raise ValueError(
                f"{out} holds a chain run with other settings: "
                + "; ".join(f"{k}: stored {a!r}, requested {b!r}" for k, (a, b) in diff.items())
                + ". Use another --out directory, or the same settings to resume."
            )
        problem = problem_from_settings(stored["problem"], logs)
        if chain.exists():
            say(f"resuming the chain in {chain}")
    else:
        if chain.exists():
            raise ValueError(f"{chain} exists without {settings_path}; remove it or use "
                             "another --out directory")  # fmt: skip
        problem = prepare_posterior(
            logs, effects=effects, params=params, sample=sample, likelihood=likelihood,
            sample_noise=sample_noise, progress=progress, seed=seed, conditioning=conditioning,
        )  # fmt: skip
        with open(settings_path, "w", encoding="utf-8") as fh:
            json.dump({"requested": requested, "problem": problem.settings()}, fh, indent=1)
    save_params_json(
        out / "params.json",
        problem.values,
        comment="calibrated by least squares (jaxlift posterior); effects: "
        + (", ".join(problem.effects) or "none"),
    )
    if n_walkers == "auto":
        n_walkers = auto_walkers(problem.ndim)
    say(
        f"sampling {', '.join(problem.names)} with {n_walkers} walkers (likelihood "
        f"{problem.likelihood}, {move.name} move, on {len(cpu_devices(devices) or (0,))} "
        f"device(s)); until {tau_factor:g} tau or {max_steps} steps"
    )
    run = sample_posterior(
        problem, chain, n_walkers=n_walkers, max_steps=max_steps, seed=seed, chunk=chunk,
        tau_factor=tau_factor, batch=batch, move=move, devices=devices,
        progress=progress_bar,
    )  # fmt: skip
    say(
        f"{run.iteration} steps, max tau {np.max(run.tau):.1f}: "
        + ("converged" if run.converged else "NOT converged")
    )
    data = write_outputs(
        problem, run, logs, out, n_predictive=n_predictive, n_loglik=n_loglik, seed=seed,
        beta_oil=beta_oil,
    )  # fmt: skip
    res = PosteriorResult(data, out)
    res._keeper = keeper  # no out_dir: the temporary folder lives as long as the result
    return res
