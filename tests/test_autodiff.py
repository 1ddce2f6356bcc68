"""Transformations of ``simulate``: vmap, reverse and forward mode, no recompiles.

Gradient checks compare against central finite differences at tight solver
tolerances (rtol 1e-10, atol 1e-11 m, 1e-11 m/s, 1e-4 Pa). There the solver's own error
is ~1e-10 of each signal, so the discrete gradient (what AD differentiates) and the
gradient of the exact solution (what FD approximates) agree to far better than the
1e-4 relative tolerance used here. The FD step is 1e-5 relative in log-parameter space:
with ~1e-12 noise in the misfit, the central-difference error is ~1e-7 relative (the
plateau between truncation and round-off, measured while writing these tests), which
leaves a factor of ~100 to the tolerance.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import finite_difference_grad, tree_allclose

import jaxlift as jl

TIGHT = dict(rtol=1e-10, atol=(1e-11, 1e-11, 1e-4))
FD_STEP = 1e-5  # relative step in log-parameter space
GRAD_RTOL = 1e-4

# One model for all gradient checks (so that it is compiled once): the baseline plant
# with two effects away from their nesting values. The run holds, lifts in stage 1 and
# stops at 2 s, so that starting and stopping (where stick-slip acts) are both in it.
TS = np.arange(0.0, 3.0, 0.01)  # 3 s at 100 Hz
PWM = np.where((TS >= 0.3) & (TS < 2.0), 0.5, 0.0)
LOAD = np.full(TS.shape, 1000.0)
INPUTS = jl.Inputs.from_arrays(TS, PWM, LOAD, 0.5)
EFFECTS = jl.make_effects("stick_slip,hose_compliance", {"dFs": 200.0, "C_h": 2e-12})

PLANT_NAMES = ("beta", "cf_con", "d", "k1")
EFFECT_NAMES = ("C_h", "dFs")
NAMES = PLANT_NAMES + EFFECT_NAMES
THETA0 = np.log([1.4e9, 10.0, 300.0, 1.9, 2e-12, 200.0])  # where the gradient is taken
REFERENCE = {"beta": 1.1e9, "cf_con": 20.0, "d": 400.0, "k1": 1.95, "C_h": 3e-12, "dFs": 100.0}


def residuals(theta, ref, adjoint=None):
    """r(theta) = [(h - h_ref) / 1 mm, (v - v_ref) / 1 cm/s, (p - p_ref) / 1 MPa] for
    the log-parameters ``theta`` (named NAMES) against a fixed reference trajectory."""
    plant, effects = jl.with_params(
        jl.Plant(), EFFECTS, dict(zip(NAMES, jnp.exp(theta), strict=True))
    )
    sol = jl.simulate(plant, effects, INPUTS, adjoint=adjoint, **TIGHT)
    h_ref, v_ref, p_ref = ref
    return jnp.concatenate(
        [(sol.height - h_ref) / 1e-3, (sol.speed - v_ref) / 1e-2, (sol.pressure - p_ref) / 1e6]
    )


def misfit(theta, ref):
    return jnp.sum(residuals(theta, ref) ** 2)


@pytest.fixture(scope="module")
def reference():
    plant, effects = jl.with_params(jl.Plant(), EFFECTS, REFERENCE)
    sol = jl.simulate(plant, effects, INPUTS, **TIGHT).check()
    return tuple(np.asarray(a) for a in (sol.height, sol.speed, sol.pressure))


@pytest.fixture(scope="module")
def gradients(reference):
    """(reverse-mode gradient with the default RecursiveCheckpointAdjoint, central FD)."""
    g_ad = np.asarray(jax.grad(misfit)(jnp.asarray(THETA0), reference))
    g_fd = finite_difference_grad(
        lambda th: misfit(jnp.asarray(th), reference), THETA0, rel_step=FD_STEP
    )
    return g_ad, g_fd


# ---------------------------------------------------------------- 1. vmap
def test_vmap_over_plants_equals_loop():
    betas = [1.4e9, 1.0e9, 0.6e9, 1.8e9]
    cf_cons = [10.0, 50.0, 0.0, 200.0]
    plants = [
        jl.with_params(jl.Plant(), (), {"beta": b, "cf_con": c})[0]
        for b, c in zip(betas, cf_cons, strict=True)
    ]

    def run(plant):
        return jl.simulate(plant, EFFECTS, INPUTS, **TIGHT)

    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *plants)
    batched = eqx.filter_vmap(run)(batch)
    looped = [run(p) for p in plants]
    assert all(bool(s.ok) for s in looped)
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *looped)
    assert batched.ys.shape == (4, TS.size, 3)
    assert tree_allclose(batched.ys, stacked.ys, rtol=1e-9)
    assert tree_allclose(batched, stacked, rtol=1e-9)
    assert bool(jnp.all(batched.ok))
    # the batch members really differ (not 4 copies of one run)
    assert float(jnp.max(jnp.abs(batched.pressure[1] - batched.pressure[3]))) > 1e3


# ---------------------------------------------------------------- 2. reverse mode vs FD
def test_reverse_mode_gradient_matches_finite_differences(gradients):
    g_ad, g_fd = (g[: len(PLANT_NAMES)] for g in gradients)
    assert np.all(np.isfinite(g_ad))
    assert np.all(g_fd != 0.0)  # every parameter matters in this run
    np.testing.assert_allclose(g_ad, g_fd, rtol=GRAD_RTOL)


# ---------------------------------------------------------------- 3. forward mode
def test_forward_mode_jacobian(reference, gradients):
    theta0 = jnp.asarray(THETA0)
    jac = np.asarray(
        jax.jacfwd(lambda th: residuals(th, reference, adjoint=diffrax.ForwardMode()))(theta0)
    )
    r0 = np.asarray(residuals(theta0, reference))
    assert jac.shape == (r0.size, len(NAMES))
    # d(sum r^2)/d theta = 2 J^T r: forward and reverse differentiate the same steps
    np.testing.assert_allclose(2.0 * jac.T @ r0, gradients[0], rtol=1e-8)
    # each column against central differences of the residual vector
    for i, name in enumerate(NAMES):
        h = FD_STEP * abs(THETA0[i])
        tp, tm = THETA0.copy(), THETA0.copy()
        tp[i] += h
        tm[i] -= h
        col_fd = (
            np.asarray(residuals(jnp.asarray(tp), reference))
            - np.asarray(residuals(jnp.asarray(tm), reference))
        ) / (2.0 * h)
        err = np.linalg.norm(jac[:, i] - col_fd) / np.linalg.norm(jac[:, i])
        assert err < GRAD_RTOL, f"column {name}: relative error {err:.2e}"


# ---------------------------------------------------------------- 4. effect parameters
def test_effect_parameter_gradient_matches_finite_differences(gradients):
    g_ad, g_fd = (g[len(PLANT_NAMES) :] for g in gradients)
    assert np.all(np.isfinite(g_ad))
    assert np.all(g_fd != 0.0)
    np.testing.assert_allclose(g_ad, g_fd, rtol=GRAD_RTOL)


# ---------------------------------------------------------------- 5. no recompiles
_TRACES: list[int] = []


class _TraceCounter(jl.AbstractEffect):
    """A do-nothing effect whose hook runs (in Python) only when JAX traces the vector
    field: it counts how often ``simulate`` is traced."""

    gain: jax.Array = jl.param(0.0, "-", 0.0, 1.0, "unused", nesting=0.0)

    name: ClassVar[str] = "_trace_counter"
    state_names: ClassVar[tuple[str, ...]] = ()
    state_scales: ClassVar[tuple[float, ...]] = ()
    overrides_acceleration: ClassVar[bool] = False

    def initial_state(self, plant, sig):
        return jnp.zeros((0,))

    def extra_flow(self, plant, z, sig):
        _TRACES.append(1)
        return self.gain * 0.0


def test_new_parameter_values_do_not_recompile():
    ts = np.arange(0.0, 1.23, 0.01)  # a shape no other test uses: the first call traces
    pwm = np.where(ts >= 0.2, 0.4, 0.0)
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full(ts.shape, 800.0), 0.4)
    plant = jl.Plant()
    _TRACES.clear()
    s1 = jl.simulate(plant, (_TraceCounter(),), inputs)
    n_traces = len(_TRACES)
    assert n_traces > 0
    # other parameter values, other input values (same shapes): no new trace
    plant2 = jl.with_params(plant, (), {"beta": 0.9e9, "cf_con": 30.0, "k1": 2.0})[0]
    inputs2 = jl.Inputs.from_arrays(ts, 0.8 * pwm, np.full(ts.shape, 1200.0), 0.9)
    s2 = jl.simulate(plant2, (_TraceCounter(gain=0.5),), inputs2)
    assert len(_TRACES) == n_traces
    assert not np.allclose(np.asarray(s1.ys), np.asarray(s2.ys))  # it did recompute


# ---------------------------------------------------------------- 6. float64 guard
def test_simulate_refuses_float32():
    code = textwrap.dedent(
        """
        import warnings
        warnings.simplefilter("ignore")
        import jax
        import numpy as np
        import jaxlift as jl
        assert not jax.config.read("jax_enable_x64")
        ts = np.arange(0.0, 0.1, 0.01)
        inputs = jl.Inputs.from_arrays(ts, 0 * ts, 0 * ts + 500.0, 1.0)
        try:
            jl.simulate(jl.Plant(), (), inputs)
        except RuntimeError as err:
            print("RuntimeError:", err)
        else:
            print("no error")
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert "RuntimeError:" in out.stdout, out.stdout
    assert "float64" in out.stdout and "jax_enable_x64" in out.stdout
