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


def sampled_closed_loop_eigenvalues(
    plant: Plant,
    effects: Sequence[AbstractEffect],
    controller: AbstractController,
    m_load: float,
    x: float,
    v_ref: float,
    T_c: float = 0.01,
    sat_gain: float | None = None,
) -> tuple[np.ndarray, float, bool]:
    """Eigenvalues (dimensionless multipliers per period) of the **sampled** closed
    loop linearised at height ``x`` [m] (frozen), steady motion at ``v_ref`` [m/s],
    load ``m_load`` [kg]: the controller's own sampled law
    (:meth:`~jaxlift.AbstractController.sampled_update`: the filter discretised
    exactly, the integral by forward Euler) on the speed sampled every ``T_c`` [s], its
    duty held (zero-order hold) on the plant linearised at the operating point and
    discretised exactly over one period (``expm`` of the augmented matrix). Stable when
    every ``|lambda| < 1``. At 100 Hz with ``N T_c`` near 1 this differs from the
    continuous eigenvalues (:func:`closed_loop_eigenvalues`): the derivative filter and
    the hold each add phase lag.

    The operating point is the continuous loop's (the same steady state: constant
    duty, zero error). ``sat_gain`` as in :func:`closed_loop_eigenvalues`. Effects
    with an input delay are refused (the delay would need the duty buffer's states).

    Returns ``(multipliers, duty at the operating point, whether it was found)``."""
    effects = canonical_effects(effects)
    if any(float(e.delay()) > 0 for e in effects):
        raise ValueError(
            "sampled_closed_loop_eigenvalues: an input delay needs the duty buffer as "
            "states; not supported (simulate the sampled loop instead)"
        )
    f64 = lambda v: jnp.asarray(v, dtype=jnp.float64)  # noqa: E731
    m, xx, vr = f64(m_load), f64(x), f64(v_ref)
    g = None if sat_gain is None else f64(sat_gain)
    z, _, resid = _equilibrium_and_jacobian(plant, effects, controller, m, xx, vr, g)
    n_plant = 3 + sum(e.n_states for e in effects)
    u_star = z[n_plant - 1]  # at steady state q_I = u (zero error, eta = 0)
    Phi, Gam = _zoh(plant, effects, m, xx, z[: n_plant - 1], u_star, f64(T_c))
    M = _sampled_jacobian(controller, plant, m, xx, vr, z, Phi, Gam, u_star, f64(T_c), g)
    u = float(u_star)
    found = bool(np.all(np.isfinite(np.asarray(z)))) and 0.0 < u < 1.0
    found = found and bool(np.all(np.abs(np.asarray(resid)) < 1e-3 * (1 + np.abs(np.asarray(z)))))
    return np.linalg.eigvals(np.asarray(M)), u, found


@eqx.filter_jit
def _zoh(plant, effects, m_load, x, yp_rest, u, T_c):
    """``(Phi, Gamma)``: the plant (height frozen) linearised at ``(yp_rest, u)`` and
    discretised with a zero-order hold over ``T_c``."""

    def field(yr, uu):
        yp = jnp.concatenate([x[None], yr])
        return plant_signals_and_derivative(0.0, yp, plant, effects, uu, m_load)[1][1:]

    A = jax.jacfwd(field, argnums=0)(yp_rest, u)
    B = jax.jacfwd(field, argnums=1)(yp_rest, u)
    n = A.shape[0]
    # in units of the states' own sizes (speed ~1e-2 m/s, pressure ~1e7 Pa): unscaled,
    # A's entries span 18 decades and expm's scaling and squaring returned NaN
    d = jnp.maximum(jnp.abs(yp_rest), 1e-3)
    As, Bs = A * d[None, :] / d[:, None], B / d
    aug = jnp.zeros((n + 1, n + 1)).at[:n, :n].set(As).at[:n, n].set(Bs)
    E = jax.scipy.linalg.expm(aug * T_c)
    return E[:n, :n] * d[:, None] / d[None, :], E[:n, n] * d


