"""Bayesian uncertainty of the calibration: an emcee posterior over the bulk modulus and
the friction parameters (and optionally any other named parameters and noise scales).

The statistical model, in one place:

* **Sampled**: ``beta, cf_con, cf_in, cf_out, d`` by default, plus the parameters of the
  switched-on effects; any other MODEL.md parameter on request. Sampling happens in the
  unconstrained coordinates of each :class:`~jaxlift.ParamInfo` (``log``/``logit``); the
  log-density includes the log-Jacobian of that transform, so the posterior is the one
  of the *physical* parameters under the priors below. Results are reported physically.
* **Fixed**: everything else at the least-squares values (the motor set among them), and
  each log's initial-height offset ``x0`` at its least-squares value (a nuisance
  parameter that the data fix to ~0.04 mm and that hardly correlates with the sampled
  ones). The posterior is therefore conditional on the calibrated motor map.
* **Priors** (:data:`DEFAULT_PRIORS`, :func:`default_prior`): explicit, physically
  motivated, wide. ``beta`` log-normal around ideal oil (1.4 GPa, x/÷ 3 at one sigma);
  friction log-normal around the nominal values of MODEL.md (x/÷ 10, ``cf_in`` x/÷ 3);
  effect parameters log-normal around their typical size (``ParamInfo.scale``, x/÷ 10).
  Every prior is truncated to the parameter's bounds.
* **Likelihood**: residuals (model - measured) / sensor noise per log and signal follow
  a zero-mean Gaussian AR(1) process, ``r_t = rho r_{t-1} + e_t``, ``e_t ~ N(0, s^2)``,
  with ``rho`` and ``s`` estimated once from the least-squares residuals of that log and
  signal (``likelihood="ar1"``, the default). On white sensor noise with a correct model
  this is the plain Gaussian likelihood with the sensor noise (``rho ~ 0``, ``s ~ 1``);
  on real logs, whose residuals are autocorrelated and larger than the sensor noise,
  it widens the posterior by about ``sqrt(chi2/N * (1 + rho) / (1 - rho))``, like the
  least-squares standard errors. ``likelihood="white"`` uses independent noise at the
  sensor levels (MODEL.md), which is over-confident on real logs. With
  ``sample_noise=True`` a factor on the noise scale of each signal (height, speed,
  pressure) is sampled too (log-normal prior, median 1, x/÷ 2).

The log-probability is one jitted JAX function of the whole batch of walkers (emcee's
``vectorize=True``); solver failures, trajectories that leave the mast and points
outside the priors' support give ``-inf``, never NaN.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import pathlib
import time
from collections.abc import Callable, Mapping, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._effects import EFFECTS
from ._fit import PARAMETER_SETS, Experiment, fit, make_experiments, resolve_free
from ._log import Log
from ._model import all_param_infos, model_params, with_params
from ._params import ParameterError, ParamInfo, from_unconstrained, to_unconstrained
from ._plant import P_ATM, Plant
from ._simulate import make_effects, simulate, x64_check

__all__ = [
    "BETA_OIL",
    "AIR_THRESHOLD",
    "LogNormal",
    "Uniform",
    "DEFAULT_PRIORS",
    "default_prior",
    "default_sample",
    "PosteriorProblem",
    "prepare_posterior",
    "make_log_prob",
    "SamplerRun",
    "sample_posterior",
    "posterior_samples",
    "air_content",
    "mean_working_pressure",
    "predictive",
    "run_posterior",
    "posterior_draws",
    "MOVES",
]

#: Bulk modulus of ideal (air-free) oil [Pa] (MODEL.md).
BETA_OIL = 1.4e9
#: Gas volume fraction at the mean working pressure above which bleeding the hydraulic
#: system is indicated (0.1 % by volume at working pressure, i.e. ~10 % free gas at
#: atmospheric pressure at 10 MPa: visibly foamy oil).
AIR_THRESHOLD = 1e-3
#: Names of the per-signal noise scale factors (sampled with ``sample_noise=True``).
NOISE_NAMES = ("noise_height", "noise_speed", "noise_pressure")
#: Solver step limit inside the log-probability (a failed solve is -inf).
SIM_MAX_STEPS = 50_000
#: emcee proposals (``move=``), by name: ``"de-snooker"`` (the default) differential
#: evolution (80 %) mixed with the DE snooker move (20 %), emcee's suggested mix;
#: ``"de"`` differential evolution alone; ``"stretch"`` emcee's own default, the
#: affine-invariant stretch move; ``"kde"`` a Gaussian KDE of the complementary half of
#: the ensemble as proposal. All leave the posterior invariant; they differ in how many
#: steps one independent sample takes (the integrated autocorrelation time tau).
#: Measured on the shipped logs (5 parameters, 32 walkers, seed 0, max tau on the first
#: 253 steps of each chain): stretch 28.5, de 16.1, de-snooker 16.3, kde 9.7; stretch
#: reached 58 after 1946 steps, de-snooker about 18 (on a Gaussian with the posterior's
#: covariance: stretch 51-57, de 17, de-snooker 19, kde 7). The KDE proposal is not the
#: default: it is an independence-type proposal that strands a walker the KDE of the
#: others does not cover (seen on the shipped logs from another start: one walker at
#: acceptance 0.01 and tau still growing past 50), and it needs several walkers per
#: dimension (10 dimensions, 32 walkers: acceptance 3 %). See
#: ``benchmarks/results_posterior.txt``.
MOVES = ("de-snooker", "de", "stretch", "kde")
DEFAULT_MOVE = "de-snooker"


# ------------------------------------------------------------------ priors
class LogNormal(eqx.Module):
    """Log-normal prior: ``log(x) ~ Normal(log(median), log(factor))``.

    ``median`` is in the parameter's unit; ``factor`` is the multiplicative one-sigma
    spread (``factor = 3``: 68 % of the prior mass within ``median / 3 … median * 3``).
    Truncated to the parameter's bounds (the normalising constant is irrelevant for
    MCMC). ``reason`` says why this prior."""

    median: float
    factor: float
    reason: str = ""

    def log_pdf(self, x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        """Log-density at ``x`` (physical units), up to a constant; ``-inf`` for x <= 0."""
        s = math.log(self.factor)
        xs = jnp.where(x > 0, x, 1.0)
        z = (jnp.log(xs) - math.log(self.median)) / s
        lp = -0.5 * z**2 - jnp.log(xs) - math.log(s) - 0.5 * math.log(2 * math.pi)
        return jnp.where(x > 0, lp, -jnp.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws (physical units)."""
        return self.median * np.exp(math.log(self.factor) * rng.standard_normal(n))

    def quantiles(self, q: ArrayLike) -> np.ndarray:
        """Quantiles (physical units, untruncated)."""
        from scipy.stats import norm

        return self.median * np.exp(math.log(self.factor) * norm.ppf(np.asarray(q)))

    def describe(self, unit: str = "") -> str:
        return f"log-normal, median {self.median:.4g} {unit}, x/÷ {self.factor:g} (1 sigma)"


