"""The emcee proposals the sampler can use, as objects: pass one to
:func:`jaxlift.sample_posterior` / :func:`jaxlift.run_posterior` as ``move=``.

All leave the posterior invariant; they differ in how many steps one independent
sample takes (the integrated autocorrelation time tau). Measured on the shipped logs
(5 parameters, 32 walkers, seed 0, max tau on the first 253 steps of each chain):
stretch 28.5, de 16.1, de-snooker 16.3, kde 9.7; stretch reached 58 after 1946 steps,
de-snooker about 18 (on a Gaussian with the posterior's covariance: stretch 51-57, de
17, de-snooker 19, kde 7). The KDE proposal is not the default: it is an
independence-type proposal that strands a walker the KDE of the others does not cover
(seen on the shipped logs from another start: one walker at acceptance 0.01 and tau
still growing past 50), and it needs several walkers per dimension (10 dimensions, 32
walkers: acceptance 3 %). See ``benchmarks/results_posterior.txt``.

``de-laplace`` (:class:`LaplaceMove`, the default) mixes the DE moves with an
independence Metropolis--Hastings proposal drawn from a multivariate Student-t around
the least-squares optimum, shaped by the posterior's own Laplace covariance (the one
the walkers start from). Where the posterior is close to that Gaussian, a proposal is
accepted about half the time and lands anywhere in the posterior, so tau falls from
~30 steps to ~5. Measured on Gaussians of the report's size (8 dimensions, 20 walkers,
four seeds, to the 50-tau rule; ``studies/sbc.py`` checks the intervals): tau 28.6 ->
5.2 steps and 1 488 -> 475 steps to converge with the exact covariance; 22.4 and
1 138 steps when every standard deviation of the proposal is 1.5x too wide or too
narrow (alternately); on a curved (banana) target 32.5 -> 9.4 and 1 638 -> 588 (these
with emcee's snooker in the mix; with :class:`SnookerUpdate` the same within a few per
cent: over 20 000 steps tau 5.3, 6.5 and 11.8 with the proposal's standard deviations
exact, 1.1x and 1.25x off, and the sampled standard deviations 0.998-1.001 of the
truth). On the shipped logs' final model (8 parameters, 20 walkers): 500 steps to
converge (tau 7.0) against 1 650 (tau 32.2) with de-snooker.

The snooker update is jaxlift's own (:class:`SnookerUpdate`): emcee's
``DESnookerMove`` does not converge to the posterior.

A move's :attr:`~AbstractMove.name` is stored with the chain: a chain resumes only
with the move it was started with.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import emcee
import equinox as eqx
import numpy as np

from .problem import PosteriorProblem


class SnookerUpdate(emcee.moves.RedBlueMove):
    """The DE snooker update of ter Braak & Vrugt (2008), as an emcee move.

    For each walker ``x`` of one quarter of the ensemble, three walkers ``z``, ``z1``,
    ``z2`` are drawn from the other three quarters (one from each, in random order);
    ``x`` moves along the line through ``z``: ``x' = x + gamma e (e . (z1 - z2))`` with
    the unit vector ``e = (x - z) / |x - z|``, and is accepted with probability
    ``min(1, p(x') / p(x) (|x' - z| / |x - z|)^(ndim - 1))``.

    Why not emcee's ``DESnookerMove`` (3.1.6, the same on its main branch in 2026-11):
    it scales ``x - z`` by ``1 / sqrt(|x - z|)`` instead of ``1 / |x - z|``, so the step
    along the line grows with the distance from ``z`` (a multiplicative move that is
    not even invariant to the units of the coordinates), and weights the acceptance
    with half the exponent. The chain then does not converge to the posterior.
    Measured on a correlated 8-dimensional Gaussian (20 walkers, 15 000 steps, two
    seeds): standard deviations 0.82 and 0.81 of the truth with emcee's move alone,
    0.948 with emcee's mix of 0.8 DE and 0.2 snooker (jaxlift's default move until
    2026-11-29; DE alone 1.00), 1.000 and 1.001 with this one alone and 0.998 and
    1.001 mixed with DE; on a 3-dimensional one (16 walkers) 0.89 against 1.00. The
    test is ``tests/test_moves.py``.
    """

    def __init__(self, gamma: float = 1.7, **kwargs):
        self.gamma = float(gamma)
        kwargs["nsplits"] = 4
        super().__init__(**kwargs)

    def get_proposal(self, s, c, random):
        n, ndim = s.shape
        q = np.empty((n, ndim), dtype=np.float64)
        log_factor = np.zeros(n, dtype=np.float64)
        for i in range(n):
            w = np.array([c[j][random.randint(len(c[j]))] for j in range(3)])
            random.shuffle(w)
            z, z1, z2 = w
            delta = s[i] - z
            r = np.linalg.norm(delta)
            if r == 0.0:  # on top of z: no line to move along; stay
                q[i] = s[i]
                continue
            e = delta / r
            q[i] = s[i] + self.gamma * e * np.dot(e, z1 - z2)
            log_factor[i] = (ndim - 1.0) * (np.log(np.linalg.norm(q[i] - z)) - np.log(r))
        return q, log_factor


class AbstractMove(eqx.Module):
    """An emcee proposal with a stable name (stored with the chain)."""

    name: ClassVar[str]
    #: whether its moves include :class:`SnookerUpdate` (chains sampled with emcee's
    #: biased snooker update are then not resumed)
    uses_snooker: ClassVar[bool] = False

    @abc.abstractmethod
    def emcee_moves(self, problem: PosteriorProblem):
        """emcee's ``moves`` argument for sampling ``problem``."""


