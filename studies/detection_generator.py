"""Independent synthetic-data generator for a detection-power study of jaxlift's diagnosis.

    python studies/detection_generator.py --out DIR [--seed 0] [--cases N] [--only ID]

Writes ``DIR/<case_id>/{fit_1,fit_2,validation}.csv`` (logs in the format of
docs/data.md) and ``DIR/<case_id>/truth.json`` (every parameter, the hidden effects,
loads, sequences, start heights, seeds) for each case of :func:`make_cases`. A case
whose ``truth.json`` exists is skipped, so an interrupted run resumes.

Independence: this file imports nothing from ``jaxlift`` (nor from ``tests/``). It is
written from docs/model.md with NumPy/SciPy only, along the lines of
``tests/scipy_reference.py`` (plain-float right-hand side, zero-order-held inputs,
integration restarted at every input change) and extends it with the bottom end stop
and all eight candidate effects in their reference forms. The solver is SciPy's
``LSODA`` (automatic switching between Adams and BDF, finite-difference Jacobian),
chosen because the bottom-stop contact (k_es = 1e8 N/m, c_es = 5e5 N*s/m), large
breakaway friction near zero speed and short motor time constants make parts of a run
stiff while the rest is not.

State: ``(x, v, p)`` then, in registry order, ``omega_m`` (motor_inertia) and
``delta, delta_rate`` (mast_compliance). ``x, v`` are the carriage's height and speed
(what the wire sensor and the speed signal measure).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import pathlib
import sys
import time
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.integrate import solve_ivp

GENERATOR_VERSION = "1"

# ---------------------------------------------------------------- constants (docs/model.md)
G = 9.81  # m/s^2
X_S1, X_S2, X_MAX = 1.5, 3.0, 4.5  # m
W_BLEND = 5e-3  # m
V_EPS = 1e-3  # m/s
P_ATM = 101325.0  # Pa
K_ES, C_ES = 1e8, 5e5  # bottom end stop: N/m, N*s/m

# measurement model
TS = 0.01  # s (100 Hz)
SIGMA_H = 0.5e-3  # m
SPEED_NOISE_POWER = 1e-7  # (m/s)^2 * s
SIGMA_V = math.sqrt(SPEED_NOISE_POWER / TS)  # ~3.16e-3 m/s

# solver
METHOD = "LSODA"
RTOL = 1e-6
MAX_STEP = 0.05  # s, inside a segment of constant input
H_LIMIT = 4.4  # m: a simulated height above this re-draws the sequence
P_DESIGN_MAX = 20e6  # Pa: a section's speed is lowered until its steady pressure is below

NOMINAL: dict[str, float] = {
    "u_batt": 24.0,
    "k1": 1.9,
    "k2": 1.8,
    "k3": 1.7,
    "z1": -3.0,
    "z2": -3.5,
    "z3": -4.0,
    "disp": 43e-6,
    "eta_v": 0.95,
    "A1": 28.27e-4,
    "A2": 22.68e-4,
    "A3": 22.68e-4,
    "ratio": 2.0,
    "m_st1": 100.0,
    "m_st2": 145.0,
    "m_st3": 140.0,
    "V0": 2.0e-3,
    "beta": 1.4e9,
    "cf_con": 10.0,
    "cf_in": 16.0,
    "cf_out": 545.0,
    "d": 300.0,
}

#: Registry order of docs/model.md; parameters at their nesting (or nominal) values.
EFFECTS: tuple[str, ...] = (
    "stick_slip",
    "motor_inertia",
    "motor_droop",
    "leakage",
    "entrained_air",
    "hose_compliance",
    "mast_compliance",
    "input_delay",
)
EFFECT_PARAMS: dict[str, dict[str, float]] = {
    "stick_slip": {"dFs": 0.0, "v_s": 0.01},
    "motor_inertia": {"tau_m": 0.0},
    "motor_droop": {"kappa": 0.0},
    "leakage": {"C_L": 0.0},
    "entrained_air": {"alpha0": 0.0},
    "hose_compliance": {"C_h": 0.0},
    "mast_compliance": {"ks_inv": 0.0, "c_s": 5e3},
    "input_delay": {"tau_d": 0.0},
}
SWITCH = {
    "stick_slip": "dFs",
    "motor_inertia": "tau_m",
    "motor_droop": "kappa",
    "leakage": "C_L",
    "entrained_air": "alpha0",
    "hose_compliance": "C_h",
    "mast_compliance": "ks_inv",
    "input_delay": "tau_d",
}

# ------------------------------------------------------------------------- draw ranges
#: Plant parameters drawn per case: (kind, a, b). "rel": nominal * U(1 - a, 1 + a);
#: "loguniform": log-uniform in [a, b]. Everything else stays nominal.
PLANT_DRAWS: dict[str, tuple[str, float, float]] = {
    "k1": ("rel", 0.20, 0.0),
    "k2": ("rel", 0.20, 0.0),
    "k3": ("rel", 0.20, 0.0),
    "z1": ("rel", 0.30, 0.0),
    "z2": ("rel", 0.30, 0.0),
    "z3": ("rel", 0.30, 0.0),
    "beta": ("loguniform", 0.3e9, 1.6e9),
    "cf_con": ("rel", 0.40, 0.0),
    "cf_in": ("rel", 0.20, 0.0),
    "cf_out": ("rel", 0.40, 0.0),
    "d": ("rel", 0.40, 0.0),
}

#: Size ranges of the hidden effects, in the physical quantity the size is drawn in
#: (log-uniform). Derived parameters: see :func:`effect_params_from_size`.
EFFECT_SIZE_RANGES: dict[str, tuple[str, float, float]] = {
    "stick_slip": ("dFs [N]", 20.0, 2000.0),
    "motor_inertia": ("tau_m [s]", 0.01, 0.5),
    "motor_droop": ("speed drop at 10 MPa [-]", 0.02, 0.30),
    "leakage": ("sink speed at 10 MPa [m/s]", 1e-4, 1e-2),
    "entrained_air": ("alpha0 [-]", 1e-3, 2.0),
    "hose_compliance": ("C_h [m^3/Pa]", 1e-13, 1e-11),
    "mast_compliance": ("ks_inv [m/N]", 1e-7, 1e-5),
    "input_delay": ("tau_d [s]", 0.01, 0.2),
}
V_S_RANGE = (2e-3, 30e-3)  # m/s, log-uniform (stick_slip's Stribeck speed)
ZETA_RANGE = (0.05, 0.5)  # damping ratio of the load on the mast spring, log-uniform
DROOP_P_REF = 1e7  # Pa: pressure at which the droop / leakage sizes are stated
DROOP_U_REF = 0.45  # duty of the reference motor speed for the droop (thesis "fast")
LOAD_RANGE = (100.0, 2000.0)  # kg, log-uniform, three loads per case
LOAD_MIN_RATIO = 1.25  # the three loads of a case differ pairwise by at least this factor
MID_START_RANGE = (0.5, 2.5)  # m
STYLES = ("thesis", "steps", "ramps")
LOG_NAMES = ("fit_1", "fit_2", "validation")


# ============================================================================ the model
def resolve_params(params: Mapping[str, float]) -> dict[str, float]:
    """Nominal plant values and nesting effect values, overridden by ``params``."""
    known = set(NOMINAL)
    for d in EFFECT_PARAMS.values():
        known |= set(d)
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown}")
    out = dict(NOMINAL)
    for d in EFFECT_PARAMS.values():
        out.update(d)
    out.update({k: float(v) for k, v in params.items()})
    return out


def _blend(x: float) -> tuple[float, float]:
    return (
        0.5 * (1.0 + math.tanh((x - X_S1) / W_BLEND)),
        0.5 * (1.0 + math.tanh((x - X_S2) / W_BLEND)),
    )


def stage_quantities(P: Mapping[str, float], x: float) -> dict[str, float]:
    """Stage-blended area, structure mass (cumulative), motor gain and offset at ``x``."""
    s1, s2 = _blend(x)
    return {
        "area": P["A1"] + (P["A2"] - P["A1"]) * s1 + (P["A3"] - P["A2"]) * s2,
        "m_st": P["m_st1"] + P["m_st2"] * s1 + P["m_st3"] * s2,
        "k": P["k1"] + (P["k2"] - P["k1"]) * s1 + (P["k3"] - P["k2"]) * s2,
        "z": P["z1"] + (P["z2"] - P["z1"]) * s1 + (P["z3"] - P["z2"]) * s2,
    }


def oil_volume(P: Mapping[str, float], x: float) -> float:
    """V(x) = V0 + [A1 clip(x,0,xs1) + A2 clip(x-xs1,0,xs2-xs1) + A3 max(x-xs2,0)] / r."""
    a1 = min(max(x, 0.0), X_S1)
    a2 = min(max(x - X_S1, 0.0), X_S2 - X_S1)
    a3 = max(x - X_S2, 0.0)
    return P["V0"] + (P["A1"] * a1 + P["A2"] * a2 + P["A3"] * a3) / P["ratio"]


def friction(P: Mapping[str, float], v: float, stick: bool) -> float:
    tv = math.tanh(v / V_EPS)
    f = P["cf_con"] * tv + P["cf_out"] * (P["cf_in"] * v) ** 5
    if stick:
        f += P["dFs"] * math.exp(-((v / P["v_s"]) ** 2)) * tv
    return f


def active_effects(P: Mapping[str, float]) -> list[str]:
    """Effects whose switch parameter is away from its nesting value 0."""
    return [e for e in EFFECTS if P[SWITCH[e]] != 0.0]


class Model:
    """docs/model.md's lift with the bottom stop and the effects switched on in ``P``."""

    def __init__(self, params: Mapping[str, float]):
        P = resolve_params(params)
        self.P = P
        self.effects = active_effects(P)
        self.inertia = "motor_inertia" in self.effects
        self.mast = "mast_compliance" in self.effects
        self.n = 3 + (1 if self.inertia else 0) + (2 if self.mast else 0)
        self.i_w = 3 if self.inertia else -1
        self.i_d = 3 + (1 if self.inertia else 0) if self.mast else -1
        atol = [1e-7, 1e-7, 1.0]
        if self.inertia:
            atol.append(1e-3)
        if self.mast:
            atol += [1e-7, 1e-6]
        self.atol = np.array(atol)

    # -- the right-hand side on plain floats, for a constant input (u, m_load)
    def make_rhs(self, u: float, m_load: float):
        P = self.P
        tanh, exp = math.tanh, math.exp
        u_volt = u * P["u_batt"]
        k1, dk12, dk23 = P["k1"], P["k2"] - P["k1"], P["k3"] - P["k2"]
        z1, dz12, dz23 = P["z1"], P["z2"] - P["z1"], P["z3"] - P["z2"]
        A1, A2, A3 = P["A1"], P["A2"], P["A3"]
        dA12, dA23 = A2 - A1, A3 - A2
        r = P["ratio"]
        m1, m2, m3 = P["m_st1"], P["m_st2"], P["m_st3"]
        pump = P["eta_v"] * P["disp"] / (2.0 * math.pi)
        V0, inv_beta = P["V0"], 1.0 / P["beta"]
        cf_con, cf_in, cf_out, d = P["cf_con"], P["cf_in"], P["cf_out"], P["d"]
        dFs, inv_vs = P["dFs"], 1.0 / P["v_s"]
        stick = dFs != 0.0
        kappa, C_L, alpha0, C_h = P["kappa"], P["C_L"], P["alpha0"], P["C_h"]
        air = alpha0 != 0.0
        inertia, i_w = self.inertia, self.i_w
        inv_tau = 1.0 / P["tau_m"] if inertia else 0.0
        mast = self.mast and m_load > 0.0
        i_d = self.i_d
        k_s = 1.0 / P["ks_inv"] if self.mast else 0.0
        c_s = P["c_s"]
        inv_w, inv_veps = 1.0 / W_BLEND, 1.0 / V_EPS
        L2 = X_S2 - X_S1
        n = self.n
        valve_open = u > 0.0

        def rhs(t, y):
            x, v, p = y[0], y[1], y[2]
            s1 = 0.5 * (1.0 + tanh((x - X_S1) * inv_w))
            s2 = 0.5 * (1.0 + tanh((x - X_S2) * inv_w))
            area = A1 + dA12 * s1 + dA23 * s2
            m_st = m1 + m2 * s1 + m3 * s2
            out = [0.0] * n
            # motor (static map, droop before the clip), motor lag, pump, check valve
            if valve_open:
                w_ss = (k1 + dk12 * s1 + dk23 * s2) * u_volt + (z1 + dz12 * s1 + dz23 * s2)
                w_ss -= kappa * p
                if w_ss < 0.0:
                    w_ss = 0.0
            else:
                w_ss = 0.0
            if inertia:
                w = y[i_w]
                out[i_w] = (w_ss - w) * inv_tau
            else:
                w = w_ss
            q = pump * w if valve_open else 0.0
            # oil volume and capacitance
            if x <= 0.0:
                vol = V0
            elif x <= X_S1:
                vol = V0 + A1 * x / r
            elif x <= X_S2:
                vol = V0 + (A1 * X_S1 + A2 * (x - X_S1)) / r
            else:
                vol = V0 + (A1 * X_S1 + A2 * L2 + A3 * (x - X_S2)) / r
            if air:
                p_abs = p + P_ATM
                if p_abs < 0.1 * P_ATM:
                    p_abs = 0.1 * P_ATM
                cap = vol * (inv_beta + alpha0 * P_ATM / (p_abs * p_abs)) + C_h
            else:
                cap = vol * inv_beta + C_h
            out[2] = (q - area * v / r - C_L * p) / cap
            # friction
            tv = tanh(v * inv_veps)
            civ = cf_in * v
            civ2 = civ * civ
            f_fric = cf_con * tv + cf_out * civ2 * civ2 * civ
            if stick:
                vr = v * inv_vs
                f_fric += dFs * exp(-vr * vr) * tv
            # bottom end stop on the carriage
            f_stop = 0.0
            if x < 0.0:
                f_stop = -K_ES * x - C_ES * v
                if f_stop < 0.0:
                    f_stop = 0.0
            out[0] = v
            if mast:
                dl, dlr = y[i_d], y[i_d + 1]
                f_spring = k_s * dl + c_s * dlr  # force of the load on the carriage
                a = (area * p / r - f_fric - d * v + f_spring + f_stop) / m_st - G
                out[1] = a
                out[i_d] = dlr
                out[i_d + 1] = -f_spring / m_load - G - a
            else:
                mass = m_load + m_st
                out[1] = (area * p / r - f_fric - d * v + f_stop) / mass - G
                if i_d >= 0:  # states carried, frozen (m_load = 0)
                    out[i_d] = 0.0
                    out[i_d + 1] = 0.0
            return out

        return rhs

    def static_motor_speed(self, u: float, x: float, p: float) -> float:
        if u <= 0.0:
            return 0.0
        sq = stage_quantities(self.P, x)
        return max(sq["k"] * u * self.P["u_batt"] + sq["z"] - self.P["kappa"] * p, 0.0)

    def initial_state(self, x0: float, m_load0: float, u0: float) -> np.ndarray:
        """At rest at ``x0`` with the static-equilibrium pressure; effect states at rest."""
        P = self.P
        sq = stage_quantities(P, x0)
        p0 = (m_load0 + sq["m_st"]) * G * P["ratio"] / sq["area"]
        y = [x0, 0.0, p0]
        if self.inertia:
            y.append(self.static_motor_speed(u0, x0, p0))
        if self.mast:
            y += [-m_load0 * G * P["ks_inv"], 0.0]
        return np.array(y, dtype=float)


