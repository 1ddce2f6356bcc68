"""What "good" means (docs/control.md): the figures of a closed-loop run, as pure JAX
functions of a :class:`~jaxlift.control.closed_loop.ClosedLoopSolution`.

The same functions serve the tuning cost (:mod:`jaxlift.control.tune`) and the reports.
All figures are differentiable w.r.t. the gains where they enter the cost (tracking,
oscillation, offset after a shift, effort); masks come from the reference (static)
or, for the stage shifts, from the crossing time interpolated linearly between
samples (continuous in the gains) with trapezoidal window edges.

Definitions (SI units; ``err = v_ref - v`` with the *true* speed ``v``):

- ``tracking_rms``: RMS of ``err`` over the whole run [m/s].
- ``osc_rms``: RMS of ``err`` band-passed to 0.5--10 Hz over the whole run [m/s];
  ``osc_stage``: the same over the samples whose *reference* height is in stage 1, 2,
  3 (NaN for a stage the reference does not reach); ``osc_sustained``: over the
  steady samples. The band-pass is zero-phase: the
  FFT of the zero-padded error times the squared magnitude of 2nd-order Butterworth
  high-pass (0.5 Hz) and low-pass (10 Hz) responses (a forward-backward filter).
- steady samples: ``v_ref`` constant and non-zero for at least ``SETTLE_S`` = 2 s.
- ``bias``: mean of ``err`` over the steady samples [m/s]; ``height_error``: final
  height minus the reference's final height [m].
- ``shift_offset``: per stage shift, the mean of ``err`` 1.5--4.5 s after the fork
  crosses ``x_s1`` resp. ``x_s2`` [m/s] (NaN where the shift is not crossed).
- ``effort``: RMS over the moving time (``v_ref != 0``) of the rate of change of
  ``u`` [1/s], with ``u`` averaged over 10 ms windows (from ``∫u dt``: exact);
  ``shut_share``: the share of moving time with the valve shut (``u_raw <= 0``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..model.constants import OUTPUT_DT
from .closed_loop import NOISE_POWER, NOISE_TS, ClosedLoopSolution
from .reference import is_moving

BAND_HZ = (0.5, 10.0)
SETTLE_S = 2.0
SHIFT_WINDOW_S = (1.5, 4.5)

Scalar = Float[Array, ""]


class Figures(eqx.Module):
    """The figures of "good" of one run (see the module docstring for definitions)."""

    tracking_rms: Scalar  # m/s
    osc_rms: Scalar  # m/s
    osc_stage: Float[Array, " 3"]  # m/s
    osc_sustained: Scalar  # m/s
    bias: Scalar  # m/s
    height_error: Scalar  # m
    shift_offset: Float[Array, " 2"]  # m/s, NaN where not crossed
    effort: Scalar  # 1/s
    shut_share: Scalar  # -

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        """Flat ``{name: value}`` in report units (mm/s, mm, 1/s, %)."""
        a = lambda x: float(np.asarray(x))
        d = {
            "tracking_rms_mmps": 1e3 * a(self.tracking_rms),
            "osc_rms_mmps": 1e3 * a(self.osc_rms),
            "osc_stage1_mmps": 1e3 * a(self.osc_stage[0]),
            "osc_stage2_mmps": 1e3 * a(self.osc_stage[1]),
            "osc_stage3_mmps": 1e3 * a(self.osc_stage[2]),
            "osc_sustained_mmps": 1e3 * a(self.osc_sustained),
            "bias_mmps": 1e3 * a(self.bias),
            "height_error_mm": 1e3 * a(self.height_error),
            "shift1_offset_mmps": 1e3 * a(self.shift_offset[0]),
            "shift2_offset_mmps": 1e3 * a(self.shift_offset[1]),
            "effort_per_s": a(self.effort),
            "shut_share_pct": 100 * a(self.shut_share),
        }
        return {prefix + k: v for k, v in d.items()}


def _butter2_sq(f, fc, highpass: bool):
    r = (f / fc) ** 4
    return r / (1.0 + r) if highpass else 1.0 / (1.0 + r)


def bandpass(
    signal: Float[Array, " n"], dt: float = OUTPUT_DT, band: tuple[float, float] = BAND_HZ
) -> Float[Array, " n"]:
    """Zero-phase band-pass of a uniformly sampled signal (period ``dt`` [s]) to
    ``band`` [Hz]: squared 2nd-order Butterworth magnitudes applied in the frequency
    domain, zero-padded to twice the length (no wrap-around). Differentiable."""
    n = signal.shape[-1]
    n_fft = int(2 ** np.ceil(np.log2(2 * n)))
    f = np.fft.rfftfreq(n_fft, dt)
    mask = _butter2_sq(f, band[0], True) * _butter2_sq(f, band[1], False)
    spec = jnp.fft.rfft(signal, n=n_fft)
    return jnp.fft.irfft(spec * jnp.asarray(mask), n=n_fft)[..., :n]


def _wmean(x, w):
    return jnp.sum(w * x) / jnp.maximum(jnp.sum(w), 1e-12)


def _wrms(x, w):
    return jnp.sqrt(_wmean(x**2, w) + 1e-30)


def ref_masks(sol: ClosedLoopSolution):
    ref = sol.reference
    ts = sol.ts
    kt, kv = ref.knots_t, ref.knots_v
    i = jnp.clip(jnp.searchsorted(kt, ts, side="right") - 1, 0, kt.shape[0] - 2)
    flat = kv[i] == kv[i + 1]
    # time since the reference last changed slope (the start of its flat piece)
    t_flat = kt[i]
    steady = flat & is_moving(sol.v_ref) & (ts - t_flat >= SETTLE_S)
    x_ref = ref.x0 + jnp.concatenate(
        [jnp.zeros(1), jnp.cumsum(0.5 * (sol.v_ref[1:] + sol.v_ref[:-1])) * OUTPUT_DT]
    )
    return steady, x_ref


def _shift_offset(sol: ClosedLoopSolution, err, x_s):
    h = sol.height
    ts = sol.ts
    above = h >= x_s
    crossed = jnp.any(above)
    k = jnp.clip(jnp.argmax(above), 1, h.shape[0] - 1)
    h0, h1 = h[k - 1], h[k]
    frac = jnp.clip((x_s - h0) / jnp.where(h1 > h0, h1 - h0, 1.0), 0.0, 1.0)
    t_s = ts[k - 1] + frac * OUTPUT_DT
    a, b = t_s + SHIFT_WINDOW_S[0], t_s + SHIFT_WINDOW_S[1]
    # trapezoidal window: continuous in (a, b), hence in the gains
    w = jnp.clip((ts - a) / OUTPUT_DT + 0.5, 0.0, 1.0) * jnp.clip((b - ts) / OUTPUT_DT + 0.5, 0, 1)
    return crossed, _wmean(err, w)


def figures(sol: ClosedLoopSolution) -> Figures:
    """The figures of "good" of a closed-loop run (jit/vmap/grad-safe)."""
    err = sol.v_ref - sol.speed
    steady, x_ref = ref_masks(sol)
    moving = is_moving(sol.v_ref).astype(err.dtype)
    steady = steady.astype(err.dtype)
    osc = bandpass(err)
    x1, x2 = sol.x_s
    stage_w = [
        (x_ref < x1).astype(err.dtype),
        ((x_ref >= x1) & (x_ref < x2)).astype(err.dtype),
        (x_ref >= x2).astype(err.dtype),
    ]
    offsets = []
    for x_s in sol.x_s:
        crossed, off = _shift_offset(sol, err, x_s)
        offsets.append(jnp.where(crossed, off, jnp.nan))
    u_avg = jnp.diff(sol.u_int) / OUTPUT_DT  # 10 ms averages
    rate = jnp.diff(u_avg) / OUTPUT_DT
    mov_mid = moving[1:-1]
    t_moving = jnp.sum(moving) * OUTPUT_DT
    return Figures(
        tracking_rms=jnp.sqrt(jnp.mean(err**2)),
        osc_rms=jnp.sqrt(jnp.mean(osc**2)),
        osc_stage=jnp.stack([jnp.where(jnp.sum(w) > 0, _wrms(osc, w), jnp.nan) for w in stage_w]),
        osc_sustained=_wrms(osc, steady),
        bias=_wmean(err, steady),
        height_error=sol.height[-1] - x_ref[-1],
        shift_offset=jnp.stack(offsets),
        effort=_wrms(rate, mov_mid),
        shut_share=sol.shut_int[-1] / jnp.maximum(t_moving, 1e-9),
    )


def noise_amplification(controller, plant, x, m_load, sampled_T_c: float | None = None):
    """RMS [-] of the part of ``u_raw`` driven by the speed-sensor noise (docs/control.md:
    held for ``T_s`` = 10 ms, sigma = sqrt(1e-7 / T_s)), averaged over each 10 ms hold
    as the effort figure is, for the linear law (no saturation), at height ``x`` [m] and
    load ``m_load`` [kg]. With ``a = N T_s`` and ``g = (1 - exp(-a)) / a`` (the hold
    average of the filter's decay) the continuous law gives
    ``sigma^2 [P^2 + 2 P D N g + 2 (D N g)^2 / (1 + exp(-a))]``; the sampled law (clock
    ``T_c = T_s``, ``alpha = 1 - exp(-N T_c)``) ``sigma^2 [P^2 + 2 P D N + 2 (D N)^2 /
    (2 - alpha)]``. Differentiable in the gains."""

    P, _, D = controller.gains(plant, jnp.asarray(x), jnp.asarray(m_load))
    N = controller.N
    sigma2 = NOISE_POWER / NOISE_TS
    if sampled_T_c is None:
        a = N * NOISE_TS
        g = -jnp.expm1(-a) / a
        ms = P**2 + 2 * P * D * N * g + 2 * (D * N * g) ** 2 / (1 + jnp.exp(-a))
    else:
        alpha = -jnp.expm1(-N * sampled_T_c)
        ms = P**2 + 2 * P * D * N + 2 * (D * N) ** 2 / (2 - alpha)
    return jnp.sqrt(sigma2 * ms)


class CostWeights(eqx.Module):
    """Scales of the tuning cost ``J = sum((figure / scale)^2)`` (a figure at its
    scale costs 1). Defaults: tracking 2 mm/s, oscillation 1 mm/s, sustained
    oscillation 0.3 mm/s, offset after each shift 2 mm/s, effort 20 1/s, noise
    amplification (:func:`noise_amplification`, RMS duty) 0.5 -- the last keeps a
    noise-free tuning from running to gains that only a noise-free sensor allows."""

    tracking: float = eqx.field(static=True, default=2e-3)
    oscillation: float = eqx.field(static=True, default=1e-3)
    sustained: float = eqx.field(static=True, default=0.3e-3)
    offset: float = eqx.field(static=True, default=2e-3)
    effort: float = eqx.field(static=True, default=20.0)
    noise: float = eqx.field(static=True, default=0.5)


def cost_from_figures(
    fig: Figures, weights: CostWeights | None = None, noise_amp: Scalar | None = None
) -> Scalar:
    """The differentiable tuning cost of one run (dimensionless, see
    :class:`CostWeights`); a shift that is not crossed contributes 0; ``noise_amp``:
    the controller's :func:`noise_amplification` (left out if None)."""
    w = CostWeights() if weights is None else weights
    extra = 0.0 if noise_amp is None else (noise_amp / w.noise) ** 2
    off = jnp.where(jnp.isnan(fig.shift_offset), 0.0, fig.shift_offset)
    return (
        (fig.tracking_rms / w.tracking) ** 2
        + (fig.osc_rms / w.oscillation) ** 2
        + (fig.osc_sustained / w.sustained) ** 2
        + jnp.sum((off / w.offset) ** 2)
        + (fig.effort / w.effort) ** 2
        + extra
    )
