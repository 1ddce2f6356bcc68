"""The candidate effects of docs/model.md: nesting, physical direction, registry.

Expected values are computed here by hand from docs/model.md (nominal numbers copied from
its table), never by the library's component laws.

Every run in this file uses one input shape (5 s at 100 Hz: 0.5 s hold, a 0.5 s pwm
ramp, a hold at constant pwm until 3.5 s, then the valve closed) and one solver
tolerance, so each effect structure is compiled once and shared between the nesting
and the direction tests. The tolerance is tight (rtol 1e-9) so that two simulations of
the same ODE agree to ~1e-8 whatever steps the controller takes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import jaxlift as jl
from jaxlift.model.constants import START_CLEARANCE

RTOL = 1e-9
ATOL = (1e-10, 1e-10, 1e-3)  # height m, speed m/s, pressure Pa

# docs/model.md, by hand
G = 9.81
P_ATM = 101325.0
U_BATT = 24.0
K1, Z1 = 1.9, -3.0  # stage 1 motor map
DISP, ETA_V = 43e-6, 0.95
A1, A2 = 28.27e-4, 22.68e-4
R = 2.0
M_ST1, M_ST2 = 100.0, 245.0  # cumulative
V0, BETA = 2.0e-3, 1.4e9
CF_CON, CF_IN, CF_OUT, V_EPS = 10.0, 16.0, 545.0, 1e-3
X_S1 = 1.5

DT = 0.01
TS = np.arange(0.0, 5.0, DT)
T_STOP = 3.5  # valve closes
N_SHIFT = 20  # samples in 0.2 s

MODEL_MD_EFFECTS = [  # docs/model.md, "Candidate effects", in table order
    "stick_slip",
    "motor_inertia",
    "motor_droop",
    "leakage",
    "entrained_air",
    "hose_compliance",
    "mast_compliance",
    "input_delay",
]
MODEL_MD_PARAMS = {  # name -> (unit as in docs/model.md, nesting value or None)
    "dFs": ("N", 0.0),
    "v_s": ("m/s", None),
    "tau_m": ("s", 0.0),
    "kappa": ("rad/(s·Pa)", 0.0),
    "C_L": ("m³/(s·Pa)", 0.0),
    "alpha0": ("-", 0.0),
    "C_h": ("m³/Pa", 0.0),
    "ks_inv": ("m/N", 0.0),
    "c_s": ("N·s/m", None),
    "tau_d": ("s", 0.0),
}
# one value away from nesting per effect, inside the physical bounds
AWAY = {
    "stick_slip": {"dFs": 300.0},
    "motor_inertia": {"tau_m": 0.2},
    "motor_droop": {"kappa": 5e-7},
    "leakage": {"C_L": 1e-12},
    "entrained_air": {"alpha0": 0.1},
    "hose_compliance": {"C_h": 3e-12},
    "mast_compliance": {"ks_inv": 1e-6},
    "input_delay": {"tau_d": 0.2},
}


def pwm_profile(level: float) -> np.ndarray:
    """0 until 0.5 s, a ramp to ``level`` at 1.0 s, ``level`` until 3.5 s, then 0."""
    return np.where(TS < T_STOP, level * np.clip((TS - 0.5) / 0.5, 0.0, 1.0), 0.0)


def inputs(level: float = 0.6, x0: float = 1.35, m_load: float = 1000.0) -> jl.Inputs:
    return jl.Inputs.from_arrays(TS, pwm_profile(level), np.full(TS.shape, m_load), x0)


def sim(plant, effects, inp):
    sol = jl.simulate(plant, effects, inp, rtol=RTOL, atol=ATOL)
    assert bool(sol.ok), sol.result
    return sol


def assert_states_close(actual, desired, rel: float) -> None:
    """|actual - desired| <= rel * (range of each column of desired), column by column."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    assert actual.shape == desired.shape
    scale = np.max(np.abs(desired), axis=0)
    err = np.max(np.abs(actual - desired), axis=0) / scale
    assert np.all(err <= rel), f"max error / scale per column: {err} > {rel}"


def plant_with(**values):
    return jl.with_params(jl.Plant(), (), values)[0]


def stage1_volume(x: float) -> float:
    assert 0.0 <= x < X_S1
    return V0 + A1 * x / R


