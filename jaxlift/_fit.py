"""Least-squares calibration: Levenberg--Marquardt through the simulation.

Residuals are the model minus the measurement of height, speed (and pressure when
the log has it), each divided by its noise level, over every fitted log. Free
parameters are optimised in unconstrained coordinates (:func:`to_unconstrained`),
reported in physical units; each log's initial height is estimated with them. The
Jacobian is forward mode through diffrax (``diffrax.ForwardMode``), jitted once per
problem structure and reused across starts, stages and calls. The default solver is
jaxlift's Levenberg--Marquardt loop (:mod:`jaxlift._lm`: measured 6x fewer
simulations than ``optimistix.LevenbergMarquardt`` here, which stays available as
``method="optimistix"``, with ``vectorize=True`` solving the starts under ``vmap``).
Multi-start: several starting points drawn from a box around the initial guess
(seeded); the best is kept. After convergence the Jacobian gives standard errors and
correlations; because the residuals of real logs are not white, the covariance is
inflated by the AR(1) factor ``(1 + rho1) / (1 - rho1)`` of the residuals (stated in
the result).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from ._effects import AbstractEffect
from ._lm import levenberg_marquardt
from ._log import Log
from ._measurement import MeasurementModel
from ._model import all_param_infos, model_params, with_params
from ._parallel import thread_map
from ._params import ParameterError, ParamInfo, from_unconstrained, to_unconstrained
from ._plant import Plant
from ._simulate import Inputs, simulate, x64_check

__all__ = [
    "PARAMETER_SETS",
    "Experiment",
    "FitResult",
    "resolve_free",
    "make_experiments",
    "residuals",
    "fit",
    "evaluate",
]

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
    motor + dynamic + effects) and/or parameter names (MODEL.md).
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
    """Experiments from logs; noise levels from the measurement model (MODEL.md)."""
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
    **simulate_kwargs,
) -> list[Float[Array, " M"]]:
    """Scaled residuals (model - measured) / sigma, one vector per experiment."""
    out = []
    for exp in experiments:
        sol = simulate(plant, effects, exp.inputs, adjoint=adjoint, **simulate_kwargs)
        out.append(_solution_residuals(sol, exp))
    return out


# ------------------------------------------------------------------ the problem
@dataclasses.dataclass(frozen=True)
class _Problem:
    plant: Plant
    effects: tuple[AbstractEffect, ...]
    experiments: tuple[Experiment, ...]
    free: tuple[str, ...]
    infos: tuple[ParamInfo, ...]
    sim_max_steps: int = 40_000
    fit_x0: bool = True

    @property
    def n_x0(self) -> int:
        """Number of initial-height offsets (one per log) appended to ``theta``."""
        return len(self.experiments) if self.fit_x0 else 0

    def to_theta(self, values: Mapping[str, float], x0_mm=None) -> Float[Array, " P"]:
        th = jnp.stack([to_unconstrained(i, values[i.name]) for i in self.infos])
        x0 = np.zeros(self.n_x0) if x0_mm is None else np.asarray(x0_mm, dtype=float)
        return jnp.concatenate([th, jnp.asarray(x0[: self.n_x0], dtype=jnp.float64)])

    def x0_mm(self, theta) -> np.ndarray:
        return np.asarray(theta)[len(self.infos) :]

    def to_values(self, theta) -> dict[str, Float[Array, ""]]:
        return {i.name: from_unconstrained(i, theta[k]) for k, i in enumerate(self.infos)}

    @property
    def spec(self) -> tuple:
        """The static part of the residual function (hashable: jit caches on it)."""
        return (self.infos, self.fit_x0, self.sim_max_steps)

    def residual_fn(self) -> Callable:
        """``(theta, args) -> r``, for optimistix and the score tests."""
        spec = self.spec
        return lambda theta, args: _residual_body(theta, args, spec)

    def residuals_at(self, theta) -> np.ndarray:
        """Residuals at ``theta`` (one compiled function for every problem of this
        structure, across calls of :func:`fit`); NaN where a simulation failed."""
        r = _residuals_jit(jnp.asarray(theta), self.args, self.spec)
        return self._mark_failures(np.asarray(r))

    def jacobian_at(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Residuals and forward-mode Jacobian (all columns of ``theta``) at ``theta``;
        residuals NaN where a simulation failed."""
        r, J = _jacobian_jit(jnp.asarray(theta), self.args, self.spec)
        return self._mark_failures(np.asarray(r)), np.asarray(J)

    def _mark_failures(self, r: np.ndarray) -> np.ndarray:
        """A failed simulation fills its log's block with exactly FAILED_RESIDUAL (which
        keeps optimistix's iterations finite); for jaxlift's own loop, mark it NaN, so
        that the step is rejected however large the misfit elsewhere."""
        off = 0
        for e in self.experiments:
            block = r[off : off + e.n_residuals]
            if np.all(block == FAILED_RESIDUAL):
                r = r.copy()
                r[off : off + e.n_residuals] = np.nan
            off += e.n_residuals
        return r

    @property
    def args(self):
        return (self.plant, self.effects, self.experiments)


