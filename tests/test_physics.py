"""The baseline plant against hand calculations from docs/model.md.

Every expected value here is computed in this file from docs/model.md's formulas and
nominal numbers (the table "Nominal parameters"), never by calling the plant's own
component laws: the simulation is the thing under test.

All runs share one input shape (5 s at 100 Hz, at most one input change), so the
simulation is compiled once for the whole file (plus once for the ``max_steps`` test).
"""

from __future__ import annotations

import math

import diffrax
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.model.constants import START_CLEARANCE

# ---------------------------------------------------------------- docs/model.md, by hand
G = 9.81  # m/s^2
U_BATT = 24.0  # V
K = (1.9, 1.8, 1.7)  # rad/(s V), stages 1..3
Z = (-3.0, -3.5, -4.0)  # rad/s
DISP = 43e-6  # m^3/rev
ETA_V = 0.95
AREA = (28.27e-4, 22.68e-4, 22.68e-4)  # m^2
R = 2.0  # fork speed / piston speed
M_ST = (100.0, 245.0, 385.0)  # kg, cumulative stage masses
V0 = 2.0e-3  # m^3
BETA = 1.4e9  # Pa
CF_CON, CF_IN, CF_OUT, D = 10.0, 16.0, 545.0, 300.0
V_EPS = 1e-3  # m/s
X_S1, X_S2, X_MAX = 1.5, 3.0, 4.5  # m

DT = 0.01  # s, 100 Hz
TS = np.arange(0.0, 5.0, DT)  # the one time grid of this file (500 samples)


def stage(x: float) -> int:
    """Index (0, 1, 2) of the stage active at height ``x`` (away from the boundaries)."""
    assert min(abs(x - X_S1), abs(x - X_S2)) > 0.05, "too close to a stage boundary"
    return 0 if x < X_S1 else (1 if x < X_S2 else 2)


def volume(x: float) -> float:
    """V(x) of docs/model.md item 5."""
    stroke = (
        AREA[0] * min(max(x, 0.0), X_S1)
        + AREA[1] * min(max(x - X_S1, 0.0), X_S2 - X_S1)
        + AREA[2] * max(x - X_S2, 0.0)
    )
    return V0 + stroke / R


def static_pressure(x: float, m_load: float) -> float:
    """p = M(x) g r / A(x) (docs/model.md, initial state)."""
    i = stage(x)
    return (m_load + M_ST[i]) * G * R / AREA[i]


def friction(v: float, cf_con: float = CF_CON, cf_out: float = CF_OUT) -> float:
    """F_f(v) of docs/model.md item 6."""
    return cf_con * math.tanh(v / V_EPS) + cf_out * (CF_IN * v) ** 5


def lifting_speed(x: float, pwm: float) -> float:
    """Steady fork speed r Q / A with Q = eta_v D omega / (2 pi), omega = k u U_batt + z."""
    i = stage(x)
    omega = max(K[i] * pwm * U_BATT + Z[i], 0.0)
    q = ETA_V * DISP * omega / (2.0 * math.pi)
    return R * q / AREA[i]


def lifting_pressure(x: float, m_load: float, v: float, d: float = D, **fric) -> float:
    """Pressure at steady speed v: A p / r = M g + F_f(v) + d v (docs/model.md item 7)."""
    i = stage(x)
    return ((m_load + M_ST[i]) * G + friction(v, **fric) + d * v) * R / AREA[i]


# ---------------------------------------------------------------- helpers
def run(plant, pwm, load, x0, **kw):
    """Simulate the file's 5 s grid with ``pwm``/``load`` arrays (or constants)."""
    pwm = np.broadcast_to(np.asarray(pwm, dtype=float), TS.shape)
    load = np.broadcast_to(np.asarray(load, dtype=float), TS.shape)
    inputs = jl.Inputs.from_arrays(TS, pwm, load, x0)
    return jl.simulate(plant, (), inputs, **kw)


def plant_with(**values):
    return jl.with_params(jl.Plant(), (), values)[0]


def zero_crossing_frequency(t: np.ndarray, y: np.ndarray) -> float:
    """Frequency [Hz] from the linearly interpolated sign changes of ``y``."""
    i = np.nonzero(np.sign(y[:-1]) * np.sign(y[1:]) < 0)[0]
    tc = t[i] - y[i] * (t[i + 1] - t[i]) / (y[i + 1] - y[i])
    assert tc.size >= 8, f"too few zero crossings ({tc.size}) to measure a frequency"
    return (tc.size - 1) / (2.0 * (tc[-1] - tc[0]))