class DESnookerMove(AbstractMove):
    """Differential evolution mixed with the DE snooker move (emcee's suggested mix);
    the default until 2026-11-29 (now :class:`LaplaceMove`). The snooker update is
    jaxlift's own (:class:`SnookerUpdate`), not emcee's ``DESnookerMove``, which does
    not sample the posterior (see there)."""

    name: ClassVar[str] = "de-snooker"
    uses_snooker: ClassVar[bool] = True
    de_weight: float = 0.8

    def emcee_moves(self, problem):
        return [
            (emcee.moves.DEMove(), self.de_weight),
            (SnookerUpdate(), 1.0 - self.de_weight),
        ]


class DEMove(AbstractMove):
    """Differential evolution alone."""

    name: ClassVar[str] = "de"

    def emcee_moves(self, problem):
        return emcee.moves.DEMove()


class StretchMove(AbstractMove):
    """emcee's own default, the affine-invariant stretch move."""

    name: ClassVar[str] = "stretch"

    def emcee_moves(self, problem):
        return emcee.moves.StretchMove()


class KDEMove(AbstractMove):
    """A Gaussian KDE of the complementary half of the ensemble as the proposal."""

    name: ClassVar[str] = "kde"

    def emcee_moves(self, problem):
        return emcee.moves.KDEMove()


class LaplaceMove(AbstractMove):
    """Differential evolution (with the snooker move, as :class:`DESnookerMove`) mixed
    with an independence Metropolis--Hastings proposal from the Laplace approximation;
    the default.

    With probability ``laplace_weight`` a step proposes, for every walker, a draw from
    a multivariate Student-t with ``nu`` degrees of freedom centred on the least-squares
    optimum ``problem.theta_opt`` with scale matrix ``scale**2 * problem.cov_theta``
    (the unconstrained coordinates' Laplace covariance: the fit's information plus the
    priors' curvature, nuisances marginalised), independent of where the walker is; it
    is accepted with the Metropolis--Hastings ratio ``p(x') q(x) / (p(x) q(x'))``. Both
    kinds of step leave the posterior invariant, so the mixture does too: the proposal
    decides only how fast the chain mixes, never what it converges to. The t's heavy
    tails and the 1.2x scale keep the ratio ``p / q`` bounded where the posterior is a
    little wider than its Laplace approximation; where it is much wider or not
    Gaussian, the independence steps are rarely accepted and the DE steps carry the
    chain (tau then stays near :class:`DESnookerMove`'s). The convergence rule (50
    tau, tau stable) is the same either way.

    Attributes:
        laplace_weight: probability of an independence step [-].
        nu: degrees of freedom of the t proposal [-].
        scale: factor on the Laplace standard deviations [-].
        de_weight: probability of DE (against snooker) within the other steps [-].
    """

    name: ClassVar[str] = "de-laplace"
    uses_snooker: ClassVar[bool] = True
    laplace_weight: float = 0.5
    nu: float = 5.0
    scale: float = 1.2
    de_weight: float = 0.8

    def __check_init__(self):
        if not 0.0 < self.laplace_weight < 1.0:
            raise ValueError(f"laplace_weight must be in (0, 1), not {self.laplace_weight}")
        if not (self.nu > 0.0 and self.scale > 0.0):
            raise ValueError(f"nu and scale must be positive, not {self.nu}, {self.scale}")

    def emcee_moves(self, problem):
        rest = 1.0 - self.laplace_weight
        proposal = _t_proposal(problem.theta_opt, problem.cov_theta, self.nu, self.scale)
        return [
            (emcee.moves.DEMove(), self.de_weight * rest),
            (SnookerUpdate(), (1.0 - self.de_weight) * rest),
            (emcee.moves.MHMove(proposal), self.laplace_weight),
        ]


def _t_proposal(mean, cov, nu: float, scale: float):
    """emcee's ``MHMove`` proposal function ``(coords, random) -> (new, log q(old) -
    log q(new))``: independent draws from a multivariate Student-t (``nu``, location
    ``mean``, scale matrix ``scale**2 cov``; random numbers from emcee's own seeded
    state, so a resumed chain is the uninterrupted one)."""
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    ndim = mean.shape[0]
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    if not np.all(np.isfinite(w)) or w.min() <= 0.0:
        raise ValueError(
            "the Laplace covariance is not positive definite (eigenvalues "
            f"{w.min():.3g} ... {w.max():.3g}): the de-laplace move needs one; use de-snooker"
        )
    root = v * (scale * np.sqrt(w))  # scale matrix = root @ root.T
    inv_root = (v / (scale * np.sqrt(w))).T

    def log_q(z):  # up to a constant, z whitened
        return -0.5 * (nu + ndim) * np.log1p(np.sum(z * z, axis=-1) / nu)

    def propose(coords, random):
        n = coords.shape[0]
        g = random.randn(n, ndim)
        u = random.chisquare(nu, size=n) / nu
        z = g / np.sqrt(u)[:, None]
        z_old = (np.asarray(coords) - mean) @ inv_root.T
        return mean + z @ root.T, log_q(z_old) - log_q(z)

    return propose


#: The moves by name (the command line's ``--move`` and stored chains use the names).
MOVES: dict[str, type[AbstractMove]] = {
    cls.name: cls for cls in (DESnookerMove, DEMove, StretchMove, KDEMove, LaplaceMove)
}
DEFAULT_MOVE = LaplaceMove.name
