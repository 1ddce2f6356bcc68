"""Levenberg--Marquardt driver for the calibration (host-side loop, jitted model calls).

Why not only ``optimistix.LevenbergMarquardt``: measured on the baseline fit of two
130 s logs (``benchmarks/bench_fit.py``), optimistix took 91 iterations where
SciPy's trust-region solver needed 11 Jacobians, and every optimistix iteration
linearises the simulation at the trial point (a forward-mode Jacobian, ~12x the cost
of the residuals alone) even when the step is then rejected. Its Cauchy termination
also waits for the step *and* every residual to stop changing, which the integrator's
own noise (adaptive steps change with the parameters) delays by tens of rejected
steps after the optimum has been reached. This driver

- evaluates only the residuals at a trial point and the Jacobian only where a step
  was accepted;
- damps isotropically in ``theta`` (Levenberg; ``theta`` are logs and logits, so this
  bounds relative changes; Marquardt's ``diag(JᵀJ)`` scaling is an option, measured
  worse on the rough chi2 surface of stick-slip) and updates the damping by Nielsen's
  rule (1999);
- stops on a statistical criterion: the decrease of chi2 that a full Gauss--Newton
  step would still bring, ``gᵀ (JᵀJ)⁺ g``, is below ``gtol · s²`` (``s²`` = chi2 per
  degree of freedom). The remaining step is then below ``sqrt(gtol)`` standard
  errors in every direction, well inside the parameters' uncertainty;
- when the damping stalls (no damped step lowers chi2, because every such step is
  mostly along well-determined directions, where the integrator's noise swamps the
  decrease), tries the undamped Gauss--Newton step along the directions the data
  determine, with a short line search, before it gives up;
- once a fit has taken ``geodesic_after`` trial steps without converging, takes
  geodesically accelerated steps (Transtrum and Sethna, 2012: "Improvements to
  the Levenberg--Marquardt algorithm for nonlinear least-squares minimization",
  arXiv:1201.5885; GSL's ``lmaccel``): the damped step ``v`` plus half the
  acceleration ``a`` that keeps the step on the curved valley of chi2, ``a`` from the
  residuals' second directional derivative along ``v`` (one extra residual evaluation
  per trial, a finite difference), the step rejected when ``2 |a| / |v| > 0.75``.
  Without it the fit crawls along such valleys: measured on the two logs of
  ``tests/test_unexplained.py`` (a quadratic drag hidden, none of the candidates), the
  baseline fit continued from its end crawled from chi2/N 2.0970 to 2.0764 in 100 trial
  steps (93 accepted, each with ``rho`` 0.3--0.5, the Gauss--Newton decrease still 0.023
  per sample), every confirmation refit the same way; with the acceleration the same
  continuation converged in 41 trials at chi2/N 2.0564 (Gauss--Newton decrease 2e-9).
  Not from the first step: where the plain steps converge, the accelerated ones take
  more of them, each with the extra evaluation (measured on the shipped logs' baseline
  fit, same optimum: 15, 38 and 40 steps in the three stages, 76 s, against 15, 30 and
  25 steps, 49 s, both beside the same other job); that fit converges within 40 trials
  in every stage, so with the switch it is the plain one to the last digit;
- does not let directions the data do not determine defeat that rule: when the
  iterations run out (or no step lowers chi2) with the fit at the noise floor
  (``s² <= noise_floor``, for residuals scaled by their noise as the fit's are) and
  the remaining Gauss--Newton decrease lies only along *undetermined* directions (a
  standard error above ``se_max`` in ``theta``: more than ~50 % of the parameter
  combination, e.g. the ``cf_in``/``cf_out`` ridge of the fifth-power friction law),
  the fit has converged; the result names those directions
  (:attr:`LMResult.undetermined`) instead of reporting an iteration limit.

``fit(..., solver=OptimistixLM())`` still runs optimistix's solver (and
``OptimistixLM(vectorize=True)`` its ``vmap`` over starting points).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

#: Largest ``2 |a| / |v|`` (acceleration against velocity) of an accepted geodesically
#: accelerated step (Transtrum and Sethna's alpha; GSL's ``avmax``, default 0.75).
ACCEL_MAX = 0.75


@dataclasses.dataclass
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes:
        theta: final parameters (all of them; only ``active`` ones were moved).
        chi2: sum of squared residuals at ``theta``.
        r, J: residuals and Jacobian at ``theta``.
        converged: the statistical stopping test was met.
        message: why it stopped.
        n_iter: accepted steps; ``n_eval``: residual evaluations at trial points;
        n_jac: Jacobian evaluations.
        gn_decrease: ``gᵀ (JᵀJ)⁺ g`` at ``theta`` (chi2 units).
        undetermined: directions (unit vectors over the ``active`` parameters, in
            ``theta``) that the data do not determine and along which the remaining
            Gauss--Newton decrease lies, when convergence was declared on them.
    """

    theta: np.ndarray
    chi2: float
    r: np.ndarray
    J: np.ndarray
    converged: bool
    message: str
    n_iter: int
    n_eval: int
    n_jac: int
    gn_decrease: float
    undetermined: list[np.ndarray] = dataclasses.field(default_factory=list)


