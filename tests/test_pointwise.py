"""The pointwise log-likelihood, observed data and posterior predictive of
``posterior.nc``: the blocks add up to the sampler's own log-likelihood, and ArviZ's
``loo``/``compare`` work on the written file."""

from __future__ import annotations

import dataclasses

import arviz as az
import numpy as np
import pytest
import xarray as xr
from scipy.signal import lfilter
from test_posterior import TRUTH, WALKERS, _batch, synthetic_logs

from jaxlift.model.params import from_unconstrained
from jaxlift.posterior.likelihood import make_log_prob
from jaxlift.posterior.pointwise import LOGLIK_VAR, block_starts, pointwise_groups
from jaxlift.posterior.predictive import predictive
from jaxlift.posterior.priors import log_abs_det_jac
from jaxlift.posterior.problem import innovation_variance_factor, prepare_posterior
from jaxlift.posterior.sampler import sample_posterior
from jaxlift.report.posterior import write_outputs


@pytest.fixture(scope="module")
def logs():
    return synthetic_logs()


@pytest.fixture(scope="module")
def problem(logs):
    return prepare_posterior(logs, params=TRUTH)  # marginal: the offsets move too


def _log_prior(problem, theta):
    total = 0.0
    for k, n in enumerate(problem.names):
        info = problem.infos[n]
        x = from_unconstrained(info, theta[k])
        total += float(problem.priors[n].log_pdf(x) + log_abs_det_jac(info, theta[k]))
    return total


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_blocks_add_up_to_the_samplers_log_likelihood(problem):
    thetas = _batch(problem, n=4, seed=5)
    preds = predictive(problem, thetas)
    groups = pointwise_groups(problem, thetas, preds, n_predictive=2, seed=1)
    ll = groups["log_likelihood"][LOGLIK_VAR]
    per_draw = np.asarray(ll.sum("block")).ravel()
    lp = make_log_prob(problem)(thetas)
    expected = lp - np.array([_log_prior(problem, t) for t in thetas])
    np.testing.assert_allclose(per_draw, expected, rtol=1e-9, atol=1e-6)
    # blocks of one second (50 Hz logs), idle seconds merged: contiguous, cover the log
    exp = problem.experiments[0]
    ts = np.asarray(exp.inputs.ts)
    mine = ll.where(ll.block_log == exp.name, drop=True)
    assert mine.block_start_s[0] == ts[0] and mine.block_end_s[-1] == ts[-1]
    np.testing.assert_allclose(mine.block_start_s[1:], mine.block_end_s[:-1] + 0.02)
    lengths = np.asarray(mine.block_end_s - mine.block_start_s) + 0.02
    assert np.all(lengths >= 1.0 - 1e-9) and np.any(lengths > 1.5)  # the holds merged
    # every block's log-likelihood differs between draws (PSIS needs that)
    assert np.all(np.ptp(np.asarray(ll)[0], axis=0) > 0)
    obs = groups["observed_data"]
    np.testing.assert_array_equal(obs[f"{exp.name}.height"], np.asarray(exp.y[0]))
    ppc = groups["posterior_predictive"][f"{exp.name}.speed"]
    assert ppc.shape == (1, 2, ts.shape[0])
    # predictive noise at the fitted level: residual sd near the sensor's sigma
    resid = np.asarray(ppc[0, 0]) - preds[0]["speed"][0]
    sigma = float(problem.experiments[0].sigma[1])
    assert 0.8 < np.std(resid) / (sigma * problem.scale[0, 1]) < 1.2
    again = pointwise_groups(problem, thetas, preds, n_predictive=2, seed=1)
    xr.testing.assert_identical(again["posterior_predictive"], groups["posterior_predictive"])


@pytest.mark.extended  # CI time: test_report_command checks az.loo on a report's posterior
def test_written_datatree_supports_loo_and_compare(problem, logs, tmp_path):
    # long enough that the thinned draws are distinct (a 60-step chain repeats rejected
    # positions, and PSIS cannot fit a tail of equal values)
    run = sample_posterior(problem, tmp_path / "chain.h5", n_walkers=WALKERS, max_steps=240,
                           seed=0, chunk=60)  # fmt: skip
    write_outputs(problem, run, logs, tmp_path, n_predictive=8, n_loglik=40, seed=0)
    dt = xr.open_datatree(tmp_path / "posterior.nc", engine="h5netcdf")
    for group in ("posterior", "prior", "observed_data", "posterior_predictive",
                  "log_likelihood"):  # fmt: skip
        assert group in dt.children, group
    loo = az.loo(dt)
    assert np.isfinite(loo.elpd)
    cmp = az.compare({"a": dt, "b": dt})
    assert list(cmp["elpd_diff"]) == [0.0, 0.0]


def test_block_starts_merge_idle_windows():
    pwm = np.array([0.0] * 5 + [0.3] * 5 + [0.0] * 10 + [0.2] * 3)
    np.testing.assert_array_equal(block_starts(pwm, 5), [0, 20])
    np.testing.assert_array_equal(block_starts(np.zeros(7), 5), [0])
    np.testing.assert_array_equal(block_starts(np.ones(12), 5), [0, 5, 10])


# ------------------------------------------------------------------ the noise model's check


def test_innovation_variance_factor_is_the_long_run_variance_ratio():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(200_000)
    assert innovation_variance_factor(white) == pytest.approx(1.0, abs=0.05)
    phi, lags = 0.5, 20
    ar = lfilter([1.0], [1.0, -phi], white)
    k = np.arange(1, lags + 1)
    expected = 1 + 2 * np.sum((1 - k / (lags + 1)) * phi**k)  # Bartlett-weighted, by hand
    assert innovation_variance_factor(ar, lags) == pytest.approx(expected, rel=0.03)
    # negative correlation (alternating signs) counts as much as positive
    alt = lfilter([1.0], [1.0, phi], white)
    assert innovation_variance_factor(alt, lags) == pytest.approx(expected, rel=0.03)


@pytest.mark.slow
def test_correlated_innovations_widen_the_noise_model(logs):
    """A slow disturbance on the speed signals (not in the model, not AR(1)) fails the
    Ljung-Box test; the noise variance of those signals is widened, the others not."""
    rng = np.random.default_rng(3)
    disturbed = []
    for lg in logs:
        drift = lfilter([1.0], [1.0, -1.6, 0.8], rng.standard_normal(lg.n)) * 1.5e-3
        disturbed.append(dataclasses.replace(lg, speed_mps=np.asarray(lg.speed_mps) + drift))
    plain = prepare_posterior(disturbed, params=TRUTH, widen=False)
    wide = prepare_posterior(disturbed, params=TRUTH)
    for c_plain, c_wide in zip(
        plain.ls_info["innovation_check"], wide.ls_info["innovation_check"], strict=True
    ):
        assert c_plain["p"] == pytest.approx(c_wide["p"])  # the same test, another model
        if c_wide["signal"] == "speed":
            assert not c_wide["white"] and c_wide["widened"] and c_wide["variance_factor"] > 1.5
            assert not c_plain["widened"]
    i = 0
    assert wide.scale[i, 1] == pytest.approx(
        plain.scale[i, 1] * np.sqrt(wide.ls_info["innovation_check"][1]["variance_factor"])
    )
