"""Where does the model fail? Regimes of a log, and the error per regime and stage.

Every function takes a :class:`~jaxlift.model.log.Log` and simulated signals sampled at the
log's time stamps (plain numpy arrays: ``height`` [m], ``speed`` [m/s], ``pressure`` [Pa]),
so it works for any model. Errors and residuals are always **model − measured**.

The pieces, in the order a calibration report uses them:

* :func:`segment_log` cuts a log into :class:`Segment` s by operating regime (``"hold"``,
  ``"fast"``, ``"slow"``, ``"ramp"``, ``"stage_shift"``) and stage;
* :func:`error_table` gives RMS and bias of the errors over the whole log, per regime and per
  stage;
* :mod:`jaxlift.analysis.oscillation` measures oscillations (frequency, amplitude, decay)
  per steady segment, and :mod:`jaxlift.analysis.residuals` describes the scaled residuals
  (spectrum, autocorrelation, effective sample size);
* :mod:`jaxlift.report.analysis_plots` draws them.

Only numpy is used; nothing here plots or prints."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from jaxtyping import Float

from ..model.constants import STAGE_BOUNDARIES_M
from ..model.log import Log

#: The regimes of :class:`Segment`, in the order tables list them.
REGIMES: tuple[str, ...] = ("hold", "fast", "slow", "ramp", "stage_shift")

X_S_DEFAULT = STAGE_BOUNDARIES_M

_PWM_TOL = 1e-6  # pwm values closer than this are "the same level" [-]
_SMOOTH_S = 0.2  # moving-average window for the height before differentiating / crossing [s]
_CROSS_HYST_M = 5e-3  # hysteresis of the stage-crossing detector [m]
SHIFT_BEFORE_S = 1.0  # a stage shift starts this long before the crossing [s]
_SHIFT_AFTER_S = 4.0  # ... and ends this long after it [s]

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


def measured_speed(log: Log) -> np.ndarray:
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
    speed = measured_speed(log)

    shift, _ = _stage_shift_mask(t, h_smooth, x_s, SHIFT_BEFORE_S, _SHIFT_AFTER_S)

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


def check_len(log: Log, name: str, x) -> np.ndarray:
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
    h = check_len(log, "height", height)
    v = check_len(log, "speed", speed)
    e_h = (h - log.height_m) * 1e3
    e_v = (v - log.speed_mps) * 1e3 if log.speed_mps is not None else np.full(log.n, np.nan)
    e_p = None
    if pressure is not None and log.pressure_pa is not None:
        e_p = (check_len(log, "pressure", pressure) - log.pressure_pa) * 1e-6
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
