"""What ArviZ needs beside the posterior to weigh models (``az.loo``, ``az.compare``) and
check them (posterior predictive checks): the observed data, posterior-predictive
draws and the pointwise log-likelihood, from the same AR(1) likelihood the sampler uses.

**Pointwise = per block of one second.** The likelihood is AR(1) per log and signal:
its terms are the innovations ``e_t = r_t - rho r_{t-1}`` (independent under the
model), so the log-likelihood splits exactly into a sum over samples. Leaving out one
sample of a 100 Hz log that the model treats as correlated says little, so the
pointwise terms are summed over blocks of ``block_s`` seconds of each log, all its
signals together (leave-one-block-out, the usual choice for time series); a second in
which the motor does not run joins the block before it (:func:`block_starts`). Their
sum over blocks is the sampler's log-likelihood. They form one variable, ``blocks``
(ArviZ's ``loo`` wants one), over a ``block`` dimension that runs through every log:
the same for every model fitted to the same logs, so that ``az.compare`` can line them
up. Observed and predicted signals
are named ``<log>.<signal>`` (e.g. ``lift_500kg.speed``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import xarray as xr
from jaxtyping import ArrayLike, Float
from scipy.signal import lfilter

from ..model.params import from_unconstrained
from .problem import NOISE_NAMES, PosteriorProblem, noise_info

SIGNALS = ("height", "speed", "pressure")
UNITS = ("m", "m/s", "Pa (gauge)")
#: The one log-likelihood variable (``az.loo`` wants one): every block of every log
#: along ``block``, with the coordinates ``block_log``, ``block_start_s``,
#: ``block_end_s`` [s].
LOGLIK_VAR = "blocks"


def block_starts(pwm: np.ndarray, per_block: int) -> np.ndarray:
    """First sample of each block: windows of ``per_block`` samples, each window in
    which the motor never runs (``pwm`` 0 throughout: the fork at rest, often exactly
    where every draw puts it, so that its log-likelihood would be the same for all
    draws and PSIS cannot fit a tail to it) merged into the window before it (the
    first such run into the window after it). Depends on the log only, so every model
    fitted to the log has the same blocks."""
    n = pwm.shape[0]
    windows = np.arange(0, n, per_block)
    moving = [bool(np.any(pwm[a : a + per_block] > 0)) for a in windows]
    keep = [a for a, m in zip(windows, moving) if m]
    if not keep:
        return np.array([0])
    keep[0] = 0  # leading idle windows join the first moving one
    return np.asarray(keep)


def _noise_factors(problem: PosteriorProblem, thetas: np.ndarray) -> np.ndarray:
    """(D, 3) factors on the noise scale of each signal (1 unless they are sampled)."""
    fac = np.ones((thetas.shape[0], 3))
    for k, n in enumerate(problem.names):
        if n in NOISE_NAMES:
            j = NOISE_NAMES.index(n)
            fac[:, j] = [float(from_unconstrained(noise_info(n), t)) for t in thetas[:, k]]
    return fac


def pointwise_groups(
    problem: PosteriorProblem,
    thetas: Float[ArrayLike, "D P"],
    preds: Sequence[dict[str, np.ndarray]],
    *,
    block_s: float = 1.0,
    n_predictive: int = 16,
    seed: int = 0,
) -> dict[str, xr.Dataset]:
    """The ``observed_data``, ``posterior_predictive`` and ``log_likelihood`` groups
    (:class:`xarray.Dataset`) from ``D`` draws (unconstrained ``thetas``) and their
    simulations ``preds`` (:func:`~jaxlift.posterior.predictive.predictive`; draws whose
    simulation failed must be left out beforehand).

    observed_data: each log's measured signals [m, m/s, Pa] over ``time.<log>``;
    posterior_predictive: the first ``n_predictive`` draws' simulations plus AR(1)
    noise of the fitted scale and correlation (seeded), in physical units, one chain;
    log_likelihood: one chain of ``D`` draws of the AR(1) log-likelihood summed over
    blocks of about ``block_s`` seconds (:data:`LOGLIK_VAR`, coordinates
    ``block_log``, ``block_start_s``, ``block_end_s``)."""
    thetas = np.asarray(thetas, dtype=float)
    fac = _noise_factors(problem, thetas)
    rng = np.random.default_rng(seed)
    observed, ppc = {}, {}
    coords = {}
    blocks, block_log, block_start, block_end = [], [], [], []
    for i, (exp, pr) in enumerate(zip(problem.experiments, preds, strict=True)):
        y = np.asarray(exp.y)
        sigma = np.asarray(exp.sigma)
        ts = np.asarray(exp.inputs.ts)
        n = y.shape[1]
        dt = float(ts[1] - ts[0]) if n > 1 else 1.0
        starts = block_starts(np.asarray(exp.inputs.pwm), max(1, int(round(block_s / dt))))
        tdim = f"time.{exp.name}"
        coords[tdim] = ts
        log_blocks = np.zeros((thetas.shape[0], len(starts)))
        for k in exp.signals:
            name = f"{exp.name}.{SIGNALS[k]}"
            model = np.asarray(pr[SIGNALS[k]])  # (D, N)
            rho = float(problem.rho[i, k])
            s = float(problem.scale[i, k]) * fac[:, k]  # (D,)
            r = (model - y[k]) / sigma[k]
            e = np.concatenate(
                [r[:, :1] * math.sqrt(1 - rho**2), r[:, 1:] - rho * r[:, :-1]], axis=1
            )
            terms = -0.5 * (e / s[:, None]) ** 2 - np.log(s)[:, None] - 0.5 * math.log(2 * math.pi)
            terms[:, 0] += 0.5 * math.log(1 - rho**2)
            log_blocks += np.add.reduceat(terms, starts, axis=1)
            observed[name] = ((tdim,), y[k], {"units": UNITS[k]})
            m = min(n_predictive, model.shape[0])
            innov = rng.standard_normal((m, n)) * s[:m, None]
            innov[:, 0] /= math.sqrt(1 - rho**2)  # stationary start
            noise = lfilter([1.0], [1.0, -rho], innov, axis=1)  # AR(1), scaled units
            ppc[name] = (("chain", "draw", tdim), (model[:m] + sigma[k] * noise)[None],
                         {"units": UNITS[k]})  # fmt: skip
        blocks.append(log_blocks)
        block_log += [exp.name] * len(starts)
        block_start.append(ts[starts])
        block_end.append(ts[np.append(starts[1:], n) - 1])

    def ds(variables):
        used = {d for v in variables.values() for d in v[0]}
        return xr.Dataset(variables, coords={d: c for d, c in coords.items() if d in used})

    loglik = xr.Dataset(
        {LOGLIK_VAR: (("chain", "draw", "block"), np.concatenate(blocks, axis=1)[None])},
        coords={
            "block_log": ("block", np.asarray(block_log, dtype=str)),
            "block_start_s": ("block", np.concatenate(block_start)),
            "block_end_s": ("block", np.concatenate(block_end)),
        },
    )
    return {
        "observed_data": ds(observed),
        "posterior_predictive": ds(ppc),
        "log_likelihood": loglik,
    }
