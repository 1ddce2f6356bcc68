"""Tests of jaxlift.analysis.regimes on synthetic logs (numpy only, fast)."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from jaxlift.analysis.oscillation import (
    log_speed_noise_floor,
    oscillation_metrics,
    oscillation_table,
    zoom_windows,
)
from jaxlift.analysis.regimes import REGIMES, error_table, segment_log
from jaxlift.analysis.residuals import residual_diagnostics
from jaxlift.model.log import Log
from jaxlift.report.analysis_plots import (
    plot_error_bars,
    plot_oscillations_vs_height,
    plot_residuals,
)

DT = 0.01
SIGMA_V = math.sqrt(1e-7 / DT)  # docs/model.md speed noise at 100 Hz [m/s]

# (pwm level, duration [s], ramp into it [s], load [kg]) -- the test run
RUN = [
    (0.0, 3.0, 0.0, 500.0),  # 0-3 hold
    (0.40, 7.0, 1.0, 500.0),  # 3-4 ramp, 4-10 fast
    (0.15, 15.0, 1.0, 500.0),  # 10-11 ramp, 11-25 slow, crosses 1.5 m (~18.6 s)
    (0.0, 5.0, 1.0, 500.0),  # 25-26 ramp, 26-30 hold (the pallet is picked up here)
    (0.40, 7.0, 1.0, 1200.0),  # 30-31 ramp, 31-37 fast with the heavier load
    (0.30, 1.5, 0.5, 1200.0),  # 37-37.5 ramp, 37.5-38.5 a short steady bit (-> ramp)
    (0.0, 4.5, 0.5, 1200.0),  # 38.5-39 ramp, 39-43 hold
]


def _truth(run=RUN, h0=0.6, dt=DT):
    """Noise-free pwm, load, speed and height of a run: speed follows ``gain(load) * pwm``
    with a 0.15 s lag; returns arrays and the time of the 1.5 m crossing."""
    total = sum(d for _, d, _, _ in run)
    n = int(round(total / dt))
    t = np.arange(n) * dt
    pwm = np.zeros(n)
    load = np.zeros(n)
    start, prev = 0.0, run[0][0]
    for level, dur, ramp, m in run:
        sel = (t >= start - 1e-9) & (t < start + dur - 1e-9)
        frac = np.clip((t[sel] - start) / ramp, 0.0, 1.0) if ramp > 0 else 1.0
        pwm[sel] = np.round(prev + (level - prev) * frac, 12)
        load[sel] = m
        start, prev = start + dur, level
    gain = np.where(load > 1000, 0.16, 0.225)  # m/s per unit duty cycle
    target = gain * pwm
    v = np.zeros(n)
    for i in range(1, n):
        v[i] = v[i - 1] + dt / 0.15 * (target[i - 1] - v[i - 1])
    h = h0 + np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)))
    tc = float(t[np.argmax(h >= 1.5)])
    return t, pwm, load, v, h, tc


def _log(seed=0, speed=True, extra_speed=None):
    t, pwm, load, v, h, tc = _truth()
    rng = np.random.default_rng(seed)
    vm = v + (0.0 if extra_speed is None else extra_speed(t))
    log = Log(
        time_s=t,
        pwm=pwm,
        height_m=h + 0.5e-3 * rng.standard_normal(t.size),
        load_kg=load,
        speed_mps=(vm + SIGMA_V * rng.standard_normal(t.size)) if speed else None,
        name="synthetic",
    )
    return log, v, h, tc


def _regime_at(segments, t):
    hits = [s for s in segments if s.t0 <= t < s.t1]
    assert len(hits) == 1
    return hits[0].regime


# ------------------------------------------------------------------------------ segmentation


@pytest.mark.parametrize("speed", [True, False])
def test_segments_regimes_at_known_times(speed):
    log, _, _, tc = _log(speed=speed)
    assert 17.0 < tc < 20.0  # the run is built to cross x_s1 in the slow section
    segs = segment_log(log)
    expected = {
        1.5: "hold",
        3.5: "ramp",
        7.0: "fast",
        10.5: "ramp",
        14.0: "slow",
        tc - 0.8: "stage_shift",
        tc + 0.1: "stage_shift",
        tc + 3.8: "stage_shift",
        24.5: "slow",
        25.5: "ramp",
        28.0: "hold",
        30.5: "ramp",
        34.0: "fast",  # heavier load: slower, still fast
        38.0: "ramp",  # steady for only 1 s
        41.0: "hold",
    }
    for t, regime in expected.items():
        assert _regime_at(segs, t) == regime, t
    assert _regime_at(segs, tc - 1.2) == "slow"
    assert _regime_at(segs, tc + 4.2) == "slow"
    # the stage-shift window is [tc - 1, tc + 4)
    (shift,) = [s for s in segs if s.regime == "stage_shift"]
    assert shift.t0 == pytest.approx(tc - 1.0, abs=0.1)
    assert shift.t1 == pytest.approx(tc + 4.0, abs=0.1)
    assert shift.stage in (1, 2)
    # stages by mean measured height
    for s in segs:
        assert s.stage == (1 if s.height < 1.5 else 2 if s.height < 3.0 else 3)
    assert segs[0].stage == 1 and segs[-1].stage == 2
    holds = [s for s in segs if s.regime == "hold"]
    assert all(s.pwm == 0.0 for s in holds)


def test_segments_cover_every_sample_once_in_order():
    log, *_ = _log()
    segs = segment_log(log)
    assert segs[0].start == 0 and segs[-1].stop == log.n
    for a, b in zip(segs[:-1], segs[1:], strict=True):
        assert a.stop == b.start
        assert a.t1 == pytest.approx(b.t0)
        # neighbours differ (else they would be one segment), unless two steady levels meet
        assert a.regime != b.regime or a.regime in ("fast", "slow", "hold")
    assert sum(s.n for s in segs) == log.n
    assert all(s.n > 0 and s.regime in REGIMES for s in segs)
    assert segs[-1].t1 == pytest.approx(log.time_s[-1] + log.sample_period)


def test_segmentation_same_with_and_without_logged_speed():
    log, *_ = _log(seed=3)
    log2 = Log(time_s=log.time_s, pwm=log.pwm, height_m=log.height_m, load_kg=log.load_kg, name="x")
    a = [(s.start, s.stop, s.regime) for s in segment_log(log)]
    b = [(s.start, s.stop, s.regime) for s in segment_log(log2)]
    assert a == b


def test_no_stage_shift_for_noise_at_the_boundary():
    """A fork parked right at x_s1: noise crosses the boundary many times, no stage shift."""
    n = 2000
    rng = np.random.default_rng(1)
    t = np.arange(n) * DT
    log = Log(
        time_s=t,
        pwm=np.zeros(n),
        height_m=1.5 + 0.5e-3 * rng.standard_normal(n),
        load_kg=np.full(n, 800.0),
        speed_mps=SIGMA_V * rng.standard_normal(n),
    )
    segs = segment_log(log)
    assert [s.regime for s in segs] == ["hold"]


def test_stepped_levels_without_ramps_give_separate_segments():
    n = 1000
    t = np.arange(n) * DT
    pwm = np.where(t < 5.0, 0.4, 0.15)
    v = np.where(t < 5.0, 0.09, 0.03)
    h = 0.2 + np.cumsum(v) * DT
    log = Log(time_s=t, pwm=pwm, height_m=h, load_kg=np.full(n, 500.0), speed_mps=v)
    segs = segment_log(log)
    assert [(s.regime, s.start, s.stop) for s in segs] == [("fast", 0, 500), ("slow", 500, n)]


# ------------------------------------------------------------------------------ error table


def test_error_table_known_offsets():
    t, pwm, load, v, h, _ = _truth()
    p = 8e6 + 1e6 * pwm
    log = Log(time_s=t, pwm=pwm, height_m=h, load_kg=load, speed_mps=v, pressure_pa=p)
    alt = np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)
    rows = error_table(log, h + 2e-3, v - 5e-3 + 3e-3 * alt, p + 0.1e6)
    groups = [r["group"] for r in rows]
    assert groups[0] == "all"
    assert {"hold", "fast", "slow", "ramp", "stage_shift", "stage 1", "stage 2"} <= set(groups)
    assert "stage 3" not in groups  # the run stays below 3 m
    for r in rows:
        assert r["rms_height_mm"] == pytest.approx(2.0, rel=1e-9)
        assert r["bias_height_mm"] == pytest.approx(2.0, rel=1e-9)
        assert r["rms_speed_mmps"] == pytest.approx(math.sqrt(34.0), rel=1e-2)
        assert r["bias_speed_mmps"] == pytest.approx(-5.0, abs=0.1)
        assert r["rms_pressure_MPa"] == pytest.approx(0.1, rel=1e-9)
        assert r["bias_pressure_MPa"] == pytest.approx(0.1, rel=1e-9)
    by = {r["group"]: r for r in rows}
    assert by["all"]["n"] == log.n
    assert by["all"]["bias_speed_mmps"] == pytest.approx(-5.0, abs=1e-9)
    assert sum(by[g]["n"] for g in REGIMES if g in by) == log.n
    assert sum(by[g]["n"] for g in ("stage 1", "stage 2")) == log.n


def test_error_table_without_pressure_or_speed():
    t, pwm, load, v, h, _ = _truth()
    log = Log(time_s=t, pwm=pwm, height_m=h, load_kg=load)
    rows = error_table(log, h - 1e-3, v, np.zeros(t.size))
    assert "rms_pressure_MPa" not in rows[0]
    assert math.isnan(rows[0]["rms_speed_mmps"])
    assert rows[0]["bias_height_mm"] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="shape"):
        error_table(log, h[:-1], v)


# ------------------------------------------------------------------------------ oscillations

T10 = np.arange(1000) * DT  # 10 s at 100 Hz


def _decaying(decay, seed, amp=5e-3, f=2.1):
    rng = np.random.default_rng(seed)
    sig = amp * np.exp(-decay * T10) * np.sin(2 * np.pi * f * T10 + 0.7)
    return sig, 0.03 + 0.002 * T10 + sig + 3e-3 * rng.standard_normal(T10.size)


def test_oscillation_metrics_decaying_sinusoid_in_noise():
    sig, v = _decaying(0.3, seed=0)
    m = oscillation_metrics(T10, v)
    assert m["freq_hz"] == pytest.approx(2.1, rel=0.02)
    # amplitude_mps: sqrt(2) x RMS of the oscillation over the stretch
    assert m["amplitude_mps"] == pytest.approx(math.sqrt(2 * np.mean(sig**2)), rel=0.15)
    assert m["amp0_mps"] == pytest.approx(5e-3, rel=0.3)  # fitted envelope at the start
    assert m["decay_per_s"] == pytest.approx(0.3, abs=0.1)
    # the estimator is unbiased on average (its spread is ~0.06 /s at this noise level)
    decays = [oscillation_metrics(T10, _decaying(0.3, seed=s)[1])["decay_per_s"] for s in range(20)]
    assert np.median(decays) == pytest.approx(0.3, abs=0.05)


def test_oscillation_metrics_sustained_and_growing():
    sig, v = _decaying(0.0, seed=1)
    m = oscillation_metrics(T10, v)
    assert m["freq_hz"] == pytest.approx(2.1, rel=0.01)
    assert m["amplitude_mps"] == pytest.approx(5e-3, rel=0.1)
    assert m["amp0_mps"] == pytest.approx(5e-3, rel=0.2)
    assert abs(m["decay_per_s"]) < 0.05
    m = oscillation_metrics(T10, _decaying(-0.1, seed=2)[1])
    assert m["decay_per_s"] == pytest.approx(-0.1, abs=0.05)


def test_oscillation_metrics_noise_free_signal():
    v = 0.02 + 4e-3 * np.exp(-0.5 * T10) * np.sin(2 * np.pi * 1.3 * T10)
    m = oscillation_metrics(T10, v, subtract_noise=False)
    assert m["freq_hz"] == pytest.approx(1.3, rel=0.01)
    assert m["decay_per_s"] == pytest.approx(0.5, abs=0.03)
    assert m["amp0_mps"] == pytest.approx(4e-3, rel=0.1)


def _noise_log(n=1000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    return Log(
        time_s=t,
        pwm=np.full(n, 0.2),
        height_m=np.linspace(1.0, 1.3, n),
        load_kg=np.full(n, 500.0),
        speed_mps=0.03 + SIGMA_V * rng.standard_normal(n),
    )


def test_pure_noise_has_no_frequency_with_the_log_noise_floor():
    log = _noise_log()
    floor = log_speed_noise_floor(log)
    # 3x the band RMS of white noise of sigma_v: sigma_v * sqrt(9.5 / 50)
    assert floor == pytest.approx(3 * SIGMA_V * math.sqrt(9.5 / 50.0))
    for seed in range(20):
        v = _noise_log(seed=seed).speed_mps
        m = oscillation_metrics(log.time_s, v, noise_floor_mps=floor)
        assert math.isnan(m["freq_hz"]) and math.isnan(m["decay_per_s"])
        assert m["rms_mps"] == pytest.approx(SIGMA_V * math.sqrt(9.5 / 50.0), rel=0.2)
    # a clear oscillation passes the same floor
    osc = 0.03 + 10e-3 * np.sin(2 * np.pi * 1.8 * log.time_s) + log.speed_mps - 0.03
    assert oscillation_metrics(log.time_s, osc, noise_floor_mps=floor)["freq_hz"] == (
        pytest.approx(1.8, rel=0.01)
    )


def test_oscillation_metrics_short_input_is_nan():
    m = oscillation_metrics(np.arange(5) * DT, np.zeros(5))
    assert all(math.isnan(x) for x in m.values())


def test_oscillation_table_measured_vs_model():
    def osc(t):  # 2 Hz, 15 mm/s, in the slow section only (stick-slip like)
        return np.where((t > 11) & (t < 25), 15e-3 * np.sin(2 * np.pi * 2.0 * t), 0.0)

    log, v, _, tc = _log(extra_speed=osc)
    model = v + np.where((log.time_s > 11) & (log.time_s < 25), 8e-3, 0.0) * np.sin(
        2 * np.pi * 2.5 * log.time_s
    )
    rows = oscillation_table(log, model)
    # the slow piece after the stage shift (tc + 4 .. 25 s) is shorter than 3 s: not analysed
    assert 25.0 - (tc + 4.0) < 3.0
    assert [r["regime"] for r in rows] == ["fast", "slow", "fast"]
    fast, slow1 = rows[0], rows[1]
    assert math.isnan(fast["meas_freq_hz"]) and math.isnan(fast["model_freq_hz"])
    assert slow1["meas_freq_hz"] == pytest.approx(2.0, rel=0.02)
    assert slow1["model_freq_hz"] == pytest.approx(2.5, rel=0.02)
    assert slow1["meas_amp_mps"] == pytest.approx(15e-3, rel=0.15)
    assert slow1["model_amp_mps"] == pytest.approx(8e-3, rel=0.15)
    assert abs(slow1["meas_decay_per_s"]) < 0.1
    assert slow1["t1"] <= tc - 0.9 and slow1["stage"] == 1
    assert rows[2]["t0"] == pytest.approx(31.0, abs=0.05) and rows[2]["stage"] == 2
    assert slow1["noise_floor_mps"] == pytest.approx(log_speed_noise_floor(log))
    for key in ("t0", "t1", "height_m", "meas_decay_per_s", "model_rms_mps"):
        assert key in slow1


# ------------------------------------------------------------------------------ residuals


def _residual_log(noise):
    n = noise.size
    t = np.arange(n) * DT
    v = np.full(n, 0.02)
    h = 0.5 + 0.02 * t
    log = Log(time_s=t, pwm=np.full(n, 0.2), height_m=h, load_kg=np.full(n, 500.0), speed_mps=v)
    return log, h, v


def test_residual_autocorrelation_white_and_ar1():
    n = 20000
    rng = np.random.default_rng(0)
    log, h, v = _residual_log(rng.standard_normal(n))
    white = SIGMA_V * rng.standard_normal(n)
    e = rng.standard_normal(n)
    ar = np.empty(n)
    ar[0] = e[0]
    for i in range(1, n):
        ar[i] = 0.8 * ar[i - 1] + math.sqrt(1 - 0.64) * e[i]
    d = residual_diagnostics(log, h + 0.5e-3 * ar, v + white)
    sp, hg = d["speed"], d["height"]
    assert abs(sp["rho1"]) < 0.03
    assert np.all(np.abs(sp["acf"][1:]) < 0.05)
    assert sp["neff_factor"] == pytest.approx(1.0, abs=0.06)
    assert sp["rms"] == pytest.approx(1.0, rel=0.03)
    assert sp["ljung_box_p"] > 1e-3
    assert hg["rho1"] == pytest.approx(0.8, abs=0.03)
    assert hg["neff_factor"] == pytest.approx(0.2 / 1.8, abs=0.02)
    assert hg["acf"][5] == pytest.approx(0.8**5, abs=0.05)
    assert hg["ljung_box_p"] < 1e-6
    assert sp["lags_s"][-1] == pytest.approx(2.0)
    assert sp["acf"][0] == 1.0
    # white unit-variance noise: one-sided PSD 2 T_s
    band = (sp["freqs_hz"] > 1) & (sp["freqs_hz"] < 45)
    assert np.mean(sp["power"][band]) == pytest.approx(2 * DT, rel=0.1)
    assert "pressure" not in d


# ------------------------------------------------------------------------------ plots, windows


def test_plots_and_zoom_windows(tmp_path):
    def osc(t):
        return np.where((t > 11) & (t < 25), 12e-3 * np.sin(2 * np.pi * 2.0 * t), 0.0)

    log, v, h, tc = _log(extra_speed=osc)
    segs = segment_log(log)
    rows_b = oscillation_table(log, v, segs)
    rows_a = oscillation_table(log, v + osc(log.time_s), segs)
    p1 = plot_oscillations_vs_height({"before": rows_b, "after": rows_a}, tmp_path / "osc.png")
    p2 = plot_residuals(log, h + 1e-3, v, tmp_path / "res.png", pressure=8e6 + 0 * v)
    p3 = plot_error_bars(
        {"before": error_table(log, h, v, segments=segs), "after": error_table(log, h, v)},
        tmp_path / "err.png",
        noise_speed_mmps=SIGMA_V * 1e3,
    )
    for p in (p1, p2, p3):
        assert os.path.getsize(p) > 1000
        with open(p, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"

    wins = zoom_windows(log, segs, n=3)
    assert 1 <= len(wins) <= 3
    assert wins == sorted(wins)
    for a, b in wins:
        assert b - a == pytest.approx(10.0)
        assert log.time_s[0] <= a and b <= log.time_s[-1] + 1e-9
    # the slow stretch with the oscillation, the stage shift and a fast section are covered
    assert any(a <= 15 and b >= 15 for a, b in wins)
    assert any(a <= tc <= b for a, b in wins)
    assert any(a <= 34 <= b or a <= 7 <= b for a, b in wins)


def test_ljung_box_on_innovations():
    """The posterior's check of its AR(1) noise model: innovations of an AR(1) process
    are white; those of an AR(2) process, whitened as if AR(1), are not."""
    from jaxlift.analysis.residuals import ljung_box

    rng = np.random.default_rng(0)
    n = 6000
    w = rng.standard_normal(n)
    ar1 = np.zeros(n)
    ar2 = np.zeros(n)
    for t in range(2, n):
        ar1[t] = 0.7 * ar1[t - 1] + w[t]
        ar2[t] = 0.5 * ar2[t - 1] + 0.3 * ar2[t - 2] + w[t]
    for x, white in ((ar1, True), (ar2, False)):
        rho = float(x[1:] @ x[:-1] / (x[:-1] @ x[:-1]))
        q, dof, p = ljung_box(x[1:] - rho * x[:-1], 20, fitted=1)
        assert dof == 19
        assert (p > 0.01) == white, (q, p)
    q, dof, p = ljung_box(w, 20)
    assert dof == 20 and 0.01 < p <= 1.0
