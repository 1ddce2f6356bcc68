"""Where does the model fail? Error and oscillation analysis of a simulation against a log.

Every function takes a :class:`~jaxlift._log.Log` and simulated signals sampled at the log's
time stamps (plain numpy arrays: ``height`` [m], ``speed`` [m/s], ``pressure`` [Pa]), so it
works for any model.  Errors and residuals are always **model − measured**.

The pieces, in the order a calibration report uses them:

* :func:`segment_log` cuts a log into :class:`Segment` s by operating regime (``"hold"``,
  ``"fast"``, ``"slow"``, ``"ramp"``, ``"stage_shift"``) and stage;
* :func:`error_table` gives RMS and bias of the errors over the whole log, per regime and per
  stage;
* :func:`oscillation_metrics` measures the oscillation of one signal (frequency, amplitude,
  decay rate); :func:`oscillation_table` applies it to every steady moving segment, for the
  measured and the simulated speed;
* :func:`residual_diagnostics` describes the scaled residuals (spectrum, autocorrelation,
  effective sample size);
* :func:`plot_oscillations_vs_height`, :func:`plot_residuals`, :func:`plot_error_bars` draw
  them (PNG, Agg backend) and :func:`zoom_windows` picks a few time windows worth a zoomed
  overlay plot (:func:`jaxlift._plots.plot_overlay`).

Only numpy and matplotlib are used; nothing here prints.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from jaxtyping import Float  # noqa: E402

from ._log import Log  # noqa: E402

__all__ = [
    "REGIMES",
    "Segment",
    "error_table",
    "log_speed_noise_floor",
    "oscillation_metrics",
    "oscillation_table",
    "plot_error_bars",
    "plot_oscillations_vs_height",
    "plot_residuals",
    "residual_diagnostics",
    "segment_log",
    "stage_of",
    "zoom_windows",
]

#: The regimes of :class:`Segment`, in the order tables list them.
REGIMES: tuple[str, ...] = ("hold", "fast", "slow", "ramp", "stage_shift")

X_S_DEFAULT: tuple[float, float] = (1.5, 3.0)  # stage boundaries [m] (MODEL.md)
SIGMA_HEIGHT_M = 0.5e-3  # height sensor noise [m] (MODEL.md)
SPEED_NOISE_POWER = 1e-7  # speed sensor noise power [(m/s)^2 s] (MODEL.md)
SIGMA_PRESSURE_PA = 5e4  # pressure sensor noise [Pa] (jaxlift._measurement default)

_PWM_TOL = 1e-6  # pwm values closer than this are "the same level" [-]
_SMOOTH_S = 0.2  # moving-average window for the height before differentiating / crossing [s]
_CROSS_HYST_M = 5e-3  # hysteresis of the stage-crossing detector [m]
_SHIFT_BEFORE_S = 1.0  # a stage shift starts this long before the crossing [s]
_SHIFT_AFTER_S = 4.0  # ... and ends this long after it [s]
_NARROW_SIGMA_HZ = 0.4  # std of the Gaussian band around the oscillation peak [Hz]
_ENV_WINDOW_S = 1.0  # window for the envelope RMS in the decay fit [s]
_REL_VAR = 0.01  # relative variance of a window power beyond noise, in the decay fit [-]

Array1 = Float[np.ndarray, " N"]


# ----------------------------------------------------------------------------------------------
# small numerical helpers


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over ``n`` samples, edges padded with the edge values."""
    if n <= 1 or x.size < 2:
        return x.astype(np.float64, copy=True)
    n = min(n, x.size)
    left = n // 2
    right = n - 1 - left
    xp = np.pad(np.asarray(x, dtype=np.float64), (left, right), mode="edge")
    c = np.concatenate(([0.0], np.cumsum(xp)))
    return (c[n:] - c[:-n]) / n


def _measured_speed(log: Log) -> np.ndarray:
    """Logged speed [m/s] if present, else the derivative of the smoothed height [m/s]."""
    if log.speed_mps is not None:
        return np.asarray(log.speed_mps, dtype=np.float64)
    return _height_derivative(log)


def _height_derivative(log: Log) -> np.ndarray:
    n_smooth = max(1, int(round(_SMOOTH_S / log.sample_period)))
    hs = _moving_average(log.height_m, n_smooth)
    return np.gradient(hs, log.time_s)