def _residual_body(theta, args, spec):
    infos, fit_x0, sim_max_steps = spec
    plant, effects, experiments = args
    p = len(infos)
    values = {i.name: from_unconstrained(i, theta[k]) for k, i in enumerate(infos)}
    plant, effects = with_params(plant, effects, values)
    if fit_x0:  # initial height of each log: a nuisance parameter, in mm
        experiments = tuple(
            eqx.tree_at(lambda e: e.inputs.x0, exp, exp.inputs.x0 + 1e-3 * theta[p + k])
            for k, exp in enumerate(experiments)
        )
    rs = residuals(
        plant, effects, experiments, adjoint=diffrax.ForwardMode(), max_steps=sim_max_steps
    )
    return jnp.concatenate(rs)


@eqx.filter_jit
def _residuals_jit(theta, args, spec):
    return _residual_body(theta, args, spec)


@eqx.filter_jit
def _jacobian_jit(theta, args, spec):
    def f(th):
        r = _residual_body(th, args, spec)
        return r, r

    J, r = jax.jacfwd(f, has_aux=True)(theta)
    return r, J


def _start_box(info: ParamInfo, value: float) -> tuple[float, float]:
    """A box of plausible starting values around ``value`` (physical units)."""
    f = info.spread
    if value == 0.0 or (info.nesting is not None and value == info.nesting):
        ref = info.scale if info.scale is not None else 1.0
        lo, hi = ref / 10.0, ref * 3.0
    elif value > 0:
        lo, hi = value / f, value * f
    else:
        lo, hi = value * f, value / f
    # keep strictly inside the bounds, by a margin relative to the parameter's range
    # (an absolute margin would empty the box of a parameter whose range is tiny, e.g.
    # a compliance in m^3/Pa)
    eps = 1e-9 * abs(info.upper - info.lower) if math.isfinite(info.upper) else 0.0
    lo = max(lo, info.lower + eps)
    hi = min(hi, info.upper - eps)
    return lo, hi


def _starts(
    problem: _Problem,
    init: Mapping[str, float],
    n: int,
    seed: int,
    x0_mm=None,
    names: Sequence[str] | None = None,
) -> np.ndarray:
    """``n`` starting points (unconstrained): ``init`` first, then a Latin hypercube of the
    start box (log-uniform for one-signed boxes) of the parameters ``names`` (default:
    all of the problem's), the others at ``init``; from ``seed``."""
    theta0 = np.asarray(problem.to_theta(init, x0_mm))
    if n <= 1:
        return theta0[None, :]
    drawn = [i for i in problem.infos if names is None or i.name in names]
    rng = np.random.default_rng(seed)
    p = len(drawn)
    u = (rng.permuted(np.tile(np.arange(n - 1), (p, 1)), axis=1).T + rng.random((n - 1, p))) / (
        n - 1
    )
    pts = [theta0]
    for row in u:
        vals = dict(init)
        for k, info in enumerate(drawn):
            lo, hi = _start_box(info, float(init[info.name]))
            if lo > 0 or hi < 0:
                v = math.copysign(math.exp(math.log(abs(lo)) + row[k] * math.log(hi / lo)), lo)
            else:
                v = lo + row[k] * (hi - lo)
            vals[info.name] = v
        pts.append(np.asarray(problem.to_theta(vals, x0_mm)))
    return np.stack(pts)


@dataclasses.dataclass
class StageResult:
    """One Levenberg--Marquardt stage (one set of free parameters)."""

    free: list[str]
    chi2: float
    converged: bool
    message: str
    num_steps: int
    wall_s: float
    start_chi2: list[float]  # final chi2 of every start (inf: failed)
    best_start: int


