"""``JumpStepSizeController`` (jaxlift.model.stepping) against diffrax's own
``ClipStepSizeController(..., jump_ts=...)``: same steps, same trajectory, same
derivatives, the jump times hit, under ``vmap`` and ``jacfwd`` too.

The lift runs here are short (6 s at 100 Hz) with ramps (pwm changes at every sample)
and holds, so that both the dense jumps of a ramp and isolated jumps occur.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.model.simulate import DEFAULT_ATOL, DTMAX, error_norm
from jaxlift.model.stepping import JumpStepSizeController, StabilityLimitedController
from jaxlift.model.vector_field import initial_state, lift_vector_field

FS = 100.0
TS = np.arange(0.0, 6.0 + 0.5 / FS, 1.0 / FS)
# hold, 0.5 s ramp up to 0.5, hold, 0.3 s ramp down to 0.2, hold, step to 0, hold
PWM = np.interp(TS, [0.0, 0.5, 1.0, 2.5, 2.8, 4.0, 4.0001, 6.0], [0, 0, 0.5, 0.5, 0.2, 0.2, 0, 0])
PWM = np.round(PWM, 4)
LOAD = np.full(TS.shape, 1000.0)
INPUTS = jl.Inputs.from_arrays(TS, PWM, LOAD, 0.4)
RTOL = 1e-6


def _pid(effects=(), rtol=RTOL):
    scales = [jnp.asarray(e.state_scales, dtype=jnp.float64) for e in effects]
    atol = jnp.concatenate([jnp.asarray(DEFAULT_ATOL), *scales]) * (rtol / RTOL)
    pid = diffrax.PIDController(rtol=rtol, atol=atol, dtmax=DTMAX, norm=error_norm)
    # as in jl.simulate: the stability limit inside, the jump handling outside
    return StabilityLimitedController(pid, lift_vector_field, atol)


def _controller(kind, jump_ts, effects=(), rtol=RTOL):
    if kind == "clip":
        return diffrax.ClipStepSizeController(_pid(effects, rtol), jump_ts=jump_ts)
    return JumpStepSizeController(_pid(effects, rtol), jump_ts)


@eqx.filter_jit
def _solve(kind, plant, effects, inputs, jump_ts, steps=False, adjoint=None, rtol=RTOL):
    """The lift as ``jl.simulate`` solves it, with the step-size controller chosen."""
    saveat = diffrax.SaveAt(steps=True) if steps else diffrax.SaveAt(ts=inputs.ts)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lift_vector_field),
        diffrax.Tsit5(),
        t0=inputs.ts[0],
        t1=inputs.ts[-1],
        dt0=None,
        y0=initial_state(plant, effects, inputs),
        args=(plant, effects, inputs),
        saveat=saveat,
        stepsize_controller=_controller(kind, jump_ts, effects, rtol),
        max_steps=16384,
        adjoint=diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
    )
    return sol.ts, sol.ys, sol.stats["num_steps"]


def _delay(tau_d):
    return jl.make_effects("input_delay", {"tau_d": tau_d})


def test_inputs_have_ramps_and_holds():
    n = INPUTS.jump_ts.size
    assert 60 < n < 200  # every sample along the ramps, plus the step to 0
    assert np.all(np.diff(np.asarray(INPUTS.jump_ts)) > 0)


@pytest.mark.parametrize("tau_d", [0.0, 0.123])
def test_same_steps_and_trajectory_as_clip(tau_d):
    plant, effects = jl.Plant(), _delay(tau_d)
    jump_ts = INPUTS.jump_ts + tau_d
    _, ys_clip, n_clip = _solve("clip", plant, effects, INPUTS, jump_ts)
    _, ys_new, n_new = _solve("new", plant, effects, INPUTS, jump_ts)
    assert int(n_new) == int(n_clip)
    # the same decisions step for step: far inside the solver tolerance
    np.testing.assert_allclose(ys_new[:, 0], ys_clip[:, 0], rtol=0, atol=1e-12)  # m
    np.testing.assert_allclose(ys_new[:, 1], ys_clip[:, 1], rtol=0, atol=1e-12)  # m/s
    np.testing.assert_allclose(ys_new[:, 2], ys_clip[:, 2], rtol=1e-12, atol=1e-6)  # Pa
    t_clip, _, _ = _solve("clip", plant, effects, INPUTS, jump_ts, steps=True)
    t_new, _, _ = _solve("new", plant, effects, INPUTS, jump_ts, steps=True)
    np.testing.assert_array_equal(np.asarray(t_new), np.asarray(t_clip))


def _step_times(jump_ts, tau_d=0.0):
    ts, _, n = _solve("new", jl.Plant(), _delay(tau_d), INPUTS, jump_ts, steps=True)
    ts = np.asarray(ts)
    return ts[np.isfinite(ts)], int(n)


@pytest.mark.parametrize("tau_d", [0.0, 0.123])
def test_lands_on_every_jump_time(tau_d):
    """A step ends just before each jump time and the next starts just after it
    (``SaveAt(steps=True)`` records the start of the next step, ``nextafter(jump)``),
    so no step straddles a discontinuity of the right-hand side."""
    jumps = np.asarray(INPUTS.jump_ts) + tau_d
    step_ts, _ = _step_times(jnp.asarray(jumps), tau_d)
    inside = jumps[jumps < TS[-1]]
    assert inside.size > 60
    landed = np.isin(np.nextafter(inside, np.inf), step_ts)
    assert landed.all(), f"jump times not stepped onto: {inside[~landed]}"
    # and no step ends on a jump time itself
    assert not np.isin(inside, step_ts).any()


def test_unreached_and_repeated_jump_times_change_nothing():
    """Padding beyond the end, a jump time listed twice (the binary-search fallback of
    the index hint) and an unsorted array all give the same steps."""
    jumps = np.asarray(INPUTS.jump_ts)
    step_ts, n = _step_times(jnp.asarray(jumps))
    padded = np.concatenate([jumps, np.full(5000, 1e6), TS[-1] + np.arange(1.0, 100.0)])
    repeated = np.sort(np.concatenate([jumps, jumps[::3]]))
    shuffled = np.random.default_rng(0).permutation(jumps)
    for other in (padded, repeated, shuffled):
        s, m = _step_times(jnp.asarray(other))
        assert m == n
        np.testing.assert_array_equal(s, step_ts)


def test_controller_state_does_not_carry_the_jump_times():
    controller = JumpStepSizeController(_pid(), INPUTS.jump_ts).wrap(jnp.asarray(1))
    y0 = initial_state(jl.Plant(), (), INPUTS)
    term = diffrax.ODETerm(lift_vector_field)
    _, state = controller.init(
        term, 0.0, TS[-1], y0, None, (jl.Plant(), (), INPUTS), diffrax.Tsit5().func, 5
    )
    sizes = [np.size(x) for x in jax.tree_util.tree_leaves(state)]
    # scalars, and the stability limit's power-iteration vector (one entry per state)
    assert max(sizes) == y0.shape[0] < INPUTS.jump_ts.shape[0]


def test_backwards_in_time_matches_clip():
    """``wrap(-1)`` (a solve from t1 down to t0), on a toy ODE driven by the same
    zero-order-held input."""
    ts, pwm = jnp.asarray(TS), jnp.asarray(PWM)

    def field(t, y, args):
        i = jnp.clip(jnp.searchsorted(ts, t, side="right") - 1, 0, ts.size - 1)
        return -y + pwm[i]

    def solve(controller):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            diffrax.Tsit5(),
            t0=TS[-1],
            t1=0.0,
            dt0=None,
            y0=jnp.asarray(0.3),
            saveat=diffrax.SaveAt(steps=True),
            stepsize_controller=controller,
            max_steps=4096,
        )
        return np.asarray(sol.ts), np.asarray(sol.ys)

    pid = diffrax.PIDController(rtol=1e-8, atol=1e-10)
    t_new, y_new = solve(JumpStepSizeController(pid, INPUTS.jump_ts))
    t_clip, y_clip = solve(diffrax.ClipStepSizeController(pid, jump_ts=INPUTS.jump_ts))
    np.testing.assert_array_equal(t_new, t_clip)
    np.testing.assert_array_equal(y_new, y_clip)
    inside = np.asarray(INPUTS.jump_ts)
    assert np.isin(np.nextafter(-inside, np.inf), -t_new[np.isfinite(t_new)]).all()


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_vmap_over_delays():
    """Batched delays shift batched jump times (``inputs.jump_ts + delay``). Vmapped, the
    lift solved with the new controller equals the same solve through diffrax's
    controller (one program, two controllers: the same steps, so equal far inside the
    solver tolerance); ``jl.simulate``, vmapped, equals each member's unbatched run to
    within the solver tolerance. (Differently compiled programs round differently: with
    jax 0.12.1 the vmapped ``jl.simulate`` differs from the vmapped solve through
    diffrax's controller by 1.1e-6 m in one member, as the unbatched runs of either
    differ from their vmapped ones, 2e-7 to 1.2e-6 m; with 0.12.0.1 they were equal.)"""
    taus = jnp.asarray([0.0, 0.05, 0.137])

    def run(tau):
        return jl.simulate(jl.Plant(), _delay(tau), INPUTS, rtol=RTOL).height

    def run_with(kind):
        def run(tau):
            return _solve(kind, jl.Plant(), _delay(tau), INPUTS, INPUTS.jump_ts + tau)[1][:, 0]

        return eqx.filter_vmap(run)(taus)

    np.testing.assert_allclose(run_with("new"), run_with("clip"), rtol=0, atol=1e-12)
    batched = eqx.filter_vmap(run)(taus)
    for i, tau in enumerate(taus):
        np.testing.assert_allclose(batched[i], run(tau), rtol=0, atol=1e-5)
    assert float(jnp.max(jnp.abs(batched[0] - batched[2]))) > 1e-2  # members differ


def _heights(theta, kind, adjoint, rtol=RTOL):
    """Height at the sample times as a function of (log beta, tau_d)."""
    plant, effects = jl.with_params(
        jl.Plant(), _delay(0.0), {"beta": jnp.exp(theta[0]), "tau_d": theta[1]}
    )
    jump_ts = INPUTS.jump_ts + theta[1]
    return _solve(kind, plant, effects, INPUTS, jump_ts, adjoint=adjoint, rtol=rtol)[1][:, 0]


THETA0 = jnp.asarray([np.log(1.2e9), 0.0837])


@pytest.mark.extended  # CI time (32 s); the step-for-step equivalence is tested above
def test_jacfwd_and_reverse_mode_match_clip():
    """d(height)/d(log beta, tau_d): forward mode (``ForwardMode``) through the new
    controller equals forward mode through diffrax's; reverse mode
    (``RecursiveCheckpointAdjoint``) agrees with both. The tau_d column flows only
    through the step ends at the shifted jump times."""
    fwd = diffrax.ForwardMode()
    jac_new = jax.jacfwd(lambda th: _heights(th, "new", fwd))(THETA0)
    jac_clip = jax.jacfwd(lambda th: _heights(th, "clip", fwd))(THETA0)
    np.testing.assert_allclose(jac_new, jac_clip, rtol=1e-10, atol=1e-14)
    assert np.max(np.abs(jac_new[:, 1])) > 0.03  # m/s (-speed): the lift starts later
    jac_rev = jax.jacrev(lambda th: _heights(th, "new", None))(THETA0)
    # (at much tighter solver tolerances reverse mode's tau_d column degrades -- with
    # diffrax's controller identically; forward mode does not, see the next test)
    np.testing.assert_allclose(jac_new, jac_rev, rtol=1e-7, atol=1e-10)


def test_jacfwd_delay_derivative_matches_finite_differences():
    """At rtol 1e-10, so that the finite differences are not dominated by the solver's
    error."""
    rtol, h = 1e-10, 1e-6
    fwd = diffrax.ForwardMode()
    d_tau = np.asarray(jax.jacfwd(lambda th: _heights(th, "new", fwd, rtol))(THETA0))[:, 1]
    fd = (
        np.asarray(_heights(THETA0.at[1].add(h), "new", fwd, rtol))
        - np.asarray(_heights(THETA0.at[1].add(-h), "new", fwd, rtol))
    ) / (2 * h)
    np.testing.assert_allclose(d_tau, fd, rtol=0, atol=1e-4 * np.max(np.abs(fd)))


def test_through_simulate_with_jacfwd():
    """The library path: ``jl.simulate`` with ``ForwardMode`` under ``jax.jacfwd``."""

    def height_mid_lift(tau):
        effects = _delay(tau)
        sol = jl.simulate(jl.Plant(), effects, INPUTS, rtol=RTOL, adjoint=diffrax.ForwardMode())
        return sol.height[200]  # t = 2 s

    d = jax.jacfwd(height_mid_lift)(jnp.asarray(0.1))
    assert np.isfinite(float(d)) and float(d) != 0.0


def test_rejects_bad_arguments():
    with pytest.raises(ValueError, match="adaptive"):
        JumpStepSizeController(diffrax.ConstantStepSize(), INPUTS.jump_ts)
    with pytest.raises(ValueError, match="floating"):
        JumpStepSizeController(_pid(), jnp.arange(3))
    with pytest.raises(ValueError, match="1-D"):
        JumpStepSizeController(_pid(), jnp.zeros((2, 2)))


# ------------------------------------------------ StabilityLimitedController
LAM = 200.0  # 1/s: stiff against DTMAX (|lambda dt| = 10 > Tsit5's ~3.5)


def _relax(theta, limited: bool):
    """y' = LAM (theta - y), y(0) = 1, at theta = 1: the solution sits at its
    equilibrium (zero error estimates, steps grow to DTMAX), but dy/dtheta =
    1 - exp(-LAM t) does not."""

    def vf(t, y, args):
        return LAM * (args - y)

    pid = diffrax.PIDController(rtol=1e-6, atol=1e-8, dtmax=DTMAX)
    controller = StabilityLimitedController(pid, vf, jnp.ones(1)) if limited else pid
    ts = jnp.linspace(0.0, 2.0, 21)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf), diffrax.Tsit5(), 0.0, 2.0, None, jnp.ones(1), args=theta,
        saveat=diffrax.SaveAt(ts=ts), stepsize_controller=controller, max_steps=4096,
        adjoint=diffrax.ForwardMode(),
    )  # fmt: skip
    return sol.ys[:, 0], ts


def test_stability_limit_keeps_forward_sensitivities_stable_at_rest():
    ts = np.linspace(0.0, 2.0, 21)
    exact = 1.0 - np.exp(-LAM * ts)
    d_plain = np.asarray(jax.jacfwd(lambda th: _relax(th, False)[0])(jnp.asarray(1.0)))
    d_limited = np.asarray(jax.jacfwd(lambda th: _relax(th, True)[0])(jnp.asarray(1.0)))
    # without the limit the sensitivity explodes (the failure this controller fixes)
    assert not np.all(np.abs(d_plain - exact) < 1e-3), d_plain
    np.testing.assert_allclose(d_limited, exact, rtol=0, atol=1e-5)
    # the solution itself is the same (at rest) either way
    np.testing.assert_allclose(_relax(1.0, True)[0], 1.0, rtol=0, atol=1e-12)


def test_mast_compliance_jacobian_at_rest_matches_finite_differences():
    """The case that failed in the diagnosis: a light carriage (the load on the mast
    spring) held at rest against the steep Coulomb friction, d(height)/d(log ks_inv)."""
    inputs = jl.Inputs.from_arrays(TS, PWM, np.full(TS.shape, 600.0), 0.05)

    def heights(log_ks):
        effs = jl.make_effects("mast_compliance", {"ks_inv": jnp.exp(log_ks), "c_s": 1000.0})
        sol = jl.simulate(jl.Plant(), effs, inputs, rtol=1e-8, adjoint=diffrax.ForwardMode())
        return sol.height

    x = jnp.asarray(np.log(5e-6))
    d = np.asarray(jax.jacfwd(heights)(x))
    h = 3e-3
    fd = (np.asarray(heights(x + h)) - np.asarray(heights(x - h))) / (2 * h)
    assert np.max(np.abs(fd)) > 1e-4  # m: the compliance shows in the height
    # forward mode differentiates the solution with the step sizes held (diffrax stops
    # their gradient), finite differences see the steps move: measured 0.12-0.5 % of
    # the largest entry for h = 1e-3..1e-2 (without the stability limit: 1e100)
    np.testing.assert_allclose(d, fd, rtol=0, atol=5e-3 * np.max(np.abs(fd)))


def test_simulate_without_stability_limit_same_solution_fewer_steps():
    """``stability_limit=False`` (value-only work: posterior, plots) drops the limit --
    fewer steps on a run with holds -- and the solution still meets the tolerance."""
    inputs = jl.Inputs.from_arrays(TS, PWM, np.full(TS.shape, 600.0), 0.05)
    effs = jl.make_effects("mast_compliance", {"ks_inv": 5e-6, "c_s": 1000.0})
    on = jl.simulate(jl.Plant(), effs, inputs)
    off = jl.simulate(jl.Plant(), effs, inputs, stability_limit=False)
    assert bool(on.ok) and bool(off.ok)
    assert int(off.num_steps) < int(on.num_steps)
    np.testing.assert_allclose(off.height, on.height, rtol=0, atol=1e-6)  # m (measured 2e-8)
    np.testing.assert_allclose(off.speed, on.speed, rtol=0, atol=3e-5)  # m/s (3e-6)


OMEGA, ZETA = 398.0, 0.63  # 1/s: the pair measured on a mast-compliance log at rest


def _oscillator(theta):
    """x'' = -OMEGA^2 (x - theta) - 2 ZETA OMEGA x', at rest at theta = 0, in the mast
    states' scales (1e-7 m, 1e-6 m/s): the scaled Jacobian is far from normal, so one
    power-iteration step's ``|J w|`` swings between 50 and 2 900/s around ``rho`` = 398/s."""

    def vf(t, y, args):
        return jnp.stack([y[1], -(OMEGA**2) * (y[0] - args) - 2 * ZETA * OMEGA * y[1]])

    pid = diffrax.PIDController(rtol=1e-6, atol=1e-8, dtmax=DTMAX)
    controller = StabilityLimitedController(pid, vf, jnp.array([1e-7, 1e-6]))
    ts = jnp.linspace(0.0, 2.0, 21)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf), diffrax.Tsit5(), 0.0, 2.0, None, jnp.zeros(2), args=theta,
        saveat=diffrax.SaveAt(ts=ts), stepsize_controller=controller, max_steps=4096,
        adjoint=diffrax.ForwardMode(),
    )  # fmt: skip
    return sol.ys[:, 0]