def _eigen_split(
    A: np.ndarray, g: np.ndarray, d: np.ndarray, s2: float, se_max: float
) -> tuple[float, list[np.ndarray], np.ndarray]:
    """The Gauss--Newton decrease along the directions the data determine, the
    directions they do not (``theta`` units; standard error above ``se_max``), and the
    Gauss--Newton step along the determined ones only (scaled coordinates)."""
    try:
        w, V = np.linalg.eigh(A)
    except np.linalg.LinAlgError:
        return np.inf, [], np.zeros_like(g)
    keep = w > max(float(w.max(initial=0.0)), 1e-300) * 1e-12
    proj = V.T @ g
    determined, loose, step = 0.0, [], np.zeros_like(g)
    for k in np.nonzero(keep)[0]:
        direction = V[:, k] / d  # a unit move along V_k in scaled coordinates, in theta
        se = np.sqrt(s2 / w[k]) * np.linalg.norm(direction)
        if se > se_max:
            loose.append(direction / np.linalg.norm(direction))
        else:
            determined += proj[k] ** 2 / w[k]
            step -= V[:, k] * (proj[k] / w[k])
    return float(determined), loose, step


def _gn_decrease(A: np.ndarray, g: np.ndarray) -> float:
    """``gᵀ A⁺ g`` with a relative eigenvalue cut-off (``A`` scaled to unit diagonal)."""
    try:
        w, V = np.linalg.eigh(A)
    except np.linalg.LinAlgError:
        return np.inf
    keep = w > max(float(w.max(initial=0.0)), 1e-300) * 1e-12
    proj = V.T @ g
    return float(np.sum(proj[keep] ** 2 / w[keep]))