class SimulationFailed(RuntimeError):
    pass


def simulate(
    params: Mapping[str, float],
    ts: np.ndarray,
    pwm: np.ndarray,
    load: np.ndarray,
    x0: float,
    rtol: float = RTOL,
    method: str = METHOD,
    max_step: float = MAX_STEP,
) -> dict[str, np.ndarray]:
    """Simulate one run with zero-order-held inputs; outputs at the sample times ``ts``.

    The plant sees ``u(t - tau_d)`` and ``m_load(t - tau_d)`` (the first sample held
    before the start); the integration is split at every time at which the (delayed)
    input changes and restarted there with ``solve_ivp``, so every jump is stepped onto.
    """
    model = Model(params)
    P = model.P
    ts = np.asarray(ts, dtype=float)
    pwm = np.asarray(pwm, dtype=float)
    load = np.asarray(load, dtype=float)
    n = ts.size
    tau_d = P["tau_d"]
    change = np.nonzero((np.diff(pwm) != 0) | (np.diff(load) != 0))[0] + 1
    t_end = float(ts[-1])
    # segments: (start time, input sample index)
    seg_t = [0.0]
    seg_i = [0]
    for k in change.tolist():
        tk = float(ts[k]) + tau_d
        if tk < t_end - 1e-12:
            seg_t.append(tk)
            seg_i.append(k)
    seg_t.append(t_end)
    ys = np.empty((n, model.n))
    y = model.initial_state(float(x0), float(load[0]), float(pwm[0]))
    ys[0] = y
    nfev = 0
    filled = 1  # samples 0..filled-1 are done
    for j in range(len(seg_i)):
        ta, tb = seg_t[j], seg_t[j + 1]
        if tb <= ta:
            continue
        k = seg_i[j]
        fun = model.make_rhs(float(pwm[k]), float(load[k]))
        hi = int(np.searchsorted(ts, tb + 1e-9, side="right"))
        t_eval = ts[filled:hi]
        t_eval = t_eval[t_eval <= tb]
        last_is_sample = t_eval.size > 0 and abs(t_eval[-1] - tb) < 1e-9
        if last_is_sample:
            t_eval = t_eval.copy()
            t_eval[-1] = tb
        else:
            t_eval = np.append(t_eval, tb)
        sol = solve_ivp(
            fun,
            (ta, tb),
            y,
            method=method,
            t_eval=t_eval,
            rtol=rtol,
            atol=model.atol,
            max_step=min(max_step, tb - ta),
        )
        nfev += sol.nfev
        if sol.status != 0 or not np.all(np.isfinite(sol.y)):
            raise SimulationFailed(f"solver failed at t = {ta:.3f} s: {sol.message}")
        m = t_eval.size - (0 if last_is_sample else 1)
        ys[filled : filled + m] = sol.y[:, :m].T
        filled += m
        y = sol.y[:, -1]
        if not (-0.01 <= y[0] <= X_MAX + 0.01):
            raise SimulationFailed(f"height {y[0]:.3f} m at t = {tb:.2f} s leaves the mast")
    if filled != n:
        raise SimulationFailed(f"internal: filled {filled} of {n} samples")
    out = {"height": ys[:, 0], "speed": ys[:, 1], "pressure": ys[:, 2], "nfev": nfev}
    if model.inertia:
        out["omega_m"] = ys[:, model.i_w]
    if model.mast:
        out["delta"] = ys[:, model.i_d]
    out["segments"] = len(seg_i)
    return out


