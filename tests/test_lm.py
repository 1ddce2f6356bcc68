"""jaxlift's Levenberg--Marquardt driver (``jaxlift/calibrate/lm.py``) on problems whose optimum
is known independently (linear least squares by ``numpy.linalg.lstsq``, a nonlinear fit
by SciPy), and ``fit(solver=LM())`` against ``fit(solver=OptimistixLM())``."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from jaxlift.calibrate.lm import levenberg_marquardt
from jaxlift.calibrate.solvers import OptimistixLM


def _numeric(fn):
    """(residuals, jacobian) callables from a numpy residual function (central FD)."""

    def jac(theta):
        r = fn(theta)
        J = np.empty((r.size, theta.size))
        for k in range(theta.size):
            h = 1e-6 * max(1.0, abs(theta[k]))
            e = np.zeros_like(theta)
            e[k] = h
            J[:, k] = (fn(theta + e) - fn(theta - e)) / (2 * h)
        return r, J

    return fn, jac


def test_linear_least_squares_matches_lstsq():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 4))
    b = rng.normal(size=200)
    exact, *_ = np.linalg.lstsq(A, b, rcond=None)
    res = levenberg_marquardt(
        lambda th: A @ th - b, lambda th: (A @ th - b, A), np.zeros(4), gtol=1e-12
    )
    assert res.converged, res.message
    # the stopping rule's promise: for a linear problem the Gauss--Newton decrease is
    # exactly the distance to the optimum in the metric A'A, below gtol * s^2
    d = res.theta - exact
    s2 = float(np.sum((A @ exact - b) ** 2)) / (200 - 4)
    assert d @ (A.T @ A) @ d <= 1e-12 * s2
    np.testing.assert_allclose(res.theta, exact, rtol=1e-6)


def test_nonlinear_fit_matches_scipy():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 4, 300)
    y = 2.5 * np.exp(-1.3 * t) * np.cos(3.1 * t) + 0.01 * rng.normal(size=t.size)

    def fn(th):
        return (th[0] * np.exp(-th[1] * t) * np.cos(th[2] * t) - y) / 0.01

    start = np.array([1.0, 0.5, 2.8])
    ref = least_squares(fn, start, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    res = levenberg_marquardt(*_numeric(fn), start, gtol=1e-10)
    assert res.converged, res.message
    np.testing.assert_allclose(res.theta, ref.x, rtol=1e-6)
    assert res.chi2 <= 2 * ref.cost + 1e-6
    # statistical stop: the remaining Gauss-Newton step is tiny against the uncertainty
    assert res.gn_decrease <= 1e-10 * res.chi2 / (t.size - 3)


def test_only_active_parameters_move():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(50, 3))
    b = rng.normal(size=50)
    start = np.array([0.3, -0.2, 0.7])
    res = levenberg_marquardt(
        lambda th: A @ th - b, lambda th: (A @ th - b, A), start, active=[0, 2], gtol=1e-12
    )
    assert res.theta[1] == start[1]
    # the optimum over the active columns with the inactive one fixed
    exact, *_ = np.linalg.lstsq(A[:, [0, 2]], b - A[:, 1] * start[1], rcond=None)
    np.testing.assert_allclose(res.theta[[0, 2]], exact, rtol=1e-8)


def test_failed_evaluations_are_rejected_not_propagated():
    """A residual that is NaN outside a region (like a simulation that fails) only
    rejects the trial step; the fit still reaches the optimum."""
    t = np.linspace(0.1, 2, 50)
    y = np.sqrt(0.8) * t

    def fn(th):
        if th[0] <= 0:
            return np.full(t.size, np.nan)
        return np.sqrt(th[0]) * t - y

    res = levenberg_marquardt(*_numeric(fn), np.array([0.05]), gtol=1e-12)
    assert res.converged and np.isfinite(res.chi2)
    np.testing.assert_allclose(res.theta, [0.8], rtol=1e-6)


def test_failure_at_the_start_is_reported():
    res = levenberg_marquardt(
        lambda th: np.full(3, np.inf), lambda th: (np.full(3, np.inf), np.zeros((3, 1))), [1.0]
    )
    assert not res.converged and "start" in res.message


def test_iteration_limit_is_reported():
    t = np.linspace(0, 4, 100)
    y = np.exp(-1.3 * t)

    def fn(th):
        return np.exp(-th[0] * t) - y

    res = levenberg_marquardt(*_numeric(fn), np.array([5.0]), max_iter=1, gtol=1e-14)
    assert not res.converged and res.message == "iteration limit reached"


@pytest.mark.slow
def test_lm_and_optimistix_reach_the_same_optimum():
    import jax

    import jaxlift as jl
    from jaxlift.calibrate.fit import fit
    from jaxlift.model.sequences import ramped_sequence

    truth = {"beta": 0.6e9, "d": 500.0}
    plant, _ = jl.with_params(jl.Plant(), (), truth)
    ts, pwm = ramped_sequence([(0.0, 1.0), (0.45, 5.0), (0.2, 5.0), (0.0, 3.0)])
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, 800.0), 0.05)
    sol = jl.simulate(plant, (), inputs)
    log = jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(3), name="short")
    init = {"beta": 0.9e9, "d": 300.0}
    a = fit([log], free="beta,d", init=init, n_starts=1)
    b = fit([log], free="beta,d", init=init, n_starts=1, solver=OptimistixLM())
    assert a.converged and b.converged
    # the same optimum: fit()'s stopping rule (gtol = 0.01) promises a remaining step
    # below sqrt(0.01) = 0.1 standard errors and a chi2 above the optimum's by less than
    # 0.01 s^2; optimistix's Cauchy test stops at least as close here
    s2 = a.chi2 / (a.n_residuals - 3)
    for name in truth:
        assert abs(a.params[name] - b.params[name]) < 0.2 * a.stderr_white[name]
    assert a.chi2 <= b.chi2 + 0.01 * s2


def test_overflowing_jacobian_rejects_the_step():
    """Where the Jacobian overflows (a simulation on the edge of failing), the step is
    rejected as if the residuals had failed."""
    t = np.linspace(0.1, 2, 50)
    y = 0.8 * t
    fn, jac = _numeric(lambda th: th[0] * t - y)

    def bad_jac(th):
        r, J = jac(th)
        return (r, np.full_like(J, 1e300)) if th[0] > 0.9 else (r, J)

    res = levenberg_marquardt(fn, bad_jac, np.array([5.0]), gtol=1e-12)
    assert not (res.converged and res.theta[0] > 0.9)
    res = levenberg_marquardt(fn, bad_jac, np.array([0.1]), gtol=1e-12)
    assert res.converged
    np.testing.assert_allclose(res.theta, [0.8], rtol=1e-6)


def _banana(scale=1.0):
    """A curved valley ``theta1 = theta0**2`` that the data pin down across (standard
    error 0.1 of ``theta1 - theta0**2``) and barely along (standard error ~10), plus
    2000 residuals of unit noise the parameters cannot change: chi2 per degree of
    freedom ~1 (x scale**2), the noise floor. From (-1.5, 0) LM crawls along the
    valley: after 6 trials the Gauss--Newton decrease left (0.022) is above the plain
    rule's 0.01 x s^2, all of it along the valley."""
    noise = np.random.default_rng(0).standard_normal(2000)

    def res(th):
        return scale * np.concatenate([[10 * (th[1] - th[0] ** 2), 0.1 * (1 - th[0])], noise])

    def jac(th):
        J = np.zeros((2002, 2))
        J[0] = [-20 * th[0], 10]
        J[1] = [-0.1, 0]
        return res(th), scale * J

    return res, jac


