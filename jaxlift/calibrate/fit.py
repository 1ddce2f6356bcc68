"""Least-squares calibration: Levenberg--Marquardt through the simulation.

Residuals are the model minus the measurement of height, speed (and pressure when
the log has it), each divided by its noise level, over every fitted log. Free
parameters are optimised in unconstrained coordinates (:func:`to_unconstrained`),
reported in physical units; each log's initial height is estimated with them. The
Jacobian is forward mode through diffrax (``diffrax.ForwardMode``), jitted once per
problem structure and reused across starts, stages and calls. The default solver is
jaxlift's Levenberg--Marquardt loop (:mod:`jaxlift.calibrate.lm`: measured 6x fewer
simulations than ``optimistix.LevenbergMarquardt`` here, which stays available as
``solver=OptimistixLM()``, with ``vectorize=True`` solving the starts under ``vmap``).
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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from tqdm.auto import tqdm

from ..model.build import all_param_infos, make_effects, model_params, with_params
from ..model.effects import AbstractEffect
from ..model.inputs import Inputs
from ..model.log import Log
from ..model.measurement import MeasurementModel
from ..model.params import ParameterError, from_unconstrained, to_unconstrained
from ..model.plant import Plant
from ..model.simulate import simulate, x64_check
from ..model.solution import Solution
from .experiment import PARAMETER_SETS, Experiment, make_experiments, residuals, resolve_free
from .lm import levenberg_marquardt
from .parallel import thread_map
from .problem import Problem, start_points
from .result import FitResult, StageResult, at_upper_bound, finish, inside_bounds
from .solvers import LM, OptimistixLM


def _lm_solve(
    problem: Problem,
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
    return offsets_and_chi2n(params, effects, logs)[0]


def offsets_and_chi2n(
    params: Mapping[str, float], effects: Sequence[str], logs: Sequence[Log]
) -> tuple[dict[str, float], dict[str, float]]:
    """:func:`estimate_x0_offsets`, and each log's chi2/N (scaled residuals, all its
    signals) at those offsets -- from the same residuals, no second simulation.
    Empty dicts if the model cannot be simulated."""

    run, experiments = _offsets_run(params, effects, logs)
    if run is None:
        return {}, {}
    ends = np.cumsum([e.n_residuals for e in experiments])
    blocks = np.split(np.asarray(run.r), ends[:-1])
    return (
        {e.name: 1e-3 * float(v) for e, v in zip(experiments, run.theta)},
        {e.name: float(np.mean(b**2)) for e, b in zip(experiments, blocks)},
    )


def heldout_residuals(
    params: Mapping[str, float], effects: Sequence[str], logs: Sequence[Log]
) -> tuple[np.ndarray | None, list[int], list[Experiment]]:
    """Scaled residuals of a model on logs it was not fitted to, each at its own
    initial-height offset (:func:`estimate_x0_offsets`): ``(r, sizes, experiments)``,
    ``r`` None if the model cannot be simulated on them."""
    run, experiments = _offsets_run(params, effects, logs)
    sizes = [e.n_residuals for e in experiments]
    return (None if run is None else np.asarray(run.r)), sizes, experiments


def _offsets_run(params, effects, logs):
    """Levenberg--Marquardt over the logs' initial-height offsets alone (the model's
    parameters held); ``(None, experiments)`` if the model cannot be simulated."""
    if not logs:
        return None, []
    effs = make_effects(effects)
    own = {k: v for k, v in params.items() if k in all_param_infos(effs)}
    plant, effs = with_params(Plant(), effs, own)
    experiments = make_experiments(logs)
    problem = Problem(plant, effs, tuple(experiments), (), ())
    theta0 = np.zeros(len(experiments))
    run = levenberg_marquardt(problem.residuals_at, problem.jacobian_at, theta0, max_iter=30)
    return (run if np.isfinite(run.chi2) else None), experiments


def fit_problem(
    experiments: Sequence[Experiment],
    effects: Sequence[str] | str,
    free: str | Sequence[str],
    init: Mapping[str, float] | None = None,
) -> Problem:
    """The least-squares problem :func:`fit` builds: the model with ``effects`` at
    ``init`` (others nominal), the parameters ``free`` (:func:`resolve_free`, in its
    order). The diagnosis's screen builds its candidates' problems here too, so that
    a candidate and its refit share one compiled residual function."""
    effs = make_effects(effects)
    plant, effs = with_params(Plant(), effs, dict(init or {}))
    names = resolve_free(free, effs)
    infos = all_param_infos(effs)
    return Problem(plant, effs, tuple(experiments), tuple(names), tuple(infos[n] for n in names))


def fit(
    logs: Sequence[Log] | Sequence[Experiment],
    *,
    effects: Sequence[str] | str = (),
    free: str | Sequence[str] | Sequence[str | Sequence[str]] = "all",
    init: Mapping[str, float] | None = None,
    x0_offsets: Mapping[str, float] | None = None,
    staged: bool = False,
    n_starts: int = 8,
    seed: int = 0,
    solver: LM | OptimistixLM | None = None,
    measurement: MeasurementModel | None = None,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
    synchronise: Sequence[float] = (),
    starts_from_logs: bool = False,
) -> FitResult:
    """Calibrate the model (plant + ``effects``) on ``logs`` by Levenberg--Marquardt.

    Args:
        logs: the fitted logs (or prepared experiments).
        effects: effects switched on (names).
        free: parameters to fit: set names / parameter names (see :func:`resolve_free`).
        init: starting values (physical units) of any parameters; others nominal.
        x0_offsets: starting values of the logs' initial-height offsets [m], by log
            name (e.g. a previous fit's :attr:`FitResult.x0_offsets`, for a warm
            start); others 0.
        staged: fit the motor set first, then the dynamic set, then all of ``free``
            (thesis 2.3.2); each stage starts from the previous optimum. An effect
            parameter declared with ``stage="motor"`` or ``"dynamic"``
            (:class:`~jaxlift.ParamInfo`; motor droop's ``kappa``) joins that stage.
        n_starts: starting points per stage (the first is the current estimate, the
            others a seeded Latin hypercube of a box around it); the best is kept.
            In a staged fit, each stage also starts from where every earlier stage
            ended.
        seed: seed of the starting points.
        solver: :class:`~jaxlift.calibrate.solvers.LM` (None: ``LM()``, jaxlift's
            Levenberg--Marquardt loop, with its step budget and stopping test) or
            :class:`~jaxlift.calibrate.solvers.OptimistixLM`.
        workers: threads running the starts of a stage side by side (:class:`LM`;
            default one per CPU core, see :mod:`jaxlift.calibrate.parallel`); the result does
            not depend on it.
        progress: called with a line of text after each stage (e.g. ``print``); when
            given, a progress bar over the starts is shown too.
        synchronise: gains [1/s], decreasing (e.g. ``(10, 3, 1, 0.3, 0.1)``): every
            start is first fitted with the simulations pulled towards the measurements
            at each gain in turn (:mod:`jaxlift.model.nudging`), each fit starting where
            the previous one ended, before the ordinary fit from there. For rough
            least-squares surfaces (a strong stick-slip), where a fit of the ordinary
            simulation stagnates far from the optimum. Only with :class:`LM`.
        starts_from_logs: in the last stage, also start from what each of ``effects``
            reads from the logs (:meth:`~jaxlift.AbstractEffect.starts_from_logs`:
            stick-slip's search on its slips' statistics), read at the ends of the two
            stages before it, with their initial-height offsets and with offsets 0
            (several: the surface is rough, and which start reaches the optimum
            varies between logs; docs/statistics.md). A stage of every free
            parameter but the effects' is added before the last: the model without
            effects, where the diagnosis reads its start. What
            ``jaxlift fit`` does. Why: a stick-slip fitted from nominal values
            otherwise ends in another basin of its rough least-squares surface
            (measured in the coverage study: chi2/N 31.9 and 2.0 on logs whose noise
            floor is 1). If every start of the last stage ends above
            :data:`NOISE_FLOOR`, the read starts are fitted again, each after fits
            pulled towards the data at :data:`READ_SYNC_GAINS` (as ``synchronise``
            does; not when ``synchronise`` is given, which already pulls them), and
            the best of all is kept. Needs logs, not experiments; only with
            :class:`LM`.

    Returns:
        A :class:`FitResult`. Raises :class:`ParameterError` on bad names.
    """
    x64_check()

    solver = LM() if solver is None else solver
    if isinstance(solver, LM):
        method, max_steps = "lm", solver.max_steps
    elif isinstance(solver, OptimistixLM):
        method, max_steps = "optimistix", solver.max_steps
        rtol, atol, vectorize = solver.rtol, solver.atol, solver.vectorize
    else:
        raise TypeError(f"solver must be LM() or OptimistixLM(), not {solver!r}")
    synchronise = tuple(float(g) for g in synchronise)
    if starts_from_logs and method != "lm":
        raise ValueError("starts_from_logs: only with jaxlift's own loop; use solver=LM()")
    if starts_from_logs and logs and isinstance(logs[0], Experiment):
        raise ValueError("starts_from_logs: the starts are read from logs; pass Log objects")
    if synchronise and method != "lm":
        raise ValueError("synchronise: the pulled fits run jaxlift's own loop; use solver=LM()")
    if not all(math.isfinite(g) and g >= 0.0 for g in synchronise):
        raise ValueError(f"synchronise: gains [1/s] must be finite and >= 0, got {synchronise}")
    experiments = (
        list(logs)
        if logs and isinstance(logs[0], Experiment)
        else make_experiments(logs, measurement)
    )
    # one problem over all free parameters (one compiled Jacobian); each stage moves
    # its own columns and the initial-height offsets
    problem = fit_problem(experiments, effects, free, init)
    plant0, effs, free_all = problem.plant, problem.effects, list(problem.free)
    infos_all = all_param_infos(effs)
    if staged:
        # each set with the effect parameters that declare it as their stage
        motor, dyn = (
            [n for n in PARAMETER_SETS[k] if n in free_all]
            + [n for n in free_all if infos_all[n].stage == k]
            for k in ("motor", "dynamic")
        )
        stage_sets = [s for s in (motor, dyn, free_all) if s]
    else:
        stage_sets = [free_all]
    if starts_from_logs:
        # the starts are read at a fit of the model without its effects (where the
        # diagnosis reads them): a stage of everything else first, when an effect
        # that reads starts has a free parameter
        if any(_reads_starts(e) and set(e.param_infos()) & set(free_all) for e in effs):
            held = {n for e in effs for n in e.param_infos()}
            rest = [n for n in free_all if n not in held]
            if rest and rest not in stage_sets:
                stage_sets.insert(len(stage_sets) - 1, rest)

    values = {k: float(v) for k, v in model_params(plant0, effs).items()}
    initial = dict(values)
    stages: list[StageResult] = []
    # initial-height offsets [mm], estimated with the rest
    x0_mm = np.array([1e3 * (x0_offsets or {}).get(e.name, 0.0) for e in experiments])
    n_res = sum(e.n_residuals for e in experiments)
    final = None
    stage_ends: list[np.ndarray] = []
    for k, names in enumerate(stage_sets):
        # keep the starting values strictly inside the bounds (logit/log transforms)
        values.update({n: inside_bounds(infos_all[n], values[n]) for n in names})
        t0 = time.perf_counter()
        desc = f"stage {k + 1}/{len(stage_sets)}"
        read: list[np.ndarray] = []  # starts read from the logs (starts_from_logs)
        if method == "lm":
            starts = start_points(problem, values, n_starts, seed + k, x0_mm, names)
            # also restart from where each earlier stage ended: a stage fitted while
            # the other parameters were still far off can lead into a false minimum
            # (measured: the dynamic stage after the motor stage drove cf_con to 0
            # and d to 5e3; the final stage from there stopped at chi2/N 1.08, from
            # the motor stage's end it reached the optimum, 1.005)
            earlier = [th for th in stage_ends if not np.allclose(th, starts[0])]
            starts = np.concatenate([starts[:1], *[th[None] for th in earlier], starts[1:]])
            if starts_from_logs and k == len(stage_sets) - 1:
                points = stage_ends[-2:] or [np.asarray(problem.to_theta(values, x0_mm))]
                read = _log_read_starts(logs, effs, values, points, problem, names)
                starts = np.concatenate([starts, *[th[None] for th in read]])
            active = np.array(
                [free_all.index(n) for n in names]
                + [len(free_all) + j for j in range(problem.n_x0)]
            )
            starts = _synchronised_starts(problem, starts, active, synchronise, solver, progress,
                                          desc, workers)  # fmt: skip
            runs = _lm_starts(problem, starts, active, solver, progress, desc, workers)
            runs, starts, pulled = _refit_read_starts(
                problem, runs, starts, read, active, solver, progress, desc, workers,
                n_res, synchronise,
            )  # fmt: skip
            chi2s = np.array([r.chi2 if np.isfinite(r.chi2) else np.inf for r in runs])
            best = int(np.argmin(chi2s))
            run = _escape_log_traps(problem, runs[best], names, free_all, active, solver)
            run = _hold_at_upper_bounds(problem, run, names, free_all, active, solver)
            chi2s[best] = run.chi2
            theta_best, ok, msg = run.theta, run.converged, run.message
            if run.undetermined:
                labels = [*names, *(f"x0 offset of {e.name}" for e in experiments)]
                msg += "; undetermined: " + "; ".join(
                    describe_direction(v, labels, [infos_all.get(n) for n in labels])
                    for v in run.undetermined
                )
            nsteps = run.n_iter
            final = run
        else:
            plant_k, effs_k = with_params(plant0, effs, values)  # the current estimate
            sub = Problem(
                plant_k,
                effs_k,
                tuple(experiments),
                tuple(names),
                tuple(infos_all[n] for n in names),
            )
            starts = start_points(sub, values, n_starts, seed + k, x0_mm)
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
            over = [n for n in names if sub_vals[n] > infos_all[n].upper]
            if over:  # the log transform does not enforce it; jaxlift's LM does (see there)
                theta_best = np.array(theta_best, dtype=np.float64)
                for n in over:
                    i = free_all.index(n)
                    theta_best[i] = float(
                        to_unconstrained(infos_all[n], at_upper_bound(infos_all[n]))
                    )
                ok = False
                msg += (
                    f"; {', '.join(over)} clipped to the upper bound and not refitted "
                    "(solver=LM() refits the others)"
                )
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
            from_logs = f", {len(read)} read from the logs" if read else ""
            if pulled:
                from_logs += f", {pulled} of them again after fits pulled towards the data"
            progress(
                f"{desc} ({len(names)} parameters, {len(starts)} starts{from_logs}): "
                f"chi2/N = {chi2s[best] / n_res:.3g}, {msg}, {nsteps} steps, {wall:.1f} s"
            )

    plant_f, effs_f = with_params(plant0, effs, values)
    rJ = (final.r, final.J) if final is not None else None
    return finish(plant_f, effs_f, experiments, free_all, values, initial, stages, x0_mm, rJ)


def log_simulator(
    params: Mapping[str, float], effects: Sequence[str], logs: Sequence[Log]
) -> Callable[[Mapping[str, float]], list[Solution] | None]:
    """``run(values)``: the model with ``effects``, at ``params`` updated by ``values``
    (physical units; parameters not given at their nominal values), simulated on each
    of ``logs`` from its first sample; None if a value is out of its bounds or a
    simulation fails. The simulator :meth:`~jaxlift.AbstractEffect.starts_from_logs` gets."""
    effs = make_effects(effects)
    infos = all_param_infos(effs)
    inputs = [Inputs.from_log(lg) for lg in logs]

    def run(values: Mapping[str, float]) -> list[Solution] | None:
        own = {k: v for k, v in {**params, **values}.items() if k in infos}
        try:
            plant, model = with_params(Plant(), effs, own)
        except ParameterError:
            return None
        sols = [simulate(plant, model, inp) for inp in inputs]
        return sols if all(bool(sol.ok) for sol in sols) else None

    return run


def _reads_starts(effect: AbstractEffect) -> bool:
    """Whether the effect's class overrides :meth:`AbstractEffect.starts_from_logs`."""
    own = type(effect).starts_from_logs.__func__
    return own is not AbstractEffect.starts_from_logs.__func__


def _log_read_starts(
    logs: Sequence[Log],
    effs: Sequence[AbstractEffect],
    values: Mapping[str, float],
    points: Sequence[np.ndarray],
    problem: Problem,
    names: Sequence[str],
) -> list[np.ndarray]:
    """The starts (unconstrained, as ``problem`` takes them) that the effects among
    ``effs`` whose parameters are in ``names`` read from ``logs``
    (:meth:`~jaxlift.AbstractEffect.starts_from_logs`; none for most effects), read at
    each of ``points`` (earlier stages' ends; ``values`` for the parameters they do
    not hold). Each start twice: with the point's initial-height offsets and with
    offsets 0, where the search simulated the logs. A value outside its parameter's
    bounds is moved inside.

    Why several: the least-squares surface of a stick-slip is rough, and which of
    these starts the fit reaches the optimum from varies from one pair of logs to the
    next (measured, from nominal values: on the logs of tests/test_slip_starts.py the
    start read at the dynamic stage's end with its offsets reached chi2/N 1.02, the
    one read at the fit without stick-slip with offsets 0 stalled at 3.28; on the
    detection study's case_047 the reverse, 14.6 and 1.09).
    """
    infos = {i.name: i for i in problem.infos}
    wanted = [e for e in effs if _reads_starts(e) and any(n in names for n in e.param_infos())]
    out: list[np.ndarray] = []
    if not wanted:
        return out
    for point in points:
        at = {**values, **{k: float(v) for k, v in problem.to_values(point).items()}}
        run = log_simulator(at, [e.name for e in effs], logs)
        offsets = [problem.x0_mm(point), np.zeros(problem.n_x0)]
        for eff in wanted:
            for guess in type(eff).starts_from_logs(logs, at, run):
                moved = {k: inside_bounds(infos[k], v) for k, v in guess.items() if k in infos}
                for x0 in offsets:
                    theta = np.asarray(problem.to_theta({**at, **moved}, x0))
                    if not any(np.array_equal(theta, th) for th in out):
                        out.append(theta)
    return out


def _escape_log_traps(problem, run, names, free_all, active, solver):
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
        theta[k] = float(to_unconstrained(info, inside_bounds(info, ref)))
        retry = _lm(problem, theta, active, solver)
        if np.isfinite(retry.chi2) and retry.chi2 < run.chi2:
            run = retry
    return run


def _hold_at_upper_bounds(problem, run, names, free_all, active, solver):
    """Hold each parameter that ``run`` drove above its upper bound at that bound and
    refit the others (the active-set step of a bounded least-squares fit).

    Why: a ``"log"`` transform keeps a parameter above its lower bound but not below its
    upper one (see :class:`~jaxlift.model.params.ParamInfo`); measured: a stick-slip fit
    left the Stribeck speed v_s at 12.8 m/s (bound 0.2 m/s), where the breakaway term
    acts as a constant extra Coulomb friction, and wrote a parameter file that every
    other command then refused. The value at the bound is flagged in the result
    (:func:`~jaxlift.calibrate.result.finish`)."""
    theta = np.array(run.theta, dtype=np.float64)
    over = []
    for name in names:
        k = free_all.index(name)
        info = problem.infos[k]
        if float(from_unconstrained(info, theta[k])) > info.upper:
            theta[k] = float(to_unconstrained(info, at_upper_bound(info)))
            over.append(k)
    if not over:
        return run
    keep = np.array([i for i in active if i not in over])
    return _lm(problem, theta, keep, solver)


#: chi2 per degree of freedom up to which a fit counts as at the sensor-noise floor
#: (residuals are scaled by the sensor noise: ~1 when the model fits): there, a fit
#: whose remaining Gauss--Newton decrease lies only along directions the data do not
#: determine has converged (see :mod:`jaxlift.calibrate.lm`).
NOISE_FLOOR = 1.5


def describe_direction(v, labels, infos) -> str:
    """A direction in ``theta`` as a combination of the parameters' transforms, largest
    components first (e.g. ``+0.98 log(cf_in) -0.20 log(cf_out)``)."""
    order = np.argsort(-np.abs(v))
    terms = []
    for k in order[:3]:
        if abs(v[k]) < 0.05:
            break
        info = infos[k]
        t = info.transform if info is not None else "identity"
        name = labels[k] if t == "identity" else f"{t}({labels[k]})"
        terms.append(f"{v[k]:+.2f} {name}")
    return " ".join(terms)


#: Levenberg--Marquardt trial steps at each gain of a synchronised fit: the pulled fits
#: only have to bring the start near the optimum of the next gain (measured on a 1.7 kN
#: stick-slip: 3-15 accepted steps per gain)
SYNC_MAX_STEPS = 30


def _synchronised_starts(problem, starts, active, gains, solver, progress, desc, workers):
    """Each start moved through fits pulled towards the data at ``gains`` in turn
    (``fit(..., synchronise=...)``); a start whose pulled fit fails stays where it was."""
    short = dataclasses.replace(solver, max_steps=SYNC_MAX_STEPS)
    for gain in gains:
        pulled = dataclasses.replace(problem, nudge_gain=float(gain))
        runs = _lm_starts(pulled, starts, active, short, progress,
                          f"{desc}, pulled at {gain:g}/s", workers)  # fmt: skip
        starts = np.stack([r.theta if np.isfinite(r.chi2) else th for r, th in zip(runs, starts)])
    return starts


#: gains [1/s] of the fits pulled towards the data (:mod:`jaxlift.model.nudging`) that
#: the starts read from the logs go through when the last stage of a fit with
#: ``starts_from_logs`` ends above :data:`NOISE_FLOOR` from every start. Why: on the
#: coverage study's case_046 (seed 18: a 37 N stick-slip at 13.7 mm/s, both logs
#: mid-mast) the slip search read a start near the truth (43 N at 12.6 mm/s, its
#: features' cost 3.5 against the truth's 8.6), yet the ordinary fit from it fell into
#: another basin (chi2/N 3.5 and 2.8: the damping d at its lower bound, the Stribeck
#: speed at 0.7 mm/s); pulled at these gains first, the same start reached the optimum,
#: chi2/N 1.06, as the fit from the truth does (docs/statistics.md, *Stages and
#: starting points*). Only then: each pulled fit costs up to SYNC_MAX_STEPS steps per
#: gain, per start.
READ_SYNC_GAINS = (10.0, 3.0, 1.0, 0.3, 0.1)


def _refit_read_starts(
    problem, runs, starts, read, active, solver, progress, desc, workers, n_res, synchronise
):
    """The last stage's ``runs`` from ``starts``, and, if every run ended above
    :data:`NOISE_FLOOR` (chi2 per residual; or failed) and there are starts ``read``
    from the logs that ``synchronise`` has not pulled already, the ordinary fits from
    those read starts after fits pulled towards the data at :data:`READ_SYNC_GAINS`
    appended. Returns ``(runs, starts, number appended)``."""
    chi2 = [r.chi2 for r in runs if np.isfinite(r.chi2)]
    if not read or synchronise or (chi2 and min(chi2) <= NOISE_FLOOR * n_res):
        return runs, starts, 0
    again = _synchronised_starts(problem, np.stack(read), active, READ_SYNC_GAINS, solver,
                                 progress, f"{desc}, read starts", workers)  # fmt: skip
    more = _lm_starts(problem, again, active, solver, progress,
                      f"{desc}, read starts after the pulled fits", workers)  # fmt: skip
    return [*runs, *more], np.concatenate([starts, again]), len(again)


def _lm(problem, theta, active, solver: LM):
    """jaxlift's Levenberg--Marquardt on ``problem`` from ``theta`` over ``active``."""
    return levenberg_marquardt(
        problem.residuals_at, problem.jacobian_at, theta, active, max_iter=solver.max_steps,
        gtol=solver.gtol, noise_floor=NOISE_FLOOR, geodesic_after=solver.geodesic_after,
    )  # fmt: skip


def _lm_starts(problem, starts, active, solver, progress, desc, workers=None):
    """jaxlift's Levenberg--Marquardt from every start, one thread per core (the
    compiled residuals and Jacobian are shared by all starts and stages)."""

    def run(th):
        return _lm(problem, th, active, solver)

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


def evaluate(
    plant: Plant, effects: Sequence[AbstractEffect], logs: Sequence[Log], measurement=None
) -> dict[str, float]:
    """chi2 / N of a model on each log (no fitting)."""
    out = {}
    for exp in make_experiments(logs, measurement):
        r = np.asarray(residuals(plant, effects, [exp])[0])
        out[exp.name] = float(r @ r / r.size)
    return out