# ============================================================ steady map for the design
def _steady_pressure(P: Mapping[str, float], x: float, v: float, m_load: float) -> float:
    sq = stage_quantities(P, x)
    force = (m_load + sq["m_st"]) * G + friction(P, v, P["dFs"] != 0.0) + P["d"] * v
    return force * P["ratio"] / sq["area"]


def design_level(P: Mapping[str, float], v_target: float, x: float, m_load: float) -> float:
    """Duty that gives the steady speed ``v_target`` at ``x`` on the (truth) static map,
    droop and leakage included: what a test engineer would tune on the truck."""
    sq = stage_quantities(P, x)
    pump = P["eta_v"] * P["disp"] / (2.0 * math.pi)
    p = _steady_pressure(P, x, v_target, m_load)
    q = v_target * sq["area"] / P["ratio"] + P["C_L"] * p
    w = q / pump + P["kappa"] * p
    u = (w - sq["z"]) / (sq["k"] * P["u_batt"])
    return min(max(u, 0.0), 0.95)


def steady_speed(P: Mapping[str, float], u: float, x: float, m_load: float) -> float:
    """Steady speed at duty ``u`` and height ``x`` (kinematic prediction; negative in a
    hold with leakage)."""
    sq = stage_quantities(P, x)
    r, area = P["ratio"], sq["area"]
    pump = P["eta_v"] * P["disp"] / (2.0 * math.pi)
    v = 0.0
    for _ in range(3):
        p = _steady_pressure(P, x, max(v, 0.0), m_load)
        w = 0.0 if u <= 0.0 else max(sq["k"] * u * P["u_batt"] + sq["z"] - P["kappa"] * p, 0.0)
        v = (pump * w - P["C_L"] * p) * r / area
    return v