def zero_crossing_frequency(t: np.ndarray, y: np.ndarray) -> float:
    i = np.nonzero(np.sign(y[:-1]) * np.sign(y[1:]) < 0)[0]
    tc = t[i] - y[i] * (t[i + 1] - t[i]) / (y[i + 1] - y[i])
    assert tc.size >= 8, f"too few zero crossings ({tc.size})"
    return (tc.size - 1) / (2.0 * (tc[-1] - tc[0]))


@pytest.fixture(scope="module")
def baseline():
    """The standard run (ramp, hold, shift 1 -> 2 at ~2.2 s, valve closed) without effects."""
    sol = sim(jl.Plant(), (), inputs())
    h = np.asarray(sol.height)
    assert h[0] < X_S1 < h[-1]  # the run does shift stage
    return sol


# ---------------------------------------------------------------- 1. nesting
NESTING_CASES = [*MODEL_MD_EFFECTS, "all_eight"]


def _effects_for(case: str):
    return jl.make_effects(MODEL_MD_EFFECTS if case == "all_eight" else case)


@pytest.mark.parametrize("case", NESTING_CASES)
def test_nesting_value_gives_baseline_exactly(case, baseline):
    """Within 1e-12 of each signal's range. stick_slip, motor_droop, leakage and
    input_delay are bit-identical to the baseline. hose_compliance and entrained_air add
    a zero to C, which changes how XLA fuses and rounds the right-hand side (1 ulp); the
    step-size controller can amplify that to the solver-tolerance level if a step
    decision flips. At rtol 1e-9 on this input they agree to ~6e-14, but that margin is
    a property of the floating-point path, not of the model."""
    effects = _effects_for(case)
    for e in effects:  # defaults are the nesting values
        for name, info in e.param_infos().items():
            if info.nesting is not None:
                assert float(jl.get_params(e)[name]) == info.nesting
    sol = sim(jl.Plant(), effects, inputs())
    assert_states_close(sol.ys[:, :3], baseline.ys, 1e-12)


@pytest.mark.parametrize("case", NESTING_CASES)
def test_nesting_value_gives_baseline_to_solver_accuracy(case, baseline):
    """The weaker, robust form of the nesting test: two solutions of the same ODE agree
    to the solver's accuracy. At rtol 1e-9 the baseline's own global error is < 1e-8 of
    each signal's range (checked against rtol 1e-11 while writing this test); 1e-6
    leaves room and still catches any term that does not vanish at nesting."""
    sol = sim(jl.Plant(), _effects_for(case), inputs())
    assert_states_close(sol.ys[:, :3], baseline.ys, 1e-6)


# ---------------------------------------------------------------- 2. physical direction
def test_leakage_fork_sinks_while_valve_closed():
    """Valve closed: dp/dt = 0 needs A v / r = -C_L p, so the fork sinks at
    v = -r C_L p / A with A p / r = M g + F_f(v) + d v (solved by fixed point here).
    Stiff damping (d = 2e4) settles the stop transient within the 1.5 s hold."""
    c_l, d, m_load = AWAY["leakage"]["C_L"], 2.0e4, 1000.0
    plant = plant_with(d=d)
    sol = sim(plant, jl.make_effects("leakage", AWAY["leakage"]), inputs())
    base = sim(plant, (), inputs())
    h, v = np.asarray(sol.height), np.asarray(sol.speed)
    assert h[TS >= T_STOP].min() > X_S1 + 0.05  # stage 2 throughout the hold
    v_sink = 0.0
    for _ in range(20):
        force = (m_load + M_ST2) * G + CF_CON * math.tanh(v_sink / V_EPS) + d * v_sink
        force += CF_OUT * (CF_IN * v_sink) ** 5
        v_sink = -R * c_l * (force * R / A2) / A2
    assert v_sink < -5e-3
    last = TS >= TS[-1] - 0.5
    np.testing.assert_allclose(np.mean(v[last]), v_sink, rtol=5e-3)
    # the baseline holds still (the same transient, no sinking)
    assert abs(float(np.mean(base.speed[last]))) < 1e-2 * abs(v_sink)
    # and it sinks during the initial hold too, before any lifting
    assert h[int(0.5 / DT)] < h[0] - 1e-3


