"""The controller and the closed loop: law, stops, sampled vs continuous, noise,
anti-windup, stability, gains files, and the closed-loop gradient against central
finite differences.

All runs are short (10--20 s references) on a fixed plant near the calibrated one of
the shipped data (beta 0.4 GPa, the fit's friction), 1000 kg unless said otherwise.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import finite_difference_grad

import jaxlift as jl
from jaxlift.control.closed_loop import SampledFilterWarning, simulate_closed_loop
from jaxlift.control.controller import (
    PID,
    THESIS_PI,
    THESIS_PID,
    ScheduledPID,
    controller_from_gains,
    load_gains,
    save_gains,
)
from jaxlift.control.gains import GainSpace
from jaxlift.control.performance import bandpass, cost_from_figures, figures
from jaxlift.control.reference import Reference, thesis_reference
from jaxlift.control.stability import closed_loop_eigenvalues

# the baseline fit of the shipped logs (runs/fit_baseline), rounded
CALIBRATED = {
    "k1": 2.045, "k2": 1.949, "k3": 1.804, "z1": -2.57, "z2": -3.292, "z3": -4.419,
    "beta": 4.04e8, "cf_con": 0.0, "cf_in": 13.5, "cf_out": 768.0, "d": 557.0,
}  # fmt: skip
PLANT = jl.with_params(jl.Plant(), (), CALIBRATED)[0]
# slow, fast through the first stage shift, slow, stop
REF = Reference.from_sections(
    [(0.0, 1.0), (0.025, 5.0), (0.09, 4.0), (0.025, 6.0), (0.0, 2.0)], m_load=1000.0, x0=1.2
)
PID_AW = PID().with_gains({**THESIS_PID, "K_aw": 15.0})


def test_reference_and_thesis_sequence():
    ref = thesis_reference(1000.0)
    h = ref.height()
    assert 100 < ref.t1 < 130
    assert h[0] == pytest.approx(0.2) and 4.0 < h[-1] < 4.45  # whole lift, inside the mast
    v = np.asarray(ref.v(ref.ts))
    assert v.max() == pytest.approx(0.09) and np.any(np.isclose(v, 0.025))
    assert np.any(h < 1.5) and np.any(h > 3.0)  # both stage shifts crossed


def test_step_response_reaches_reference():
    sol = simulate_closed_loop(PLANT, (), PID_AW, REF).check()
    t = np.asarray(sol.ts)
    v = np.asarray(sol.speed)
    for t_end, level in ((6.0, 0.025), (10.0, 0.09), (16.0, 0.025)):
        window = (t > t_end - 1.0) & (t <= t_end)
        assert abs(v[window].mean() - level) < 0.02 * level
    # stopped: valve shut, fork at rest, controller states held
    stop = t > 17.0  # after the ramp down
    assert np.all(np.asarray(sol.u)[stop] == 0.0)
    assert abs(v[stop].mean()) < 5e-4 and np.abs(v[stop]).max() < 5e-3  # sealed: rings
    q = np.asarray(sol.q_I)
    assert np.all(q[t < 1.0] == 0.0)  # held (at 0) during the initial hold
    assert np.ptp(q[t > 17.0]) == 0.0


def test_law_clips_and_stops():
    out = PID().output(PLANT, jnp.asarray(1.0), 1000.0, jnp.asarray(0.1), 0.0, 0.0, True)
    assert float(out.u) == 1.0 and float(out.u_raw) > 1.0
    out = PID().output(PLANT, jnp.asarray(1.0), 1000.0, jnp.asarray(-0.1), 0.0, 0.0, True)
    assert float(out.u) == 0.0
    out = PID().output(PLANT, jnp.asarray(1.0), 1000.0, jnp.asarray(0.1), 0.3, 0.0, False)
    assert float(out.u) == 0.0 and float(out.dq_I) == 0.0 and float(out.deta) == 0.0


@pytest.mark.slow
def test_sampled_converges_to_continuous():
    cont = simulate_closed_loop(PLANT, (), PID_AW, REF).check()
    errs = []
    for T_c in (0.01, 0.002, 0.0005):
        samp = simulate_closed_loop(PLANT, (), PID_AW, REF, sampled=True, T_c=T_c).check()
        errs.append(float(jnp.max(jnp.abs(samp.speed - cont.speed))))
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 0.1 * errs[0] and errs[2] < 5e-4  # m/s


def test_noise_is_repeatable_and_seeded():
    a = simulate_closed_loop(PLANT, (), PID_AW, REF, noise_seed=3)
    b = simulate_closed_loop(PLANT, (), PID_AW, REF, noise_seed=3)
    c = simulate_closed_loop(PLANT, (), PID_AW, REF, noise_seed=4)
    assert bool(a.ok) and bool(c.ok)
    np.testing.assert_array_equal(np.asarray(a.ys), np.asarray(b.ys))
    assert not np.allclose(np.asarray(a.speed), np.asarray(c.speed))
    noise = np.asarray(a.v_meas - a.speed)
    assert 2.5e-3 < noise.std() < 4.0e-3  # sigma = sqrt(1e-7 / 0.01) = 3.16 mm/s
    # held for 10 ms: the output samples (10 ms apart) see independent values
    assert abs(np.corrcoef(noise[1:], noise[:-1])[0, 1]) < 0.1


def test_anti_windup_removes_offset_after_stage_shift():
    """A fast lift slowed down just before the first stage shift, 1500 kg: the valve
    shuts while the fork runs on and the integral winds down; without anti-windup the
    error 1.5-4.5 s after the shift is off by ~3 mm/s, with K_aw = I/P it is mostly
    gone (docs/control.md: anti-windup mainly cures windup at u = 0 when slowing down)."""
    ref = Reference.from_sections(
        [(0.0, 1.0), (0.09, 3.0), (0.02, 8.0), (0.0, 2.0)], m_load=1500.0, x0=1.35, ramp_s=0.2
    )
    off = {}
    for k_aw in (0.0, 15.0):
        ctrl = PID().with_gains({**THESIS_PID, "K_aw": k_aw})
        sol = simulate_closed_loop(PLANT, (), ctrl, ref).check()
        off[k_aw] = float(figures(sol).shift_offset[0])
    assert abs(off[0.0]) > 1e-3
    assert abs(off[15.0]) < 0.25 * abs(off[0.0])


def test_pi_unstable_at_slow_speed_pid_stable():
    for x in (0.75, 2.25, 3.75):
        eig_pi, u, found = closed_loop_eigenvalues(
            PLANT, (), PID().with_gains(THESIS_PI), 1000.0, x, 0.025
        )
        assert found and 0 < u < 1
        assert eig_pi.real.max() > 0.5
        eig_pid, _, found = closed_loop_eigenvalues(
            PLANT, (), PID().with_gains(THESIS_PID), 1000.0, x, 0.025
        )
        assert found and eig_pid.real.max() < -0.5
    # and the nonlinear simulation agrees: PI oscillates, PID does not
    ref = Reference.from_sections([(0.0, 1.0), (0.025, 12.0), (0.0, 2.0)], x0=2.0)
    osc = {}
    for name, g in (("PI", THESIS_PI), ("PID", THESIS_PID)):
        sol = simulate_closed_loop(PLANT, (), PID().with_gains(g), ref).check()
        osc[name] = float(figures(sol).osc_sustained)
    assert osc["PI"] > 10 * osc["PID"] and osc["PI"] > 2e-3


def test_scheduled_equal_to_plain_when_flat():
    sched = ScheduledPID.from_pid(PID_AW)
    a = simulate_closed_loop(PLANT, (), PID_AW, REF)
    b = simulate_closed_loop(PLANT, (), sched, REF)
    np.testing.assert_allclose(np.asarray(a.ys), np.asarray(b.ys), rtol=1e-9, atol=1e-9)
    g = ScheduledPID.from_stage_gains(
        np.full((3, 3), 10.0), np.full((3, 3), 30.0), 100.0, 0.0, masses=(500.0, 1500.0)
    )
    np.testing.assert_allclose(np.asarray(g.stage_gains(1000.0)), 20.0)
    np.testing.assert_allclose(float(g.P_m2), 0.02)


def test_gains_file_roundtrip_and_errors(tmp_path):
    path = tmp_path / "gains.json"
    save_gains(path, PID_AW, comment="test")
    assert load_gains(path).gain_values() == PID_AW.gain_values()
    sched = ScheduledPID.from_pid(PID_AW)
    save_gains(tmp_path / "s.json", sched)
    assert isinstance(load_gains(tmp_path / "s.json"), ScheduledPID)
    with pytest.raises(jl.ParameterError, match="'P'.*outside its bounds"):
        controller_from_gains({"P": -1.0, "I": 300.0})
    path.write_text(json.dumps({"P": 20.0, "Kp": 3.0}))
    with pytest.raises(jl.ParameterError, match="unknown parameter 'Kp'"):
        load_gains(path)
    with pytest.raises(jl.ParameterError, match="D_b2.*negative"):
        controller_from_gains({"D_b2": 1.0, "D_m2": -0.01})
    with pytest.raises(jl.ParameterError, match="not found"):
        load_gains(tmp_path / "missing.json")


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_input_delay_closed_loop():
    """The sampled form delays the held duties exactly: replaying the controller's
    duties open loop through ``simulate`` with the same ``input_delay`` reproduces the
    closed-loop trajectory."""
    eff = jl.make_effects("input_delay", {"tau_d": 0.0})
    with pytest.raises(ValueError, match="input_delay.*sampled"):
        simulate_closed_loop(PLANT, eff, PID_AW, REF)
    base = simulate_closed_loop(PLANT, (), PID_AW, REF, sampled=True).check()
    zero = simulate_closed_loop(PLANT, eff, PID_AW, REF, sampled=True).check()
    np.testing.assert_allclose(np.asarray(zero.ys), np.asarray(base.ys), rtol=1e-9, atol=1e-9)
    eff = jl.make_effects("input_delay", {"tau_d": 0.035})
    late = simulate_closed_loop(PLANT, eff, PID_AW, REF, sampled=True).check()
    assert not np.allclose(np.asarray(late.speed), np.asarray(base.speed), atol=1e-4)
    ts = np.asarray(late.ts)
    inputs = jl.Inputs.from_arrays(ts, np.asarray(late.u), np.full(ts.shape, 1000.0), 1.2)
    replay = jl.simulate(PLANT, eff, inputs).check()
    np.testing.assert_allclose(np.asarray(replay.height), np.asarray(late.height), atol=2e-6)
    np.testing.assert_allclose(np.asarray(replay.speed), np.asarray(late.speed), atol=2e-5)


def test_fast_filter_in_sampled_form_warns():
    ctrl = PID().with_gains({**THESIS_PID, "N": 10000.0})
    with pytest.warns(SampledFilterWarning, match="N T_c"):
        simulate_closed_loop(PLANT, (), ctrl, REF, sampled=True)


def test_bandpass_passes_band_only():
    t = np.arange(0, 20, 0.01)
    inband = np.sin(2 * np.pi * 2.0 * t)
    slow = np.sin(2 * np.pi * 0.05 * t)
    fast = np.sin(2 * np.pi * 40.0 * t)
    out = np.asarray(bandpass(jnp.asarray(inband + slow + fast)))
    mid = slice(300, -300)
    np.testing.assert_allclose(out[mid], inband[mid], atol=0.06)


def _cost_fn(space, sampled, rtol):
    def f(theta):
        sol = simulate_closed_loop(
            PLANT,
            (),
            space.from_theta(theta),
            REF,
            sampled=sampled,
            rtol=rtol,
            atol=(1e-11, 1e-11, 1e-4),
        )
        return cost_from_figures(figures(sol))

    return f


@pytest.mark.slow
def test_closed_loop_gradient_matches_finite_differences_sampled():
    """Sampled form (10 ms clock): u is constant over each period, so the cost is
    smooth almost everywhere; AD and central FD (step 1e-5 in log-gain) agree to 1e-4."""
    space = GainSpace.for_controller(PID_AW)
    theta = space.to_theta(PID_AW)
    f = _cost_fn(space, True, 1e-10)
    g_ad = np.asarray(jax.jit(jax.grad(f))(jnp.asarray(theta)))
    g_fd = finite_difference_grad(jax.jit(f), theta, rel_step=1e-5)
    assert np.all(np.abs(g_fd) > 1e-3)  # every gain matters
    np.testing.assert_allclose(g_ad, g_fd, rtol=1e-4)


@pytest.mark.slow
def test_closed_loop_gradient_matches_finite_differences_continuous():
    """Continuous form: the clip at 0 and 1 puts kinks inside solver steps, so the
    discrete solution is only piecewise smooth in the gains and central differences
    with steps below ~1e-5 are dominated by step-sequence noise (effort uses second
    differences of the 10 ms averages). With a 1e-4 step AD and FD agree to 2 %
    (measured: <= 0.5 % on each figure, 2.4 % on the smallest cost component)."""
    space = GainSpace.for_controller(PID_AW)
    theta = space.to_theta(PID_AW)
    f = _cost_fn(space, False, 1e-10)
    g_ad = np.asarray(jax.jit(jax.grad(f))(jnp.asarray(theta)))
    g_fd = finite_difference_grad(jax.jit(f), theta, rel_step=1e-4)
    scale = np.linalg.norm(g_fd)
    np.testing.assert_allclose(g_ad, g_fd, rtol=0.03, atol=2e-3 * scale)
    # the largest component (P) to 0.1 %
    i = int(np.argmax(np.abs(g_fd)))
    assert abs(g_ad[i] - g_fd[i]) < 1e-3 * abs(g_fd[i])