# ============================================================================ sequences
def _style_sections(style: str, rng: np.random.Generator, duration: float) -> dict:
    """Sections in speed space. Kinds: ("hold", dur), ("level", v, dur), ("ramp", v, dur)
    (a linear pwm ramp from the current duty to the duty of speed v; v = 0: to pwm 0)."""
    t0 = float(rng.uniform(2.0, 3.0))
    secs: list[tuple] = [("hold", t0)]
    final_hold = float(rng.uniform(2.0, 5.0))
    t = t0
    if style == "thesis":
        ramp_s = float(rng.choice([0.5, 1.0]))
        kind = "fast" if rng.uniform() < 0.7 else "slow"
        while t < duration - final_hold - 3.0:
            if kind == "fast":
                v, dur = rng.uniform(0.06, 0.10), rng.uniform(3.0, 7.0)
            else:
                v, dur = rng.uniform(0.015, 0.035), rng.uniform(8.0, 20.0)
            secs.append(("level", float(v), float(dur)))
            t += dur
            if kind == "slow" and rng.uniform() < 0.4:
                h = float(rng.uniform(2.0, 5.0))
                secs.append(("hold", h))
                t += h
            kind = "slow" if kind == "fast" else ("fast" if rng.uniform() < 0.85 else "slow")
    elif style == "steps":
        ramp_s = 0.0
        while t < duration - final_hold - 2.0:
            if rng.uniform() < 0.25 and secs[-1][0] != "hold":
                h = float(rng.uniform(1.5, 6.0))
                secs.append(("hold", h))
                t += h
            else:
                v = math.exp(rng.uniform(math.log(0.01), math.log(0.10)))
                dur = float(rng.uniform(2.0, 12.0))
                secs.append(("level", v, dur))
                t += dur
    elif style == "ramps":
        ramp_s = 0.0
        while t < duration - final_hold - 4.0:
            if rng.uniform() < 0.2 and secs[-1][0] != "hold":
                dur = float(rng.uniform(4.0, 12.0))
                secs.append(("ramp", 0.0, dur))
                h = float(rng.uniform(2.0, 5.0))
                secs.append(("hold", h))
                t += dur + h
                continue
            v = math.exp(rng.uniform(math.log(0.01), math.log(0.10)))
            dur = float(rng.uniform(6.0, 25.0))
            secs.append(("ramp", v, dur))
            t += dur
            if rng.uniform() < 0.4:
                pdur = float(rng.uniform(2.0, 8.0))
                secs.append(("plateau", pdur))
                t += pdur
    else:
        raise ValueError(f"unknown style {style!r}")
    # trim the moving sections so that the run lasts ``duration`` with the final hold
    excess = t + final_hold - duration
    while excess > 1e-9 and len(secs) > 1:
        last = secs[-1]
        cut = min(excess, last[-1] - 1.0)
        if cut >= last[-1] - 1.0 - 1e-9 and last[-1] - cut < 1.5:
            secs.pop()  # too short after trimming: drop it
            excess -= last[-1]
            continue
        secs[-1] = (*last[:-1], last[-1] - cut)
        excess -= cut
    secs.append(("hold", final_hold - min(excess, 0.0)))
    return {"sections": secs, "ramp_s": ramp_s}


