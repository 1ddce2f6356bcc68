"""The sampler's proposals (jaxlift.posterior.moves) on problems whose posterior is
known exactly: the de-laplace move's Metropolis--Hastings factor, what it samples,
how fast it mixes, and that a resumed chain is the uninterrupted one."""

import dataclasses

import emcee
import h5py
import numpy as np
import pytest
from scipy import stats

import jaxlift as jl
from jaxlift.posterior.moves import MOVES, SnookerUpdate, _t_proposal
from jaxlift.posterior.sampler import posterior_samples, sample_posterior

NDIM = 6


def _target_cov() -> np.ndarray:
    """A correlated covariance (correlations up to ~0.9, sds 0.3 ... 2)."""
    a = np.random.default_rng(7).normal(size=(NDIM, NDIM))
    c = a @ a.T / NDIM + 0.05 * np.eye(NDIM)
    sd = np.geomspace(0.3, 2.0, NDIM)
    d = np.sqrt(np.diag(c))
    return c / np.outer(d, d) * np.outer(sd, sd)


COV = _target_cov()
MEAN = np.linspace(-1.0, 1.0, NDIM)


@dataclasses.dataclass
class GaussianProblem:
    """What the sampler reads of a posterior problem. ``cov_theta`` is the covariance
    the walkers start from and the de-laplace move proposes from: here the target's,
    each standard deviation 1.25x too wide or too narrow (alternately), as a Laplace
    approximation is never exact."""

    theta_opt: np.ndarray
    cov_theta: np.ndarray
    names: tuple = tuple(f"x{i}" for i in range(NDIM))

    @property
    def ndim(self) -> int:
        return self.theta_opt.size

    def to_physical(self, theta):
        theta = np.asarray(theta)
        return {n: theta[..., i] for i, n in enumerate(self.names)}


def _problem() -> GaussianProblem:
    off = np.diag(np.where(np.arange(NDIM) % 2 == 0, 1.25, 0.8))
    return GaussianProblem(MEAN + 0.05, off @ COV @ off)


_PREC = np.linalg.inv(COV)


def _log_prob(theta):
    d = np.atleast_2d(theta) - MEAN
    return -0.5 * np.einsum("ni,ij,nj->n", d, _PREC, d)


def test_the_proposal_factor_is_the_t_density_ratio():
    """The factor emcee's MHMove adds to the log-probability difference is log q(old) -
    log q(new) for the multivariate t (scipy's density as the oracle), and the draws
    have the t's location and scale."""
    mean, cov, nu, scale = MEAN, COV, 5.0, 1.2
    propose = _t_proposal(mean, cov, nu, scale)
    rng = np.random.RandomState(3)
    old = rng.normal(size=(7, NDIM)) * 2.0
    new, factor = propose(old, rng)
    q = stats.multivariate_t(loc=mean, shape=scale**2 * cov, df=nu)
    np.testing.assert_allclose(factor, q.logpdf(old) - q.logpdf(new), rtol=1e-10, atol=1e-10)
    many, _ = propose(np.zeros((40_000, NDIM)), np.random.RandomState(4))
    # covariance of a t: shape * nu / (nu - 2)
    np.testing.assert_allclose(many.mean(0), mean, atol=0.05)
    np.testing.assert_allclose(np.cov(many.T), scale**2 * cov * nu / (nu - 2), rtol=0.1, atol=0.05)


def test_the_move_checks_its_settings_and_the_covariance():
    with pytest.raises(ValueError, match="laplace_weight"):
        jl.LaplaceMove(laplace_weight=1.0)
    with pytest.raises(ValueError, match="nu and scale"):
        jl.LaplaceMove(scale=0.0)
    bad = GaussianProblem(MEAN, -np.eye(NDIM))
    with pytest.raises(ValueError, match="not positive definite.*de-snooker"):
        jl.LaplaceMove().emcee_moves(bad)
    assert MOVES["de-laplace"] is jl.LaplaceMove