def test_input_delay_shifts_the_trajectory():
    """The plant starts at rest and is time-invariant, so a pure delay of tau_d = 0.2 s
    (20 samples) shifts the whole trajectory by 20 samples."""
    plant = jl.Plant()
    base = sim(plant, (), inputs())
    sol = sim(plant, jl.make_effects("input_delay", AWAY["input_delay"]), inputs())
    yb, yd = np.asarray(base.ys), np.asarray(sol.ys)
    assert_states_close(yd[N_SHIFT:], yb[:-N_SHIFT], 1e-7)
    np.testing.assert_array_equal(yd[:N_SHIFT], yb[:1].repeat(N_SHIFT, axis=0))

    def t_start(h):  # first time the fork is 1 mm up
        return TS[np.argmax(h > h[0] + 1e-3)]

    delay = t_start(yd[:, 0]) - t_start(yb[:, 0])
    np.testing.assert_allclose(delay, 0.2, atol=DT / 2)


def test_motor_droop_slows_lifting():
    """omega = k U + z - kappa p; with cf_out = 0 the steady state is linear:
    v = r eta D (k U + z - kappa p) / (2 pi A),  p = (M g + cf_con + d v) r / A."""
    kappa, d, m_load, level = AWAY["motor_droop"]["kappa"], 1.0e4, 1000.0, 0.6
    plant = plant_with(d=d, cf_out=0.0)
    inp = inputs(level, x0=0.3)  # stage 1 throughout
    base = sim(plant, (), inp)
    sol = sim(plant, jl.make_effects("motor_droop", AWAY["motor_droop"]), inp)
    c = R * ETA_V * DISP / (2.0 * math.pi * A1)  # v per rad/s
    m = m_load + M_ST1
    # v = c (w0 - kappa (m g + cf_con + d v) r / A1)  =>  solve for v
    w0 = K1 * level * U_BATT + Z1
    v_hand = c * (w0 - kappa * (m * G + CF_CON) * R / A1) / (1.0 + c * kappa * d * R / A1)
    hold = (TS > 3.0) & (TS < T_STOP)
    np.testing.assert_allclose(np.mean(sol.speed[hold]), v_hand, rtol=1e-3)
    np.testing.assert_allclose(np.mean(base.speed[hold]), c * w0, rtol=1e-3)
    assert v_hand < 0.9 * c * w0  # noticeably slower, at these numbers
    assert float(sol.height[-1]) < float(base.height[-1]) - 0.03


def test_motor_inertia_lags_the_motor_speed():
    """d omega/dt = (omega_ss - omega) / tau_m with a zero-order-held pwm: in stage 1
    omega_ss = max(k1 u U + z1, 0) is constant between samples, so the exact solution
    is omega_{n+1} = omega_ss,n + (omega_n - omega_ss,n) exp(-dt / tau_m)."""
    tau = AWAY["motor_inertia"]["tau_m"]
    level = 0.6
    plant = jl.Plant()
    inp = inputs(level, x0=0.3)  # stage 1 throughout
    base = sim(plant, (), inp)
    sol = sim(plant, jl.make_effects("motor_inertia", AWAY["motor_inertia"]), inp)
    assert sol.state_names[3] == "motor_inertia.omega_m"
    omega_ss = np.maximum(K1 * pwm_profile(level) * U_BATT + Z1, 0.0)
    omega = np.zeros_like(TS)
    for n in range(TS.size - 1):
        omega[n + 1] = omega_ss[n] + (omega[n] - omega_ss[n]) * math.exp(-DT / tau)
    np.testing.assert_allclose(np.asarray(sol.ys[:, 3]), omega, rtol=0, atol=1e-6)
    # the fork's speed rises later (by ~tau_m for a ramp through a first-order lag) ...
    vb, vs = np.asarray(base.speed), np.asarray(sol.speed)
    v_end = float(np.mean(vb[(TS > 3.0) & (TS < T_STOP)]))
    t50 = [TS[np.argmax(v > 0.5 * v_end)] for v in (vb, vs)]
    assert 0.5 * tau < t50[1] - t50[0] < 1.5 * tau
    # ... to the same steady speed
    np.testing.assert_allclose(np.mean(vs[(TS > 3.0) & (TS < T_STOP)]), v_end, rtol=2e-3)


