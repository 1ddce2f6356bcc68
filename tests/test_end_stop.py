"""The bottom end stop: logs that start on it and leaking forks that sink onto it
simulate like any other run; above the stop nothing changes."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.model.constants import END_STOP_OMEGA, START_CLEARANCE, G

TS = np.arange(0.0, 40.0, 0.01)
LIFT = np.where((TS > 2.0) & (TS < 6.0), 0.6, 0.0)  # a short lift, then the valve shut
REST_DEPTH = G / END_STOP_OMEGA**2  # m, where the fork rests on the stop


def _log_on_the_stop(seed=0, n=800, bias=-0.3e-3):
    """A log whose initial hold reads the stop: 0 + sensor noise, mean slightly < 0."""
    rng = np.random.default_rng(seed)
    ts = TS[:n]
    pwm = np.where(ts > 2.0, 0.5, 0.0)
    height = bias + 0.5e-3 * rng.standard_normal(n)
    return jl.Log(time_s=ts, pwm=pwm, height_m=height, load_kg=np.full(n, 700.0), name="stop")


def test_a_log_that_starts_on_the_stop_starts_at_zero():
    log = _log_on_the_stop()
    assert np.mean(log.height_m[:200]) < 0  # the hold's mean is below the stop
    assert jl.initial_height(log) == 0.0
    sol = jl.simulate(jl.Plant(), (), jl.Inputs.from_log(log))
    assert bool(sol.ok)
    h = np.asarray(sol.height)
    # at rest at the start, just off the contact's tie (START_CLEARANCE): no contact force
    assert h[0] == START_CLEARANCE and h.min() > -1e-6
    assert h[-1] > 0.02  # and it lifts


def test_a_start_below_the_stop_is_lifted_onto_it():
    """An initial-height offset (the fit's nuisance) cannot start a run below 0."""
    inputs = jl.Inputs.from_arrays(TS[:300], np.zeros(300), np.full(300, 500.0), -0.012)
    sol = jl.simulate(jl.Plant(), (), inputs)
    assert bool(sol.ok)
    assert float(sol.height[0]) == START_CLEARANCE


@pytest.mark.parametrize("load", [0.0, 800.0, 2000.0])
def test_a_leaking_fork_sinks_onto_the_stop_and_rests_there(load):
    # 1e-10 m^3/(s Pa): the unloaded fork sinks at ~5 cm/s, the loaded one falls at
    # ~0.8 m/s onto the stop
    plant, effects = jl.with_params(jl.Plant(), jl.make_effects(["leakage"]), {"C_L": 1e-10})
    inputs = jl.Inputs.from_arrays(TS, LIFT, np.full(TS.size, load), 0.0)
    sol = jl.simulate(plant, effects, inputs)
    assert bool(sol.ok), sol.result
    h, p = np.asarray(sol.height), np.asarray(sol.pressure)
    rest = h[TS > 30.0]
    # rests g / w^2 below 0 (0.11 mm), whatever the load; the oil has leaked away
    np.testing.assert_allclose(rest, -REST_DEPTH, atol=2e-6)
    assert np.all(np.abs(p[TS > 30.0]) < 1e3)
    assert h.min() > -3 * REST_DEPTH  # the impact does not go deep


def test_the_stop_changes_nothing_above_zero():
    """A run that stays above the stop is the same with the stop switched off."""
    inputs = jl.Inputs.from_arrays(TS, LIFT, np.full(TS.size, 900.0), 0.4)
    with_stop = jl.simulate(jl.Plant(), (), inputs)
    no_stop = jl.simulate(jl.Plant(omega_es=0.0), (), inputs)
    assert bool(with_stop.ok) and float(with_stop.height.min()) > 0.3
    np.testing.assert_array_equal(np.asarray(with_stop.ys), np.asarray(no_stop.ys))


def test_contact_force_is_one_sided_and_starts_at_zero():
    plant = jl.Plant()
    f = lambda x, v: float(plant.end_stop_force(jnp.asarray(x), jnp.asarray(v), 500.0))
    assert f(1e-3, -0.1) == 0.0  # above the stop
    assert f(0.0, -0.1) == 0.0  # touching: no jump with the impact speed
    assert f(-1e-4, 0.0) > 0.0  # pressed in: pushes up
    assert f(-1e-5, 1.0) == 0.0  # leaving fast: never pulls
    mass = 500.0 + 100.0  # load + carriage (stage 1)
    np.testing.assert_allclose(f(-REST_DEPTH, 0.0), mass * G, rtol=1e-12)  # holds the weight


def test_gradient_through_the_stop_is_finite():
    """The fit differentiates runs that rest on the stop (forward mode, as LM does)."""
    inputs = jl.Inputs.from_arrays(TS[:2000], LIFT[:2000], np.full(2000, 600.0), 0.0)
    effects = jl.make_effects(["leakage"])

    def final_height(c_l):
        plant, effs = jl.with_params(jl.Plant(), effects, {"C_L": c_l})
        sol = jl.simulate(plant, effs, inputs, adjoint=diffrax.ForwardMode())
        return sol.height[-1]

    g = jax.jacfwd(final_height)(jnp.asarray(1e-11))
    assert np.isfinite(float(g))


@pytest.mark.parametrize("load", [111.0, 800.0])
def test_derivative_of_a_start_on_the_stop_is_that_of_raising_it(load):
    """A run that starts exactly at 0 (a log on the stop) has, in forward mode, the
    derivative with respect to its initial height of raising the start (the
    one-sided finite difference upwards): the stop's contact must not leak into the
    tangent at the tie ``x = 0``. It did with ``jnp.maximum`` (derivative 1/2 at the
    tie): the tangent took half the contact stiffness, the solver stepping for the
    primal let it grow to 1e19, and every fit on such a log stalled at its start. At
    111 kg it grew to 3e10 even so, until the start moved off the tie
    (``START_CLEARANCE``): the fork chattered across 0 on round-off."""
    n = 1500
    pwm = np.where(TS[:n] > 3.0, 0.5, 0.0)  # a hold on the stop, then a lift

    def heights(x0):
        inputs = jl.Inputs.from_arrays(TS[:n], pwm, np.full(n, load), x0)
        sol = jl.simulate(jl.Plant(), (), inputs, adjoint=diffrax.ForwardMode())
        return sol.height

    _, tangent = jax.jvp(heights, (jnp.asarray(0.0),), (jnp.asarray(1.0),))
    step = 1e-4  # 0.1 mm: large against the integrator's own noise (rtol 1e-6)
    fd = (np.asarray(heights(jnp.asarray(step))) - np.asarray(heights(jnp.asarray(0.0)))) / step
    tangent = np.asarray(tangent)
    assert np.all(np.isfinite(tangent))
    np.testing.assert_allclose(tangent, fd, atol=1e-3)
    assert tangent[0] == 1.0  # raising the start raises the first sample one for one
    assert np.max(np.abs(tangent)) < 2.0