def test_de_laplace_samples_the_posterior_and_mixes_faster(tmp_path):
    """On a correlated Gaussian whose Laplace covariance is off by 25 % per standard
    deviation, both moves converge to the target (means within 5 Monte Carlo standard
    errors, standard deviations within 10 %), and de-laplace's autocorrelation time is
    well below de-snooker's (measured with this seed: 10.8 against 22.9 steps, 650
    against 1 150 steps to converge; with the exact covariance the gap is wider, ~5
    against ~29 steps on an 8-dimensional Gaussian, docs/statistics.md)."""
    problem = _problem()
    runs = {}
    for move in ("de-snooker", "de-laplace"):
        run = sample_posterior(
            problem, tmp_path / f"{move}.h5", n_walkers=16, max_steps=6000, seed=11,
            move=MOVES[move](), log_prob=_log_prob,
        )  # fmt: skip
        assert run.converged, (move, run.iteration, run.tau)
        draws, _, _ = posterior_samples(problem, run.path, run.tau)
        x = np.stack([draws[n].ravel() for n in problem.names], axis=-1)
        n_eff = 16 * (run.iteration - 3 * np.max(run.tau)) / np.max(run.tau)
        se = np.sqrt(np.diag(COV) / n_eff)
        assert np.all(np.abs(x.mean(0) - MEAN) < 5 * se), (move, x.mean(0) - MEAN, se)
        np.testing.assert_allclose(x.std(0), np.sqrt(np.diag(COV)), rtol=0.1)
        runs[move] = run
    assert np.max(runs["de-laplace"].tau) < 0.7 * np.max(runs["de-snooker"].tau), {
        m: np.max(r.tau) for m, r in runs.items()
    }
    assert runs["de-laplace"].iteration < runs["de-snooker"].iteration


def test_a_resumed_de_laplace_chain_is_the_uninterrupted_one(tmp_path):
    """The independence proposals draw from emcee's stored random state: 30 + 30 steps
    give the same chain, bit for bit, as 60."""
    problem = _problem()

    def run(path, steps):
        return sample_posterior(
            problem, path, n_walkers=16, max_steps=steps, seed=2, chunk=30,
            move=jl.LaplaceMove(), log_prob=_log_prob,
        )  # fmt: skip

    run(tmp_path / "a.h5", 60)
    run(tmp_path / "b.h5", 30)
    again = run(tmp_path / "b.h5", 60)
    assert again.resumed_from == 30 and again.move == "de-laplace"
    a = emcee.backends.HDFBackend(str(tmp_path / "a.h5"), name="mcmc", read_only=True)
    b = emcee.backends.HDFBackend(str(tmp_path / "b.h5"), name="mcmc", read_only=True)
    assert np.array_equal(a.get_chain(), b.get_chain())
    assert a.get_chain().shape == (60, 16, NDIM)


def _long_run_sd_ratio(move, seed: int, steps: int = 6000, walkers: int = 16) -> float:
    """Mean over coordinates of the sampled standard deviation over the true one."""
    s = emcee.EnsembleSampler(walkers, NDIM, _log_prob, vectorize=True, moves=move)
    s._random = np.random.RandomState(seed)
    start = np.random.default_rng(seed).multivariate_normal(MEAN, COV, size=walkers)
    s.run_mcmc(start, steps, progress=False)
    x = s.get_chain(discard=500).reshape(-1, NDIM)
    return float(np.mean(x.std(0) / np.sqrt(np.diag(COV))))


def test_the_snooker_update_samples_the_posterior_and_emcees_does_not():
    """jaxlift's snooker update alone keeps the posterior: the sampled standard
    deviations are the true ones (within 5 %; measured 1.004 here, 1.00 on 8
    dimensions). emcee's DESnookerMove (3.1.6) does not: 0.85 of the truth here (0.81
    on 8 dimensions).
    Should emcee fix its move this test fails, and jaxlift can use emcee's again."""
    ours = _long_run_sd_ratio(SnookerUpdate(), seed=1)
    theirs = _long_run_sd_ratio(emcee.moves.DESnookerMove(), seed=1)
    assert abs(ours - 1.0) < 0.05, ours
    assert theirs < 0.9, theirs


def test_a_chain_sampled_with_emcees_snooker_is_not_resumed(tmp_path):
    """A chain stored before the fix (no snooker revision in the file) is refused by
    the moves that use the snooker update, with the reason and what to do."""
    problem = _problem()
    path = tmp_path / "old.h5"
    sample_posterior(problem, path, n_walkers=16, max_steps=10, seed=1, chunk=10,
                     log_prob=_log_prob)  # fmt: skip
    with h5py.File(path, "a") as fh:
        del fh["mcmc"].attrs["jaxlift_snooker"]  # as every chain written before
    with pytest.raises(ValueError, match="emcee's DESnookerMove.*delete the file"):
        sample_posterior(problem, path, n_walkers=16, max_steps=20, seed=1, chunk=10,
                         log_prob=_log_prob)  # fmt: skip
    # a move without the snooker update resumes it
    with h5py.File(path, "a") as fh:
        fh["mcmc"].attrs["jaxlift_move"] = "de"
    run = sample_posterior(problem, path, n_walkers=16, max_steps=20, seed=1, chunk=10,
                           move=jl.DEMove(), log_prob=_log_prob)  # fmt: skip
    assert run.resumed_from == 10 and run.iteration == 20