@dataclasses.dataclass
class FitResult:
    """A calibrated model and how well each parameter is determined.

    Attributes:
        params: every parameter of the model (plant + effects), physical units.
        initial: the parameters the fit started from.
        free: the names of the fitted parameters.
        effects: names of the switched-on effects.
        chi2: sum of squared scaled residuals at the optimum (fitted logs).
        n_residuals: number of residuals.
        chi2_per_log: ``{log name: chi2 / n}``.
        stderr: ``{name: standard error}`` (physical units), AR(1)-inflated.
        corr: correlation matrix of the free parameters (order of ``free``).
        x0_offsets: ``{log name: offset}`` [m] of each log's initial height from the
            mean over its initial hold, estimated with the parameters (a nuisance
            parameter: 0.5 mm sensor noise over a 2 s hold leaves a ~0.04 mm error that
            the data see and no physical parameter can absorb).
        rho1: lag-1 autocorrelation of the residuals; ``inflation`` = (1+rho1)/(1-rho1).
        undetermined: free parameters the data cannot determine (relative standard
            error > 50 % or singular direction), with the reason.
        stages: per-stage convergence information.
    """

    params: dict[str, float]
    initial: dict[str, float]
    free: list[str]
    effects: list[str]
    chi2: float
    n_residuals: int
    chi2_per_log: dict[str, float]
    stderr: dict[str, float]
    stderr_white: dict[str, float]
    corr: np.ndarray
    x0_offsets: dict[str, float]
    rho1: float
    inflation: float
    undetermined: dict[str, str]
    stages: list[StageResult]

    @property
    def converged(self) -> bool:
        """Whether the final stage converged (earlier stages of a staged fit only
        prepare its start; their status is in ``stages``)."""
        return self.stages[-1].converged

    def model(self) -> tuple[Plant, tuple[AbstractEffect, ...]]:
        """The calibrated plant and effects."""
        from ._simulate import make_effects

        return with_params(Plant(), make_effects(self.effects), self.params)


def _lm_solve(
    problem: _Problem,
    theta_starts: np.ndarray,
    *,
    max_steps: int,
    rtol: float,
    atol: float,
    vectorize: bool,
    progress: bool,
    desc: str = "",
):
    """Levenberg--Marquardt from every start: all at once with ``vmap``
    (``vectorize=True``), or one after the other through one compiled solve.

    On CPU the loop is the faster of the two (measured: a ``vmap`` of 4 diffrax
    solves cost 13x one solve, because the batched adaptive loop runs every member's
    steps for all), so it is the default; ``vmap`` pays off on accelerators."""
    fn = problem.residual_fn()
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)

    def one(theta, args):
        sol = optx.least_squares(fn, solver, theta, args, max_steps=max_steps, throw=False)
        r = fn(sol.value, args)
        return sol.value, sol.result, sol.stats["num_steps"], jnp.sum(r**2)

    if vectorize:
        out = eqx.filter_jit(jax.vmap(one, in_axes=(0, None)))(
            jnp.asarray(theta_starts), problem.args
        )
        value, result, steps, chi2 = out
        return np.asarray(value), np.asarray(result._value), np.asarray(steps), np.asarray(chi2)
    solve = eqx.filter_jit(one)
    outs = []
    bar = tqdm(theta_starts, desc=desc, unit="start", disable=not progress, leave=False)
    for th in bar:
        value, result, steps, chi2 = solve(jnp.asarray(th), problem.args)
        outs.append((np.asarray(value), int(result._value), int(steps), float(chi2)))
        bar.set_postfix(best_chi2=f"{min(o[3] for o in outs):.4g}")
    values = np.stack([o[0] for o in outs])
    return (
        values,
        np.asarray([o[1] for o in outs]),
        np.asarray([o[2] for o in outs]),
        np.asarray([o[3] for o in outs]),
    )


def estimate_x0_offsets(
    params: Mapping[str, float], effects: Sequence[str], logs: Sequence[Log]
) -> dict[str, float]:
    """The initial-height offset [m] of each log under a given model, everything else
    held: the nuisance parameter a fit estimates for its own logs, estimated the same
    way (Levenberg--Marquardt, one column per log) for logs it has not seen.

    Why: a log's first height sample carries the sensor noise (and, with leakage, the
    fork already moves during the first hold); a held-out log simulated from it is
    offset by ~1 sigma throughout, which inflated held-out chi2/N to ~3 with the true
    parameters of a leakage run (measured). The offset is not a prediction of the model,
    so judging a model on held-out logs should not charge it."""
    return _offsets_and_chi2n(params, effects, logs)[0]