def stage_of(
    height_m: float | np.ndarray, x_s: tuple[float, float] = X_S_DEFAULT
) -> int | np.ndarray:
    """Stage (1, 2, 3) of a height [m]: 1 below ``x_s[0]``, 2 below ``x_s[1]``, else 3."""
    h = np.asarray(height_m, dtype=np.float64)
    s = 1 + (h >= x_s[0]).astype(int) + (h >= x_s[1]).astype(int)
    return int(s) if s.ndim == 0 else s


def _runs(x: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs ``[start, stop)`` of equal consecutive values of ``x``."""
    if x.size == 0:
        return []
    brk = np.flatnonzero(x[1:] != x[:-1]) + 1
    starts = np.concatenate(([0], brk))
    stops = np.concatenate((brk, [x.size]))
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def _next_pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


# ----------------------------------------------------------------------------------------------
# segmentation


@dataclasses.dataclass(frozen=True)
class Segment:
    """A stretch of a log in one operating regime.

    Attributes:
        start: index of the first sample.
        stop: index one past the last sample (``log.time_s[start:stop]`` is the segment).
        t0: time of the first sample [s].
        t1: end time [s]: the time of sample ``stop`` (the next segment's ``t0``), or the last
            time stamp plus one sample period for the last segment; segments tile
            ``[t_first, t_last + T_s)`` without gaps.
        regime: one of :data:`REGIMES`.
        stage: 1, 2 or 3, the stage of the mean measured height (boundaries ``x_s``).
        pwm: mean commanded duty cycle over the segment [-].
        height: mean measured height over the segment [m].
    """

    start: int
    stop: int
    t0: float
    t1: float
    regime: str
    stage: int
    pwm: float
    height: float

    @property
    def n(self) -> int:
        """Number of samples."""
        return self.stop - self.start

    @property
    def duration(self) -> float:
        """``t1 - t0`` [s]."""
        return self.t1 - self.t0

    @property
    def slice(self) -> slice:
        """``slice(start, stop)``, to index the log's arrays."""
        return slice(self.start, self.stop)


def _stage_shift_mask(
    t: np.ndarray, h_smooth: np.ndarray, x_s: Sequence[float], before_s: float, after_s: float
) -> tuple[np.ndarray, list[float]]:
    """Samples within ``[t_c - before_s, t_c + after_s)`` of an upward crossing ``t_c`` of a
    stage boundary by the smoothed height (with hysteresis, so that noise on a fork parked at
    the boundary does not count as many crossings). Returns the mask and the crossing times."""
    mask = np.zeros(t.shape, dtype=bool)
    crossings: list[float] = []
    for xb in x_s:
        below = h_smooth < xb
        cand = np.flatnonzero(below[:-1] & ~below[1:]) + 1
        low = np.flatnonzero(h_smooth < xb - _CROSS_HYST_M)
        high = np.flatnonzero(h_smooth >= xb + _CROSS_HYST_M)
        last = -1  # index of the last accepted crossing
        for i in cand:
            # armed: below the boundary at the start (first crossing), or back below
            # xb - hysteresis since the last accepted crossing
            if last < 0:
                armed = bool(below[0]) or bool(np.any(low < i))
            else:
                armed = bool(np.any((low > last) & (low < i)))
            # a real passage: the height then gets above xb + hysteresis before it falls back
            # below xb - hysteresis
            j = high[high > i]
            k = low[low > i]
            genuine = j.size > 0 and (k.size == 0 or j[0] < k[0])
            if not (armed and genuine):
                continue
            last = int(i)
            tc = float(t[i])
            crossings.append(tc)
            mask |= (t >= tc - before_s) & (t < tc + after_s)
    return mask, sorted(crossings)


def segment_log(
    log: Log,
    *,
    x_s: tuple[float, float] = X_S_DEFAULT,
    fast_speed: float = 0.05,
    min_steady_s: float = 2.0,
) -> list[Segment]:
    """Cut a log into segments by operating regime; every sample lies in exactly one segment,
    and the segments come in time order.

    Rules:

    * **steady** sections: the commanded ``pwm`` stays at one level (within 1e-6) for at least
      ``min_steady_s`` [s].  A steady section at ``pwm == 0`` is ``"hold"``; a moving one is
      ``"fast"`` when its mean measured speed is at least ``fast_speed`` [m/s], else
      ``"slow"``.  The mean speed is taken over the section outside stage shifts, from the
      logged speed or, when the log has none, from the derivative of the height smoothed over
      0.2 s.  (Classing by measured speed rather than by ``pwm`` keeps the labels right when
      the load, and with it the speed at a given ``pwm``, changes.)
    * ``"ramp"``: where ``pwm`` changes, and steady bits shorter than ``min_steady_s``;
      adjacent ramp samples form one segment.
    * ``"stage_shift"``: from 1 s before to 4 s after the measured height (smoothed over
      0.2 s, with 5 mm hysteresis against noise) crosses ``x_s[0]`` or ``x_s[1]`` upwards.
      This label overrides the others: a steady section cut by a stage shift gives a segment
      before and one after it, with the section's regime.

    Args:
        log: the measured run.
        x_s: stage boundaries [m].
        fast_speed: mean speed from which a moving steady section counts as fast [m/s].
        min_steady_s: shortest steady section [s].

    Returns:
        The segments, in time order, tiling the log.
    """
    t = np.asarray(log.time_s, dtype=np.float64)
    n = t.size
    ts = log.sample_period
    pwm = np.asarray(log.pwm, dtype=np.float64)
    h = np.asarray(log.height_m, dtype=np.float64)
    n_smooth = max(1, int(round(_SMOOTH_S / ts)))
    h_smooth = _moving_average(h, n_smooth)
    speed = _measured_speed(log)

    shift, _ = _stage_shift_mask(t, h_smooth, x_s, _SHIFT_BEFORE_S, _SHIFT_AFTER_S)

    # runs of constant pwm: a new run starts where pwm moves by more than the tolerance
    level_id = np.concatenate(([0], np.cumsum(np.abs(np.diff(pwm)) > _PWM_TOL)))
    # group id per sample: steady runs keep their own id, all ramp samples share -1 (so that
    # adjacent ramp pieces merge)
    group = np.full(n, -1, dtype=np.int64)
    label = np.full(n, REGIMES.index("ramp"), dtype=np.int64)
    for a, b in _runs(level_id):
        if (b - a) * ts < min_steady_s - 0.5 * ts:
            continue
        group[a:b] = a
        if np.all(pwm[a:b] <= _PWM_TOL):
            label[a:b] = REGIMES.index("hold")
            continue
        free = ~shift[a:b]
        v = speed[a:b][free] if free.sum() * ts >= 0.5 else speed[a:b]
        fast = float(np.mean(v)) >= fast_speed
        label[a:b] = REGIMES.index("fast" if fast else "slow")
    label[shift] = REGIMES.index("stage_shift")
    group[shift] = -2

    key = label * (n + 3) + (group + 2)
    segments = []
    for a, b in _runs(key):
        t1 = float(t[b]) if b < n else float(t[-1] + ts)
        hm = float(np.mean(h[a:b]))
        segments.append(
            Segment(
                start=a,
                stop=b,
                t0=float(t[a]),
                t1=t1,
                regime=REGIMES[int(label[a])],
                stage=stage_of(hm, x_s),
                pwm=float(np.mean(pwm[a:b])),
                height=hm,
            )
        )
    return segments


# ----------------------------------------------------------------------------------------------
# error table


def _check_len(log: Log, name: str, x) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (log.n,):
        raise ValueError(
            f"{name}: expected an array of shape ({log.n},) at the log's time stamps, "
            f"got shape {a.shape}"
        )
    return a


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2))) if x.size else math.nan


