"""Stability of the closed loop: operating points along the lift, the eigenvalues of
the linearised loop (continuous and sampled), and a table of the least stable ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model.constants import G
from ..model.effects import AbstractEffect
from ..model.inputs import Inputs
from ..model.plant import Plant
from ..model.vector_field import (
    canonical_effects,
    initial_state,
    plant_signals_and_derivative,
    split_state,
)
from .closed_loop import NOISE_POWER, NOISE_TS
from .controller import AbstractController


# ------------------------------------------------------------------ stability
def operating_points(plant: Plant) -> list[tuple[str, float]]:
    """Heights [m] along the lift: the middle and both ends of every stage."""
    x1, x2, xm = plant.x_s1, plant.x_s2, plant.x_max
    return [
        ("stage 1 low", 0.3),
        ("stage 1 mid", 0.75),
        ("stage 1 top", x1 - 0.1),
        ("stage 2 low", x1 + 0.1),
        ("stage 2 mid", 0.5 * (x1 + x2)),
        ("stage 2 top", x2 - 0.1),
        ("stage 3 low", x2 + 0.1),
        ("stage 3 mid", 0.5 * (x2 + xm)),
        ("stage 3 top", xm - 0.2),
    ]


def _cl_field_frozen(z, x, v_ref, plant, effects, ctrl, m_load, sat_gain):
    """Closed-loop derivative of all states but ``x`` (``x`` frozen), no noise."""
    n_plant = 3 + sum(e.n_states for e in effects)
    yp = jnp.concatenate([x[None], z[: n_plant - 1]])
    q_I, eta = z[n_plant - 1], z[n_plant]
    out = ctrl.output(plant, x, m_load, v_ref - yp[1], q_I, eta, True, sat_gain=sat_gain)
    _, dyp = plant_signals_and_derivative(0.0, yp, plant, effects, out.u, m_load)
    return jnp.concatenate([dyp[1:], jnp.stack([out.dq_I, out.deta])])


@eqx.filter_jit
def _equilibrium_and_jacobian(plant, effects, ctrl, m_load, x, v_ref, sat_gain):
    # first guess: force balance at v_ref, the duty that delivers the flow
    inputs = Inputs(
        ts=jnp.asarray([0.0, 1.0]),
        pwm=jnp.zeros(2),
        load_kg=jnp.stack([m_load, m_load]),
        jump_ts=jnp.asarray([1.0]),
        x0=x,
    )
    y0 = initial_state(plant, effects, inputs)
    area, r = plant.area(x), plant.ratio
    p = ((m_load + plant.stage_mass(x)) * G + plant.friction(v_ref) + plant.d * v_ref) * r / area
    omega = area * v_ref / r * 2 * jnp.pi / (plant.eta_v * plant.disp)
    k = plant.staged(x, plant.k1, plant.k2, plant.k3)
    zz = plant.staged(x, plant.z1, plant.z2, plant.z3)
    u = (omega - zz) / k / plant.u_batt
    (_, _, _), zs = split_state(y0, effects)
    z = jnp.concatenate([jnp.stack([v_ref, p]), *zs, jnp.stack([u, 0.0])])
    f = lambda z: _cl_field_frozen(z, x, v_ref, plant, effects, ctrl, m_load, sat_gain)

    def newton(z, _):
        J = jax.jacfwd(f)(z)
        dz = jnp.linalg.solve(J, -f(z))
        return z + dz, None

    z, _ = jax.lax.scan(newton, z, None, length=12)
    J = jax.jacfwd(f)(z)
    resid = f(z)
    return z, J, resid


def closed_loop_eigenvalues(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    controller: AbstractController,
    m_load: float,
    x: float,
    v_ref: float,
    sat_gain: float | None = None,
) -> tuple[np.ndarray, float, bool]:
    """Eigenvalues [1/s] of the closed loop linearised at height ``x`` [m] (frozen),
    steady motion at ``v_ref`` [m/s], load ``m_load`` [kg]; ``sat_gain``: slope of the
    saturation (None: 1, the noise-free interior). Returns ``(eigenvalues, duty at the
    operating point, whether the operating point was found with 0 < u < 1)``."""
    effects = canonical_effects(effects)
    z, J, resid = _equilibrium_and_jacobian(
        plant,
        effects,
        controller,
        jnp.asarray(m_load, dtype=jnp.float64),
        jnp.asarray(x, dtype=jnp.float64),
        jnp.asarray(v_ref, dtype=jnp.float64),
        None if sat_gain is None else jnp.asarray(sat_gain, dtype=jnp.float64),
    )
    n_plant = 3 + sum(e.n_states for e in effects)
    u = float(z[n_plant - 1])
    scale = np.abs(np.asarray(J)).max(axis=1) * np.maximum(np.abs(np.asarray(z)), 1e-6) + 1e-12
    found = bool(np.all(np.abs(np.asarray(resid)) <= 1e-6 * scale)) and 0.0 < u < 1.0
    return np.linalg.eigvals(np.asarray(J)), u, found


def noise_describing_gain(
    controller: AbstractController,
    plant: Plant,
    x: float,
    m_load: float,
    u_op: float,
    *,
    sampled: bool = False,
    T_c: float = 0.01,
    seed: int = 0,
    n_samples: int = 2000,
    sub: int = 64,
) -> float:
    """Incremental gain of the saturation ``clip(., 0, 1)`` for a small signal on top of
    the sensor noise's part of ``u_raw`` around the duty ``u_op``: the probability
    that ``u_op + xi`` is inside (0, 1) (Booton), over time. ``xi = P n + D N (n - eta_n)``
    with ``eta_n`` the filtered noise (the slow integral path is left out); continuous
    form on ``sub`` points per noise hold, sampled form at the clock instants."""
    P, _, D = (float(g) for g in controller.gains(plant, jnp.asarray(x), jnp.asarray(m_load)))
    N = float(controller.N)
    rng = np.random.default_rng(seed)
    n = rng.normal(0.0, math.sqrt(NOISE_POWER / NOISE_TS), n_samples)
    if sampled:
        reps = max(1, int(round(NOISE_TS / T_c)))
        nk = np.repeat(n, reps)
        a = 1.0 - math.exp(-N * T_c)
        eta, xi = 0.0, np.empty(nk.size)
        for i, v in enumerate(nk):
            xi[i] = P * v + D * N * (v - eta)
            eta += a * (v - eta)
    else:
        tau = (np.arange(sub) + 0.5) / sub * NOISE_TS
        eta, xs = 0.0, []
        for v in n:
            dev = (v - eta) * np.exp(-N * tau)  # n - eta_n within the hold
            xs.append(P * v + D * N * dev)
            eta = v - (v - eta) * math.exp(-N * NOISE_TS)
        xi = np.concatenate(xs)
    inside = (u_op + xi > 0.0) & (u_op + xi < 1.0)
    return float(np.mean(inside))


def stability_table(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    controller: AbstractController,
    m_load: float,
    *,
    speeds: Sequence[float] = (0.025, 0.09),
    noise: bool = False,
    sampled: bool = False,
    T_c: float = 0.01,
) -> list[dict]:
    """Max real part of the closed-loop eigenvalues at :func:`operating_points` and
    ``speeds`` [m/s]; with ``noise`` the saturation's slope is the noise describing
    gain (:func:`noise_describing_gain`). Rows: point, x, v_ref, u, gain, max_real,
    the eigenvalue's frequency [Hz], stable."""
    rows = []
    for label, x in operating_points(plant):
        for v in speeds:
            eig, u, found = closed_loop_eigenvalues(plant, effects, controller, m_load, x, v)
            g = 1.0
            if noise and found:
                g = noise_describing_gain(controller, plant, x, m_load, u, sampled=sampled, T_c=T_c)
                eig, _, _ = closed_loop_eigenvalues(
                    plant, effects, controller, m_load, x, v, sat_gain=g
                )
            i = int(np.argmax(eig.real))
            rows.append(
                dict(
                    point=label,
                    x_m=x,
                    v_ref_mps=v,
                    u=u,
                    sat_gain=g,
                    max_real_per_s=float(eig.real[i]) if found else float("nan"),
                    freq_hz=abs(float(eig.imag[i])) / (2 * math.pi) if found else float("nan"),
                    stable=bool(found and eig.real[i] < 0),
                )
            )
    return rows
