"""An independent NumPy/SciPy implementation of docs/model.md's lift, for cross-checks.

Written from the specification (``docs/model.md``) (baseline equations, plus the ``stick_slip``
and ``hose_compliance`` effects in their reference forms), *not* from jaxlift's code,
so that agreement between the two is evidence that both implement the spec.

Design, chosen to make this a fair peer in the benchmarks (not a strawman):

* the right-hand side works on plain Python floats with the ``math`` module (a
  ``numpy`` scalar expression costs several times more per call);
* inputs are zero-order held; the integration is split at every sample where
  ``pwm`` or ``load_kg`` change and the integrator restarted there, so the
  discontinuities are stepped onto exactly (no error from stepping over a jump);
  within a segment the input is a constant bound into the closure;
* an analytic Jacobian is supplied to the implicit methods (LSODA in stiff mode,
  Radau, BDF).

State ``y = (x, v, p)``: height [m], fork speed [m/s], gauge pressure [Pa].
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Mapping

import numpy as np
from scipy.integrate import odeint, solve_ivp

__all__ = [
    "NOMINAL",
    "EFFECT_DEFAULTS",
    "rhs",
    "jacobian",
    "initial_state",
    "simulate_scipy",
    "make_core",
    "make_jacobian",
    "static_pressure",
]

G = 9.81  # m/s^2
X_S1, X_S2, X_MAX = 1.5, 3.0, 4.5  # m: stage boundaries and full height
W_BLEND = 5e-3  # m: width of the tanh stage blend
V_EPS = 1e-3  # m/s: Coulomb smoothing speed

#: docs/model.md's nominal parameters (names as in parameter files).
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

#: The effects implemented here and the defaults of their parameters. An effect is
#: switched on when any of its parameters appears in ``params``.
EFFECT_DEFAULTS: dict[str, dict[str, float]] = {
    "stick_slip": {"dFs": 0.0, "v_s": 0.01},
    "hose_compliance": {"C_h": 0.0},
}


def _resolve(params: Mapping[str, object]) -> dict[str, float]:
    """Nominal values overridden by ``params``; effect parameters default to their
    nesting values. Unknown names raise (an effect this module does not implement
    must not be silently ignored)."""
    known = set(NOMINAL)
    for d in EFFECT_DEFAULTS.values():
        known |= set(d)
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"scipy_reference does not implement parameter(s) {unknown}")
    out = dict(NOMINAL)
    for d in EFFECT_DEFAULTS.values():
        out.update(d)
    for k, v in params.items():
        out[k] = float(np.asarray(v))
    return out


def make_core(params: Mapping[str, object]) -> Callable[..., tuple[float, float, float]]:
    """``deriv(x, v, p, u, m_load) -> (dx/dt, dv/dt, dp/dt)`` on plain floats."""
    P = _resolve(params)
    tanh, exp = math.tanh, math.exp
    u_batt = P["u_batt"]
    k1, dk12, dk23 = P["k1"], P["k2"] - P["k1"], P["k3"] - P["k2"]
    z1, dz12, dz23 = P["z1"], P["z2"] - P["z1"], P["z3"] - P["z2"]
    A1, A2, A3 = P["A1"], P["A2"], P["A3"]
    dA12, dA23 = A2 - A1, A3 - A2
    r = P["ratio"]
    m1, m2, m3 = P["m_st1"], P["m_st2"], P["m_st3"]  # cumulative: m1, m1+m2, m1+m2+m3
    pump = P["eta_v"] * P["disp"] / (2.0 * math.pi)  # m^3 per rad
    V0, inv_beta, C_h = P["V0"], 1.0 / P["beta"], P["C_h"]
    cf_con, cf_in, cf_out, d = P["cf_con"], P["cf_in"], P["cf_out"], P["d"]
    dFs, v_s = P["dFs"], P["v_s"]
    stick = dFs != 0.0
    inv_w, inv_veps, inv_vs = 1.0 / W_BLEND, 1.0 / V_EPS, 1.0 / v_s
    L2 = X_S2 - X_S1

    def deriv(x: float, v: float, p: float, u: float, m_load: float):
        s1 = 0.5 * (1.0 + tanh((x - X_S1) * inv_w))
        s2 = 0.5 * (1.0 + tanh((x - X_S2) * inv_w))
        area = A1 + dA12 * s1 + dA23 * s2
        mass = m_load + m1 + m2 * s1 + m3 * s2
        # voltage unit, motor map, pump, check valve (closed for u = 0)
        if u > 0.0:
            omega = (k1 + dk12 * s1 + dk23 * s2) * (u * u_batt) + (z1 + dz12 * s1 + dz23 * s2)
            q = pump * omega if omega > 0.0 else 0.0
        else:
            q = 0.0
        # oil volume under pressure (continuous, piecewise linear in x)
        if x <= X_S1:
            stroke = A1 * (x if x > 0.0 else 0.0)
        elif x <= X_S2:
            stroke = A1 * X_S1 + A2 * (x - X_S1)
        else:
            stroke = A1 * X_S1 + A2 * L2 + A3 * (x - X_S2)
        cap = (V0 + stroke / r) * inv_beta + C_h
        dp = (q - area * v / r) / cap
        # friction (opposing motion), fork and load
        tv = tanh(v * inv_veps)
        civ = cf_in * v
        civ2 = civ * civ
        f_fric = cf_con * tv + cf_out * civ2 * civ2 * civ
        if stick:
            vr = v * inv_vs
            f_fric += dFs * exp(-vr * vr) * tv
        a = (area * p / r - f_fric - d * v) / mass - G
        return v, a, dp

    return deriv


def make_jacobian(params: Mapping[str, object]) -> Callable[..., list[list[float]]]:
    """``jac(x, v, p, u, m_load)``: the analytic 3x3 Jacobian of :func:`make_core`'s
    right-hand side."""
    P = _resolve(params)
    tanh, exp = math.tanh, math.exp
    u_batt = P["u_batt"]
    k1, dk12, dk23 = P["k1"], P["k2"] - P["k1"], P["k3"] - P["k2"]
    z1, dz12, dz23 = P["z1"], P["z2"] - P["z1"], P["z3"] - P["z2"]
    A1, A2, A3 = P["A1"], P["A2"], P["A3"]
    dA12, dA23 = A2 - A1, A3 - A2
    r = P["ratio"]
    m1, m2, m3 = P["m_st1"], P["m_st2"], P["m_st3"]
    pump = P["eta_v"] * P["disp"] / (2.0 * math.pi)
    V0, inv_beta, C_h = P["V0"], 1.0 / P["beta"], P["C_h"]
    cf_con, cf_in, cf_out, d = P["cf_con"], P["cf_in"], P["cf_out"], P["d"]
    dFs, v_s = P["dFs"], P["v_s"]
    inv_w, inv_veps, inv_vs = 1.0 / W_BLEND, 1.0 / V_EPS, 1.0 / v_s
    L2 = X_S2 - X_S1

    def jac(x: float, v: float, p: float, u: float, m_load: float):
        t1 = tanh((x - X_S1) * inv_w)
        t2 = tanh((x - X_S2) * inv_w)
        s1, s2 = 0.5 * (1.0 + t1), 0.5 * (1.0 + t2)
        ds1, ds2 = 0.5 * (1.0 - t1 * t1) * inv_w, 0.5 * (1.0 - t2 * t2) * inv_w
        area = A1 + dA12 * s1 + dA23 * s2
        d_area = dA12 * ds1 + dA23 * ds2
        mass = m_load + m1 + m2 * s1 + m3 * s2
        d_mass = m2 * ds1 + m3 * ds2
        q, dq_dx = 0.0, 0.0
        if u > 0.0:
            volt = u * u_batt
            omega = (k1 + dk12 * s1 + dk23 * s2) * volt + (z1 + dz12 * s1 + dz23 * s2)
            if omega > 0.0:
                q = pump * omega
                dq_dx = pump * ((dk12 * ds1 + dk23 * ds2) * volt + dz12 * ds1 + dz23 * ds2)
        if x <= X_S1:
            stroke, d_stroke = (A1 * x, A1) if x > 0.0 else (0.0, 0.0)
        elif x <= X_S2:
            stroke, d_stroke = A1 * X_S1 + A2 * (x - X_S1), A2
        else:
            stroke, d_stroke = A1 * X_S1 + A2 * L2 + A3 * (x - X_S2), A3
        cap = (V0 + stroke / r) * inv_beta + C_h
        d_cap = d_stroke / r * inv_beta
        num = q - area * v / r
        ddp_dx = ((dq_dx - d_area * v / r) * cap - num * d_cap) / (cap * cap)
        ddp_dv = -area / (r * cap)
        tv = tanh(v * inv_veps)
        dtv = (1.0 - tv * tv) * inv_veps
        f_fric = cf_con * tv + cf_out * (cf_in * v) ** 5
        df_dv = cf_con * dtv + 5.0 * cf_out * cf_in * (cf_in * v) ** 4
        if dFs != 0.0:
            vr = v * inv_vs
            e = exp(-vr * vr)
            f_fric += dFs * e * tv
            df_dv += dFs * e * (dtv - 2.0 * vr * inv_vs * tv)
        force = area * p / r - f_fric - d * v
        da_dx = d_area * p / (r * mass) - force * d_mass / (mass * mass)
        da_dv = (-df_dv - d) / mass
        da_dp = area / (r * mass)
        return [[0.0, 1.0, 0.0], [da_dx, da_dv, da_dp], [ddp_dx, ddp_dv, 0.0]]

    return jac


def _zoh(t: float, ts, pwm, load) -> tuple[float, float]:
    """Zero-order hold: the sample at or before ``t`` (the first one before start)."""
    i = bisect.bisect_right(ts, t) - 1
    i = min(max(i, 0), len(ts) - 1)
    return float(pwm[i]), float(load[i])


def rhs(t: float, y, params: Mapping[str, object], ts, pwm, load) -> np.ndarray:
    """docs/model.md's right-hand side ``dy/dt`` at ``(t, y)`` with zero-order-held inputs.

    Convenience form (it resolves the parameters on every call); the integrator
    below binds them once with :func:`make_core`.
    """
    u, m_load = _zoh(float(t), np.asarray(ts, dtype=float).tolist(), pwm, load)
    x, v, p = (float(c) for c in y)
    return np.array(make_core(params)(x, v, p, u, m_load))


def jacobian(t: float, y, params: Mapping[str, object], ts, pwm, load) -> np.ndarray:
    """Analytic Jacobian of :func:`rhs` with respect to ``y``."""
    u, m_load = _zoh(float(t), np.asarray(ts, dtype=float).tolist(), pwm, load)
    x, v, p = (float(c) for c in y)
    return np.array(make_jacobian(params)(x, v, p, u, m_load))


def static_pressure(params: Mapping[str, object], x: float, m_load: float) -> float:
    """``p_0 = M(x) g r / A(x)``: the pressure that holds the fork at rest."""
    P = _resolve(params)
    s1 = 0.5 * (1.0 + math.tanh((x - X_S1) / W_BLEND))
    s2 = 0.5 * (1.0 + math.tanh((x - X_S2) / W_BLEND))
    area = P["A1"] + (P["A2"] - P["A1"]) * s1 + (P["A3"] - P["A2"]) * s2
    mass = m_load + P["m_st1"] + P["m_st2"] * s1 + P["m_st3"] * s2
    return mass * G * P["ratio"] / area


#: docs/model.md: every run starts 1 µm above max(x0, 0) (off the end stop's tie)
START_CLEARANCE_M = 1e-6


def initial_state(params: Mapping[str, object], x0: float, m_load0: float) -> np.ndarray:
    """At rest at height ``max(x0, 0) + 1 µm``, pressure at static equilibrium
    (docs/model.md)."""
    x = max(float(x0), 0.0) + START_CLEARANCE_M
    return np.array([x, 0.0, static_pressure(params, x, float(m_load0))])


def simulate_scipy(
    params: Mapping[str, object],
    ts,
    pwm,
    load,
    x0: float,
    method: str = "LSODA",
    rtol: float = 1e-6,
    atol: tuple[float, float, float] | float = (1e-7, 1e-7, 1.0),
    use_jac: bool = True,
) -> dict[str, np.ndarray]:
    """Simulate one test run with ``scipy.integrate.solve_ivp`` (or ``odeint``).

    The run is split into segments at every sample where ``pwm`` or ``load`` change;
    each segment is integrated with its constant input by a fresh ``solve_ivp`` call
    started from the state at the end of the previous one.

    Args:
        params: ``{name: value}`` with docs/model.md's names (missing plant parameters take
            their nominal values; ``dFs``/``v_s`` and ``C_h`` switch the effects on).
        ts, pwm, load: sample times [s], duty cycle, load [kg] (zero-order hold).
        x0: initial height [m]; the fork starts at rest at static pressure.
        method: a ``solve_ivp`` method (``"LSODA"``, ``"Radau"``, ``"RK45"``, ...), or
            ``"odeint"`` for ODEPACK's LSODA through ``scipy.integrate.odeint`` (same
            algorithm, less Python overhead per call).
        rtol, atol: tolerances; ``atol`` per state (x, v, p).
        use_jac: give the analytic Jacobian to the implicit methods.

    Returns:
        ``{"height", "speed", "pressure"}`` at ``ts``, and ``"nfev"`` (right-hand-side
        calls in total) and ``"segments"``.
    """
    ts = np.asarray(ts, dtype=np.float64)
    pwm = np.asarray(pwm, dtype=np.float64)
    load = np.asarray(load, dtype=np.float64)
    n = ts.size
    if not (pwm.shape == load.shape == ts.shape and ts.ndim == 1 and n >= 2):
        raise ValueError("ts, pwm and load must be 1-D arrays of the same length >= 2")
    deriv = make_core(params)
    implicit = ("LSODA", "Radau", "BDF", "odeint")
    jac_core = make_jacobian(params) if use_jac and method in implicit else None
    change = np.nonzero((np.diff(pwm) != 0) | (np.diff(load) != 0))[0] + 1
    bounds = [0, *change.tolist(), n - 1]
    if bounds[-2] == n - 1:  # a change at the last sample: nothing to integrate after it
        bounds.pop()
    atol_arr = np.broadcast_to(np.asarray(atol, dtype=np.float64), (3,)).copy()
    ys = np.empty((n, 3))
    y = initial_state(params, x0, load[0])
    ys[0] = y
    nfev = 0
    ts_list = ts.tolist()
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        u, m_load = float(pwm[a]), float(load[a])

        def fun(t, yy, u=u, m_load=m_load):
            x, v, p = yy.tolist()
            return deriv(x, v, p, u, m_load)

        jac = None
        if jac_core is not None:

            def jac(t, yy, u=u, m_load=m_load):
                x, v, p = yy.tolist()
                return jac_core(x, v, p, u, m_load)

        if method == "odeint":  # ODEPACK's LSODA driven directly (less Python per call)
            seg, info = odeint(
                fun,
                y,
                ts[a : b + 1],
                Dfun=jac,
                rtol=rtol,
                atol=atol_arr,
                tfirst=True,
                full_output=True,
                mxstep=100_000,
                tcrit=ts[b : b + 1],  # never step past the segment's end
            )
            if info["message"] != "Integration successful.":
                raise RuntimeError(f"odeint failed at t = {ts_list[a]:.3f} s: {info['message']}")
            nfev += int(info["nfe"][-1])
            ys[a + 1 : b + 1] = seg[1:]
            y = seg[-1]
        else:
            kwargs = {"jac": jac} if jac is not None else {}
            sol = solve_ivp(
                fun,
                (ts_list[a], ts_list[b]),
                y,
                method=method,
                t_eval=ts[a : b + 1],
                rtol=rtol,
                atol=atol_arr,
                **kwargs,
            )
            if sol.status != 0:
                raise RuntimeError(f"solve_ivp failed at t = {ts_list[a]:.3f} s: {sol.message}")
            nfev += sol.nfev
            ys[a + 1 : b + 1] = sol.y[:, 1:].T
            y = sol.y[:, -1]
        if not 0.0 - 0.01 <= y[0] <= X_MAX + 0.01:
            raise RuntimeError(
                f"the fork left the mast's range at t = {ts_list[b]:.2f} s "
                f"(height {y[0]:.3f} m); end stops are not modelled here"
            )
    return {
        "height": ys[:, 0],
        "speed": ys[:, 1],
        "pressure": ys[:, 2],
        "nfev": nfev,
        "segments": len(bounds) - 1,
    }