def _render(
    P: Mapping[str, float],
    sections: Sequence[tuple],
    ramp_s: float,
    x0: float,
    top: float,
    m_load: float,
    speed_scale: float,
    truncate: bool,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Sample the sections into a pwm sequence (levels from the speed targets at the
    predicted height of each section's start); kinematic height prediction; with
    ``truncate`` the pwm is ramped down to 0 when the prediction reaches ``top``.
    Returns (ts, pwm, predicted final height)."""
    total = sum(s[-1] for s in sections)
    n = int(round(total / TS)) + 1
    ts = np.round(np.arange(n) * TS, 9)
    pwm = np.zeros(n)
    x = x0
    prev = 0.0
    i = 0
    stopped_at = None
    v_min = 0.006
    for sec in sections:
        kind, dur = sec[0], sec[-1]
        m = int(round(dur / TS))
        if kind == "hold":
            target, start, length = 0.0, prev, ramp_s
        elif kind == "plateau":
            target, start, length = prev, prev, 0.0
        else:
            v = min(max(sec[1] * speed_scale, 0.008), 0.10) if sec[1] > 0 else 0.0
            while v > 0.008 and _steady_pressure(P, max(x, X_S2 + 0.1), v, m_load) > P_DESIGN_MAX:
                v = max(0.85 * v, 0.008)  # keep the steady pressure in stage 3 below 20 MPa
            target = 0.0 if v == 0.0 else design_level(P, v, x, m_load)
            if v > 0.0:  # never stall in the stages above
                for xs in (0.75, 2.25, 3.75):
                    if xs > x:
                        target = max(target, design_level(P, v_min, xs, m_load))
            start = prev
            length = ramp_s if kind == "level" else dur
        for j in range(m):
            if i >= n:
                break
            if stopped_at is not None:
                frac = min((i - stopped_at[0]) * TS / max(ramp_s, TS), 1.0)
                val = stopped_at[1] * (1.0 - frac)
            elif length > 0.0:
                val = start + (target - start) * min((j + 1) * TS / length, 1.0)
            else:
                val = target
            pwm[i] = val
            x += steady_speed(P, val, x, m_load) * TS
            x = max(x, 0.0)
            if truncate and stopped_at is None and x >= top:
                stopped_at = (i, val)
            i += 1
        prev = target if stopped_at is None else 0.0
    pwm[i:] = 0.0 if stopped_at is not None else prev
    pwm[0] = 0.0
    pwm = np.clip(np.round(pwm, 4), 0.0, 1.0)
    return ts, pwm, x


def make_sequence(
    P: Mapping[str, float],
    style: str,
    rng: np.random.Generator,
    x0: float,
    m_load: float,
    top_scale: float = 1.0,
    duration_range: tuple[float, float] | None = None,
) -> dict:
    """A pwm sequence of ``style`` from ``x0`` that lifts to about ``top`` (predicted).
    ``duration_range`` [s] overrides the style's range of lengths (the fleet study's
    shorter logs)."""
    start_bottom = x0 <= 0.0
    if style == "thesis":
        lo, hi = (100.0, 150.0) if start_bottom else (60.0, 110.0)
        top = float(rng.uniform(3.8, 4.2))
    else:
        lo, hi = 60.0, 150.0
        top = float(rng.uniform(max(x0 + 0.8, 2.0), 4.2))
    top = x0 + (top - x0) * top_scale
    if duration_range is not None:
        lo, hi = duration_range
    duration = float(rng.uniform(lo, hi))
    spec = _style_sections(style, rng, duration)
    _, _, x_raw = _render(P, spec["sections"], spec["ramp_s"], x0, 1e9, m_load, 1.0, False)
    lift_raw = max(x_raw - x0, 1e-3)
    scale = float(np.clip((top - x0) / lift_raw, 0.4, 3.0))
    ts, pwm, x_end = _render(P, spec["sections"], spec["ramp_s"], x0, top, m_load, scale, True)
    return {
        "ts": ts,
        "pwm": pwm,
        "style": style,
        "duration_s": float(ts[-1]),
        "target_top_m": top,
        "predicted_top_m": float(x_end),
        "speed_scale": scale,
        "ramp_s": spec["ramp_s"],
        "n_sections": len(spec["sections"]),
    }


# ============================================================================= cases
def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def effect_params_from_size(
    effect: str, size: float, rng: np.random.Generator, m_ref: float
) -> tuple[dict[str, float], dict[str, float]]:
    """(parameters, derived description) of ``effect`` at ``size`` (in the unit of
    :data:`EFFECT_SIZE_RANGES`); secondary parameters drawn from ``rng``."""
    N = NOMINAL
    if effect == "stick_slip":
        v_s = _loguniform(rng, *V_S_RANGE)
        return {"dFs": size, "v_s": v_s}, {}
    if effect == "motor_inertia":
        return {"tau_m": size}, {}
    if effect == "motor_droop":
        w_ref = N["k1"] * DROOP_U_REF * N["u_batt"] + N["z1"]
        return {"kappa": size * w_ref / DROOP_P_REF}, {
            "speed_drop_at_10MPa": size,
            "reference_motor_speed_rad_s": w_ref,
        }
    if effect == "leakage":
        return {"C_L": size * N["A1"] / (N["ratio"] * DROOP_P_REF)}, {
            "sink_speed_at_10MPa_mps": size
        }
    if effect == "entrained_air":
        return {"alpha0": size}, {}
    if effect == "hose_compliance":
        return {"C_h": size}, {}
    if effect == "mast_compliance":
        zeta = _loguniform(rng, *ZETA_RANGE)
        c_s = 2.0 * zeta * math.sqrt(m_ref / size)
        f_hz = math.sqrt(1.0 / (size * m_ref)) / (2.0 * math.pi)
        return {"ks_inv": size, "c_s": c_s}, {
            "damping_ratio": zeta,
            "reference_load_kg": m_ref,
            "load_on_spring_frequency_hz": f_hz,
        }
    if effect == "input_delay":
        return {"tau_d": size}, {}
    raise ValueError(effect)


def _draw_loads(rng: np.random.Generator) -> list[float]:
    while True:
        loads = sorted(round(_loguniform(rng, *LOAD_RANGE)) for _ in range(3))
        if loads[1] >= LOAD_MIN_RATIO * loads[0] and loads[2] >= LOAD_MIN_RATIO * loads[1]:
            order = rng.permutation(3)
            return [float(loads[i]) for i in order]


def make_cases(
    seed: int = 0, n_null: int = 24, sizes_per_effect: int = 8, n_pairs: int = 12
) -> list[dict]:
    """The case specifications (deterministic in ``seed``): ``n_null`` cases without a
    hidden effect, ``sizes_per_effect`` sizes of each of the eight effects (stratified
    log-uniform over the size range: one draw in each of ``sizes_per_effect`` equal
    bins of the log range), and ``n_pairs`` distinct pairs of two different effects at
    log-uniform sizes. The cases are shuffled, so the first N are a mix; the case ids
    (``case_000`` ...) do not reveal the truth. Default: 24 + 64 + 12 = 100 cases."""
    rng = np.random.default_rng(seed)
    kinds: list[list[tuple[str, float | None]]] = [[] for _ in range(n_null)]
    for e in EFFECTS:
        _, lo, hi = EFFECT_SIZE_RANGES[e]
        edges = np.linspace(math.log(lo), math.log(hi), sizes_per_effect + 1)
        for b in range(sizes_per_effect):
            kinds.append([(e, float(math.exp(rng.uniform(edges[b], edges[b + 1]))))])
    all_pairs = list(itertools.combinations(EFFECTS, 2))
    if n_pairs > len(all_pairs):
        raise ValueError(f"at most {len(all_pairs)} distinct pairs")
    for idx in rng.choice(len(all_pairs), size=n_pairs, replace=False):
        kinds.append([(e, None) for e in all_pairs[int(idx)]])
    order = rng.permutation(len(kinds))
    cases = []
    for ci, ki in enumerate(order.tolist()):
        hidden = kinds[ki]
        params: dict[str, float] = {}
        for name, (how, a, b) in PLANT_DRAWS.items():
            if how == "rel":
                params[name] = NOMINAL[name] * float(rng.uniform(1.0 - a, 1.0 + a))
            else:
                params[name] = _loguniform(rng, a, b)
        loads = _draw_loads(rng)
        m_ref = float(math.exp(np.mean(np.log(loads))))
        effects, sizes, derived = [], {}, {}
        for e, size in hidden:
            if size is None:
                size = _loguniform(rng, *EFFECT_SIZE_RANGES[e][1:])
            ep, der = effect_params_from_size(e, size, rng, m_ref)
            params.update(ep)
            effects.append(e)
            sizes[e] = size
            if der:
                derived[e] = der
        logs = []
        for li, name in enumerate(LOG_NAMES):
            bottom = bool(rng.uniform() < 0.5)
            x0 = 0.0
            if not bottom:
                while True:
                    x0 = float(rng.uniform(*MID_START_RANGE))
                    if abs(x0 - X_S1) > 0.05:
                        break
            logs.append(
                {
                    "name": name,
                    "role": "held_out" if name == "validation" else "fitted",
                    "style": str(rng.choice(STYLES)),
                    "load_kg": loads[li],
                    "start": "bottom" if bottom else "mid_mast",
                    "x0_m": x0,
                }
            )
        cases.append(
            {
                "case_id": f"case_{ci:03d}",
                "seed": seed,
                "case_seed": int(rng.integers(0, 2**31 - 1)),
                "kind": "null" if not effects else ("single" if len(effects) == 1 else "pair"),
                "hidden_effects": effects,
                "effect_sizes": sizes,
                "effect_size_units": {e: EFFECT_SIZE_RANGES[e][0] for e in effects},
                "derived": derived,
                "params": params,
                "logs": logs,
            }
        )
    return cases


# ============================================================================ writing
def _write_csv(path: pathlib.Path, ts, pwm, height, load, speed) -> None:
    lines = ["time_s,pwm,height_m,load_kg,speed_mps"]
    for row in zip(ts, pwm, height, load, speed):
        lines.append(",".join(f"{float(v):.9g}" for v in row))
    tmp = path.with_suffix(".csv.tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tmp.replace(path)


def generate_log(spec: dict, log: dict, li: int, max_attempts: int = 8) -> dict:
    """Sequence, simulation and measurement of one log; re-draws the sequence (new
    attempt seed, lower top) while the simulated height exceeds 4.4 m or the solver fails."""
    P = resolve_params(spec["params"])
    errors = []
    for attempt in range(max_attempts):
        rng = np.random.default_rng([spec["case_seed"], li, attempt])
        seq = make_sequence(
            P, log["style"], rng, log["x0_m"], log["load_kg"], top_scale=0.93**attempt,
            duration_range=log.get("duration_range_s"),
        )  # fmt: skip
        load = np.full_like(seq["ts"], log["load_kg"])
        try:
            sim = simulate(spec["params"], seq["ts"], seq["pwm"], load, log["x0_m"])
        except SimulationFailed as exc:
            errors.append(f"attempt {attempt}: {exc}")
            continue
        h_max = float(np.max(sim["height"]))
        if not np.all(np.isfinite(sim["height"])) or h_max > H_LIMIT:
            errors.append(f"attempt {attempt}: max height {h_max:.3f} m")
            continue
        noise_rng = np.random.default_rng([spec["case_seed"], li, attempt, 1])
        n = seq["ts"].size
        height = sim["height"] + SIGMA_H * noise_rng.standard_normal(n)
        speed = sim["speed"] + SIGMA_V * noise_rng.standard_normal(n)
        moving = seq["pwm"] > 0
        return {
            "ts": seq["ts"],
            "pwm": seq["pwm"],
            "load": load,
            "height": height,
            "speed": speed,
            "sim": sim,
            "info": {
                **{k: seq[k] for k in ("style", "duration_s", "ramp_s", "n_sections")},
                "target_top_m": seq["target_top_m"],
                "predicted_top_m": seq["predicted_top_m"],
                "speed_scale": seq["speed_scale"],
                "attempt": attempt,
                "rejected_attempts": errors,
                "n_samples": int(n),
                "true_max_height_m": h_max,
                "true_min_height_m": float(np.min(sim["height"])),
                "true_final_height_m": float(sim["height"][-1]),
                "true_max_speed_mps": float(np.max(sim["speed"])),
                "true_mean_pressure_moving_pa": float(np.mean(sim["pressure"][moving]))
                if moving.any()
                else None,
                "true_max_pressure_pa": float(np.max(sim["pressure"])),
                "nfev": int(sim["nfev"]),
                "segments": int(sim["segments"]),
                "noise_seed": [spec["case_seed"], li, attempt, 1],
                "sequence_seed": [spec["case_seed"], li, attempt],
            },
        }
    raise SimulationFailed(f"{spec['case_id']} {log['name']}: no valid log: {errors}")


def write_case(spec: dict, out_dir: str | pathlib.Path, verbose: bool = True) -> dict | None:
    """Write ``out_dir/<case_id>/{fit_1,fit_2,validation}.csv`` and ``truth.json``.
    Skips a case whose ``truth.json`` exists (returns None). ``truth.json`` is written
    last, so its presence marks a complete case."""
    case_dir = pathlib.Path(out_dir) / spec["case_id"]
    truth_path = case_dir / "truth.json"
    if truth_path.exists():
        return None
    case_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    logs_out = []
    summaries = []
    for li, log in enumerate(spec["logs"]):
        t0 = time.perf_counter()
        res = generate_log(spec, log, li)
        _write_csv(
            case_dir / f"{log['name']}.csv",
            res["ts"],
            res["pwm"],
            res["height"],
            res["load"],
            res["speed"],
        )
        info = {**log, **res["info"], "wall_s": round(time.perf_counter() - t0, 3)}
        logs_out.append(info)
        h, s = res["height"], res["speed"]
        summaries.append(
            {
                "name": log["name"],
                "style": log["style"],
                "load_kg": log["load_kg"],
                "x0_m": log["x0_m"],
                "duration_s": float(res["ts"][-1]),
                "max_height_m": float(h.max()),
                "min_height_m": float(h.min()),
                "speed_rms_mps": float(np.sqrt(np.mean(s**2))),
                "nan": bool(not (np.all(np.isfinite(h)) and np.all(np.isfinite(s)))),
                "wall_s": info["wall_s"],
                "attempt": info["attempt"],
            }
        )
    P = resolve_params(spec["params"])
    truth = {
        "case_id": spec["case_id"],
        "seed": spec["seed"],
        "case_seed": spec["case_seed"],
        "kind": spec["kind"],
        "hidden_effects": spec["hidden_effects"],
        "effect_sizes": spec["effect_sizes"],
        "effect_size_units": spec["effect_size_units"],
        "derived": spec["derived"],
        "params": {k: P[k] for k in NOMINAL}
        | {k: P[k] for e in spec["hidden_effects"] for k in EFFECT_PARAMS[e]},
        "all_params": P,
        "drawn_params": sorted(PLANT_DRAWS),
        "logs": logs_out,
        "generator": {
            "file": "studies/detection_generator.py",
            "version": GENERATOR_VERSION,
            "solver": f"scipy.integrate.solve_ivp {METHOD}",
            "rtol": RTOL,
            "atol": {
                "x": 1e-7,
                "v": 1e-7,
                "p": 1.0,
                "omega_m": 1e-3,
                "delta": 1e-7,
                "delta_rate": 1e-6,
            },
            "max_step_s": MAX_STEP,
            "end_stop": {"k_es": K_ES, "c_es": C_ES},
            "sample_period_s": TS,
            "sigma_height_m": SIGMA_H,
            "sigma_speed_mps": SIGMA_V,
            "speed_noise_power": SPEED_NOISE_POWER,
        },
        "wall_s": round(time.perf_counter() - t_start, 3),
    }
    tmp = truth_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(truth, indent=2) + "\n", encoding="utf-8")
    tmp.replace(truth_path)
    return {"case_id": spec["case_id"], "wall_s": truth["wall_s"], "logs": summaries}


def _describe(spec: dict) -> str:
    if not spec["hidden_effects"]:
        return "null"
    return "+".join(spec["hidden_effects"])


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", type=int, default=None, help="only the first N cases")
    ap.add_argument("--only", default=None, help="one case: id (case_007) or index (7)")
    ap.add_argument("--quiet", action="store_true", help="no per-log summary lines")
    args = ap.parse_args(argv)
    cases = make_cases(seed=args.seed)
    if args.only is not None:
        key = args.only
        sel = [
            c
            for c in cases
            if c["case_id"] == key or (key.isdigit() and c["case_id"] == f"case_{int(key):03d}")
        ]
        if not sel:
            ap.error(f"no case {key!r}")
        cases = sel
    elif args.cases is not None:
        cases = cases[: args.cases]
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    n_done = 0
    for i, spec in enumerate(cases):
        res = write_case(spec, out)
        tag = f"[{i + 1}/{len(cases)}] {spec['case_id']}"
        if res is None:
            print(f"{tag}: exists, skipped", flush=True)
            continue
        n_done += 1
        print(f"{tag}: {_describe(spec)}  {res['wall_s']:.1f} s", flush=True)
        if not args.quiet:
            for s in res["logs"]:
                print(
                    f"    {s['name']:<10} {s['style']:<6} {s['load_kg']:6.0f} kg "
                    f"x0 {s['x0_m']:.2f} m  {s['duration_s']:6.1f} s  "
                    f"h {s['min_height_m']:+.4f}..{s['max_height_m']:.3f} m  "
                    f"speed rms {1e3 * s['speed_rms_mps']:.1f} mm/s  "
                    f"{'NaN!' if s['nan'] else 'ok'}  {s['wall_s']:.1f} s"
                    + (f" (attempt {s['attempt']})" if s["attempt"] else ""),
                    flush=True,
                )
    dt = time.perf_counter() - t_all
    if n_done:
        print(f"{n_done} case(s) in {dt:.1f} s ({dt / n_done:.1f} s per case)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
