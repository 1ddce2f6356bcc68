"""The result of a fit: parameter values, standard errors, correlations, parameters
the data cannot determine, chi2 per log, and the stages that led there.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pandas as pd

from ..model.build import Model, all_param_infos, with_params
from ..model.params import ParamInfo, from_unconstrained
from .problem import Problem


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

    @property
    def failed_starts(self) -> int:
        """Starts whose simulation failed (dropped: the best of the others is kept)."""
        return sum(not math.isfinite(c) for c in self.start_chi2)


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
        model: the calibrated :class:`~jaxlift.model.build.Model` (plant + effects at
            ``params``), built once here for every later step.
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
    model: Model

    @property
    def converged(self) -> bool:
        """Whether the final stage converged (earlier stages of a staged fit only
        prepare its start; their status is in ``stages``)."""
        return self.stages[-1].converged

    # -- for notebooks ----------------------------------------------------------------

    def table(self):
        """The parameters as a :class:`pandas.DataFrame` indexed by name: ``unit``,
        ``start``, ``value``, ``stderr`` (physical units, AR(1)-inflated; NaN for a
        fixed parameter), ``rel_stderr``, ``free`` and ``determined`` (``"yes"``, the
        reason it is not, or ``"fixed"``)."""
        infos = all_param_infos(self.effects)
        rows = []
        for name, value in self.params.items():
            se = self.stderr.get(name, math.nan)
            free = name in self.free
            rows.append(
                {
                    "parameter": name,
                    "unit": infos[name].unit if name in infos else "",
                    "start": self.initial.get(name, math.nan),
                    "value": value,
                    "stderr": se,
                    "rel_stderr": abs(se / value) if value else math.nan,
                    "free": free,
                    "determined": self.undetermined.get(name, "yes") if free else "fixed",
                }
            )
        return pd.DataFrame(rows).set_index("parameter")

    def _repr_html_(self) -> str:
        head = (
            f"<p><b>Fit</b> of the model with effects {', '.join(self.effects) or 'none'}: "
            f"{'converged' if self.converged else '<b>not converged</b>'}; chi2/N "
            + ", ".join(f"{k} {v:.3g}" for k, v in self.chi2_per_log.items())
            + f" (1 = sensor noise); residual lag-1 autocorrelation {self.rho1:.2f}.</p>"
        )
        return head + self.table().to_html(float_format=lambda x: f"{x:.4g}")


def inside_bounds(info: ParamInfo, v: float) -> float:
    lo, hi = info.lower, info.upper
    span = (hi - lo) if math.isfinite(hi - lo) else max(abs(v), 1.0)
    eps = 1e-6 * span
    if v <= lo:
        v = lo + (info.scale if info.scale and info.scale < 0.1 * span else eps)
    if v >= hi:
        v = hi - eps
    return v


#: relative distance (of the bounds' span) below an upper bound at which a parameter is
#: held there and reported as at the bound: the round trip through a transform must not
#: carry it past the bound (a parameter file with it would then be refused)
UPPER_MARGIN = 1e-9


def at_upper_bound(info: ParamInfo) -> float:
    """Where a parameter pushed past its (finite) upper bound is held."""
    return info.upper - UPPER_MARGIN * (info.upper - info.lower)


def finish(plant0, effs, experiments, free, values, initial, stages, x0_mm, rJ=None) -> FitResult:
    """Standard errors, correlations and the rest of the :class:`FitResult`, from the
    residuals and Jacobian ``rJ`` at the optimum (computed here when not given)."""
    infos = all_param_infos(effs)
    problem = Problem(plant0, effs, tuple(experiments), tuple(free), tuple(infos[n] for n in free))
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
    rho1 = pooled_rho1(r, [e.n_residuals for e in experiments], experiments)
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
        elif math.isfinite(info.upper) and val >= info.upper - 2 * UPPER_MARGIN * (
            info.upper - info.lower
        ):
            undetermined[name] = (
                f"held at its upper bound {info.upper:g} {info.unit} (the data push it "
                "further); its standard error there means nothing"
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
        model=Model(*with_params(plant0, effs, values)),
    )


def pooled_rho1(r, sizes, experiments) -> float:
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