def _offsets_and_chi2n(
    params: Mapping[str, float], effects: Sequence[str], logs: Sequence[Log]
) -> tuple[dict[str, float], dict[str, float]]:
    """:func:`estimate_x0_offsets`, and each log's chi2/N (scaled residuals, all its
    signals) at those offsets -- from the same residuals, no second simulation.
    Empty dicts if the model cannot be simulated."""
    from ._simulate import make_effects

    if not logs:
        return {}, {}
    effs = make_effects(effects)
    own = {k: v for k, v in params.items() if k in all_param_infos(effs)}
    plant, effs = with_params(Plant(), effs, own)
    experiments = make_experiments(logs)
    problem = _Problem(plant, effs, tuple(experiments), (), ())
    theta0 = np.zeros(len(experiments))
    run = levenberg_marquardt(problem.residuals_at, problem.jacobian_at, theta0, max_iter=30)
    if not np.isfinite(run.chi2):
        return {}, {}
    ends = np.cumsum([e.n_residuals for e in experiments])
    blocks = np.split(np.asarray(run.r), ends[:-1])
    return (
        {e.name: 1e-3 * float(v) for e, v in zip(experiments, run.theta)},
        {e.name: float(np.mean(b**2)) for e, b in zip(experiments, blocks)},
    )


