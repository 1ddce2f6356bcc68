"""Nudging (a simulation pulled towards the measurements) and the synchronised fit it
serves: gain 0 is the model itself, a gain pulls a wrong model onto the data, and a
synchronised fit of a stick-slip log from far off reaches the truth."""

import jax
import numpy as np
import pytest
from helpers import tree_allclose

import jaxlift as jl
from jaxlift.model.nudging import Nudging
from jaxlift.model.sequences import ramped_sequence

TRUTH = dict(beta=0.8e9, cf_con=15.0, d=250.0)


def _log(plant, effects, sections, load=900.0, x0=0.3, seed=0, name="run"):
    ts, pwm = ramped_sequence(sections)
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
    sol = jl.simulate(plant, effects, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
    assert sol.ok
    return jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(seed), name=name), inputs


def _nudging(log, gain, with_speed=True):
    return Nudging.of(log.time_s, log.height_m, log.speed_mps if with_speed else None, gain)


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_gain_zero_is_the_model_itself():
    plant, _ = jl.with_params(jl.Plant(), (), TRUTH)
    log, inputs = _log(plant, (), [(0.0, 1.0), (0.3, 3.0), (0.0, 2.0)])
    ref = jl.simulate(plant, (), inputs)
    nudged = jl.simulate(plant, (), inputs, nudging=_nudging(log, 0.0))
    assert nudged.ok and tree_allclose(nudged.ys, ref.ys, rtol=1e-9, atol=1e-12)


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
@pytest.mark.parametrize("with_speed", [True, False])
def test_a_gain_pulls_a_wrong_model_onto_the_data(with_speed):
    """A model whose motor runs 20 % slow (k1, k2, k3), with half the bulk modulus and
    four times the damping of the truth, simulated against the truth's log: pulled at
    5/s (by height and speed, or by the height alone where a log has no speed), its
    height error is a fraction of the unpulled one's, and stronger pulls bring it closer
    still."""
    truth, _ = jl.with_params(jl.Plant(), (), TRUTH)
    slow = {k: 0.8 * float(getattr(truth, k)) for k in ("k1", "k2", "k3")}
    wrong, _ = jl.with_params(jl.Plant(), (), dict(TRUTH, beta=0.4e9, d=1000.0, **slow))
    log, inputs = _log(truth, (), [(0.0, 1.0), (0.25, 4.0), (0.0, 2.0), (0.4, 3.0)])

    def rms(gain):
        nudging = None if gain is None else _nudging(log, gain, with_speed)
        sol = jl.simulate(wrong, (), inputs, nudging=nudging)
        assert sol.ok
        return float(np.sqrt(np.mean((np.asarray(sol.height) - log.height_m) ** 2)))

    free, weak, strong = rms(None), rms(5.0), rms(50.0)
    assert free > 5e-3  # the wrong model is centimetres off
    assert weak < 0.3 * free and strong < weak


def test_synchronise_rejects_bad_gains_and_the_optimistix_solver():
    with pytest.raises(ValueError, match="finite and >= 0"):
        jl.fit([], synchronise=(3.0, -1.0))
    with pytest.raises(ValueError, match="solver=LM"):
        jl.fit([], synchronise=(3.0,), solver=jl.OptimistixLM())


@pytest.mark.slow
def test_synchronised_fit_of_a_stick_slip_log_reaches_the_truth():
    """A 1.2 kN breakaway force at a Stribeck speed of 4 mm/s on a slow lift (the fork
    sticks and slips), fitted from a start far off (breakaway 150 N at 15 mm/s, bulk
    modulus 30 % low, damping 4x), where the ordinary fit stagnates far above the noise
    floor: the synchronised fit ends at the noise floor with
    the breakaway force, the Stribeck speed and the bulk modulus within three standard
    errors of the truth (and within 10 %)."""
    truth = dict(TRUTH, dFs=1200.0, v_s=0.004)
    effects = jl.make_effects("stick_slip")
    plant, effs = jl.with_params(jl.Plant(), effects, truth)
    sections = [(0.0, 1.0), (0.12, 8.0), (0.0, 1.5), (0.15, 6.0), (0.0, 1.0)]
    log, _ = _log(plant, effs, sections, load=1200.0, x0=0.4, seed=3, name="slow_lift")
    start = dict(truth, dFs=150.0, v_s=0.015, beta=0.56e9, d=1000.0)
    kw = dict(effects="stick_slip", free="beta,cf_con,d,dFs,v_s", init=start, n_starts=1,
              workers=1)  # fmt: skip
    # the ordinary fit from there stagnates (measured: chi2/N 11, dFs 207 N)
    ordinary = jl.fit([log], **kw)
    assert ordinary.chi2 / ordinary.n_residuals > 2.0
    res = jl.fit([log], **kw, synchronise=(10.0, 3.0, 1.0, 0.3, 0.1))
    assert res.chi2 / res.n_residuals < 1.1, res.chi2 / res.n_residuals
    for name in ("dFs", "v_s", "beta"):
        err = abs(res.params[name] - truth[name])
        assert err < 3 * res.stderr[name], (name, res.params[name], res.stderr[name])
        assert err < 0.1 * truth[name], (name, res.params[name])