@eqx.filter_jit
def _sampled_jacobian(controller, plant, m_load, x, v_ref, z, Phi, Gam, u_star, T_c, sat_gain):
    """Jacobian of one period of the sampled loop at its fixed point ``z``."""
    n = Phi.shape[0]

    def period(w):
        yr, q, eta = w[:n], w[n], w[n + 1]
        e = v_ref - yr[0]  # the speed, sampled at the period's start
        u, u_raw, q1, eta1 = controller.sampled_update(plant, x, m_load, e, q, eta, True, T_c)
        if sat_gain is not None:  # value clip(u_raw), slope sat_gain (as in the continuous)
            u = jax.lax.stop_gradient(u) + sat_gain * (u_raw - jax.lax.stop_gradient(u_raw))
        y_next = z[:n] + Phi @ (yr - z[:n]) + Gam * (u - u_star)
        return jnp.concatenate([y_next, jnp.stack([q1, eta1])])

    return jax.jacfwd(period)(z)


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
    the eigenvalue's frequency [Hz], stable.

    ``sampled``: the sampled loop's multipliers
    (:func:`sampled_closed_loop_eigenvalues`, clock ``T_c``), given as the equivalent
    rates ``log(lambda) / T_c`` (so that ``max_real_per_s`` and ``freq_hz`` read as in
    the continuous table; stable when ``|lambda| < 1``, i.e. ``max_real_per_s < 0``),
    plus the spectral radius ``max_abs_multiplier``. Without an input delay only (the
    continuous eigenvalues are given otherwise, and the row says so)."""
    has_delay = any(float(e.delay()) > 0 for e in canonical_effects(effects))
    discrete = sampled and not has_delay

    def eigs(x, v, g=None):
        if discrete:
            lam, u, found = sampled_closed_loop_eigenvalues(
                plant, effects, controller, m_load, x, v, T_c, sat_gain=g
            )
            rates = np.log(lam.astype(complex)) / T_c
            return rates, u, found, float(np.max(np.abs(lam)))
        eig, u, found = closed_loop_eigenvalues(plant, effects, controller, m_load, x, v, g)
        return eig, u, found, float("nan")

    rows = []
    for label, x in operating_points(plant):
        for v in speeds:
            eig, u, found, radius = eigs(x, v)
            g = 1.0
            if noise and found:
                g = noise_describing_gain(controller, plant, x, m_load, u, sampled=sampled, T_c=T_c)
                eig, _, _, radius = eigs(x, v, g)
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
                    form="sampled" if discrete else "continuous",
                    max_abs_multiplier=radius,
                )
            )
    return rows


def sampled_spectral_radius(
    controller: AbstractController,
    plant: Plant,
    effects: Sequence[AbstractEffect],
    loads: Sequence[float],
    T_c: float = 0.01,
) -> float:
    """The largest ``|lambda|`` of the sampled loop (:func:`sampled_closed_loop_eigenvalues`,
    no noise) over :func:`operating_points`, 0.025 and 0.09 m/s, and ``loads`` [kg];
    below 1: stable on the clock everywhere. Operating points that could not be found
    are skipped."""
    worst = 0.0
    for m in loads:
        for r in stability_table(plant, effects, controller, float(m), sampled=True, T_c=T_c):
            if np.isfinite(r["max_abs_multiplier"]) and np.isfinite(r["max_real_per_s"]):
                worst = max(worst, r["max_abs_multiplier"])
    return worst


#: The factors of the coarse search of :func:`stabilise_for_clock`: proportional gain,
#: integral-to-proportional ratio, derivative gain (each relative to the start), and
#: the filter bandwidth capped at ``0.3 / T_c`` or not.
STABILISING_FACTORS = dict(P=(1.0, 0.5, 0.25), I_over_P=(1.0, 0.5, 0.25), D=(1.0, 0.5, 0.25, 0.1))


def _scaled_gains(controller: AbstractController, fp, fi, fd, n_cap) -> AbstractController:
    vals = controller.gain_values()
    out = {}
    for name, v in vals.items():
        head = name.split("_")[0]
        f = {"P": fp, "I": fp * fi, "D": fd}.get(head, 1.0)
        out[name] = v * f
    if n_cap is not None and "N" in vals:
        out["N"] = min(vals["N"], n_cap)
    return controller.with_gains(out)


def clock_candidates(
    controller: AbstractController,
    plant: Plant,
    effects: Sequence[AbstractEffect],
    loads: Sequence[float],
    T_c: float = 0.01,
    *,
    radius: float | None = None,
) -> list[tuple[float, AbstractController]]:
    """``controller`` and the coarse grid of scaled versions of it
    (:data:`STABILISING_FACTORS`: the proportional, integral and derivative gains
    scaled down, the derivative filter capped at ``0.3 / T_c`` or not), each with its
    largest ``|lambda|`` on the clock (:func:`sampled_spectral_radius`); ``controller``
    first (``radius``: its radius, if already known)."""
    if radius is None:
        radius = sampled_spectral_radius(controller, plant, effects, loads, T_c)
    out = [(radius, controller)]
    n_cap = 0.3 / T_c
    for fp in STABILISING_FACTORS["P"]:
        for fi in STABILISING_FACTORS["I_over_P"]:
            for fd in STABILISING_FACTORS["D"]:
                for cap in (None, n_cap):
                    if (fp, fi, fd, cap) == (1.0, 1.0, 1.0, None):
                        continue  # the controller itself
                    cand = _scaled_gains(controller, fp, fi, fd, cap)
                    out.append((sampled_spectral_radius(cand, plant, effects, loads, T_c), cand))
    return out


def gains_text(controller: AbstractController) -> str:
    """``"P 20, I 300, ..."``: a controller's gains in a sentence (3 digits)."""
    return ", ".join(f"{k} {v:.3g}" for k, v in controller.gain_values().items())


