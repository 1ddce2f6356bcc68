"""An independent closed loop: the sampled PID of docs/control.md on the SciPy plant of
:mod:`scipy_reference`, with the figures of "good" computed here in NumPy.

Written from the specification (docs/control.md: "Sampled form", "Sensor noise", "What
'good' means"), *not* from jaxlift's code, and sharing none of it: the plant is
``scipy_reference.make_core`` integrated by SciPy's LSODA with its analytic Jacobian,
the controller law and the band-pass are written out below. It is the check of
issue #18: the gains the tuner recommends, run as the vehicle runs them (every
``T_c`` = 10 ms, duty held, the speed sensor noisy), give the figures the tuner claims.

What it takes from jaxlift as *data*, not code: the reference's knots (times and
speeds; the reference speed at a sample instant is ``numpy.interp`` of them) and, when
a comparison must be exact rather than statistical, the noise samples of one seed
(``v_meas - v`` of a jaxlift run at the sample instants). With the same noise the two
loops must agree to the solvers' tolerance; with its own noise (``rng``) this loop is a
fully independent draw of the same random experiment.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from scipy.integrate import solve_ivp
from scipy_reference import initial_state, make_core, make_jacobian

#: docs/control.md: noise power [(m/s)^2 s] and hold [s] of the speed sensor
NOISE_POWER, NOISE_HOLD = 1e-7, 0.01
NOISE_SIGMA = math.sqrt(NOISE_POWER / NOISE_HOLD)  # 3.16 mm/s


def closed_loop_scipy(
    params: Mapping[str, float],
    gains: Mapping[str, float],
    knots_t,
    knots_v,
    m_load: float,
    x0: float,
    *,
    T_c: float = 0.01,
    noise=None,
    rtol: float = 1e-7,
) -> dict[str, np.ndarray]:
    """The sampled loop of docs/control.md, every ``T_c`` [s] from ``t = 0`` to the last
    knot: at ``t_k`` the controller reads ``v_meas = v(t_k) + noise_k`` and sets the duty
    held until ``t_k + T_c``::

        u_raw = P e + q_I + D N (e - eta),   u = clip(u_raw, 0, 1)
        q_I  += T_c (I e + K_aw (u - u_raw))
        eta  += (1 - exp(-N T_c)) (e - eta)

    with ``u = 0`` and the states held where ``v_ref(t_k) = 0``.

    Args:
        params: plant parameters (``scipy_reference`` names; ``dFs``/``v_s``, ``C_h``
            switch its two effects on).
        gains: ``P, I, D, N, K_aw``.
        knots_t, knots_v: the reference, piecewise linear [s, m/s].
        m_load: load [kg]; x0: start height [m] (at rest, static pressure).
        T_c: controller period [s]; the outputs are at every ``T_c``.
        noise: speed-sensor noise at each sample instant [m/s] (None: none).
        rtol: LSODA's relative tolerance.

    Returns:
        ``ts, v_ref, x, v, p, u`` at the sample instants (``u``: the duty held from
        there).
    """
    knots_t = np.asarray(knots_t, dtype=float)
    knots_v = np.asarray(knots_v, dtype=float)
    n = int(round(knots_t[-1] / T_c)) + 1
    ts = np.arange(n) * T_c
    v_ref = np.interp(ts, knots_t, knots_v)
    noise = np.zeros(n) if noise is None else np.asarray(noise, dtype=float)
    if noise.shape != (n,):
        raise ValueError(f"noise must have {n} samples, got {noise.shape}")
    P, I, D, N, K_aw = (float(gains[k]) for k in ("P", "I", "D", "N", "K_aw"))  # noqa: E741
    alpha = 1.0 - math.exp(-N * T_c)
    deriv, jac_core = make_core(params), make_jacobian(params)
    y = initial_state(params, x0, m_load)
    q_I = eta = 0.0
    ys = np.empty((n, 3))
    us = np.zeros(n)
    ys[0] = y
    for k in range(n - 1):
        e = v_ref[k] - (y[1] + noise[k])
        if v_ref[k] == 0.0:
            u = 0.0
        else:
            u_raw = P * e + q_I + D * N * (e - eta)
            u = min(max(u_raw, 0.0), 1.0)
            q_I += T_c * (I * e + K_aw * (u - u_raw))
            eta += alpha * (e - eta)
        us[k] = u
        sol = solve_ivp(
            lambda t, yy, u=u: deriv(yy[0], yy[1], yy[2], u, m_load),
            (ts[k], ts[k + 1]),
            y,
            method="LSODA",
            jac=lambda t, yy, u=u: jac_core(yy[0], yy[1], yy[2], u, m_load),
            rtol=rtol,
            atol=(1e-8, 1e-8, 1.0),
        )
        if sol.status != 0:
            raise RuntimeError(f"LSODA failed at t = {ts[k]:.2f} s: {sol.message}")
        y = sol.y[:, -1]
        ys[k + 1] = y
    us[-1] = us[-2]
    return {"ts": ts, "v_ref": v_ref, "x": ys[:, 0], "v": ys[:, 1], "p": ys[:, 2], "u": us}


def band_pass(err: np.ndarray, dt: float, band=(0.5, 10.0)) -> np.ndarray:
    """docs/control.md's zero-phase band-pass: FFT of the signal zero-padded to a power
    of two of at least twice its length, times ``|H_hp|^2 |H_lp|^2`` of 2nd-order
    Butterworth filters at ``band`` [Hz]."""
    n = err.size
    m = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfftfreq(m, dt)
    r_hp = (f / band[0]) ** 4
    gain = r_hp / (1.0 + r_hp) / (1.0 + (f / band[1]) ** 4)
    return np.fft.irfft(np.fft.rfft(err, m) * gain, m)[:n]


def figures(run: Mapping[str, np.ndarray], dt: float = 0.01) -> dict[str, float]:
    """``tracking_rms`` and ``osc_rms`` [mm/s] of a run (docs/control.md), from the true
    speed, over the whole run."""
    err = run["v_ref"] - run["v"]
    return {
        "tracking_rms_mmps": 1e3 * float(np.sqrt(np.mean(err**2))),
        "osc_rms_mmps": 1e3 * float(np.sqrt(np.mean(band_pass(err, dt) ** 2))),
    }


def white_noise(n: int, seed: int) -> np.ndarray:
    """The sensor noise of docs/control.md drawn here (NumPy), one value per 10 ms."""
    return np.random.default_rng(seed).normal(0.0, NOISE_SIGMA, n)