def _mean(x: np.ndarray) -> float:
    return float(np.mean(x)) if x.size else math.nan


def error_table(
    log: Log,
    height: Array1,
    speed: Array1,
    pressure: Array1 | None = None,
    segments: Sequence[Segment] | None = None,
    *,
    x_s: tuple[float, float] = X_S_DEFAULT,
) -> list[dict]:
    """RMS and bias of the errors (model − measured), overall, per regime and per stage.

    Args:
        log: the measured run.
        height: simulated height at the log's time stamps [m].
        speed: simulated speed [m/s].
        pressure: simulated pressure [Pa], optional.
        segments: from :func:`segment_log` (computed with defaults when not given).
        x_s: stage boundaries [m] for the per-stage rows.

    Returns:
        One dict per group, in the order ``"all"``, the regimes present (order of
        :data:`REGIMES`), then ``"stage 1"``, ``"stage 2"``, ``"stage 3"`` where present.
        Keys: ``group``, ``n`` (samples), ``rms_height_mm``, ``bias_height_mm`` [mm],
        ``rms_speed_mmps``, ``bias_speed_mmps`` [mm/s] (NaN when the log has no speed), and,
        when both the log and the simulation have a pressure, ``rms_pressure_MPa``,
        ``bias_pressure_MPa`` [MPa].  Regime rows group the samples by segment; stage rows by
        the measured height of each sample.
    """
    h = _check_len(log, "height", height)
    v = _check_len(log, "speed", speed)
    e_h = (h - log.height_m) * 1e3
    e_v = (v - log.speed_mps) * 1e3 if log.speed_mps is not None else np.full(log.n, np.nan)
    e_p = None
    if pressure is not None and log.pressure_pa is not None:
        e_p = (_check_len(log, "pressure", pressure) - log.pressure_pa) * 1e-6
    if segments is None:
        segments = segment_log(log, x_s=x_s)
    regime = np.empty(log.n, dtype=object)
    for s in segments:
        regime[s.start : s.stop] = s.regime
    stage = stage_of(log.height_m, x_s)

    groups: list[tuple[str, np.ndarray]] = [("all", np.ones(log.n, dtype=bool))]
    groups += [(r, regime == r) for r in REGIMES]
    groups += [(f"stage {k}", stage == k) for k in (1, 2, 3)]
    rows = []
    for name, m in groups:
        if not m.any():
            continue
        row = {
            "group": name,
            "n": int(m.sum()),
            "rms_height_mm": _rms(e_h[m]),
            "bias_height_mm": _mean(e_h[m]),
            "rms_speed_mmps": _rms(e_v[m]),
            "bias_speed_mmps": _mean(e_v[m]),
        }
        if e_p is not None:
            row["rms_pressure_MPa"] = _rms(e_p[m])
            row["bias_pressure_MPa"] = _mean(e_p[m])
        rows.append(row)
    return rows


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

    m = _next_pow2(2 * n)
    f = np.fft.rfftfreq(m, dt)
    x = np.fft.rfft(r, m)
    inband = (f >= band[0]) & (f <= band[1])
    y = np.fft.irfft(x * inband, m)[:n]
    rms = float(np.sqrt(np.mean(y**2)))
    out["rms_mps"] = rms

    # spectral peak: coarse on the power spectrum smoothed over ~0.1 Hz (robust to single noise
    # bins), refined on the 16x zero-padded spectrum (no taper, so that a decaying oscillation
    # at the start of the stretch keeps its weight) by parabolic interpolation of log |X|
    mz = _next_pow2(16 * n)
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
    ``σ_v = sqrt(speed_noise_power / T_s)`` (MODEL.md; ≈ 3.2 mm/s at 100 Hz) has after
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
            the log's white speed noise ``σ_v = sqrt(1e-7 / T_s)`` (MODEL.md).
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
    vm = _check_len(log, "speed_model", speed_model)
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
# residuals


