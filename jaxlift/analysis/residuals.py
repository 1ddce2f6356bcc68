"""Residual statistics: autocorrelation, Welch spectra and the Ljung--Box test against
the sensor-noise floor.
"""

from __future__ import annotations

import math

import numpy as np

from ..model.constants import SIGMA_HEIGHT_M, SIGMA_PRESSURE_PA, SPEED_NOISE_POWER
from ..model.log import Log
from .oscillation import next_pow2
from .regimes import Array1, check_len

# ----------------------------------------------------------------------------------------------
# residuals


def _acf(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Biased sample autocorrelation of ``x`` (mean removed) at lags 0..max_lag."""
    x = x - x.mean()
    n = x.size
    max_lag = min(max_lag, n - 1)
    m = next_pow2(2 * n)
    fx = np.fft.rfft(x, m)
    c = np.fft.irfft(np.abs(fx) ** 2, m)[: max_lag + 1]
    if c[0] <= 0:
        return np.concatenate(([1.0], np.zeros(max_lag)))
    return c / c[0]


def _welch(x: np.ndarray, dt: float, segment_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD [unit²/Hz] of ``x`` (Hann, 50 % overlap, mean removed per piece)."""
    n = x.size
    nseg = int(min(n, max(16, round(segment_s / dt))))
    hop = max(1, nseg // 2)
    win = np.hanning(nseg) if nseg > 2 else np.ones(nseg)
    scale = 1.0 / (np.sum(win**2) / dt)
    acc = np.zeros(nseg // 2 + 1)
    k = 0
    for a in range(0, n - nseg + 1, hop):
        seg = x[a : a + nseg]
        acc += np.abs(np.fft.rfft((seg - seg.mean()) * win)) ** 2
        k += 1
    psd = acc / max(k, 1) * scale
    psd[1:] *= 2.0
    if nseg % 2 == 0:
        psd[-1] /= 2.0
    return np.fft.rfftfreq(nseg, dt), psd


def _chi2_sf(q: float, dof: int) -> float:
    """Survival function of chi² (Wilson–Hilferty normal approximation)."""
    if dof <= 0 or not math.isfinite(q):
        return math.nan
    a = 2.0 / (9.0 * dof)
    zz = ((max(q, 0.0) / dof) ** (1.0 / 3.0) - (1.0 - a)) / math.sqrt(a)
    return 0.5 * math.erfc(zz / math.sqrt(2.0))


def ljung_box(x: np.ndarray, lags: int = 20, fitted: int = 0) -> tuple[float, int, float]:
    """Ljung--Box test of whiteness: ``Q = n (n + 2) sum_k acf_k^2 / (n - k)`` over lags
    ``1..lags``, against chi^2 with ``lags - fitted`` degrees of freedom (``fitted``: the
    number of parameters of a model whose innovations ``x`` are, e.g. 1 for AR(1)).
    Returns ``(Q, degrees of freedom, p-value)``; a small p says ``x`` is not white."""
    x = np.asarray(x, dtype=np.float64)
    m = min(lags, x.size - 2)
    if m < 1:
        return math.nan, 0, math.nan
    acf = _acf(x, m)
    n = x.size
    ks = np.arange(1, m + 1)
    q = float(n * (n + 2) * np.sum(acf[1 : m + 1] ** 2 / (n - ks)))
    dof = max(m - fitted, 1)
    return q, dof, _chi2_sf(q, dof)


def _diagnose(r: np.ndarray, sigma: float, dt: float, max_lag_s: float, lb_lags: int) -> dict:
    z = r / sigma
    max_lag = max(1, int(round(max_lag_s / dt)))
    acf = _acf(z, max_lag)
    rho1 = float(acf[1]) if acf.size > 1 else math.nan
    n = z.size
    m = min(lb_lags, acf.size - 1)
    ks = np.arange(1, m + 1)
    q = float(n * (n + 2) * np.sum(acf[1 : m + 1] ** 2 / (n - ks))) if m > 0 else math.nan
    freqs, power = _welch(z, dt, 10.0)
    return {
        "sigma": float(sigma),
        "scaled": z,
        "mean": float(np.mean(z)),
        "rms": float(np.sqrt(np.mean(z**2))),
        "freqs_hz": freqs,
        "power": power,
        "lags_s": np.arange(acf.size) * dt,
        "acf": acf,
        "rho1": rho1,
        "neff_factor": float(np.clip((1.0 - rho1) / (1.0 + rho1), 0.0, None)),
        "ljung_box_q": q,
        "ljung_box_lags": int(m),
        "ljung_box_p": _chi2_sf(q, m),
    }


def residual_diagnostics(
    log: Log,
    height: Array1,
    speed: Array1,
    pressure: Array1 | None = None,
    *,
    sigma_height_m: float = SIGMA_HEIGHT_M,
    speed_noise_power: float = SPEED_NOISE_POWER,
    sigma_pressure_pa: float = SIGMA_PRESSURE_PA,
    max_lag_s: float = 2.0,
    ljung_box_lags: int = 20,
) -> dict[str, dict]:
    """Statistics of the scaled residuals ``(model − measured) / σ`` of height and speed (and
    pressure, when both the log and the simulation have one).

    With a right model the scaled residuals are white with unit variance; structure in their
    spectrum (a peak at the oscillation frequency) or a large lag-1 autocorrelation shows what
    the model misses, and ``n_eff / n`` says how far a χ² that treats samples as independent
    overstates the evidence.

    Args:
        log: the measured run.
        height: simulated height [m]; speed: simulated speed [m/s]; pressure: simulated
            pressure [Pa], optional.
        sigma_height_m: height noise σ [m] (docs/model.md: 0.5 mm).
        speed_noise_power: speed noise power [(m/s)² s]; σ_v = sqrt(power / T_s) [m/s].
        sigma_pressure_pa: pressure noise σ [Pa].
        max_lag_s: longest autocorrelation lag [s].
        ljung_box_lags: number of lags (samples) in the Ljung–Box statistic.

    Returns:
        ``{"height": d, "speed": d, "pressure": d}`` (speed only when the log has speed,
        pressure only as said above), each ``d`` with: ``sigma`` (the scale, in the signal's SI
        unit), ``scaled`` (the scaled residual, dimensionless), ``mean``, ``rms`` (of the
        scaled residual), ``freqs_hz`` [Hz] and ``power`` (Welch periodogram of the scaled
        residual, 10 s Hann pieces, one-sided, [1/Hz]: white unit-variance noise gives
        ``2 T_s``), ``lags_s`` [s] and ``acf`` (autocorrelation, lag 0 to ``max_lag_s``),
        ``rho1`` (lag-1 autocorrelation), ``neff_factor`` (``n_eff / n = (1 − ρ1)/(1 + ρ1)``,
        AR(1) approximation, ≥ 0), ``ljung_box_q``, ``ljung_box_lags``, ``ljung_box_p``
        (Ljung–Box Q over the first lags and its χ² p-value, Wilson–Hilferty approximation:
        p ≈ 0 means the residuals are not white).
    """
    h = check_len(log, "height", height)
    v = check_len(log, "speed", speed)
    dt = log.sample_period
    out = {"height": _diagnose(h - log.height_m, sigma_height_m, dt, max_lag_s, ljung_box_lags)}
    if log.speed_mps is not None:
        sv = math.sqrt(speed_noise_power / dt)
        out["speed"] = _diagnose(v - log.speed_mps, sv, dt, max_lag_s, ljung_box_lags)
    if pressure is not None and log.pressure_pa is not None:
        p = check_len(log, "pressure", pressure)
        out["pressure"] = _diagnose(
            p - log.pressure_pa, sigma_pressure_pa, dt, max_lag_s, ljung_box_lags
        )
    return out