# ---------------------------------------------------------------- 1. static equilibrium
@pytest.mark.parametrize("m_load", [0.0, 800.0, 2500.0])
@pytest.mark.parametrize("x0", [0.5, 2.0, 4.0])
def test_static_equilibrium_holds(x0, m_load):
    sol = run(jl.Plant(), 0.0, m_load, x0)
    assert bool(sol.ok)
    p_hand = static_pressure(x0, m_load)
    # every start is START_CLEARANCE (1 µm) above x0 (docs/model.md, initial state)
    np.testing.assert_allclose(np.asarray(sol.height), x0 + START_CLEARANCE, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.speed), 0.0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(float(sol.pressure[0]), p_hand, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(sol.pressure), p_hand, rtol=1e-9)


# ---------------------------------------------------------------- 2. steady lifting speed
# Stiff damping d = 1e4 N s/m and no fifth-power friction: the hydraulic mode (2-5 Hz)
# then has a damping ratio of 0.1-0.3 and decays at d / (2 M) >= 2.6 1/s (M <= 1885 kg
# here), so it has died out (< 1e-4) before the last second, which is averaged. (The
# nominal fifth-power friction, steep at 0.1 m/s, overdamps the mode and leaves a slow
# tail of ~0.5 s instead.) The steady speed r Q / A follows from dp/dt = 0 alone and
# depends on neither damping nor friction.
@pytest.mark.parametrize(
    ("x0", "pwm", "m_load"),
    [(0.3, 0.5, 1000.0), (0.3, 0.7, 500.0), (1.8, 0.6, 1000.0), (3.2, 0.6, 1500.0)],
)
def test_steady_lifting_speed(x0, pwm, m_load):
    d = 1.0e4
    sol = run(plant_with(d=d, cf_out=0.0), pwm, m_load, x0)
    assert bool(sol.ok)
    last = TS >= TS[-1] - 1.0
    x_last = float(np.mean(sol.height[last]))
    assert stage(x0) == stage(x_last), "the run left its stage"
    v_hand = lifting_speed(x0, pwm)
    np.testing.assert_allclose(float(np.mean(sol.speed[last])), v_hand, rtol=5e-3)
    # and the pressure that pushes it: A p / r = M g + cf_con + d v (cf_out = 0)
    p_hand = lifting_pressure(x_last, m_load, v_hand, d=d, cf_out=0.0)
    np.testing.assert_allclose(float(np.mean(sol.pressure[last])), p_hand, rtol=5e-3)


# ---------------------------------------------------------------- 3. hydraulic frequency
# Valve closed; a +2 % load step at t = 0.5 s (zero-order held) kicks the fork. With
# cf_con = cf_out = 0 the plant is linear spring (oil, k = beta (A/r)^2 / V) on mass
# (M = m_load + m_st) with only the viscous d = 300 N s/m: damping ratio
# d / (2 sqrt(k M)) < 1 %, so the ringing lasts the whole run and the damped frequency
# equals the undamped one to < 1e-4. (The Coulomb term cf_con tanh(v / 1 mm/s) would act
# at these mm/s speeds like a relay with a slope of 1e4 N s/m and stop the ringing.)
@pytest.mark.parametrize("x0", [0.7, 2.2, 3.8])
def test_hydraulic_ringdown_frequency(x0):
    m0 = 1000.0
    m1 = 1.02 * m0
    load = np.where(TS >= 0.5, m1, m0)
    sol = run(plant_with(cf_con=0.0, cf_out=0.0), 0.0, load, x0)
    assert bool(sol.ok)
    after = TS > 0.55
    f_sim = zero_crossing_frequency(TS[after], np.asarray(sol.speed)[after])
    i = stage(x0)
    k_oil = BETA * (AREA[i] / R) ** 2 / volume(x0)
    f_hand = math.sqrt(k_oil / (m1 + M_ST[i])) / (2.0 * math.pi)
    assert 1.0 < f_hand < 6.0  # sanity of the hand numbers (docs/model.md: 1-3 Hz at ~1000 kg)
    np.testing.assert_allclose(f_sim, f_hand, rtol=0.03)
    # a small signal: a step force dF on a spring k overshoots to twice the static
    # deflection dF / k (a millimetre or so)
    peak = float(np.max(np.abs(np.asarray(sol.height) - x0)))
    np.testing.assert_allclose(peak, 2.0 * (m1 - m0) * G / k_oil, rtol=0.05)