def _acf(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Biased sample autocorrelation of ``x`` (mean removed) at lags 0..max_lag."""
    x = x - x.mean()
    n = x.size
    max_lag = min(max_lag, n - 1)
    m = _next_pow2(2 * n)
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
        sigma_height_m: height noise σ [m] (MODEL.md: 0.5 mm).
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
    h = _check_len(log, "height", height)
    v = _check_len(log, "speed", speed)
    dt = log.sample_period
    out = {"height": _diagnose(h - log.height_m, sigma_height_m, dt, max_lag_s, ljung_box_lags)}
    if log.speed_mps is not None:
        sv = math.sqrt(speed_noise_power / dt)
        out["speed"] = _diagnose(v - log.speed_mps, sv, dt, max_lag_s, ljung_box_lags)
    if pressure is not None and log.pressure_pa is not None:
        p = _check_len(log, "pressure", pressure)
        out["pressure"] = _diagnose(
            p - log.pressure_pa, sigma_pressure_pa, dt, max_lag_s, ljung_box_lags
        )
    return out


# ----------------------------------------------------------------------------------------------
# windows for zoomed plots


def _band_power_series(t: np.ndarray, v: np.ndarray, band: tuple[float, float]) -> np.ndarray:
    n = v.size
    if n < 4:
        return np.zeros(n)
    dt = float(np.median(np.diff(t)))
    m = _next_pow2(2 * n)
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
    speed = _measured_speed(log)
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
    shifts = [clip(s.t0 + _SHIFT_BEFORE_S - 3.0) for s in segments if s.regime == "stage_shift"]
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


# ----------------------------------------------------------------------------------------------
# plots


def _save(fig, path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.fspath(path)


_REGIME_MARKER = {"slow": "o", "fast": "s"}


def plot_oscillations_vs_height(
    rows_by_label: Mapping[str, Sequence[dict]], path: str | os.PathLike
) -> str:
    """Oscillation frequency (top) and amplitude (bottom) against mean height [m].

    ``rows_by_label`` maps a model label (e.g. ``"before"``, ``"after"``) to rows of
    :func:`oscillation_table`.  Measured values are black (taken once, from the rows of all
    labels, duplicates removed), each model in its own colour; circles are slow segments,
    squares fast ones; hollow markers are amplitudes of segments below the noise floor (no
    frequency).  Frequency in Hz, amplitude in mm/s; the dashed line is the measured noise
    floor as an amplitude.  Returns the PNG path.
    """
    fig, (ax_f, ax_a) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)

    def draw(rows, prefix, color, label):
        for regime, marker in _REGIME_MARKER.items():
            rr = [r for r in rows if r["regime"] == regime]
            if not rr:
                continue
            hgt = np.array([r["height_m"] for r in rr])
            fr = np.array([r[f"{prefix}_freq_hz"] for r in rr], dtype=float)
            am = np.array([r[f"{prefix}_amp_mps"] for r in rr], dtype=float) * 1e3
            det = np.isfinite(fr)
            lab = f"{label} ({regime})"
            ax_f.plot(hgt[det], fr[det], marker, color=color, ls="none", ms=6, label=lab)
            ax_a.plot(hgt[det], am[det], marker, color=color, ls="none", ms=6, label=lab)
            ax_a.plot(hgt[~det], am[~det], marker, mfc="none", mec=color, ls="none", ms=6)

    seen = set()
    meas = []
    for rows in rows_by_label.values():
        for r in rows:
            key = (round(r["t0"], 6), round(r["t1"], 6), round(r["height_m"], 6))
            if key not in seen:
                seen.add(key)
                meas.append(r)
    draw(meas, "meas", "k", "measured")
    for i, (label, rows) in enumerate(rows_by_label.items()):
        draw(rows, "model", f"C{i}", label)
    floors = [r["noise_floor_mps"] for r in meas if "noise_floor_mps" in r]
    if floors:
        # amplitude of a sinusoid that just reaches the floor is about sqrt(2) x floor
        ax_a.axhline(math.sqrt(2) * max(floors) * 1e3, color="0.5", ls="--", lw=0.8)
    for x in X_S_DEFAULT:
        ax_f.axvline(x, color="0.7", lw=0.8)
        ax_a.axvline(x, color="0.7", lw=0.8)
    ax_f.set_ylabel("frequency [Hz]")
    ax_a.set_ylabel("amplitude [mm/s]")
    ax_a.set_xlabel("mean height [m]")
    for ax in (ax_f, ax_a):
        ax.grid(alpha=0.3)
    handles, labels = ax_f.get_legend_handles_labels()
    if handles:
        ax_f.legend(fontsize=8, ncol=2)
    ax_f.set_title("oscillations of the speed in steady moving segments")
    return _save(fig, path)


def _binned_mean(x: np.ndarray, y: np.ndarray, nbins: int = 30) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0 or np.ptp(x) == 0:
        return np.array([]), np.array([])
    edges = np.linspace(x.min(), x.max(), nbins + 1)
    k = np.clip(np.digitize(x, edges) - 1, 0, nbins - 1)
    cnt = np.bincount(k, minlength=nbins)
    s = np.bincount(k, weights=y, minlength=nbins)
    keep = cnt >= 5
    centers = 0.5 * (edges[1:] + edges[:-1])
    return centers[keep], s[keep] / cnt[keep]


def plot_residuals(
    log: Log,
    height: Array1,
    speed: Array1,
    path: str | os.PathLike,
    pressure: Array1 | None = None,
) -> str:
    """Residual diagnostics on a 2×3 grid, residual = model − measured speed [mm/s] (the
    height residual [mm] when the log has no speed): against time; its spectrum (Welch,
    log scale); the autocorrelation of the scaled speed and height residuals; against the
    simulated speed [m/s] (not the measured one: its noise is in the residual too, which
    would draw a spurious slope of -1), the measured height [m], and the pressure [MPa]
    (simulated when given, else logged).  Scatter plots carry binned means (red).  Returns
    the PNG path."""
    h = _check_len(log, "height", height)
    v = _check_len(log, "speed", speed)
    diag = residual_diagnostics(log, h, v)
    t = log.time_s
    if log.speed_mps is not None:
        res = (v - log.speed_mps) * 1e3
        rname, runit, key = "speed residual", "mm/s", "speed"
    else:
        res = (h - log.height_m) * 1e3
        rname, runit, key = "height residual", "mm", "height"
    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5))

    ax = axes[0, 0]
    ax.plot(t, res, lw=0.4, color="C0")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"{rname} [{runit}]")

    ax = axes[0, 1]
    f, p = diag[key]["freqs_hz"], diag[key]["power"]
    sig = diag[key]["sigma"] * 1e3
    ax.semilogy(f[1:], p[1:] * sig**2, lw=0.8, color="C0", label="residual")
    ax.axhline(2 * log.sample_period * sig**2, color="0.5", ls="--", lw=0.8, label="sensor noise")
    ax.set_xlim(0.0, min(f[-1], 20.0))
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"PSD [({runit})²/Hz]")
    ax.legend(fontsize=8)

    ax = axes[0, 2]
    for name, d in diag.items():
        if name == "pressure":
            continue
        ax.plot(d["lags_s"], d["acf"], lw=0.9, label=f"{name} (ρ1 = {d['rho1']:.2f})")
    bound = 2.0 / math.sqrt(log.n)
    ax.axhspan(-bound, bound, color="0.85")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("lag [s]")
    ax.set_ylabel("autocorrelation [-]")
    ax.legend(fontsize=8)

    xs = [
        (v, "simulated speed [m/s]"),
        (np.asarray(log.height_m), "measured height [m]"),
    ]
    if pressure is not None:
        xs.append((_check_len(log, "pressure", pressure) * 1e-6, "simulated pressure [MPa]"))
    elif log.pressure_pa is not None:
        xs.append((np.asarray(log.pressure_pa) * 1e-6, "measured pressure [MPa]"))
    else:
        xs.append((None, "pressure"))
    for ax, (x, xl) in zip(axes[1], xs, strict=True):
        if x is None:
            ax.text(0.5, 0.5, "no pressure", ha="center", va="center", transform=ax.transAxes)
            ax.set_xticks([])
            ax.set_yticks([])
            continue
        ax.plot(x, res, ",", color="C0", alpha=0.4)
        bx, by = _binned_mean(x, res)
        ax.plot(bx, by, "-", color="C3", lw=1.2)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(xl)
        ax.set_ylabel(f"{rname} [{runit}]")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    fig.suptitle(f"{log.name}: residuals (model − measured)")
    return _save(fig, path)


def plot_error_bars(
    table_by_label: Mapping[str, Sequence[dict]],
    path: str | os.PathLike,
    *,
    noise_speed_mmps: float | None = None,
    noise_height_mm: float | None = None,
) -> str:
    """Grouped bars of the RMS speed error [mm/s] (top) and RMS height error [mm] (bottom) per
    group of :func:`error_table`, one bar colour per label (e.g. ``"before"``, ``"after"``).
    Groups are listed in the order they first appear.  ``noise_speed_mmps`` /
    ``noise_height_mm``: sensor noise σ, drawn as a dashed line (the RMS error of a perfect
    model).  Returns the PNG path."""
    groups: list[str] = []
    for rows in table_by_label.values():
        for r in rows:
            if r["group"] not in groups:
                groups.append(r["group"])
    labels = list(table_by_label)
    nl = max(1, len(labels))
    x = np.arange(len(groups))
    width = 0.8 / nl
    fig, axes = plt.subplots(2, 1, figsize=(max(7, 0.9 * len(groups) + 2), 6.5), sharex=True)
    for ax, key, unit, noise in (
        (axes[0], "rms_speed_mmps", "RMS speed error [mm/s]", noise_speed_mmps),
        (axes[1], "rms_height_mm", "RMS height error [mm]", noise_height_mm),
    ):
        if noise is not None:
            ax.axhline(noise, color="0.3", ls="--", lw=0.9, label="sensor noise")
        for i, label in enumerate(labels):
            by_group = {r["group"]: r.get(key, math.nan) for r in table_by_label[label]}
            vals = np.array([by_group.get(g, math.nan) for g in groups], dtype=float)
            ax.bar(x + (i - (nl - 1) / 2) * width, np.nan_to_num(vals), width, label=label)
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    axes[1].set_xticks(x, groups, rotation=30, ha="right")
    return _save(fig, path)