def test_a_fit_at_the_noise_floor_converges_along_an_undetermined_ridge():
    res, jac = _banana()
    out = levenberg_marquardt(res, jac, np.array([-1.5, 0.0]), max_iter=6, noise_floor=1.5)
    assert out.converged, out.message
    assert "undetermined" in out.message and len(out.undetermined) == 1
    th0 = out.theta[0]
    tangent = np.array([1.0, 2 * th0]) / np.hypot(1.0, 2 * th0)  # along the valley
    assert abs(abs(out.undetermined[0] @ tangent) - 1) < 1e-2
    # the determined direction is converged: within a tenth of its standard error
    assert abs(out.theta[1] - th0**2) < 0.01
    assert out.gn_decrease > 0.01  # the plain rule alone would have said "not converged"


def test_the_ridge_rule_needs_the_noise_floor_and_a_ridge():
    res, jac = _banana(scale=3.0)  # chi2 per dof ~9: not the noise floor
    out = levenberg_marquardt(res, jac, np.array([-1.5, 0.0]), max_iter=6, noise_floor=1.5)
    assert not out.converged and out.message == "iteration limit reached"
    # well determined in every direction: the iteration limit is still a failure
    A = np.random.default_rng(1).normal(size=(50, 3))
    b = A @ np.array([1.0, -2.0, 0.5])
    out = levenberg_marquardt(
        lambda th: np.exp(A @ th) - np.exp(b),
        lambda th: (np.exp(A @ th) - np.exp(b), np.exp(A @ th)[:, None] * A),
        np.zeros(3),
        max_iter=2,
    )
    assert not out.converged and out.undetermined == []


