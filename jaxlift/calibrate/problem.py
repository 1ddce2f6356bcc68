"""A least-squares problem built once: the experiments, which parameters are free (on
their unconstrained scale), the jitted residuals and forward-mode Jacobian, and the
starting points of a fit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..model.build import with_params
from ..model.effects import AbstractEffect
from ..model.params import ParamInfo, from_unconstrained, to_unconstrained
from ..model.plant import Plant
from .experiment import FAILED_RESIDUAL, Experiment, residuals


# ------------------------------------------------------------------ the problem
@dataclasses.dataclass(frozen=True)
class Problem:
    plant: Plant
    effects: tuple[AbstractEffect, ...]
    experiments: tuple[Experiment, ...]
    free: tuple[str, ...]
    infos: tuple[ParamInfo, ...]
    #: solver step limit of each simulation; the same as :func:`~jaxlift.simulate`'s.
    #: It was 40 000: a breakaway force of 1.7 kN at a Stribeck speed of 3.5 mm/s
    #: takes 102 471 steps on a 132 s log, so every refit that started near the
    #: true size failed at its first evaluation (silently, as a failed start) and
    #: the case ended ``unexplained``. At 200 000 a refit started there stays there
    #: (chi2/N 1.008, 42 s). A limit costs nothing until it is reached; simulations
    #: that need it are slow (stiff stick-slip: ~1.7x longer diagnoses, measured).
    sim_max_steps: int = 200_000
    fit_x0: bool = True
    #: simulate each log pulled towards its measurements with this gain [1/s]
    #: (:mod:`jaxlift.model.nudging`: the stages of a synchronised fit); None: the model
    nudge_gain: float | None = None

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
        return (self.infos, self.fit_x0, self.sim_max_steps, self.nudge_gain is not None)

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
        # the gain is traced, not static: one compilation serves every gain
        gain = jnp.asarray(self.nudge_gain or 0.0, dtype=jnp.float64)
        return (self.plant, self.effects, self.experiments, gain)


def _residual_body(theta, args, spec):
    infos, fit_x0, sim_max_steps, nudged = spec
    plant, effects, experiments, gain = args
    p = len(infos)
    values = {i.name: from_unconstrained(i, theta[k]) for k, i in enumerate(infos)}
    plant, effects = with_params(plant, effects, values)
    if fit_x0:  # initial height of each log: a nuisance parameter, in mm
        experiments = tuple(
            eqx.tree_at(lambda e: e.inputs.x0, exp, exp.inputs.x0 + 1e-3 * theta[p + k])
            for k, exp in enumerate(experiments)
        )
    rs = residuals(
        plant, effects, experiments, adjoint=diffrax.ForwardMode(), max_steps=sim_max_steps,
        nudge_gain=gain if nudged else None,
    )  # fmt: skip
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


def start_points(
    problem: Problem,
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