class Uniform(eqx.Module):
    """Uniform prior on ``[lower, upper]`` (physical units); ``reason`` says why."""

    lower: float
    upper: float
    reason: str = ""

    def log_pdf(self, x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        inside = (x >= self.lower) & (x <= self.upper)
        return jnp.where(inside, -math.log(self.upper - self.lower), -jnp.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.uniform(self.lower, self.upper, n)

    def quantiles(self, q: ArrayLike) -> np.ndarray:
        return self.lower + (self.upper - self.lower) * np.asarray(q)

    def describe(self, unit: str = "") -> str:
        return f"uniform on [{self.lower:.4g}, {self.upper:.4g}] {unit}"


Prior = LogNormal | Uniform

#: The priors of the dynamic set and of the noise factors (physical units).
DEFAULT_PRIORS: dict[str, Prior] = {
    "beta": LogNormal(
        BETA_OIL, 3.0, "ideal oil (1.4 GPa) as the centre; air, hoses and seals can only "
        "soften it, by up to an order of magnitude in practice: x/÷ 3"
    ),
    "cf_con": LogNormal(10.0, 10.0, "Coulomb friction of the cylinder seals, nominal 10 N; "
                        "a few N to a few hundred N: x/÷ 10"),
    "cf_in": LogNormal(16.0, 3.0, "speed scale of the fifth-power friction, nominal 16 s/m; "
                       "only cf_out * cf_in^5 is seen in the data, so this prior decides "
                       "how the product is split: x/÷ 3"),
    "cf_out": LogNormal(545.0, 10.0, "fifth-power friction coefficient, nominal 545 N: "
                        "x/÷ 10"),
    "d": LogNormal(300.0, 10.0, "viscous damping, nominal 300 N s/m: x/÷ 10"),
    "noise_height": LogNormal(1.0, 2.0, "factor on the height noise scale: x/÷ 2 around 1"),
    "noise_speed": LogNormal(1.0, 2.0, "factor on the speed noise scale: x/÷ 2 around 1"),
    "noise_pressure": LogNormal(1.0, 2.0, "factor on the pressure noise scale: x/÷ 2"),
}  # fmt: skip


def default_prior(info: ParamInfo) -> Prior:
    """The prior of a parameter: :data:`DEFAULT_PRIORS` where listed; an effect parameter
    log-normal around its typical size ``info.scale`` (its nominal is the nesting value
    0) x/÷ 10; another positive parameter log-normal around its nominal x/÷ 2; a
    parameter with two finite bounds and a logit transform uniform on its bounds."""
    if info.name in DEFAULT_PRIORS:
        return DEFAULT_PRIORS[info.name]
    if info.nesting is not None and info.scale is not None and info.nominal == info.nesting:
        return LogNormal(
            float(info.scale), 10.0, f"effect parameter: around its typical size "
            f"{info.scale:g} {info.unit}, x/÷ 10 (the nesting value {info.nesting:g} "
            "is approached, not excluded)"
        )  # fmt: skip
    if info.transform == "log" and info.nominal > 0:
        return LogNormal(float(info.nominal), 2.0, "around the nominal value, x/÷ 2")
    if math.isfinite(info.lower) and math.isfinite(info.upper):
        return Uniform(float(info.lower), float(info.upper), "uniform on the bounds")
    raise ParameterError(f"parameter {info.name!r}: no default prior; give one")


def default_sample(effects: Sequence[str]) -> list[str]:
    """The default sampled parameters: the dynamic set and the effects' parameters."""
    names = list(PARAMETER_SETS["dynamic"])
    for e in make_effects(effects):
        names.extend(n for n in type(e).param_infos() if n not in names)
    return names


def _noise_info(name: str) -> ParamInfo:
    return ParamInfo(name, "-", 1.0, 0.0, 1e3, f"factor on the {name[6:]} noise scale")


def _log_abs_det_jac(info: ParamInfo, theta: Float[Array, ""]) -> Float[Array, ""]:
    """``log |d x / d theta|`` of :func:`from_unconstrained`."""
    if info.transform == "log":
        return theta
    if info.transform == "logit":
        return math.log(info.upper - info.lower) - jax.nn.softplus(-theta) - jax.nn.softplus(theta)
    return jnp.zeros_like(theta)


# ------------------------------------------------------------------ the problem
@dataclasses.dataclass
class PosteriorProblem:
    """Everything the log-probability needs, and how it was set up.

    Attributes:
        names: sampled coordinates, in order (MODEL.md names; ``noise_*`` factors last).
        infos: ``ParamInfo`` of each sampled coordinate (bounds, unit, transform).
        priors: prior of each sampled coordinate (physical units).
        values: the full parameter set at the least-squares optimum (physical units);
            the sampled ones start there, the others stay fixed.
        effects: names of the switched-on effects.
        experiments: the logs, initial heights shifted by ``x0_offsets``.
        x0_offsets: initial-height offset of each log [m] (fixed, least squares).
        rho: lag-1 autocorrelation of the least-squares residuals, ``(n_logs, 3)``
            (height, speed, pressure; 0 where the log lacks the signal or for
            ``likelihood="white"``).
        scale: innovation standard deviation of the AR(1) residual model, in units of
            the sensor noise, ``(n_logs, 3)`` (1 for ``"white"``).
        likelihood: ``"ar1"`` or ``"white"``.
        theta_opt: the optimum in unconstrained coordinates.
        cov_theta: covariance of the least-squares estimate in unconstrained
            coordinates (starts the walkers).
        ls_info: least-squares facts for the report (chi2/N per log, rho1, ...).
    """

    names: tuple[str, ...]
    infos: dict[str, ParamInfo]
    priors: dict[str, Prior]
    values: dict[str, float]
    effects: tuple[str, ...]
    experiments: tuple[Experiment, ...]
    x0_offsets: dict[str, float]
    rho: np.ndarray
    scale: np.ndarray
    likelihood: str
    theta_opt: np.ndarray
    cov_theta: np.ndarray
    ls_info: dict

    @property
    def ndim(self) -> int:
        return len(self.names)

    @property
    def param_names(self) -> list[str]:
        """The sampled physical parameters (without the noise factors)."""
        return [n for n in self.names if n not in NOISE_NAMES]

    def to_physical(self, theta: Float[ArrayLike, "... P"]) -> dict[str, np.ndarray]:
        """Physical values of unconstrained coordinates (any leading shape)."""
        theta = np.asarray(theta)
        return {
            n: np.asarray(from_unconstrained(self.infos[n], theta[..., k]))
            for k, n in enumerate(self.names)
        }

    def settings(self) -> dict:
        """JSON-able description (stored beside the chain; compared on resume)."""
        return {
            "names": list(self.names),
            "effects": list(self.effects),
            "likelihood": self.likelihood,
            "values": self.values,
            "x0_offsets": self.x0_offsets,
            "rho": self.rho.tolist(),
            "scale": self.scale.tolist(),
            "theta_opt": self.theta_opt.tolist(),
            "cov_theta": self.cov_theta.tolist(),
            "logs": [e.name for e in self.experiments],
            "log_hashes": [_exp_hash(e) for e in self.experiments],
            "ls_info": self.ls_info,
            "priors": {n: _prior_to_json(p) for n, p in self.priors.items()},
        }


def _prior_to_json(p: Prior) -> dict:
    d = {"kind": type(p).__name__}
    d.update({f.name: getattr(p, f.name) for f in dataclasses.fields(p)})
    return d


def _prior_from_json(d: Mapping) -> Prior:
    d = dict(d)
    cls = {"LogNormal": LogNormal, "Uniform": Uniform}[d.pop("kind")]
    return cls(**d)


def _exp_hash(e: Experiment) -> str:
    h = hashlib.sha256()
    for a in (e.inputs.ts, e.inputs.pwm, e.inputs.load_kg, e.y):
        h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
    return h.hexdigest()[:16]


def _resolve_sample(sample, effects) -> list[str]:
    """Sampled parameter names: as ``--free`` of the fit (sets and names)."""
    if sample is None:
        return default_sample(effects)
    try:
        return resolve_free(sample, make_effects(effects))
    except ParameterError as err:
        raise ParameterError(str(err).replace("--free:", "--sample:", 1)) from None


def _ar1_stats(r: np.ndarray) -> tuple[float, float]:
    """``rho`` and innovation scale of a zero-mean AR(1) fitted to ``r``."""
    rho = float(np.clip(r[1:] @ r[:-1] / max(float(r[:-1] @ r[:-1]), 1e-300), -0.99, 0.99))
    e = np.concatenate([[r[0] * math.sqrt(1 - rho**2)], r[1:] - rho * r[:-1]])
    return rho, float(np.sqrt(np.mean(e**2)))


def prepare_posterior(
    logs: Sequence[Log],
    *,
    effects: Sequence[str] | str = (),
    params: Mapping[str, float] | None = None,
    sample: Sequence[str] | str | None = None,
    likelihood: str = "ar1",
    sample_noise: bool = False,
    priors: Mapping[str, Prior] | None = None,
    n_starts: int = 2,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> PosteriorProblem:
    """Set up the posterior: least squares first, then the likelihood's noise model.

    Args:
        logs: the logs (CSV data; ``jaxlift.read_log``).
        effects: effects switched on.
        params: calibrated parameter values (e.g. ``params.json`` of ``jaxlift fit``);
            ``None``: a full staged least-squares fit from the nominal values first.
        sample: parameters to sample (names or sets ``dynamic``, ``motor``,
            ``effects``); default the dynamic set plus the effects' parameters.
        likelihood: ``"ar1"`` (default) or ``"white"`` (see the module docstring).
        sample_noise: also sample a noise-scale factor per signal.
        priors: priors overriding :func:`default_prior` (physical units).
        n_starts, seed: multi-start of the full fit (only when ``params`` is None).
        progress: called with a line of text per stage.

    Returns:
        A :class:`PosteriorProblem`. The sampled parameters are re-fitted by least
        squares (with the initial-height offsets) from ``params``: that optimum and its
        covariance start the walkers, its residuals give the AR(1) noise model.
    """
    x64_check()
    if likelihood not in ("ar1", "white"):
        raise ValueError(f"likelihood must be 'ar1' or 'white', not {likelihood!r}")
    effs = make_effects(effects)
    eff_names = tuple(e.name for e in effs)
    infos_all = all_param_infos(effs)
    names = _resolve_sample(sample, eff_names)
    say = progress or (lambda _line: None)
    if params is None:
        say("least squares: full staged fit from the nominal values (no --params given)")
        full = fit(
            logs, effects=eff_names, free="all", staged=True, n_starts=n_starts, seed=seed,
            progress=progress,
        )  # fmt: skip
        params = full.params
    else:
        stray = sorted(set(params) - set(infos_all))
        if stray:
            raise ParameterError(
                f"parameter(s) {stray} belong to effects that are not switched on "
                f"({list(eff_names)}); add them with --effects"
            )
    say(f"least squares: re-fitting the sampled parameters {', '.join(names)}")
    ls = fit(logs, effects=eff_names, free=names, init=params, n_starts=1, progress=progress)
    values = {k: float(v) for k, v in ls.params.items()}
    experiments = tuple(
        eqx.tree_at(lambda e: e.inputs.x0, exp, exp.inputs.x0 + ls.x0_offsets[exp.name])
        for exp in make_experiments(logs)
    )
    # the AR(1) noise model from the least-squares residuals, per log and signal
    plant, effs_v = with_params(Plant(), effs, values)
    rho = np.zeros((len(experiments), 3))
    scale = np.ones((len(experiments), 3))
    chi2n = {}
    for i, exp in enumerate(experiments):
        sol = simulate(plant, effs_v, exp.inputs).check(f"simulating {exp.name}")
        r = np.asarray(exp.scaled_residuals(sol))
        chi2n[exp.name] = {("height", "speed", "pressure")[k]: float(np.mean(r[k] ** 2))
                           for k in exp.signals}  # fmt: skip
        if likelihood == "ar1":
            for k in exp.signals:
                rho[i, k], scale[i, k] = _ar1_stats(r[k])
    all_names = list(names) + (
        [n for k, n in enumerate(NOISE_NAMES) if any(k in e.signals for e in experiments)]
        if sample_noise
        else []
    )
    infos = {n: (infos_all[n] if n in infos_all else _noise_info(n)) for n in all_names}
    pri = {n: (priors or {}).get(n) or default_prior(infos[n]) for n in all_names}
    theta_opt = np.array([float(to_unconstrained(infos[n], values.get(n, 1.0))) for n in all_names])
    ls_info = {
        "chi2_per_signal": chi2n,
        "rho1_pooled": ls.rho1,
        "stderr": ls.stderr,
        "converged": ls.converged,
    }
    problem = PosteriorProblem(
        names=tuple(all_names),
        infos=infos,
        priors=pri,
        values=values,
        effects=eff_names,
        experiments=experiments,
        x0_offsets=dict(ls.x0_offsets),
        rho=rho,
        scale=scale,
        likelihood=likelihood,
        theta_opt=theta_opt,
        cov_theta=np.eye(len(all_names)),
        ls_info=ls_info,
    )
    say("Laplace covariance at the optimum (starts the walkers)")
    problem.cov_theta = _start_covariance(problem)
    return problem


def _start_covariance(problem: PosteriorProblem) -> np.ndarray:
    """A Laplace covariance at the optimum in the unconstrained coordinates: the
    Gauss--Newton information of the likelihood (forward-mode Jacobian of the whitened
    AR(1) innovations through the simulation) plus the priors' curvature. A direction
    the data do not constrain (``cf_in`` against ``cf_out``) so starts at the prior's
    width. The noise factors start with a spread of 2 %."""
    names = problem.names
    phys = [k for k, n in enumerate(names) if n not in NOISE_NAMES]
    infos = [problem.infos[names[k]] for k in phys]
    plant0, effs0 = with_params(Plant(), make_effects(problem.effects), problem.values)
    args = (plant0, effs0, problem.experiments, jnp.asarray(problem.rho),
            jnp.asarray(problem.scale))  # fmt: skip

    def innovations(th, args):
        plant0, effs0, experiments, rho, scale = args
        values = {info.name: from_unconstrained(info, th[j]) for j, info in enumerate(infos)}
        plant, effs = with_params(plant0, effs0, values)
        out = []
        for i, exp in enumerate(experiments):
            sol = simulate(plant, effs, exp.inputs, adjoint=diffrax.ForwardMode())
            r = exp.scaled_residuals(sol)
            for k in exp.signals:
                rr, c = r[k], rho[i, k]
                e = jnp.concatenate([rr[:1] * jnp.sqrt(1 - c**2), rr[1:] - c * rr[:-1]])
                out.append(e / scale[i, k])
        return jnp.concatenate(out)

    th0 = jnp.asarray(problem.theta_opt[phys])
    jac = np.asarray(jax.jit(jax.jacfwd(innovations))(th0, args))
    jac = np.where(np.isfinite(jac), jac, 0.0)
    curv = np.array(
        [1.0 / math.log(p.factor) ** 2 if isinstance(p, LogNormal) else 1e-2
         for p in (problem.priors[n] for n in names)]
    )  # fmt: skip
    h = np.diag(curv)
    h[np.ix_(phys, phys)] += jac.T @ jac
    w, v = np.linalg.eigh(h)
    w = np.maximum(w, 1e-12 * w.max())
    cov = (v / w) @ v.T
    for j, n in enumerate(names):
        if n in NOISE_NAMES:
            cov[j, :] = cov[:, j] = 0.0
            cov[j, j] = 0.02**2
    return 0.5 * (cov + cov.T)


def problem_from_settings(settings: Mapping, logs: Sequence[Log]) -> PosteriorProblem:
    """Rebuild a :class:`PosteriorProblem` from :meth:`PosteriorProblem.settings` and the
    same logs (checked by content hash)."""
    exps = make_experiments(logs)
    hashes = [_exp_hash(e) for e in exps]
    if hashes != list(settings["log_hashes"]) or [e.name for e in exps] != list(settings["logs"]):
        raise ValueError(
            f"the logs {[e.name for e in exps]} are not the ones the stored chain was run on "
            f"({settings['logs']}); use another --out directory"
        )
    off = settings["x0_offsets"]
    exps = tuple(
        eqx.tree_at(lambda e: e.inputs.x0, exp, exp.inputs.x0 + off[exp.name]) for exp in exps
    )
    effs = make_effects(settings["effects"])
    infos_all = all_param_infos(effs)
    names = tuple(settings["names"])
    return PosteriorProblem(
        names=names,
        infos={n: (infos_all[n] if n in infos_all else _noise_info(n)) for n in names},
        priors={n: _prior_from_json(p) for n, p in settings["priors"].items()},
        values=dict(settings["values"]),
        effects=tuple(settings["effects"]),
        experiments=exps,
        x0_offsets=dict(off),
        rho=np.asarray(settings["rho"]),
        scale=np.asarray(settings["scale"]),
        likelihood=settings["likelihood"],
        theta_opt=np.asarray(settings["theta_opt"]),
        cov_theta=np.asarray(settings["cov_theta"]),
        ls_info=dict(settings["ls_info"]),
    )


# ------------------------------------------------------------------ log-probability
def _ar1_loglik(r, rho, s):
    """Exact log-likelihood of a zero-mean stationary Gaussian AR(1) with innovation
    standard deviation ``s``: ``r_0 ~ N(0, s^2 / (1 - rho^2))``, then innovations."""
    n = r.shape[0]
    e = jnp.concatenate([r[:1] * jnp.sqrt(1.0 - rho**2), r[1:] - rho * r[:-1]])
    return (
        -0.5 * jnp.sum(e**2) / s**2
        - n * jnp.log(s)
        + 0.5 * jnp.log(1.0 - rho**2)
        - 0.5 * n * math.log(2 * math.pi)
    )


def _log_prob_args(problem: PosteriorProblem):
    """The arguments of the jitted log-probability (arrays passed, not closed over:
    see STACK-NOTES)."""
    plant0, effs0 = with_params(Plant(), make_effects(problem.effects), problem.values)
    return (
        plant0,
        effs0,
        problem.experiments,
        jnp.asarray(problem.rho),
        jnp.asarray(problem.scale),
        jnp.asarray(problem.theta_opt),
    )


def _prior_key(problem: PosteriorProblem) -> tuple:
    return tuple((n, problem.priors[n]) for n in problem.names)


@functools.lru_cache(maxsize=32)
def _single_fn(names: tuple[str, ...], effects: tuple[str, ...], prior_key: tuple,
               max_steps: int):  # fmt: skip
    """The log-probability of one walker, ``f(theta, args)`` (not jitted); cached by
    configuration so that a resumed run in the same process compiles nothing new."""
    infos_all = all_param_infos(make_effects(effects))
    infos = [infos_all[n] if n in infos_all else _noise_info(n) for n in names]
    priors = [p for _, p in prior_key]
    phys = [k for k, n in enumerate(names) if n not in NOISE_NAMES]
    noise_idx = {NOISE_NAMES.index(n): k for k, n in enumerate(names) if n in NOISE_NAMES}

    def f(theta, args):
        plant0, effs0, experiments, rho, scale, ref = args
        xs = [from_unconstrained(info, theta[k]) for k, info in enumerate(infos)]
        inside = jnp.all(jnp.isfinite(theta))
        log_prior = jnp.zeros(())
        for k, info in enumerate(infos):
            inside = inside & (xs[k] >= info.lower) & (xs[k] <= info.upper)
            log_prior = log_prior + priors[k].log_pdf(xs[k]) + _log_abs_det_jac(info, theta[k])
        inside = inside & jnp.isfinite(log_prior)
        # out of support: simulate at the optimum instead (cheap, then masked to -inf)
        safe = jnp.where(inside, theta, ref)
        values = {names[k]: from_unconstrained(infos[k], safe[k]) for k in phys}
        plant, effs = with_params(plant0, effs0, values)
        fac = [noise_idx.get(j) for j in range(3)]
        fac = [jnp.ones(()) if k is None else from_unconstrained(infos[k], safe[k]) for k in fac]
        ll = jnp.zeros(())
        ok = inside
        for i, exp in enumerate(experiments):
            sol = simulate(plant, effs, exp.inputs, max_steps=max_steps, stability_limit=False)
            r = exp.scaled_residuals(sol)
            ok = ok & (sol.result == diffrax.RESULTS.successful) & sol.in_range
            for k in exp.signals:
                ll = ll + _ar1_loglik(r[k], rho[i, k], scale[i, k] * fac[k])
        lp = log_prior + ll
        ok = ok & jnp.isfinite(lp)
        return jnp.where(ok, lp, -jnp.inf)

    return f


@functools.lru_cache(maxsize=32)
def _batched_fn(names, effects, prior_key, max_steps, batch, devices=None):
    """The jitted batch function ``core(thetas, args)``. With ``devices`` (a tuple of
    several devices) the batch is split evenly across them with ``shard_map``, each
    device running ``batch`` over its share (the batch size must be a multiple of the
    number of devices: :func:`make_log_prob` pads)."""
    single = _single_fn(names, effects, prior_key, max_steps)
    if batch == "vmap":
        inner = jax.vmap(single, in_axes=(0, None))
    elif batch == "map":

        def inner(th, a):
            return jax.lax.map(lambda t: single(t, a), th)

    elif batch == "single":
        one = jax.jit(single)

        def core(th, a):
            return jnp.stack([one(t, a) for t in th])

        return core
    else:
        raise ValueError(f"batch must be 'vmap', 'map' or 'single', not {batch!r}")
    if devices is None or len(devices) < 2:
        return jax.jit(inner)
    from jax.sharding import Mesh, PartitionSpec

    mesh = Mesh(np.asarray(devices), ("walkers",))
    return jax.jit(
        jax.shard_map(
            inner,
            mesh=mesh,
            in_specs=(PartitionSpec("walkers"), PartitionSpec()),
            out_specs=PartitionSpec("walkers"),
            check_vma=False,
        )
    )


def _devices(devices: int | None) -> tuple | None:
    """The devices a batch is split across: the first ``devices`` local devices of
    the default backend (all of them for ``None``); ``None`` for one."""
    avail = jax.local_devices()
    n = len(avail) if devices is None else int(devices)
    if n < 1 or n > len(avail):
        raise ValueError(f"devices must be 1 ... {len(avail)} (local devices), not {devices}")
    return tuple(avail[:n]) if n > 1 else None


def make_log_prob(
    problem: PosteriorProblem,
    *,
    batch: str = "map",
    max_steps: int = SIM_MAX_STEPS,
    devices: int | None = None,
) -> Callable[[Float[ArrayLike, "B P"]], Float[np.ndarray, " B"]]:
    """The log-posterior density (up to a constant) in unconstrained coordinates.

    Args:
        problem: from :func:`prepare_posterior`.
        batch: ``"vmap"``: one jitted ``vmap`` over the batch of walkers; ``"map"``:
            one jitted ``jax.lax.map`` (walkers one after the other inside the compiled
            function); ``"single"``: a jitted function of one walker, called in a Python
            loop (for comparison only).
        max_steps: solver step limit of each simulation.
        devices: split the batch across this many local devices (``"map"`` and
            ``"vmap"``; ``shard_map``, one compiled call). ``None``: all local devices
            of the default backend. On a CPU JAX has one device unless the program
            asked for more before its first JAX operation, e.g.
            ``jax.config.update("jax_num_cpu_devices", 2)`` (what ``jaxlift
            posterior`` does, one per core): each device then runs its share of the
            walkers on its own core. The values do not depend on the split.

    Returns:
        ``f(thetas)`` with ``thetas`` of shape ``(B, P)`` -> ``(B,)`` float64 numpy array
        (``-inf`` for failed solves / outside the prior support, never NaN). The jitted
        core is ``f.jitted(thetas, f.args)`` (its batch a multiple of ``f.n_devices``).
    """
    devs = None if batch == "single" else _devices(devices)
    nd = 1 if devs is None else len(devs)
    key = (problem.names, problem.effects, _prior_key(problem), int(max_steps))
    core = _batched_fn(*key, batch, devs)
    args = _log_prob_args(problem)

    def f(thetas):
        th = np.atleast_2d(np.asarray(thetas, dtype=np.float64))
        m = th.shape[0]
        if m % nd:  # pad to a multiple of the number of devices
            th = np.concatenate([th, np.repeat(th[-1:], nd - m % nd, axis=0)])
        out = np.asarray(core(jnp.asarray(th), args), dtype=np.float64)[:m]
        return np.where(np.isnan(out), -np.inf, out)  # belt and braces: never NaN

    f.jitted = core
    f.args = args
    f.n_devices = nd
    return f


class _EmceeLogProb:
    """emcee's ``vectorize=True`` callable: evaluates in batches of a fixed size (half
    the walkers, as the stretch move asks), so the jitted function compiles once."""

    def __init__(self, f, batch_size: int):
        self.f = f
        self.batch_size = batch_size
        self.n_evals = 0

    def __call__(self, coords):
        coords = np.atleast_2d(np.asarray(coords, dtype=np.float64))
        n, b = coords.shape[0], self.batch_size
        out = []
        for i in range(0, n, b):
            blk = coords[i : i + b]
            m = blk.shape[0]
            if m < b:
                blk = np.concatenate([blk, np.repeat(blk[-1:], b - m, axis=0)])
            out.append(self.f(blk)[:m])
        self.n_evals += n
        return np.concatenate(out)


# ------------------------------------------------------------------ sampling
@dataclasses.dataclass
class SamplerRun:
    """Where an emcee run stands.

    Attributes:
        path: the HDF5 chain.
        iteration: steps in the chain.
        tau: integrated autocorrelation time of each coordinate [steps] (emcee,
            ``tol=0``: an estimate even on a short chain).
        converged: chain longer than ``tau_factor`` x max tau with tau stable.
        resumed_from: steps that were already in the chain when this run began.
        acceptance: mean acceptance fraction.
        wall_s: wall time of this run [s]; n_evals: log-probability evaluations.
        tau_history: ``(iteration, max tau)`` at each check.
        move: the emcee proposal (:data:`MOVES`); n_devices: devices the walkers were
            split across.
    """

    path: str
    iteration: int
    tau: np.ndarray
    converged: bool
    resumed_from: int
    acceptance: float
    wall_s: float
    n_evals: int
    tau_history: list[tuple[int, float]]
    tau_factor: float
    n_walkers: int
    move: str = "stretch"
    n_devices: int = 1


def _initial_coords(problem: PosteriorProblem, n_walkers: int, seed: int, f) -> np.ndarray:
    """Walkers drawn around the least-squares optimum from its covariance (seeded);
    draws with -inf log-probability are redrawn (up to 20 rounds)."""
    rng = np.random.default_rng(seed)
    cov = problem.cov_theta
    coords = rng.multivariate_normal(problem.theta_opt, cov, size=n_walkers, method="eigh")
    for _ in range(20):
        lp = _EmceeLogProb(f, max(n_walkers // 2, 1))(coords)
        bad = ~np.isfinite(lp)
        if not bad.any():
            return coords
        coords[bad] = rng.multivariate_normal(
            problem.theta_opt, 0.25 * cov, size=int(bad.sum()), method="eigh"
        )
    raise ValueError(
        "could not start the walkers: the log-probability is -inf around the least-squares "
        "optimum (solver failures or prior support); check the calibration"
    )


def sample_posterior(
    problem: PosteriorProblem,
    chain_path: str | os.PathLike,
    *,
    n_walkers: int = 32,
    max_steps: int = 20_000,
    seed: int = 0,
    chunk: int = 50,
    tau_factor: float = 50.0,
    batch: str = "map",
    move: str = DEFAULT_MOVE,
    devices: int | None = None,
    log_prob: Callable | None = None,
    progress: bool | Callable[[int], None] = False,
) -> SamplerRun:
    """Run (or resume) emcee's ensemble sampler into an HDF5 file until converged.

    Args:
        problem: from :func:`prepare_posterior`.
        chain_path: HDF5 file (emcee ``HDFBackend``, group ``mcmc``). If it holds steps,
            the run resumes from the last one: emcee stores its random state with every
            step, so an interrupted and resumed run gives the same chain, bit for bit,
            as an uninterrupted one with the same seed.
        n_walkers: ensemble size (even, > 2 x number of sampled coordinates).
        max_steps: step limit (total, including resumed steps); reaching it first
            means "not converged".
        seed: seeds the initial walkers (numpy ``Generator``) and emcee's random state.
        chunk: steps between convergence checks (at absolute multiples of ``chunk``).
        tau_factor: converged when steps > ``tau_factor`` x max tau and every tau
            changed by less than 5 % since the previous check.
        batch: how the log-probability goes over the walkers (:func:`make_log_prob`).
        move: emcee proposal, one of :data:`MOVES` (stored with the chain; a resumed
            chain must use the move it was started with).
        devices: devices the walkers are split across (:func:`make_log_prob`).
        log_prob: a ready :func:`make_log_prob` function (saves a compile).
        progress: show a tqdm progress bar (``True``), or a callable called with the
            iteration after each step (may raise to stop the run).

    Returns:
        A :class:`SamplerRun`.
    """
    import emcee
    from tqdm.auto import tqdm

    ndim = problem.ndim
    if n_walkers < 2 * ndim or n_walkers % 2:
        raise ValueError(f"n_walkers must be even and at least {2 * ndim}, not {n_walkers}")
    moves = _emcee_moves(move)
    f = log_prob or make_log_prob(problem, batch=batch, devices=devices)
    lp_fn = _EmceeLogProb(f, n_walkers // 2)
    backend = emcee.backends.HDFBackend(os.fspath(chain_path), name="mcmc")
    start = backend.iteration if os.path.exists(chain_path) and backend.initialized else 0
    if start > 0:
        with backend.open() as fh:  # chains from before the choice: the stretch move
            stored_move = str(fh["mcmc"].attrs.get("jaxlift_move", "stretch"))
        if stored_move != move:
            raise ValueError(
                f"{chain_path}: the stored chain was run with the {stored_move!r} move, "
                f"this run asks for {move!r}; resume with the same move"
            )
        if backend.shape != (n_walkers, ndim):
            raise ValueError(
                f"{chain_path}: the stored chain has {backend.shape} (walkers, parameters), "
                f"this run asks for {(n_walkers, ndim)}"
            )
        state = backend.get_last_sample()  # coords, log_prob and emcee's random state
        if state.random_state is None:
            raise ValueError(f"{chain_path}: the chain has no stored random state")
    else:
        backend.reset(n_walkers, ndim)
        with backend.open("a") as fh:
            fh["mcmc"].attrs["jaxlift_move"] = move
        coords = _initial_coords(problem, n_walkers, seed, f)
        state = emcee.State(coords, random_state=np.random.RandomState(seed).get_state())
    sampler = emcee.EnsembleSampler(
        n_walkers, ndim, lp_fn, vectorize=True, backend=backend, moves=moves
    )
    it = start
    t0 = time.perf_counter()
    bar = tqdm(total=max_steps, initial=it, desc="MCMC", unit="step", disable=progress is not True)
    tau = np.full(ndim, np.nan)
    tau_prev = None
    history: list[tuple[int, float]] = []
    converged = False
    try:
        if it > 0:
            tau, converged, tau_prev = _check(backend, it, tau_factor, None)
        while it < max_steps and not converged:
            n = min(chunk - it % chunk, max_steps - it)
            for st in sampler.sample(
                state, iterations=n, store=True, skip_initial_state_check=it > 0
            ):
                state = st
                it += 1
                bar.update(1)
                if callable(progress):
                    progress(it)
            tau, converged, tau_prev = _check(backend, it, tau_factor, tau_prev)
            history.append((it, float(np.max(tau))))
            bar.set_postfix(tau=f"{np.max(tau):.0f}", need=f"{tau_factor * np.max(tau):.0f}")
    finally:
        bar.close()
    acc = float(np.mean(backend.accepted / max(backend.iteration, 1)))
    return SamplerRun(
        path=os.fspath(chain_path),
        iteration=it,
        tau=tau,
        converged=converged,
        resumed_from=start,
        acceptance=acc,
        wall_s=time.perf_counter() - t0,
        n_evals=lp_fn.n_evals,
        tau_history=history,
        tau_factor=tau_factor,
        n_walkers=n_walkers,
        move=move,
        n_devices=getattr(f, "n_devices", 1),
    )


def _emcee_moves(move: str):
    """emcee's ``moves`` argument for a name in :data:`MOVES`."""
    import emcee

    if move == "stretch":
        return emcee.moves.StretchMove()
    if move == "de":
        return emcee.moves.DEMove()
    if move == "de-snooker":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if move == "kde":
        return emcee.moves.KDEMove()
    raise ValueError(f"move must be one of {', '.join(MOVES)}, not {move!r}")


def _check(backend, it, tau_factor, tau_prev):
    with np.errstate(invalid="ignore"):  # a walker that has not moved yet: tau NaN
        tau = np.asarray(backend.get_autocorr_time(tol=0), dtype=float)
    stable = tau_prev is not None and bool(np.all(np.abs(tau - tau_prev) < 0.05 * tau))
    converged = bool(np.all(np.isfinite(tau)) and it > tau_factor * np.max(tau) and stable)
    return tau, converged, tau


def chain_status(chain_path: str | os.PathLike, tau_factor: float = 50.0) -> dict:
    """Steps, tau and convergence of a stored chain (read-only)."""
    import emcee

    b = emcee.backends.HDFBackend(os.fspath(chain_path), name="mcmc", read_only=True)
    it = b.iteration
    tau = np.asarray(b.get_autocorr_time(tol=0), dtype=float)
    return {"iteration": it, "tau": tau, "enough": bool(it > tau_factor * np.max(tau))}


def posterior_samples(
    problem: PosteriorProblem,
    chain_path: str | os.PathLike,
    tau: Float[ArrayLike, " P"],
    *,
    burn_factor: float = 3.0,
    thin_factor: float = 0.5,
) -> tuple[dict[str, np.ndarray], np.ndarray, dict]:
    """Physical samples from the stored chain, burn-in discarded and thinned.

    Burn-in: ``burn_factor`` x max tau steps (at most half the chain); thinning every
    ``thin_factor`` x min tau steps. Returns ``({name: (walkers, draws)}, log_prob
    (walkers, draws), {"burn": .., "thin": ..})``."""
    import emcee

    b = emcee.backends.HDFBackend(os.fspath(chain_path), name="mcmc", read_only=True)
    tau = np.asarray(tau, dtype=float)
    it = b.iteration
    burn = int(min(math.ceil(burn_factor * np.nanmax(tau)), it // 2))
    thin = max(1, int(thin_factor * np.nanmin(tau)))
    chain = b.get_chain(discard=burn, thin=thin)  # (draws, walkers, P)
    lp = b.get_log_prob(discard=burn, thin=thin)
    phys = problem.to_physical(np.swapaxes(chain, 0, 1))
    return phys, np.swapaxes(lp, 0, 1), {"burn": burn, "thin": thin}


# ------------------------------------------------------------------ air content
def air_content(
    beta_eff: Float[ArrayLike, "..."], p_mean: float, beta_oil: float = BETA_OIL
) -> Float[np.ndarray, "..."]:
    """Gas volume fraction at pressure ``p_mean`` that explains ``beta_eff`` (MODEL.md).

    ``phi = p_mean * (1 / beta_eff - 1 / beta_oil)``: isothermal free gas, whose
    compliance per volume is ``phi / p``, added to that of ideal oil. ``p_mean`` is the
    absolute pressure [Pa] (the gas law), ``beta_eff`` and ``beta_oil`` in Pa; the result
    is a volume fraction (0.01 = 1 %), negative when the oil is stiffer than
    ``beta_oil``."""
    return p_mean * (1.0 / np.asarray(beta_eff, dtype=float) - 1.0 / beta_oil)


def mean_working_pressure(problem: PosteriorProblem) -> float:
    """Mean absolute pressure [Pa] over the moving parts of the logs (samples with
    ``pwm > 0``), simulated with the calibrated model: gauge line pressure + 1 atm."""
    plant, effs = with_params(Plant(), make_effects(problem.effects), problem.values)
    tot, n = 0.0, 0
    for exp in problem.experiments:
        sol = simulate(plant, effs, exp.inputs).check(f"simulating {exp.name}")
        moving = np.asarray(exp.inputs.pwm) > 0
        p = np.asarray(sol.pressure)[moving]
        tot += float(np.sum(p))
        n += int(p.size)
    return tot / max(n, 1) + P_ATM


def air_verdict(phi_samples: np.ndarray, p_mean: float, has_hose: bool,
                threshold: float = AIR_THRESHOLD, prob: float = 0.9) -> dict:  # fmt: skip
    """The air-content statement for a service engineer: 90 % HDI of the gas fraction
    at the mean working pressure, and whether bleeding is indicated (whole HDI above
    ``threshold``), not indicated (whole HDI below) or undecided."""
    lo, hi = _hdi(phi_samples, prob)
    mean = float(np.mean(phi_samples))
    alpha0_hi = hi * p_mean / P_ATM
    p_mpa = p_mean / 1e6
    if lo > threshold:
        verdict, action = "indicated", "bleeding the system is indicated"
    elif hi < threshold:
        verdict, action = "not indicated", "bleeding the system is not indicated"
    else:
        verdict, action = (
            "undecided",
            (
                "the data cannot decide whether bleeding is needed (the interval straddles "
                f"the {threshold:.1%} threshold)"
            ),
        )
    text = (
        f"Between {max(lo, 0) * 100:.3g} and {max(hi, 0) * 100:.3g} % gas by volume at "
        f"{p_mpa:.1f} MPa (90 % credible interval, attributing all softening to air); "
        f"{action}."
    )
    if lo < 0 < hi or hi <= 0:
        text += " Oil as stiff as ideal oil is within the interval."
    if alpha0_hi > 0.2 and lo > 0:
        text += (
            f" At atmospheric pressure that much gas would be {lo * p_mean / P_ATM:.0%}–"
            f"{alpha0_hi:.0%} of the oil volume — implausible as free air alone; a soft "
            "hose or seal compliance is the likelier cause of most of the softening."
        )
    if has_hose:
        text += (
            " The model includes hose compliance (`C_h`): `beta` is then the oil's own "
            "bulk modulus and the hoses' share of the softening is not counted as air."
        )
    else:
        text += (
            " Hose and seal compliance (not in this model) would soften the system in the "
            "same way; `jaxlift diagnose` distinguishes the two (hose compliance makes the "
            "oscillation frequency vary less with height), and `--effects hose_compliance` "
            "separates them here."
        )
    return {
        "phi_mean": mean,
        "phi_hdi90": [lo, hi],
        "p_mean_pa_abs": p_mean,
        "threshold": threshold,
        "verdict": verdict,
        "text": text,
    }


def _hdi(x: np.ndarray, prob: float = 0.9) -> tuple[float, float]:
    """Shortest interval holding ``prob`` of the samples."""
    x = np.sort(np.asarray(x, dtype=float).ravel())
    n = x.size
    k = max(1, int(math.ceil(prob * n)))
    if k >= n:
        return float(x[0]), float(x[-1])
    w = x[k - 1 :] - x[: n - k + 1]
    i = int(np.argmin(w))
    return float(x[i]), float(x[i + k - 1])


# ------------------------------------------------------------------ predictive
def predictive(
    problem: PosteriorProblem, thetas: Float[ArrayLike, "D P"], batch_size: int = 16
) -> list[dict[str, np.ndarray]]:
    """Simulated height [m] and speed [m/s] of every log for each draw (unconstrained
    coordinates), ``[{"height": (D, N), "speed": (D, N), "ok": (D,)}]`` per log."""
    plant0, effs0 = with_params(Plant(), make_effects(problem.effects), problem.values)
    bs = max(1, min(batch_size, int(np.shape(thetas)[0])))
    fn = _predictive_fn(problem.names, problem.effects, bs)
    res = fn(jnp.asarray(thetas), (plant0, effs0, problem.experiments))
    return [{"height": np.asarray(h), "speed": np.asarray(v), "ok": np.asarray(ok)}
            for h, v, ok in res]  # fmt: skip


@functools.lru_cache(maxsize=16)
def _predictive_fn(names: tuple[str, ...], effects: tuple[str, ...], batch_size: int):
    infos_all = all_param_infos(make_effects(effects))
    infos = [infos_all[n] if n in infos_all else _noise_info(n) for n in names]
    phys = [k for k, n in enumerate(names) if n not in NOISE_NAMES]

    def one(theta, args):
        plant0, effs0, experiments = args
        values = {names[k]: from_unconstrained(infos[k], theta[k]) for k in phys}
        plant, effs = with_params(plant0, effs0, values)
        outs = []
        for exp in experiments:
            sol = simulate(plant, effs, exp.inputs, max_steps=SIM_MAX_STEPS, stability_limit=False)
            outs.append((sol.height, sol.speed, sol.ok))
        return outs

    return jax.jit(lambda th, a: jax.lax.map(lambda t: one(t, a), th, batch_size=batch_size))


# ------------------------------------------------------------------ whole job
SETTINGS_FILE = "posterior_settings.json"


def run_posterior(
    logs: Sequence[Log],
    out_dir: str | os.PathLike,
    *,
    effects: Sequence[str] | str = (),
    params: Mapping[str, float] | None = None,
    sample: Sequence[str] | str | None = None,
    likelihood: str = "ar1",
    sample_noise: bool = False,
    n_walkers: int = 32,
    max_steps: int = 20_000,
    seed: int = 0,
    chunk: int = 50,
    tau_factor: float = 50.0,
    n_predictive: int = 64,
    beta_oil: float = BETA_OIL,
    batch: str = "map",
    move: str = DEFAULT_MOVE,
    devices: int | None = None,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
) -> dict:
    """The whole job behind ``jaxlift posterior``: set up (least squares), sample (or
    resume the chain in ``out_dir``), summarise and report.

    Writes into ``out_dir``: ``chain.h5`` (emcee), ``posterior_settings.json`` (the
    set-up, compared on resume), ``params.json`` (the calibrated values, as ``jaxlift
    fit`` writes them), ``posterior.nc`` (ArviZ DataTree), ``summary.csv``,
    ``posterior.json``, ``figures/*.png``, ``report.md`` and ``report.html``.

    If ``out_dir`` already has a chain, the run resumes it; the requested settings must
    match the stored ones (else :class:`ValueError`; ``move`` among them: a directory
    from before the choice of move holds a stretch-move chain). ``move`` and
    ``devices``: see :func:`sample_posterior`. Returns the content of
    ``posterior.json``."""
    from ._params import save_params_json
    from ._posterior_report import write_outputs

    say = progress or (lambda _line: None)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    chain = out / "chain.h5"
    settings_path = out / SETTINGS_FILE
    _emcee_moves(move)  # a bad name fails here, before the least squares
    requested = {
        "effects": sorted(e.name for e in make_effects(effects)),
        "sample": None if sample is None else _as_list(sample),
        "likelihood": likelihood,
        "sample_noise": bool(sample_noise),
        "n_walkers": int(n_walkers),
        "seed": int(seed),
        "move": move,
        "params": None if params is None else {k: float(v) for k, v in params.items()},
    }
    if settings_path.exists():
        with open(settings_path, encoding="utf-8") as fh:
            stored = json.load(fh)
        stored["requested"].setdefault("move", "stretch")  # the only one before
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
            sample_noise=sample_noise, progress=progress, seed=seed,
        )  # fmt: skip
        with open(settings_path, "w", encoding="utf-8") as fh:
            json.dump({"requested": requested, "problem": problem.settings()}, fh, indent=1)
    save_params_json(
        out / "params.json",
        problem.values,
        comment="calibrated by least squares (jaxlift posterior); effects: "
        + (", ".join(problem.effects) or "none"),
    )
    say(
        f"sampling {', '.join(problem.names)} with {n_walkers} walkers (likelihood "
        f"{problem.likelihood}, {move} move, on {len(_devices(devices) or (0,))} "
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
    return write_outputs(
        problem, run, logs, out, n_predictive=n_predictive, seed=seed, beta_oil=beta_oil
    )


def _as_list(sample) -> list[str]:
    if isinstance(sample, str):
        return [s.strip() for s in sample.split(",") if s.strip()]
    return list(sample)


def posterior_draws(
    out_dir: str | os.PathLike, n: int, seed: int
) -> tuple[list[str], list[dict[str, float]]]:
    """``n`` posterior draws of the full parameter set from a ``jaxlift posterior`` run.

    Args:
        out_dir: the output directory of :func:`run_posterior` / ``jaxlift posterior``.
        n: number of draws (without replacement while the stored draws suffice).
        seed: seed of the selection (numpy ``Generator``).

    Returns:
        ``(effects, draws)``: the names of the switched-on effects, and ``n`` dicts
        ``{name: value}`` with every model parameter (MODEL.md names, physical units):
        the sampled ones from the posterior, the others at their calibrated values.
    """
    import xarray as xr

    out = pathlib.Path(out_dir)
    settings_path = out / SETTINGS_FILE
    nc = out / "posterior.nc"
    for p in (settings_path, nc):
        if not p.exists():
            raise FileNotFoundError(f"{p}: not found; run `jaxlift posterior ... --out {out}`")
    with open(settings_path, encoding="utf-8") as fh:
        settings = json.load(fh)["problem"]
    names = [n for n in settings["names"] if n not in NOISE_NAMES]
    with xr.open_datatree(nc, engine="h5netcdf") as tree:
        post = tree["posterior"].to_dataset()
        flat = {k: np.asarray(post[k]).ravel() for k in names}
    m = next(iter(flat.values())).size
    rng = np.random.default_rng(seed)
    idx = rng.choice(m, size=n, replace=n > m)
    values = {k: float(v) for k, v in settings["values"].items()}
    draws = [{**values, **{k: float(flat[k][i]) for k in names}} for i in idx]
    return list(settings["effects"]), draws


def _model_values(problem: PosteriorProblem) -> dict[str, float]:
    plant, effs = with_params(Plant(), make_effects(problem.effects), problem.values)
    return {k: float(v) for k, v in model_params(plant, effs).items()}


def effect_names() -> list[str]:
    return list(EFFECTS)
