"""Parameter draws for robust tuning and its evaluation: from a posterior directory or
from a fit's covariance, as batches of plants and effects.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ..calibrate.parallel import cpu_cores, thread_map
from ..model.build import all_param_infos, with_params
from ..model.effects import EFFECTS, AbstractEffect
from ..model.params import ParameterError, from_unconstrained, load_params_json, to_unconstrained
from ..model.plant import Plant
from ..model.vector_field import (
    canonical_effects,
)
from ..posterior.predictive import posterior_draws
from .controller import AbstractController
from .cost import closed_loop_costs, stack_references
from .performance import (
    CostWeights,
    Figures,
)
from .reference import Reference


# ------------------------------------------------------------------ parameter draws
@dataclasses.dataclass
class DrawSet:
    """Parameter draws of the plant (+ effects).

    Attributes:
        source: where they came from (posterior, or least-squares covariance), as text.
        effects: effect names of the model.
        draws: one ``{name: value}`` per draw (physical units, docs/model.md names).
    """

    source: str
    effects: list[str]
    draws: list[dict[str, float]]

    def split(self, n_first: int) -> tuple[DrawSet, DrawSet]:
        """The first ``n_first`` draws and the rest (e.g. tuning / held-out)."""
        return (
            DrawSet(self.source, self.effects, self.draws[:n_first]),
            DrawSet(self.source, self.effects, self.draws[n_first:]),
        )


#: Stated spreads (standard deviation of the log of the parameter) used when there is
#: neither a posterior nor a fit's covariance -- a hand-written parameter file, or the
#: nominal model: what a calibration of this lift typically leaves uncertain (bulk
#: modulus +-20 %, friction and damping +-30 %, the fifth-power speed scale +-5 % as it
#: enters to the fifth power), and +-30 % on the size of every effect switched on.
STATED_SPREADS: dict[str, float] = {
    "beta": 0.2, "cf_con": 0.3, "cf_in": 0.05, "cf_out": 0.3, "d": 0.3,
}  # fmt: skip
EFFECT_SPREAD = 0.3


def stated_spread_draws(
    n: int, seed: int, values: Mapping[str, float], effects: Sequence[str], why: str
) -> DrawSet:
    """``n`` draws around ``values`` with :data:`STATED_SPREADS` (log-normal, clipped to
    the bounds); every parameter of the switched-on ``effects`` that is not at its
    nesting value with :data:`EFFECT_SPREAD`. ``why``: why no posterior or fit was used."""
    infos = all_param_infos(list(effects))
    spreads = {k: s for k, s in STATED_SPREADS.items() if k in values}
    for e in effects:
        for k, info in EFFECTS[e].param_infos().items():
            if k in values and values[k] > 0 and values[k] != info.nesting:
                spreads[k] = EFFECT_SPREAD
    rng = np.random.default_rng(seed)
    names = sorted(spreads)
    z = rng.standard_normal((n, len(names)))
    draws = []
    for row in z:
        d = {k: float(v) for k, v in values.items()}
        for j, k in enumerate(names):
            x = float(values[k]) * math.exp(spreads[k] * row[j])
            d[k] = float(np.clip(x, infos[k].lower, infos[k].upper))
        draws.append(d)
    text = ", ".join(f"{k} x/÷ {math.exp(s):.2f}" for k, s in sorted(spreads.items()))
    return DrawSet(f"stated spreads ({why}): log-normal, {text}", list(effects), draws)


def parameter_draws(
    n: int,
    seed: int,
    *,
    posterior_dir: str | os.PathLike | None = None,
    fit_dir: str | os.PathLike | None = None,
    values: Mapping[str, float] | None = None,
    effects: Sequence[str] = (),
) -> DrawSet:
    """``n`` draws of the model parameters from ``seed``.

    From the posterior (``jaxlift.posterior.predictive.posterior_draws(posterior_dir, n, seed)``)
    when ``posterior_dir`` is given and that works; else from the least-squares fit in
    ``fit_dir`` (``params.json`` and ``metrics.json``: standard errors and, where
    present, the correlation matrix; independent otherwise): a Gaussian in the
    unconstrained coordinate of each parameter (log/logit, delta method), except for a
    parameter whose standard error is large against its distance to the bound (>
    half of it), which is drawn in physical units and clipped to its bounds. Unfitted
    parameters are fixed. Without either (no posterior, no ``fit_dir``, or a parameter
    file without the fit's ``metrics.json``, e.g. a hand-written one), from
    :data:`STATED_SPREADS` around ``values`` (the model's parameters; ``effects``
    switched on), or around the parameter file's values. ``source`` says which was
    used."""
    notes = []
    if posterior_dir is not None:
        try:
            eff, draws = posterior_draws(posterior_dir, n, seed)
            return DrawSet(f"posterior samples from {posterior_dir}", list(eff), list(draws))
        except (ImportError, FileNotFoundError, OSError, ValueError) as err:
            notes.append(f"posterior in {posterior_dir} not usable ({err})")
    infos = all_param_infos("all")
    if fit_dir is None:
        if values is None:
            raise ParameterError(
                "no parameter draws: give a posterior directory, a fit directory "
                "(params.json + metrics.json from `jaxlift fit`) or the model's values"
            )
        why = "; ".join([*notes, "no posterior and no fit covariance"])
        return stated_spread_draws(n, seed, values, effects, why)
    fit_dir = os.fspath(fit_dir)
    ppath = os.path.join(fit_dir, "params.json")
    if not os.path.exists(ppath):  # a parameter file not written by `jaxlift fit`
        if values is None:
            raise ParameterError(
                f"no parameter draws: {ppath} not found, and no model values given"
            )
        why = "; ".join([*notes, f"{ppath} not found: no fit covariance"])
        return stated_spread_draws(n, seed, values, effects, why)
    file_values = load_params_json(ppath, infos)
    mpath = os.path.join(fit_dir, "metrics.json")
    try:
        with open(mpath, encoding="utf-8") as fh:
            metrics = json.load(fh)
    except FileNotFoundError:
        base = dict(values) if values is not None else file_values
        why = "; ".join([*notes, f"{mpath} not found: no fit covariance"])
        return stated_spread_draws(n, seed, base, effects, why)
    values = file_values
    se = {k: float(v) for k, v in (metrics.get("stderr") or {}).items() if v is not None}
    se = {k: v for k, v in se.items() if k in values and math.isfinite(v) and v > 0}
    names = sorted(se)
    corr = np.eye(len(names))
    if "correlation" in metrics:
        cn = metrics["correlation"]["names"]
        cm = np.asarray(metrics["correlation"]["matrix"], dtype=float)
        idx = {k: i for i, k in enumerate(cn)}
        for a, na in enumerate(names):
            for b, nb in enumerate(names):
                if na in idx and nb in idx:
                    corr[a, b] = cm[idx[na], idx[nb]]
    else:
        notes.append("metrics.json has no correlation matrix: parameters drawn independently")
    mean, sd, logspace = [], [], []
    for k in names:
        info, v = infos[k], values[k]
        theta = float(to_unconstrained(info, v))
        eps = 1e-6 * max(abs(v), 1e-12)
        slope = (
            float(to_unconstrained(info, v + eps)) - float(to_unconstrained(info, v - eps))
        ) / (2 * eps)
        dist = min(v - info.lower, info.upper - v)
        use_log = info.transform != "identity" and se[k] < 0.5 * dist and math.isfinite(slope)
        logspace.append(use_log)
        mean.append(theta if use_log else v)
        sd.append(se[k] * abs(slope) if use_log else se[k])
    cov = np.outer(sd, sd) * corr
    cov = 0.5 * (cov + cov.T) + 1e-12 * np.diag(np.square(sd))
    rng = np.random.default_rng(seed)
    z = rng.multivariate_normal(np.asarray(mean), cov, size=n, method="eigh")
    draws = []
    for row in z:
        d = dict(values)
        for j, k in enumerate(names):
            info = infos[k]
            x = float(from_unconstrained(info, row[j])) if logspace[j] else float(row[j])
            d[k] = float(np.clip(x, info.lower, info.upper))
        draws.append(d)
    effects = [e for e in metrics.get("effects", []) or []]
    if not effects:
        effects = [n_ for n_, c in EFFECTS.items() if set(c.param_infos()) & set(values)]
    notes.insert(0, f"least-squares covariance of the fit in {fit_dir} (no posterior)")
    return DrawSet("; ".join(notes), list(effects), draws)


def batch_models(
    plant: Plant, effects: Sequence[AbstractEffect], draws: Sequence[Mapping[str, float]]
) -> tuple[Plant, tuple[AbstractEffect, ...]]:
    """Stack ``(plant, effects)`` with each draw's values (names the model does not
    have, e.g. effect parameters when the effects are off, are ignored)."""
    effects = canonical_effects(effects)
    known = set(all_param_infos(effects))
    models = [
        with_params(plant, effects, {k: v for k, v in d.items() if k in known}) for d in draws
    ]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *models)


#: :func:`closed_loop_costs` compiled once per model structure, run configuration and
#: batch shape, so that the gain sets of a robustness report share one compilation
#: (called uncompiled, ``lax.map`` traced and compiled its body again for every gain
#: set: 55 of the 240 s of the README's report's robustness section, 2026-11-29).
_compiled_costs = eqx.filter_jit(closed_loop_costs)


def evaluate_draws(
    controller: AbstractController,
    plants: Plant,
    effects: tuple[AbstractEffect, ...],
    reference: Reference,
    *,
    weights: CostWeights | None = None,
    noise_seeds: ArrayLike | None = None,
    workers: int | None = None,
    **sim_kw,
) -> tuple[np.ndarray, np.ndarray, Figures]:
    """Costs, success flags and figures of one controller over stacked draws (leading
    axis ``B`` of ``plants``/``effects``) on one reference: arrays of length ``B``.

    ``noise_seeds``: see :func:`closed_loop_costs` (``(1,)``, or ``(B, 1)`` with a
    noise realisation per draw). The draws run one after the other (``lax.map``; a
    single ODE solve uses one core) in ``workers`` chunks side by side on threads
    (default: one per core; :mod:`jaxlift.calibrate.parallel`). Every chunk has the
    same size -- the last is padded with copies of the last draw, whose results are
    dropped -- so there is one compiled shape, and each draw's result does not depend
    on ``workers`` (tested). ``sim_kw`` go to :func:`simulate_closed_loop`."""
    refs = stack_references([reference])
    n = int(jax.tree.leaves(plants)[0].shape[0])
    seeds = None if noise_seeds is None else np.asarray(noise_seeds)
    k = max(1, min(n, cpu_cores() if workers is None else int(workers)))
    size = -(-n // k)

    def chunk(i: int):
        idx = np.minimum(np.arange(i * size, (i + 1) * size), n - 1)
        p, e = jax.tree.map(lambda a: a[idx], (plants, effects))
        s = seeds[idx] if seeds is not None and seeds.ndim == 2 else seeds
        out = _compiled_costs(
            controller, p, e, refs, batched_plants=True, weights=weights,
            noise_seeds=s, **sim_kw,
        )  # fmt: skip
        return jax.tree.map(lambda a: np.asarray(a[:, 0]), out)

    parts = list(thread_map(chunk, range(k), workers=k))
    return jax.tree.map(lambda *xs: np.concatenate(xs)[:n], *parts)