def test_stability_limit_sees_a_complex_pair_in_badly_scaled_states(monkeypatch):
    """The posterior's walkers could not start on a mast-compliance case: the Jacobian
    column of log ks_inv was 1.7e114 after a hold, because ``|J w|`` alone let steps of
    0.05 s through (``|lambda dt|`` = 20). The Ritz radius on ``span{w, J w}`` sees the
    pair; without it the same sensitivity explodes (so this test can fail)."""
    import jaxlift.model.stepping as stepping

    ts = np.linspace(0.0, 2.0, 21)
    wd = OMEGA * np.sqrt(1 - ZETA**2)
    exact = 1 - np.exp(-ZETA * OMEGA * ts) * (
        np.cos(wd * ts) + ZETA / np.sqrt(1 - ZETA**2) * np.sin(wd * ts)
    )
    d = np.asarray(jax.jacfwd(_oscillator)(jnp.asarray(0.0)))
    np.testing.assert_allclose(d, exact, rtol=0, atol=1e-5)
    monkeypatch.setattr(stepping, "_ritz_radius", lambda w, jw, rho, jjw: jnp.zeros(()))
    d_power = np.asarray(jax.jacfwd(_oscillator)(jnp.asarray(0.0)))
    assert not np.all(np.abs(d_power - exact) < 1e-3), d_power
