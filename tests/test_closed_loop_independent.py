"""The closed loop checked outside jaxlift (issue #18): the sampled, noisy loop of
docs/control.md built on the SciPy plant (tests/scipy_closed_loop.py, which shares no
code with jaxlift's closed loop or tuner) against ``jaxlift.simulate_closed_loop``.

The shipped logs' true model (data/truth.json: baseline + stick_slip + hose_compliance,
both of which the SciPy plant implements) at 500 and 1 500 kg, a quarter of the
thesis-like reference (27.5 s: hold, fast, slow, hold, ...), the controller every 10 ms.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest
from scipy_closed_loop import NOISE_SIGMA, closed_loop_scipy, figures, white_noise

import jaxlift as jl

ROOT = pathlib.Path(__file__).resolve().parent.parent
TRUTH = {k: v for k, v in json.loads((ROOT / "data/truth.json").read_text()).items() if k[0] != "_"}
#: a low-gain set that is stable on the 10 ms clock (the issue's hand-found one, with a
#: filter and anti-windup), and the thesis PID, which is not (|lambda| 2.18)
LOW_GAINS = dict(P=5.0, I=60.0, D=0.5, N=24.6, K_aw=12.0)
THESIS = dict(P=20.0, I=300.0, D=2.0, N=100.0, K_aw=0.0)


def _jax_run(gains, m_load, noise_seed):
    plant, effects, _ = jl.calibrated_model(str(ROOT / "data/truth.json"), None)
    ref = jl.thesis_reference(m_load, time_scale=0.25)
    sol = jl.simulate_closed_loop(
        plant, effects, jl.PID().with_gains(gains), ref, sampled=True, T_c=0.01,
        noise_seed=noise_seed,
    )  # fmt: skip
    assert bool(sol.ok)
    return ref, sol


def _scipy_run(ref, gains, m_load, noise):
    return closed_loop_scipy(
        TRUTH, gains, np.asarray(ref.knots_t), np.asarray(ref.knots_v), m_load,
        float(ref.x0), noise=noise,
    )  # fmt: skip


@pytest.mark.parametrize("m_load", [500.0, 1500.0])
def test_same_noise_same_trajectory(m_load):
    """With the noise samples of one jaxlift seed fed to the SciPy loop, a loop that is
    stable on its clock follows the same trajectory to the solvers' tolerance: the
    plant, the sampled law (with its stops), the hold and the noise's timing agree."""
    ref, sol = _jax_run(LOW_GAINS, m_load, noise_seed=3)
    v_jax = np.asarray(sol.ys[:, 1])
    noise = np.asarray(sol.v_meas) - v_jax
    assert 0.8 * NOISE_SIGMA < np.std(noise) < 1.2 * NOISE_SIGMA
    run = _scipy_run(ref, LOW_GAINS, m_load, noise)
    assert run["ts"].shape == np.asarray(sol.ts).shape
    # 1e-4 m/s = 0.1 mm/s: 3 % of the noise, 4 % of the slow speed; measured 6e-6 m/s
    np.testing.assert_allclose(run["v"], v_jax, atol=1e-4)
    np.testing.assert_allclose(run["x"], np.asarray(sol.ys[:, 0]), atol=1e-5)
    np.testing.assert_allclose(run["u"], np.asarray(sol.u), atol=2e-3)
    mine = figures(run)
    theirs = jl.closed_loop_figures(sol).as_dict()
    for k in ("tracking_rms_mmps", "osc_rms_mmps"):
        assert mine[k] == pytest.approx(theirs[k], rel=5e-3), k


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_figures_agree_in_distribution_with_independent_noise():
    """Each loop with its own noise (jax.random vs NumPy): the figures of "good" are
    draws of the same random variable, so their means over seeds agree within their
    spread -- including for the thesis gains, which are unstable on the 10 ms clock
    (trajectories then diverge after a few seconds, the figures do not)."""
    m_load, seeds = 500.0, range(4)
    osc = {}
    for name, gains in (("low", LOW_GAINS), ("thesis", THESIS)):
        ours, theirs = [], []
        ref = None
        for s in seeds:
            ref, sol = _jax_run(gains, m_load, noise_seed=s)
            f = jl.closed_loop_figures(sol).as_dict()
            theirs.append([f["tracking_rms_mmps"], f["osc_rms_mmps"]])
            run = _scipy_run(ref, gains, m_load, white_noise(ref.n_out, 100 + s))
            ours.append(list(figures(run).values()))
        ours, theirs = np.array(ours), np.array(theirs)
        spread = np.sqrt(ours.var(0, ddof=1) / len(ours) + theirs.var(0, ddof=1) / len(theirs))
        diff = np.abs(ours.mean(0) - theirs.mean(0))
        assert np.all(diff < 4 * spread + 0.02 * theirs.mean(0)), (name, ours, theirs)
        osc[name] = ours[:, 1].mean()
    # the check tells gain sets apart: the thesis gains oscillate more (measured on the
    # SciPy loop: 5.2 mm/s low gains, about 9-10 mm/s thesis)
    assert osc["thesis"] > 1.3 * osc["low"], osc