def stabilise_for_clock(
    controller: AbstractController,
    plant: Plant,
    effects: Sequence[AbstractEffect],
    loads: Sequence[float],
    T_c: float = 0.01,
) -> tuple[AbstractController, str | None]:
    """A starting point for tuning the sampled loop: ``controller`` itself if it is
    stable on the clock (:func:`sampled_spectral_radius` < 1), else the most stable of
    a coarse grid of scaled versions of it (:func:`clock_candidates`). Returns the
    controller and a note saying what was done (None when nothing was).
    (:func:`jaxlift.control.tune.tune_gains` chooses among the stable candidates by
    the tuning cost itself; this is the choice by stability alone.)

    Why: derivatives through an unstable loop grow with every period (a multiplier
    of 1.12 per 10 ms is 1e78 over 16 s) and the saturation that bounds the run does
    not bound them: the thesis gains (``N T_c`` = 1) are unstable sampled at 100 Hz at
    slow speed, and tuning from them stalled at its first step (measured: Jacobian
    columns of 1e18-1e33 where finite differences gave 5e3-8e3). From a stable start
    the forward-mode Jacobian agrees with finite differences."""
    r0 = sampled_spectral_radius(controller, plant, effects, loads, T_c)
    if r0 < 1.0:
        return controller, None
    cands = clock_candidates(controller, plant, effects, loads, T_c, radius=r0)
    r, chosen = min(cands, key=lambda rc: rc[0])
    return chosen, unstable_start_note(r0, r, chosen, T_c)


def unstable_start_note(r0: float, r: float, chosen: AbstractController, T_c: float) -> str:
    """What :func:`stabilise_for_clock` did, as a sentence."""
    head = f"the starting gains are unstable sampled every {T_c:g} s (largest |lambda| {r0:.3g})"
    if r < 1.0:
        return (
            f"{head}; tuning starts from the most stable of a coarse grid of scaled "
            f"versions: {gains_text(chosen)} (|lambda| {r:.3g})"
        )
    return (
        f"{head} and no scaled version is stable (best {r:.3g}: {gains_text(chosen)}); "
        "tuning starts from it, but derivatives through an unstable loop are unreliable"
    )