def test_stick_slip_oscillates_at_low_speed():
    """At ~2 cm/s the breakaway term dFs exp(-(v/v_s)^2) tanh(v/v_eps) falls with speed
    (negative damping): the fork sticks and slips, and the speed swings down to zero."""
    level = 0.16  # omega = 1.9 * 0.16 * 24 - 3 = 4.3 rad/s: v ~ 2 cm/s
    plant = jl.Plant()
    inp = inputs(level, x0=0.3)
    base = sim(plant, (), inp)
    sol = sim(plant, jl.make_effects("stick_slip", AWAY["stick_slip"]), inp)
    hold = (TS > 2.0) & (TS < T_STOP)
    vb, vs = np.asarray(base.speed)[hold], np.asarray(sol.speed)[hold]
    v_mean = R * ETA_V * DISP * (K1 * level * U_BATT + Z1) / (2.0 * math.pi * A1)
    np.testing.assert_allclose(np.mean(vb), v_mean, rtol=0.02)
    assert np.std(vs) > 4.0 * np.std(vb)
    assert np.min(vs) < 0.1 * v_mean  # touches zero speed
    assert np.min(vb) > 0.5 * v_mean  # the baseline does not


def _ringdown_frequency(sol) -> tuple[float, float, float]:
    """(frequency of the speed after the valve closes, mean height, mean pressure)."""
    after = TS > T_STOP + 0.1
    f = zero_crossing_frequency(TS[after], np.asarray(sol.speed)[after])
    return f, float(np.mean(sol.height[after])), float(np.mean(sol.pressure[after]))


def _hand_frequency(capacitance: float, mass: float) -> float:
    """Oil spring (A/r)^2 / C on mass M."""
    return math.sqrt((A1 / R) ** 2 / (capacitance * mass)) / (2.0 * math.pi)


# The valve closes at 3.5 s while the fork lifts at ~2 cm/s: the fork rings. cf_con =
# cf_out = 0 make the plant linear and lightly damped (only d = 300 N s/m), see
# test_physics.py::test_hydraulic_ringdown_frequency.
RING_LEVEL, RING_X0, RING_LOAD = 0.16, 0.7, 1000.0


@pytest.fixture(scope="module")
def ring_plant():
    return plant_with(cf_con=0.0, cf_out=0.0)


@pytest.fixture(scope="module")
def ring_baseline(ring_plant):
    sol = sim(ring_plant, (), inputs(RING_LEVEL, RING_X0, RING_LOAD))
    f, x, _ = _ringdown_frequency(sol)
    m = RING_LOAD + M_ST1
    np.testing.assert_allclose(f, _hand_frequency(stage1_volume(x) / BETA, m), rtol=0.01)
    return f


def test_hose_compliance_lowers_frequency(ring_plant, ring_baseline):
    c_h = AWAY["hose_compliance"]["C_h"]
    effects = jl.make_effects("hose_compliance", AWAY["hose_compliance"])
    sol = sim(ring_plant, effects, inputs(RING_LEVEL, RING_X0, RING_LOAD))
    f, x, _ = _ringdown_frequency(sol)
    f_hand = _hand_frequency(stage1_volume(x) / BETA + c_h, RING_LOAD + M_ST1)
    np.testing.assert_allclose(f, f_hand, rtol=0.01)
    assert f < 0.8 * ring_baseline


def test_entrained_air_lowers_frequency(ring_plant, ring_baseline):
    """C = V (1/beta + alpha0 p_atm / p_abs^2); the library uses the absolute pressure
    in Boyle's law (documented deviation from docs/model.md's gauge ``p``), so do we."""
    alpha0 = AWAY["entrained_air"]["alpha0"]
    effects = jl.make_effects("entrained_air", AWAY["entrained_air"])
    sol = sim(ring_plant, effects, inputs(RING_LEVEL, RING_X0, RING_LOAD))
    f, x, p = _ringdown_frequency(sol)
    v = stage1_volume(x)
    f_hand = _hand_frequency(v * (1.0 / BETA + alpha0 * P_ATM / (p + P_ATM) ** 2), 1100.0)
    np.testing.assert_allclose(f, f_hand, rtol=0.01)
    assert f < 0.95 * ring_baseline


