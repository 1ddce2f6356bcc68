"""Oscillations in a log or a simulation: frequency, amplitude and decay per segment,
the speed noise floor, and zoom windows around the strongest oscillations.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..model.constants import SPEED_NOISE_POWER
from ..model.log import Log
from .regimes import SHIFT_BEFORE_S, Array1, Segment, check_len, measured_speed, segment_log

_NARROW_SIGMA_HZ = 0.4  # std of the Gaussian band around the oscillation peak [Hz]
_ENV_WINDOW_S = 1.0  # window for the envelope RMS in the decay fit [s]
_REL_VAR = 0.01  # relative variance of a window power beyond noise, in the decay fit [-]


def next_pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


# ----------------------------------------------------------------------------------------------
# oscillations


def _nan_metrics() -> dict:
    return {
        "freq_hz": math.nan,
        "amplitude_mps": math.nan,
        "amp0_mps": math.nan,
        "decay_per_s": math.nan,
        "rms_mps": math.nan,
        "noise_rms_mps": math.nan,
    }


def oscillation_metrics(
    t: Array1,
    v: Array1,
    *,
    band: tuple[float, float] = (0.5, 10.0),
    noise_floor_mps: float = 0.0,
    subtract_noise: bool = True,
) -> dict:
    """Frequency, amplitude and decay of the oscillation in one signal over a steady stretch.

    Method:

    1. remove a linear trend; band-limit to ``band`` [Hz] by zeroing FFT bins (zero-padded to
       twice the length, so nothing wraps around). ``rms_mps`` is the RMS of that signal.
    2. ``freq_hz``: the highest peak in ``band`` of the Hann-windowed spectrum, zero-padded
       16× and refined by parabolic interpolation of the log magnitude.  NaN (and so is
       ``decay_per_s``) when ``rms_mps`` is not above ``noise_floor_mps`` (or is round-off,
       below 1e-9 × the RMS of ``v``): then there is no oscillation to report, only noise.
    3. the signal is band-passed again with a Gaussian band (standard deviation 0.4 Hz) around
       the peak, and its envelope taken (analytic signal via FFT), corrected for the filter's
       edge effect.  The sensor-noise power in that band is estimated from the median of the
       spectrum away from the peak (white noise) and subtracted when ``subtract_noise``.
    4. ``amplitude_mps`` = √2 × RMS of the narrow-band signal (noise removed): the amplitude
       of a sustained sinusoid; for a decaying one its RMS-equivalent amplitude over the
       stretch.  ``amp0_mps``: the fitted envelope at the first sample.
    5. ``decay_per_s``: minus the slope of the log of the envelope RMS over 1 s windows (half
       overlapping), fitted by weighted least squares with weights (S/P)², S the window's
       signal power and P its total power, so noise-dominated windows count little.
       Positive = decaying (``exp(-decay t)``), ≈ 0 = sustained, negative = growing.

    Args:
        t: sample times [s], uniformly spaced.
        v: the signal, e.g. a speed [m/s] (all amplitudes are in the signal's unit).
        band: frequency band [Hz] in which to look for the oscillation.
        noise_floor_mps: smallest band RMS [m/s] reported as an oscillation.
        subtract_noise: remove the estimated white-noise power (for measured signals; turn off
            for noise-free simulated ones).

    Returns:
        ``freq_hz`` [Hz], ``amplitude_mps``, ``amp0_mps`` [m/s], ``decay_per_s`` [1/s],
        ``rms_mps`` [m/s], ``noise_rms_mps`` (estimated noise RMS in the narrow band [m/s]).
        All NaN for fewer than 16 samples.
    """
    t = np.asarray(t, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if t.shape != v.shape or t.ndim != 1:
        raise ValueError(f"t and v must be 1-D of equal length, got {t.shape} and {v.shape}")
    n = t.size
    out = _nan_metrics()
    if n < 16:
        return out
    dt = float(np.median(np.diff(t)))
    tc = t - t.mean()
    a_mat = np.stack([tc, np.ones(n)], axis=1)
    coef, *_ = np.linalg.lstsq(a_mat, v, rcond=None)
    r = v - a_mat @ coef

    m = next_pow2(2 * n)
    f = np.fft.rfftfreq(m, dt)
    x = np.fft.rfft(r, m)
    inband = (f >= band[0]) & (f <= band[1])
    y = np.fft.irfft(x * inband, m)[:n]
    rms = float(np.sqrt(np.mean(y**2)))
    out["rms_mps"] = rms

    # spectral peak: coarse on the power spectrum smoothed over ~0.1 Hz (robust to single noise
    # bins), refined on the 16x zero-padded spectrum (no taper, so that a decaying oscillation
    # at the start of the stretch keeps its weight) by parabolic interpolation of log |X|
    mz = next_pow2(16 * n)
    fz = np.fft.rfftfreq(mz, dt)
    xz = np.abs(np.fft.rfft(r, mz))
    dfz = float(fz[1] - fz[0])
    bz = np.flatnonzero((fz >= band[0]) & (fz <= band[1]))
    if bz.size == 0:
        return out
    half = max(1, int(round(0.1 / dfz)))
    kern = np.exp(-0.5 * (np.arange(-3 * half, 3 * half + 1) / half) ** 2)
    smooth = np.convolve(xz**2, kern, mode="same")
    kc = int(bz[np.argmax(smooth[bz])])
    near = bz[np.abs(bz - kc) <= 2 * half]
    k = int(near[np.argmax(xz[near])])
    f0 = float(fz[k])
    if 0 < k < fz.size - 1 and np.all(xz[k - 1 : k + 2] > 0):
        la, lb, lc = np.log(xz[k - 1 : k + 2])
        den = la - 2 * lb + lc
        if den < 0:
            f0 += 0.5 * (la - lc) / den * dfz

    # noise: white, estimated from the median periodogram away from the peak
    per = np.abs(x) ** 2 / n  # E = variance per sample for white noise
    away = inband & (np.abs(f - f0) > 4 * _NARROW_SIGMA_HZ)
    if away.sum() < 8:
        away = inband
    noise_var = float(np.median(per[away]) / math.log(2)) if subtract_noise else 0.0

    # narrow band around the peak, analytic signal, edge gain
    hn = np.exp(-0.5 * ((f - f0) / _NARROW_SIGMA_HZ) ** 2) * inband
    zfull = np.zeros(m, dtype=np.complex128)
    zfull[: f.size] = x * hn
    zfull[1 : (m + 1) // 2] *= 2.0
    if m % 2 == 0:
        zfull[m // 2] = 0.0
    z = np.fft.ifft(zfull)[:n]
    gain = np.fft.irfft(np.fft.rfft(np.ones(n), m) * np.exp(-0.5 * (f / _NARROW_SIGMA_HZ) ** 2), m)
    gain = np.clip(gain[:n], 1e-3, None)
    # noise power of |z|^2: 2 x the variance of the real narrow-band noise (two-sided |H|^2)
    h2 = hn**2
    mean_h2 = (h2[0] + 2 * h2[1:].sum() - (h2[-1] if m % 2 == 0 else 0.0)) / m
    noise_z = 2.0 * noise_var * mean_h2
    out["noise_rms_mps"] = float(np.sqrt(noise_z / 2.0))
    pz = np.abs(z) ** 2 / gain**2
    out["amplitude_mps"] = float(np.sqrt(max(float(np.mean(pz)) - noise_z, 0.0)))

    # no oscillation: below the floor, or only round-off left after the detrending
    if not (rms > noise_floor_mps and rms > 1e-9 * float(np.sqrt(np.mean(v**2)))):
        return out
    out["freq_hz"] = float(f0)

    # decay: envelope power over ~1 s windows, fitted with A^2 exp(-2 decay t) + noise
    ok = np.flatnonzero(gain >= 0.8)
    if ok.size < 4:
        return out
    w_len = min(max(2, int(round(_ENV_WINDOW_S / dt))), ok.size)
    hop = max(1, w_len // 4)
    starts = np.arange(int(ok[0]), int(ok[-1]) - w_len + 2, hop)
    if starts.size < 2:
        return out
    c = np.concatenate(([0.0], np.cumsum(pz)))
    pw = (c[starts + w_len] - c[starts]) / w_len
    ct = np.concatenate(([0.0], np.cumsum(t)))
    tw = (ct[starts + w_len] - ct[starts]) / w_len - t[0]
    fit = _fit_envelope(tw, pw, noise_z)
    if fit is not None:
        out["decay_per_s"], out["amp0_mps"] = fit
    return out


def _fit_envelope(tw: np.ndarray, pw: np.ndarray, noise: float) -> tuple[float, float] | None:
    """Fit ``pw ≈ a² exp(-2 d tw) + noise`` (window powers ``pw`` at times ``tw`` [s] from the
    start) by iteratively reweighted least squares.  Weights: 1 / the variance of a window power
    of signal power S in noise power N, ∝ N² + 2 S N (+ a 1 % relative spread of S, for
    oscillations that are not exactly exponential and for noise-free signals).  Grid search
    over the decay ``d`` [1/s] in [-3, 10], then a finer grid; ``a²`` is linear.  Returns
    ``(d, a)`` or None."""
    scale = float(np.max(pw))
    if not scale > 0 or np.ptp(tw) <= 0:
        return None
    pw, noise = pw / scale, noise / scale  # the fit is scale-invariant; avoids over/underflow
    y = pw - noise
    if not np.any(y > 0):
        return None

    def best(grid: np.ndarray, w: np.ndarray) -> tuple[float, float]:
        g = np.exp(-2.0 * grid[:, None] * tw[None, :])  # (grid, windows)
        sgg = (w * g * g).sum(axis=1)
        sgy = (w * g * y).sum(axis=1)
        a2 = np.clip(sgy / sgg, 0.0, None)
        cost = (w * (y[None, :] - a2[:, None] * g) ** 2).sum(axis=1)
        i = int(np.argmin(cost))
        return float(grid[i]), float(a2[i])

    # growth rates limited so that exp(-4 d t) cannot overflow on long stretches
    d_lo = max(-3.0, -150.0 / float(np.max(tw)))
    w = 1.0 / np.maximum(pw, 1e-300) ** 2
    d, a2 = 0.0, 0.0
    for _ in range(4):
        d, a2 = best(np.linspace(d_lo, 10.0, 261), w)
        d, a2 = best(np.linspace(max(d - 0.05, d_lo), d + 0.05, 101), w)
        sig = a2 * np.exp(-2.0 * d * tw)
        w = 1.0 / np.maximum(noise**2 + 2.0 * sig * noise + _REL_VAR * sig**2, 1e-300)
    if a2 <= 0:
        return None
    return d, math.sqrt(a2 * scale)


def log_speed_noise_floor(
    log: Log,
    *,
    band: tuple[float, float] = (0.5, 10.0),
    factor: float = 3.0,
    speed_noise_power: float = SPEED_NOISE_POWER,
) -> float:
    """Default noise floor [m/s] for the measured speed of ``log`` in :func:`oscillation_metrics`.

    ``factor`` × the RMS that white sensor noise of standard deviation
    ``σ_v = sqrt(speed_noise_power / T_s)`` (docs/model.md; ≈ 3.2 mm/s at 100 Hz) has after
    band-limiting to ``band``: ``σ_v · sqrt((f_hi − f_lo) / f_Nyquist)`` (≈ 1.3 mm/s for
    0.5–10 Hz at 100 Hz, so the default floor is ≈ 3.9 mm/s).  Pure noise exceeds it with
    negligible probability; a sustained sinusoid needs an amplitude of about
    √2 · sqrt(floor² − noise²) ≈ 5 mm/s to pass it.
    """
    ts = log.sample_period
    nyq = 0.5 / ts
    lo, hi = max(band[0], 0.0), min(band[1], nyq)
    sigma_v = math.sqrt(speed_noise_power / ts)
    return factor * sigma_v * math.sqrt(max(hi - lo, 0.0) / nyq)


def oscillation_table(
    log: Log,
    speed_model: Array1,
    segments: Sequence[Segment] | None = None,
    *,
    noise_floor: float | None = None,
    model_noise_floor: float | None = None,
    band: tuple[float, float] = (0.5, 10.0),
    min_duration_s: float = 3.0,
) -> list[dict]:
    """Oscillation metrics of the measured and the simulated speed on every steady moving
    segment (``"fast"``, ``"slow"``) of at least ``min_duration_s`` [s].

    Args:
        log: the measured run (its ``speed_mps`` is the measured signal; a log without speed
            gets NaN measured metrics).
        speed_model: simulated speed at the log's time stamps [m/s].
        segments: from :func:`segment_log` (computed with defaults when not given).
        noise_floor: band RMS [m/s] below which the measured speed is taken for noise (no
            frequency, no decay).  Default: :func:`log_speed_noise_floor`, 3× the band RMS of
            the log's white speed noise ``σ_v = sqrt(1e-7 / T_s)`` (docs/model.md).
        model_noise_floor: the same for the (noise-free) simulated speed.  Default:
            ``sqrt(noise_floor² − σ_band²)``, σ_band the band RMS of the sensor noise alone:
            the oscillation RMS that, with the sensor's noise added, would reach the measured
            floor — so a model oscillation is reported exactly when it would be seen in such a
            log, which keeps the comparison fair.
        band: frequency band [Hz].
        min_duration_s: shortest segment analysed [s].

    Returns:
        One dict per segment, in time order: ``t0``, ``t1`` [s], ``regime``, ``stage``,
        ``height_m`` (mean measured height [m]), ``pwm``, ``meas_freq_hz`` [Hz],
        ``meas_amp_mps`` [m/s], ``meas_decay_per_s`` [1/s], ``meas_rms_mps`` [m/s], the same
        with ``model_`` for the simulation, and ``noise_floor_mps`` [m/s].
    """
    vm = check_len(log, "speed_model", speed_model)
    if segments is None:
        segments = segment_log(log)
    noise_band = log_speed_noise_floor(log, band=band, factor=1.0)
    if noise_floor is None:
        noise_floor = log_speed_noise_floor(log, band=band)
    if model_noise_floor is None:
        model_noise_floor = math.sqrt(max(noise_floor**2 - noise_band**2, 0.0))
    rows = []
    for s in segments:
        if s.regime not in ("fast", "slow") or s.duration < min_duration_s - 1e-9:
            continue
        t = log.time_s[s.slice]
        if log.speed_mps is not None:
            mm = oscillation_metrics(
                t, log.speed_mps[s.slice], band=band, noise_floor_mps=noise_floor
            )
        else:
            mm = _nan_metrics()
        ms = oscillation_metrics(
            t, vm[s.slice], band=band, noise_floor_mps=model_noise_floor, subtract_noise=False
        )
        rows.append(
            {
                "t0": s.t0,
                "t1": s.t1,
                "regime": s.regime,
                "stage": s.stage,
                "height_m": s.height,
                "pwm": s.pwm,
                "meas_freq_hz": mm["freq_hz"],
                "meas_amp_mps": mm["amplitude_mps"],
                "meas_decay_per_s": mm["decay_per_s"],
                "meas_rms_mps": mm["rms_mps"],
                "model_freq_hz": ms["freq_hz"],
                "model_amp_mps": ms["amplitude_mps"],
                "model_decay_per_s": ms["decay_per_s"],
                "model_rms_mps": ms["rms_mps"],
                "noise_floor_mps": noise_floor,
            }
        )
    return rows


# ----------------------------------------------------------------------------------------------
# windows for zoomed plots


def _band_power_series(t: np.ndarray, v: np.ndarray, band: tuple[float, float]) -> np.ndarray:
    n = v.size
    if n < 4:
        return np.zeros(n)
    dt = float(np.median(np.diff(t)))
    m = next_pow2(2 * n)
    f = np.fft.rfftfreq(m, dt)
    vv = v - np.polyval(np.polyfit(t - t[0], v, 1), t - t[0])
    y = np.fft.irfft(np.fft.rfft(vv, m) * ((f >= band[0]) & (f <= band[1])), m)[:n]
    return y**2


def zoom_windows(
    log: Log,
    segments: Sequence[Segment],
    n: int = 3,
    *,
    width_s: float = 10.0,
    band: tuple[float, float] = (0.5, 10.0),
) -> list[tuple[float, float]]:
    """A few interesting time windows of about ``width_s`` [s] for zoomed overlay plots.

    Candidates, in this order of priority: the stretch of a ``"slow"`` segment with the
    largest measured oscillation (band power of the measured speed, or of the derivative of
    the height when the log has no speed); the first stage shift (starting 3 s before it);
    the longest ``"fast"`` segment; then the other stage shifts and slow segments by
    oscillation.  Windows overlapping an already chosen one by more than half are skipped.

    Returns:
        Up to ``n`` windows ``(t0, t1)`` [s] within the log, sorted by time.
    """
    t = log.time_s
    t_first, t_last = float(t[0]), float(t[-1])
    speed = measured_speed(log)
    width = min(width_s, t_last - t_first)

    def clip(a: float) -> tuple[float, float]:
        a = min(max(a, t_first), t_last - width)
        return (float(a), float(a + width))

    slow: list[tuple[float, tuple[float, float]]] = []
    for s in segments:
        if s.regime != "slow" or s.n < 4:
            continue
        ts_seg = t[s.slice]
        pw = _band_power_series(ts_seg, speed[s.slice], band)
        k = max(1, int(round(width / log.sample_period)))
        if pw.size > k:
            c = np.concatenate(([0.0], np.cumsum(pw)))
            best = int(np.argmax(c[k:] - c[:-k]))
            score = float((c[best + k] - c[best]) / k)
            start = float(ts_seg[best])
        else:
            score = float(np.mean(pw))
            start = 0.5 * (s.t0 + s.t1) - 0.5 * width
        slow.append((score, clip(start)))
    slow.sort(key=lambda x: -x[0])
    shifts = [clip(s.t0 + SHIFT_BEFORE_S - 3.0) for s in segments if s.regime == "stage_shift"]
    fast = sorted((s for s in segments if s.regime == "fast"), key=lambda s: -s.duration)
    fast_w = [clip(0.5 * (s.t0 + s.t1) - 0.5 * width) for s in fast]

    candidates: list[tuple[float, float]] = []
    candidates += [w for _, w in slow[:1]]
    candidates += shifts[:1]
    candidates += fast_w[:1]
    candidates += shifts[1:]
    candidates += [w for _, w in slow[1:]]
    candidates += fast_w[1:]

    chosen: list[tuple[float, float]] = []
    for w in candidates:
        if len(chosen) >= n:
            break
        if any(min(w[1], c[1]) - max(w[0], c[0]) > 0.5 * width for c in chosen):
            continue
        chosen.append(w)
    return sorted(chosen)