def levenberg_marquardt(
    residuals: Callable[[np.ndarray], np.ndarray],
    jacobian: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    theta0: np.ndarray,
    active: np.ndarray | None = None,
    *,
    max_iter: int = 100,
    gtol: float = 1e-2,
    max_chi2: float = np.inf,
    scaling: str = "identity",
    noise_floor: float | None = None,
    se_max: float = 0.5,
    max_rescues: int = 10,
    geodesic_after: int | None = 40,
    callback: Callable[[int, float], None] | None = None,
) -> LMResult:
    """Minimise ``sum(residuals(theta)**2)`` over ``theta[active]``.

    Args:
        residuals: ``theta -> r`` (1-D array).
        jacobian: ``theta -> (r, J)`` with ``J = dr/dtheta`` (all columns).
        theta0: start.
        active: indices of the parameters to move (default all).
        max_iter: limit on trial steps (accepted + rejected).
        gtol: stop when the Gauss--Newton predicted decrease of chi2 is below
            ``gtol`` times chi2 per degree of freedom (see the module docstring).
        max_chi2: a chi2 at or above this marks a failed evaluation (e.g. a failed
            simulation), treated like a non-finite one: the step is rejected.
        scaling: damping ``lambda * D``: ``"identity"`` (Levenberg: isotropic in
            ``theta``, natural when ``theta`` are logs/logits, i.e. relative changes) or
            ``"marquardt"`` (``D = diag(JᵀJ)``, running maximum; scale-invariant, but it
            lets weakly determined parameters take huge steps: on the rough chi2 surface
            of stick-slip it stalled at chi2/N 4.0 where the isotropic damping reached 1.2).
        noise_floor, se_max: when the iterations run out or stagnate with chi2 per
            degree of freedom at most ``noise_floor`` and the remaining decrease only
            along directions with a standard error above ``se_max`` (``theta`` units),
            the fit has converged along its determined directions (module docstring).
            Only for residuals scaled by their noise (chi2 per degree of freedom ~1 when
            the model fits): None (default) switches the rule off.
        max_rescues: how many times a stalled damping may be bypassed by an undamped
            Gauss--Newton step along the determined directions (see the comment in
            the loop); 0 switches it off.
        geodesic_after: from this trial step on, geodesically accelerated steps (module
            docstring); 0: from the start; None: never (the plain damped step).
        callback: called with (trial number, current chi2) after each trial.
    """
    theta = np.array(theta0, dtype=np.float64)
    idx = np.arange(theta.size) if active is None else np.asarray(active, dtype=int)
    r, J = jacobian(theta)
    r, J = np.asarray(r), np.asarray(J)
    n_eval, n_jac, n_iter = 0, 1, 0
    chi2 = float(r @ r)
    dof = max(r.size - idx.size, 1)

    def done(converged: bool, message: str, dec: float = np.nan, loose=()) -> LMResult:
        return LMResult(
            theta, chi2, r, J, converged, message, n_iter, n_eval, n_jac, dec, list(loose)
        )

    def on_a_ridge(dec: float) -> LMResult | None:
        """Converged but for directions the data do not determine (at the noise floor)."""
        s2 = chi2 / dof
        if noise_floor is None or s2 > noise_floor:
            return None
        determined, loose, _ = _eigen_split(As, gs, d, s2, se_max)
        if loose and determined <= gtol * s2:
            return done(True, "converged (the rest is along undetermined directions)", dec, loose)
        return None

    if not (np.isfinite(chi2) and chi2 < max_chi2):
        return done(False, "the model could not be evaluated at the start")

    def normal_equations(J, r, D2):
        # an overflow here (a simulation on the edge of failing) is detected by the
        # callers, which reject the point
        with np.errstate(over="ignore", invalid="ignore"):
            Ja = np.where(np.isfinite(J[:, idx]), J[:, idx], 0.0)
            A = Ja.T @ Ja
            g = Ja.T @ r
            if scaling == "marquardt":
                D2 = np.maximum(D2, np.diag(A))
            elif D2 is None:  # isotropic: one constant scale, from the start
                D2 = np.full(idx.size, float(np.max(np.diag(A), initial=0.0)))
            d = np.sqrt(np.where(D2 > 0, D2, 1.0))
            return A / np.outer(d, d), g / d, d, D2

    if scaling not in ("identity", "marquardt"):
        raise ValueError(f"scaling must be 'identity' or 'marquardt', not {scaling!r}")
    As, gs, d, D2 = normal_equations(J, r, np.zeros(idx.size) if scaling == "marquardt" else None)
    if not (np.all(np.isfinite(As)) and np.all(np.isfinite(gs))):
        return done(False, "the Jacobian is not finite at the start")

    def linearise(theta_new):
        """The accepted-point state at ``theta_new``, or None where its Jacobian overflows.

        Returns (theta, r, J, As, gs, d, D2, chi2, dec); the one place both kinds of step
        (damped, and the Gauss--Newton bypass) accept a point.
        """
        nonlocal n_jac
        r_new, J_new = (np.asarray(a) for a in jacobian(theta_new))
        n_jac += 1
        As_new, gs_new, d_new, D2_new = normal_equations(J_new, r_new, D2)
        if not (np.all(np.isfinite(As_new)) and np.all(np.isfinite(gs_new))):
            return None
        chi2_new = float(r_new @ r_new)
        return (
            theta_new, r_new, J_new, As_new, gs_new, d_new, D2_new, chi2_new,
            _gn_decrease(As_new, gs_new),
        )  # fmt: skip

    lam, nu = 1e-3, 2.0
    rescues = 0
    dec = _gn_decrease(As, gs)
    for trial in range(max_iter):
        s2 = chi2 / dof
        if dec <= gtol * s2:
            return done(True, "converged", dec)
        if lam > 1e16:
            # No damped step lowers chi2. The isotropic damping also stalls short of
            # the optimum: where the data determine some directions far better than
            # others, every damped step is mostly along the well-determined ones, whose
            # decrease (already near the optimum) is below the integrator's noise, so
            # it is rejected and the damping grows. Measured on a coverage case
            # (case_051) refitted from its truth: "stagnated" with cf_con and d one
            # standard error from the optimum, where half the Gauss--Newton step
            # lowered chi2 by 2.9. So before giving up, take the undamped Gauss--Newton
            # step along the determined directions (a short line search), as long as
            # it lowers chi2.
            if rescues < max_rescues:
                rescues += 1
                gn = _eigen_split(As, gs, d, s2, se_max)[2]
                best = None
                for alpha in (1.0, 0.5, 0.25):
                    trial_theta = theta.copy()
                    trial_theta[idx] += alpha * gn / d
                    r_new = np.asarray(residuals(trial_theta))
                    n_eval += 1
                    chi2_new = float(r_new @ r_new)
                    ok = np.isfinite(chi2_new) and chi2_new < min(chi2, max_chi2)
                    if ok and (best is None or chi2_new < best[0]):
                        best = (chi2_new, trial_theta)
                point = linearise(best[1]) if best is not None else None
                if point is not None:
                    theta, r, J, As, gs, d, D2, chi2, dec = point
                    n_iter += 1
                    if callback is not None:
                        callback(trial, chi2)
                    continue
            # at the optimum up to the integrator's noise, unless the Gauss--Newton
            # decrease is still large
            if dec <= 100 * gtol * s2:
                return done(True, "converged (no further decrease within integrator noise)", dec)
            return on_a_ridge(dec) or done(False, "stagnated: no step lowers chi2", dec)
        damped = As + lam * np.eye(idx.size)
        try:
            step_s = -np.linalg.solve(damped, gs)
        except np.linalg.LinAlgError:
            lam *= nu
            nu *= 2.0
            continue
        # the decrease the linear model predicts for the damped step (for an accelerated
        # step too: the acceleration is a second-order correction, as in GSL's lmaccel)
        pred = -(2.0 * gs @ step_s + step_s @ As @ step_s)
        rho, point = -np.inf, None
        curved = False  # the valley curves more than a step of this length can follow
        if geodesic_after is not None and trial >= geodesic_after and pred > 0:
            # the residuals' second derivative along the step, by a finite difference
            # (h = 0.1 of the step, Transtrum and Sethna's choice); the acceleration is
            # the damped Gauss--Newton answer to it
            h = 0.1
            trial_theta = theta.copy()
            trial_theta[idx] += h * step_s / d
            r_h = np.asarray(residuals(trial_theta))
            n_eval += 1
            Ja = np.where(np.isfinite(J[:, idx]), J[:, idx], 0.0)
            with np.errstate(over="ignore", invalid="ignore"):
                rvv = (2.0 / h) * ((r_h - r) / h - Ja @ (step_s / d))
                acc_s = -np.linalg.solve(damped, (Ja.T @ rvv) / d)
            ratio = 2.0 * np.linalg.norm(acc_s) / max(float(np.linalg.norm(step_s)), 1e-300)
            curved = not (np.all(np.isfinite(acc_s)) and ratio <= ACCEL_MAX)
            if not curved:
                step_s = step_s + 0.5 * acc_s
        if not curved:  # else rejected without evaluating it: a shorter step next
            trial_theta = theta.copy()
            trial_theta[idx] += step_s / d
            r_new = np.asarray(residuals(trial_theta))
            n_eval += 1
            chi2_new = float(r_new @ r_new)
            ok = np.isfinite(chi2_new) and chi2_new < max_chi2 and pred > 0
            rho = (chi2 - chi2_new) / pred if ok else -np.inf
            point = linearise(trial_theta) if rho > 1e-4 else None
        if point is not None:
            theta, r, J, As, gs, d, D2, chi2, dec = point
            n_iter += 1
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
        else:  # rejected (too curved, or the Jacobian there overflowed)
            lam *= nu
            nu *= 2.0
        if callback is not None:
            callback(trial, chi2)
    if dec <= gtol * chi2 / dof:
        return done(True, "converged", dec)
    return on_a_ridge(dec) or done(False, "iteration limit reached", dec)