def test_ringdown_frequency_falls_with_height():
    load = np.where(TS >= 0.5, 1020.0, 1000.0)
    plant = plant_with(cf_con=0.0, cf_out=0.0)
    after = TS > 0.55
    freqs = [
        zero_crossing_frequency(TS[after], np.asarray(run(plant, 0.0, load, x0).speed)[after])
        for x0 in (0.7, 2.2, 3.8)
    ]
    assert freqs[0] > freqs[1] > freqs[2]


# ---------------------------------------------------------------- 4. stage shift
def test_fork_stalls_at_stage_boundary():
    """Lift at pwm 0.3 through x_s1 = 1.5 m with 1000 kg.

    Stage 1 and stage 2 are each at steady speed r Q_i / A_i and at their lifting
    pressure (M_i g + F_f(v) + d v) r / A_i. At the boundary the fork needs a higher
    pressure (heavier stage, smaller area), so it slows while the pump builds the
    pressure up. With docs/model.md's blend width w = 5 mm the stall is partial: quasi-
    statically (p = p_static(x) along the blend) the speed at x_s1 is
    Q / (A/r + C dp_static/dx) ~ 0.6 of the stage-1 speed at these numbers; the fork's
    inertia makes the dip a bit deeper. We require < 0.7.
    """
    pwm, m_load, x0 = 0.3, 1000.0, 1.35
    sol = run(jl.Plant(), pwm, m_load, x0)
    assert bool(sol.ok)
    h, v, p = (np.asarray(a) for a in (sol.height, sol.speed, sol.pressure))
    assert np.all(np.diff(h) >= 0.0), "the fork went down while lifting"

    v1, v2 = lifting_speed(1.4, pwm), lifting_speed(1.6, pwm)
    p1 = lifting_pressure(1.4, m_load, v1)
    p2 = lifting_pressure(1.6, m_load, v2)
    p_static1, p_static2 = static_pressure(1.4, m_load), static_pressure(1.6, m_load)
    assert p_static2 > 1.3 * p_static1  # the hand numbers: a real step up

    before = (h > 1.42) & (h < 1.47)  # steady stage 1, before the blend
    after = (h > 1.54) & (TS >= TS[-1] - 0.7)  # steady stage 2, at the end
    assert before.sum() >= 20 and after.sum() >= 20
    np.testing.assert_allclose(np.mean(v[before]), v1, rtol=5e-3)
    np.testing.assert_allclose(np.mean(p[before]), p1, rtol=5e-3)
    np.testing.assert_allclose(np.mean(v[after]), v2, rtol=5e-3)
    np.testing.assert_allclose(np.mean(p[after]), p2, rtol=5e-3)

    near = np.abs(h - X_S1) < 0.03
    i_min = np.flatnonzero(near)[np.argmin(v[near])]
    assert 0.0 < v[i_min] < 0.7 * v1, f"no stall: min speed {v[i_min]:.4f} m/s, v1 = {v1:.4f}"
    assert abs(h[i_min] - X_S1) < 0.01  # the stall is at the boundary
    assert p1 < p[i_min] < p2  # the pressure is on its way up
    # the pressure climbs from stage 1's to stage 2's while the fork crosses the blend
    x_mid = np.interp(0.5 * (p1 + p2), p[near], h[near])
    assert abs(x_mid - X_S1) < 0.01
    assert v[-1] > 0.9 * v2  # and lifting resumes


# ---------------------------------------------------------------- 5. end stop
def test_lifting_past_full_height_is_reported():
    sol = run(jl.Plant(), 0.6, 1000.0, 4.2)  # ~0.12 m/s for 5 s: past 4.5 m at ~2.6 s
    assert float(np.max(sol.height)) > X_MAX + 0.05
    assert sol.result == diffrax.RESULTS.successful  # the solver itself was fine
    assert not bool(sol.in_range)
    assert not bool(sol.ok)
    with pytest.raises(jl.SimulationError, match="range"):
        sol.check()


def test_run_within_range_is_ok():
    sol = run(jl.Plant(), 0.6, 1000.0, 3.6)  # ends at ~4.2 m
    assert float(np.max(sol.height)) < X_MAX
    assert bool(sol.in_range) and bool(sol.ok)
    assert sol.check() is sol


# ---------------------------------------------------------------- 6. solver failure
def test_max_steps_is_a_result_code_not_an_exception():
    sol = run(jl.Plant(), 0.6, 1000.0, 0.5, max_steps=16)  # does not raise
    assert sol.result != diffrax.RESULTS.successful
    assert sol.result == diffrax.RESULTS.max_steps_reached
    assert not bool(sol.ok)
    with pytest.raises(jl.SimulationError, match="solver"):
        sol.check()