def fit(
    logs: Sequence[Log] | Sequence[Experiment],
    *,
    effects: Sequence[str] | str = (),
    free: str | Sequence[str] | Sequence[str | Sequence[str]] = "all",
    init: Mapping[str, float] | None = None,
    staged: bool = False,
    n_starts: int = 8,
    seed: int = 0,
    max_steps: int = 100,
    gtol: float = 1e-2,
    method: str = "lm",
    rtol: float = 1e-5,
    atol: float = 1e-5,
    measurement: MeasurementModel | None = None,
    vectorize: bool = False,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Calibrate the model (plant + ``effects``) on ``logs`` by Levenberg--Marquardt.

    Args:
        logs: the fitted logs (or prepared experiments).
        effects: effects switched on (names).
        free: parameters to fit: set names / parameter names (see :func:`resolve_free`).
        init: starting values (physical units) of any parameters; others nominal.
        staged: fit the motor set first, then the dynamic set, then all of ``free``
            (thesis 2.3.2); each stage starts from the previous optimum.
        n_starts: starting points per stage (the first is the current estimate, the
            others a seeded Latin hypercube of a box around it); the best is kept.
            In a staged fit, each stage also starts from where every earlier stage
            ended.
        seed: seed of the starting points.
        max_steps: Levenberg--Marquardt trial steps per start.
        gtol: stopping test of ``method="lm"``: the chi2 decrease a full Gauss--Newton
            step would still bring is below ``gtol`` x chi2 per degree of freedom
            (the remaining step is below ``sqrt(gtol)`` standard errors); see
            :mod:`jaxlift._lm`.
        method: ``"lm"`` (jaxlift's Levenberg--Marquardt loop around the jitted
            residuals and forward-mode Jacobian; default, faster, see ``_lm.py``) or
            ``"optimistix"`` (``optimistix.LevenbergMarquardt``).
        rtol, atol: optimistix's Cauchy termination (``method="optimistix"`` only).
        vectorize: with ``method="optimistix"``, solve the starts together with
            ``vmap`` (pays off on accelerators; on CPU a loop is faster).
        workers: threads running the starts of a stage side by side (``method="lm"``;
            default one per CPU core, see :mod:`jaxlift._parallel`); the result does
            not depend on it.
        progress: called with a line of text after each stage (e.g. ``print``); when
            given, a progress bar over the starts is shown too.

    Returns:
        A :class:`FitResult`. Raises :class:`ParameterError` on bad names.
    """
    x64_check()
    from ._simulate import make_effects

    if method not in ("lm", "optimistix"):
        raise ValueError(f"method must be 'lm' or 'optimistix', not {method!r}")
    if vectorize and method != "optimistix":
        raise ValueError("vectorize=True needs method='optimistix'")
    experiments = (
        list(logs)
        if logs and isinstance(logs[0], Experiment)
        else make_experiments(logs, measurement)
    )
    effs = make_effects(effects)
    plant0, effs = with_params(Plant(), effs, dict(init or {}))
    free_all = resolve_free(free, effs)
    if staged:
        motor = [n for n in PARAMETER_SETS["motor"] if n in free_all]
        dyn = [n for n in PARAMETER_SETS["dynamic"] if n in free_all]
        stage_sets = [s for s in (motor, dyn, free_all) if s]
    else:
        stage_sets = [free_all]

    values = {k: float(v) for k, v in model_params(plant0, effs).items()}
    initial = dict(values)
    infos_all = all_param_infos(effs)
    stages: list[StageResult] = []
    x0_mm = np.zeros(len(experiments))  # initial-height offsets, estimated with the rest
    n_res = sum(e.n_residuals for e in experiments)
    # one problem over all free parameters (one compiled Jacobian); each stage moves
    # its own columns and the initial-height offsets
    problem = _Problem(
        plant0, effs, tuple(experiments), tuple(free_all), tuple(infos_all[n] for n in free_all)
    )
    final = None
    stage_ends: list[np.ndarray] = []
    for k, names in enumerate(stage_sets):
        # keep the starting values strictly inside the bounds (logit/log transforms)
        values.update({n: _inside(infos_all[n], values[n]) for n in names})
        t0 = time.perf_counter()
        desc = f"stage {k + 1}/{len(stage_sets)}"
        if method == "lm":
            starts = _starts(problem, values, n_starts, seed + k, x0_mm, names)
            # also restart from where each earlier stage ended: a stage fitted while
            # the other parameters were still far off can lead into a false minimum
            # (measured: the dynamic stage after the motor stage drove cf_con to 0
            # and d to 5e3; the final stage from there stopped at chi2/N 1.08, from
            # the motor stage's end it reached the optimum, 1.005)
            earlier = [th for th in stage_ends if not np.allclose(th, starts[0])]
            starts = np.concatenate([starts[:1], *[th[None] for th in earlier], starts[1:]])
            active = np.array(
                [free_all.index(n) for n in names]
                + [len(free_all) + j for j in range(problem.n_x0)]
            )
            runs = _lm_starts(problem, starts, active, max_steps, gtol, progress, desc, workers)
            chi2s = np.array([r.chi2 if np.isfinite(r.chi2) else np.inf for r in runs])
            best = int(np.argmin(chi2s))
            run = _escape_log_traps(problem, runs[best], names, free_all, active, max_steps, gtol)
            chi2s[best] = run.chi2
            theta_best, ok, msg = run.theta, run.converged, run.message
            nsteps = run.n_iter
            final = run
        else:
            plant_k, effs_k = with_params(plant0, effs, values)  # the current estimate
            sub = _Problem(
                plant_k,
                effs_k,
                tuple(experiments),
                tuple(names),
                tuple(infos_all[n] for n in names),
            )
            starts = _starts(sub, values, n_starts, seed + k, x0_mm)
            thetas, codes, steps, chi2s = _lm_solve(
                sub,
                starts,
                max_steps=max_steps,
                rtol=rtol,
                atol=atol,
                vectorize=vectorize,
                progress=progress is not None,
                desc=desc,
            )
            chi2s = np.where(np.isfinite(chi2s), chi2s, np.inf)
            best = int(np.argmin(chi2s))
            sub_vals = sub.to_values(thetas[best])
            theta_best = np.asarray(
                problem.to_theta({**values, **sub_vals}, sub.x0_mm(thetas[best]))
            )
            ok = bool(codes[best] == 0)
            msg = "converged" if ok else _lm_message(int(codes[best]))
            nsteps = int(np.asarray(steps)[best])
            final = None
        wall = time.perf_counter() - t0
        for n, v in problem.to_values(theta_best).items():
            values[n] = float(v)
        x0_mm = problem.x0_mm(theta_best)
        stage_ends.append(np.asarray(theta_best))
        stages.append(
            StageResult(
                free=list(names),
                chi2=float(chi2s[best]),
                converged=bool(ok),
                message=msg,
                num_steps=nsteps,
                wall_s=wall,
                start_chi2=[float(c) for c in chi2s],
                best_start=best,
            )
        )
        if progress is not None:
            progress(
                f"{desc} ({len(names)} parameters, {len(starts)} starts): "
                f"chi2/N = {chi2s[best] / n_res:.3g}, {msg}, {nsteps} steps, {wall:.1f} s"
            )

    plant_f, effs_f = with_params(plant0, effs, values)
    rJ = (final.r, final.J) if final is not None else None
    return _finish(plant_f, effs_f, experiments, free_all, values, initial, stages, x0_mm, rJ)


def _escape_log_traps(problem, run, names, free_all, active, max_steps, gtol):
    """Restart the LM from ``run`` with each baseline parameter that it drove to
    (nearly) its lower bound of 0 set back to its nominal value; keep what lowers chi2.

    Why: on a log scale a parameter near 0 is far from everything (Coulomb friction
    at 0.03 N is 6.5 log units from 22 N) and its column of the Jacobian vanishes with
    it, so the LM cannot come back once another parameter has taken over its part
    (measured: leakage + motor inertia hidden, cf_con 0.035 N and d 1224 N s/m instead
    of 22 and 420, chi2/N 1.09 instead of 1.01; the shipped baseline fit's cf_con
    7.5e-6 N). Effects' switch parameters (those with a nesting value) are left alone:
    near 0 they mean "effect absent", which is a legitimate answer."""
    for name in names:
        info = problem.infos[free_all.index(name)]
        if info.nesting is not None or info.transform != "log" or info.lower != 0.0:
            continue
        k = free_all.index(name)
        ref = abs(info.nominal) if info.nominal else (info.scale or 1.0)
        value = float(from_unconstrained(info, run.theta[k]))
        if value > 1e-2 * ref:
            continue
        theta = np.array(run.theta, dtype=np.float64)
        theta[k] = float(to_unconstrained(info, _inside(info, ref)))
        retry = levenberg_marquardt(
            problem.residuals_at, problem.jacobian_at, theta, active,
            max_iter=max_steps, gtol=gtol,
        )  # fmt: skip
        if np.isfinite(retry.chi2) and retry.chi2 < run.chi2:
            run = retry
    return run


def _lm_starts(problem, starts, active, max_steps, gtol, progress, desc, workers=None):
    """jaxlift's Levenberg--Marquardt from every start, one thread per core (the
    compiled residuals and Jacobian are shared by all starts and stages)."""

    def run(th):
        return levenberg_marquardt(
            problem.residuals_at, problem.jacobian_at, th, active, max_iter=max_steps,
            gtol=gtol,
        )  # fmt: skip

    runs = []
    bar = tqdm(total=len(starts), desc=desc, unit="start", disable=progress is None, leave=False)
    for r in thread_map(run, list(starts), workers):
        runs.append(r)
        bar.update()
        bar.set_postfix(best_chi2=f"{min(r.chi2 for r in runs):.4g}")
    bar.close()
    return runs


def _lm_message(code: int) -> str:
    """Text of an optimistix result code."""
    for member in (
        "max_steps_reached",
        "nonlinear_divergence",
        "nonfinite_input",
        "nonlinear_max_steps_reached",
        "singular",
        "breakdown",
        "stagnation",
    ):
        res = getattr(optx.RESULTS, member, None)
        if res is not None and int(res._value) == code:
            return member.replace("_", " ")
    return f"not converged (optimistix result {code})"


def _inside(info: ParamInfo, v: float) -> float:
    lo, hi = info.lower, info.upper
    span = (hi - lo) if math.isfinite(hi - lo) else max(abs(v), 1.0)
    eps = 1e-6 * span
    if v <= lo:
        v = lo + (info.scale if info.scale and info.scale < 0.1 * span else eps)
    if v >= hi:
        v = hi - eps
    return v


def _finish(plant0, effs, experiments, free, values, initial, stages, x0_mm, rJ=None) -> FitResult:
    """Standard errors, correlations and the rest of the :class:`FitResult`, from the
    residuals and Jacobian ``rJ`` at the optimum (computed here when not given)."""
    infos = all_param_infos(effs)
    problem = _Problem(plant0, effs, tuple(experiments), tuple(free), tuple(infos[n] for n in free))
    theta = problem.to_theta(values, x0_mm)
    r, J = problem.jacobian_at(theta) if rJ is None else rJ
    # d(physical)/d(theta), diagonal
    dx = np.array(
        [
            float(jax.grad(from_unconstrained, argnums=1)(info, theta[i]))
            for i, info in enumerate(problem.infos)
        ]
        + [1e-3] * problem.n_x0  # initial-height offsets: theta in mm
    )
    n, p = J.shape
    chi2 = float(r @ r)
    s2 = chi2 / max(n - p, 1)
    rho1 = _pooled_rho1(r, [e.n_residuals for e in experiments], experiments)
    inflation = (1 + rho1) / max(1 - rho1, 1e-3)
    # covariance in the unconstrained coordinates (columns scaled for the SVD), then to
    # physical units by the delta method: cov_x = D cov_theta D, D = dx/dtheta. Working in
    # theta avoids dividing by dx, which vanishes for a parameter driven to its bound.
    J = np.where(np.isfinite(J), J, 0.0)
    # column norms without overflow: a parameter far out on a log/logit transform can
    # have derivatives of 1e160 and more, whose squares are not representable
    big = np.max(np.abs(J), axis=0, initial=0.0)
    big = np.where(big > 0, big, 1.0)
    col = big * np.sqrt(np.sum((J / big) ** 2, axis=0))
    no_info = col <= 1e-12 * max(float(col.max(initial=0.0)), 1e-300)
    col = np.where(no_info, 1.0, col)
    U, S, Vt = np.linalg.svd(J / col, full_matrices=False)
    cutoff = S[0] * 1e-8 if S.size else 0.0
    keep = S > cutoff
    inv_s2 = np.zeros_like(S)
    inv_s2[keep] = (1.0 / S[keep]) ** 2  # S > 1e-8 S[0] > 0 and S[0] ~ 1: no overflow
    cov_theta = ((Vt.T * inv_s2) @ Vt) / np.outer(col, col) * s2
    cov = cov_theta * np.outer(dx, dx)
    se_white = np.sqrt(np.maximum(np.diag(cov), 0.0))
    se = se_white * math.sqrt(inflation)
    d = np.where(se_white > 0, se_white, 1.0)
    q = len(free)  # the physical parameters; the initial-height offsets follow them
    corr = (cov / np.outer(d, d))[:q, :q]
    x0_off = {e.name: 1e-3 * float(v) for e, v in zip(experiments, problem.x0_mm(theta))}
    undetermined = {}
    for k, name in enumerate(free):
        val = values[name]
        info = infos[name]
        ref = abs(info.nominal) or (info.scale or 1.0)
        if no_info[k]:
            undetermined[name] = "the data carry no information on it here"
        elif info.transform == "log" and val - info.lower < 1e-3 * ref:
            undetermined[name] = (
                f"driven to its lower bound {info.lower:g} {info.unit}; its standard "
                "error there means nothing"
            )
        elif S.size and np.any((S <= cutoff) & (np.abs(Vt[:, k]) > 0.3)):
            undetermined[name] = "in a direction the data do not constrain (singular Jacobian)"
        elif val != 0 and se[k] / abs(val) > 0.5:
            undetermined[name] = f"relative standard error {se[k] / abs(val):.0%} > 50 %"
        elif val == 0 and se[k] > 0:
            undetermined[name] = "at zero"
    per_log = {}
    off = 0
    for e in experiments:
        m = e.n_residuals
        per_log[e.name] = float(np.sum(r[off : off + m] ** 2) / m)
        off += m
    return FitResult(
        params=dict(values),
        initial=initial,
        free=list(free),
        effects=[e.name for e in effs],
        chi2=chi2,
        n_residuals=n,
        chi2_per_log=per_log,
        stderr={name: float(se[k]) for k, name in enumerate(free)},
        stderr_white={name: float(se_white[k]) for k, name in enumerate(free)},
        corr=corr,
        x0_offsets=x0_off,
        rho1=rho1,
        inflation=inflation,
        undetermined=undetermined,
        stages=stages,
    )


def _pooled_rho1(r, sizes, experiments) -> float:
    """Lag-1 autocorrelation of the residuals, pooled over logs and signals."""
    num = den = 0.0
    off = 0
    for e, m in zip(experiments, sizes):
        n_sig = len(e.signals)
        block = r[off : off + m].reshape(n_sig, -1)
        off += m
        for row in block:
            row = row - row.mean()
            num += float(row[1:] @ row[:-1])
            den += float(row @ row)
    return float(np.clip(num / den, -0.99, 0.99)) if den > 0 else 0.0


def evaluate(
    plant: Plant, effects: Sequence[AbstractEffect], logs: Sequence[Log], measurement=None
) -> dict[str, float]:
    """chi2 / N of a model on each log (no fitting)."""
    out = {}
    for exp in make_experiments(logs, measurement):
        r = np.asarray(residuals(plant, effects, [exp])[0])
        out[exp.name] = float(r @ r / r.size)
    return out