def test_mast_compliance_carriage_is_the_height_state(ring_plant, ring_baseline):
    """The load rides on a spring k_s = 1/ks_inv on the carriage: a two-mass system
    (carriage m_st on the oil spring, load on k_s). Its lower mode is below the rigid
    frequency. The first state is still the carriage height (the wire sensor), which
    starts at x0 at rest; the load hangs at delta = -m_load g / k_s."""
    ks_inv = AWAY["mast_compliance"]["ks_inv"]
    inp = inputs(RING_LEVEL, RING_X0, RING_LOAD)
    sol = sim(ring_plant, jl.make_effects("mast_compliance", AWAY["mast_compliance"]), inp)
    assert sol.state_names[:5] == (
        "height_m",
        "speed_mps",
        "pressure_pa",
        "mast_compliance.delta",
        "mast_compliance.delta_rate",
    )
    y = np.asarray(sol.ys)
    x_start = RING_X0 + START_CLEARANCE  # docs/model.md: every start 1 µm up
    assert y[0, 0] == x_start and y[0, 1] == 0.0 and y[0, 4] == 0.0
    np.testing.assert_allclose(y[0, 3], -RING_LOAD * G * ks_inv, rtol=1e-12)
    # at rest during the initial hold: carriage at x0, load hanging still
    hold = TS < 0.5
    np.testing.assert_allclose(y[hold, 0], x_start, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y[hold, 3], -RING_LOAD * G * ks_inv, rtol=1e-6)
    # the lower mode of the two-mass system, by hand
    f, x, _ = _ringdown_frequency(sol)
    k_oil = BETA * (A1 / R) ** 2 / stage1_volume(x)
    k_s = 1.0 / ks_inv
    stiffness = np.array([[k_oil + k_s, -k_s], [-k_s, k_s]])
    masses = np.diag([M_ST1, RING_LOAD])
    w2 = np.sort(np.linalg.eigvals(np.linalg.solve(masses, stiffness)).real)
    np.testing.assert_allclose(f, math.sqrt(w2[0]) / (2.0 * math.pi), rtol=0.02)
    assert f < 0.9 * ring_baseline


# ---------------------------------------------------------------- 3. the registry
def test_registry_names_are_model_md_names():
    assert list(jl.EFFECTS) == MODEL_MD_EFFECTS
    for name, cls in jl.EFFECTS.items():
        assert cls.name == name
        assert issubclass(cls, jl.AbstractEffect)


def _unit(s: str) -> str:
    """Spelling-insensitive unit: 'm³/(s·Pa)' == 'm^3/(s Pa)'."""
    return s.replace("³", "3").replace("^", "").replace("·", "").replace(" ", "")


def test_effect_parameters_have_units_bounds_and_nesting():
    seen = {}
    for cls in jl.EFFECTS.values():
        for name, info in cls.param_infos().items():
            assert name not in seen, f"{name} is declared twice"
            seen[name] = info
    assert set(seen) == set(MODEL_MD_PARAMS)
    plant_names = set(jl.param_infos(jl.Plant))
    assert not plant_names & set(seen)  # flat names are unique across the model
    for name, info in seen.items():
        unit, nesting = MODEL_MD_PARAMS[name]
        assert info.unit and _unit(info.unit) == _unit(unit), (name, info.unit)
        assert info.description
        assert math.isfinite(info.lower) and math.isfinite(info.upper)
        assert info.lower < info.upper
        assert info.lower <= info.nominal <= info.upper
        if nesting is None:
            assert info.nesting is None, name
        else:
            assert info.nesting == nesting, name
            assert info.nominal == nesting, f"{name}: default is not the nesting value"
            assert info.lower == nesting, f"{name}: docs/model.md says {name} >= {nesting}"
    # the away-from-nesting values used in this file are physical
    for values in AWAY.values():
        for name, value in values.items():
            seen[name].check(value)


def test_effect_order_does_not_matter():
    effects = jl.make_effects(MODEL_MD_EFFECTS, {k: v for d in AWAY.values() for k, v in d.items()})
    assert [e.name for e in effects] == MODEL_MD_EFFECTS
    inp = inputs()
    forward = sim(jl.Plant(), effects, inp)
    backward = sim(jl.Plant(), tuple(reversed(effects)), inp)
    assert forward.state_names == backward.state_names
    np.testing.assert_array_equal(np.asarray(forward.ys), np.asarray(backward.ys))


def test_make_effects_unknown_name():
    with pytest.raises(ValueError, match="no_such_effect"):
        jl.make_effects("leakage,no_such_effect")
    with pytest.raises(ValueError, match="stickslip"):
        jl.make_effects(["stickslip"])


def test_make_effects_values_and_order():
    effects = jl.make_effects("input_delay, leakage", {"C_L": 2e-12, "tau_d": 0.1})
    assert [e.name for e in effects] == ["leakage", "input_delay"]  # registry order
    assert float(effects[0].C_L) == 2e-12 and float(effects[1].tau_d) == 0.1