# ~260 s (a whole default tuning): out of CI's time since 2026-12-04. In CI the tuner is
# checked by tests/test_tuning.py (tuned gains beat the thesis gains, robust tuning,
# the command) and this loop by the two tests above; run with -m extended.
@pytest.mark.extended
def test_tuned_gains_meet_the_targets_on_the_independent_loop():
    """Issue #18's acceptance, checked outside the tuner. The gains are tuned as
    ``jaxlift tune`` tunes them by default -- the loop as deployed (sampled every
    10 ms, duty held), the speed sensor's noise averaged over its four seeds, from the
    thesis PID with ``K_aw = I/P`` -- on the shipped logs' true model at 500 and
    1 500 kg along the whole 110 s reference. Then the SciPy loop, with noise of its
    own (NumPy, seeds the tuner never saw), runs the tuned and the thesis gains:

    - tuned: tracking RMS <= 5 mm/s and oscillation RMS <= 3 mm/s at both loads;
    - tuned better than the thesis gains on both figures at both loads;
    - the tuner's own simulation (jaxlift, its own seeds) claims figures that agree
      with the independent loop's within the noise (the mean over seeds differs by
      less than 4 standard errors of the difference, plus 3 %).

    Measured (2 cores): tuned 4.0 / 2.2 mm/s at both loads, thesis 8.0 / 7.4 (500 kg)
    and 12.1 / 11.7 (1 500 kg)."""
    from jaxlift.control.tune import tune_gains
    from jaxlift.workflows.tune import DEFAULT_NOISE_SEEDS

    plant, effects, _ = jl.calibrated_model(str(ROOT / "data/truth.json"), None)
    loads = (500.0, 1500.0)
    refs = [jl.thesis_reference(m) for m in loads]
    start = jl.PID().with_gains({**THESIS, "K_aw": THESIS["I"] / THESIS["P"]})
    res = tune_gains(
        start, plant, effects, refs, sampled=True, T_c=0.01, noise_seeds=DEFAULT_NOISE_SEEDS
    )
    assert res.n_failed == 0
    tuned = res.controller.gain_values()
    seeds = range(3)
    for ref in refs:
        figs = {}
        for name, gains in (("tuned", tuned), ("thesis", THESIS)):
            runs = [
                _scipy_run(ref, gains, float(ref.m_load), white_noise(ref.n_out, 500 + s))
                for s in seeds
            ]
            figs[name] = np.array([list(figures(r).values()) for r in runs])
        mine = figs["tuned"].mean(0)
        assert mine[0] <= 5.0 and mine[1] <= 3.0, (ref.m_load, mine)
        assert np.all(mine < figs["thesis"].mean(0)), (ref.m_load, figs)
        claimed = []
        for s in seeds:  # the tuner's simulation, seeds it was not tuned on
            sol = jl.simulate_closed_loop(
                plant, effects, res.controller, ref, sampled=True, T_c=0.01, noise_seed=50 + s
            )
            f = jl.closed_loop_figures(sol).as_dict()
            claimed.append([f["tracking_rms_mmps"], f["osc_rms_mmps"]])
        claimed = np.array(claimed)
        n = len(seeds)
        spread = np.sqrt(figs["tuned"].var(0, ddof=1) / n + claimed.var(0, ddof=1) / n)
        assert np.all(np.abs(mine - claimed.mean(0)) < 4 * spread + 0.03 * mine), (mine, claimed)