def _stiff_and_soft(seed: int):
    """Linear least squares with one parameter determined 300x better than the others
    and a small residual jitter that jumps when ``theta`` moves (as an adaptive
    integrator's does: ~0.1 chi2 units here), started from the truth, which is up to
    2.5 standard errors from the optimum in the weak directions."""
    n = 4000
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, 3))
    X[:, 0] *= 300.0
    X[:, 2] = 0.3 * X[:, 2] + 0.05 * X[:, 1]
    noise = rng.standard_normal(n)
    truth = np.array([0.2, -0.3, 0.5])

    def res(th):
        cell = np.abs(np.floor(th * 1e7).astype(np.int64)) % (2**31)
        return X @ (th - truth) + noise + 1e-3 * np.random.default_rng(cell).standard_normal(n)

    optimum = truth + np.linalg.lstsq(X, -noise, rcond=None)[0]
    se = np.sqrt(np.diag(np.linalg.inv(X.T @ X)))
    return res, (lambda th: (res(th), X)), truth, optimum, se


def test_a_stalled_damping_is_bypassed_by_gauss_newton_steps():
    """Started near the optimum in the well-determined direction, every damped step is
    swamped by the jitter and rejected, and the isotropic damping grows until it stalls
    where it started in the weak directions (found on a coverage case refitted from its
    truth). The undamped Gauss--Newton step along the determined directions still
    lowers chi2: with it the fit reaches the optimum."""
    worst_stalled = 0.0
    for seed in range(1, 6):
        res, jac, truth, optimum, se = _stiff_and_soft(seed)
        stalled = levenberg_marquardt(res, jac, truth.copy(), noise_floor=1.5, max_rescues=0)
        worst_stalled = max(worst_stalled, float(np.max(np.abs(stalled.theta - optimum) / se)))
        out = levenberg_marquardt(res, jac, truth.copy(), noise_floor=1.5)
        assert out.converged, (seed, out.message)
        np.testing.assert_array_less(np.abs(out.theta - optimum) / se, 0.1)
    assert worst_stalled > 0.7  # the problem does stall the damped steps alone


def test_geodesic_steps_reach_the_optimum_where_damped_steps_run_off():
    """Two decay rates (log-transformed, as the fit's parameters are) fitted to their
    sum: a curved valley, and flat plateaus where a rate runs off to infinity (its
    exponential vanishes, and with it the gradient). From random starts over three
    decades, the geodesically accelerated steps reach SciPy's optimum from every one;
    the plain damped steps are left on a plateau from some (measured: 6 of 40),
    stopping there as "converged" because the gradient vanishes."""
    t = np.linspace(0, 5, 60)
    rng = np.random.default_rng(0)
    y = np.exp(-0.5 * t) + np.exp(-2.0 * t) + 1e-3 * rng.normal(size=t.size)

    def fn(th):
        return (np.exp(-np.exp(th[0]) * t) + np.exp(-np.exp(th[1]) * t) - y) / 1e-3

    ref = least_squares(fn, np.log([3.0, 5.0]), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    best = 2 * ref.cost
    starts = np.random.default_rng(1).uniform(np.log(0.02), np.log(50.0), size=(40, 2))
    reached = {True: 0, False: 0}
    for start in starts:
        for geodesic in (True, False):
            res = levenberg_marquardt(*_numeric(fn), start, gtol=1e-8, max_iter=500,
                                      geodesic_after=0 if geodesic else None)  # fmt: skip
            if res.chi2 < best * (1 + 1e-6):
                reached[geodesic] += 1
                # the same optimum (the two rates may come out in either order)
                np.testing.assert_allclose(np.sort(res.theta), np.sort(ref.x), rtol=1e-4)
    assert reached[True] == len(starts), reached
    assert reached[False] < len(starts), reached  # the problem does defeat plain steps


def test_a_fit_that_converges_early_takes_only_plain_steps():
    """Accelerated steps start after ``geodesic_after`` trials: a fit that converges
    before is the plain one, step for step (the same floating-point result)."""
    t = np.linspace(0, 4, 300)
    y = 2.5 * np.exp(-1.3 * t) * np.cos(3.1 * t)

    def fn(th):
        return (th[0] * np.exp(-th[1] * t) * np.cos(th[2] * t) - y) / 0.01

    plain = levenberg_marquardt(*_numeric(fn), np.array([1.0, 0.5, 2.8]), geodesic_after=None)
    default = levenberg_marquardt(*_numeric(fn), np.array([1.0, 0.5, 2.8]))
    assert plain.converged and plain.n_iter < 40
    assert np.array_equal(plain.theta, default.theta) and plain.n_eval == default.n_eval
    accelerated = levenberg_marquardt(*_numeric(fn), np.array([1.0, 0.5, 2.8]), geodesic_after=0)
    assert accelerated.n_eval > plain.n_eval  # the extra evaluation per trial
