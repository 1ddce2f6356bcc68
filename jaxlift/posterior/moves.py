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
import dataclasses
import math
from collections.abc import Callable
from typing import ClassVar

import emcee
import equinox as eqx
import numpy as np
from arviz_stats.base import array_stats

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

    def settle(
        self, problem: PosteriorProblem, log_prob: Callable[[np.ndarray], np.ndarray], seed: int
    ) -> AbstractMove:
        """The move with the choices it makes before a new chain starts (from the
        problem and a few seeded log-probability evaluations ``log_prob(thetas (B, P))
        -> (B,)``), so that every step of the chain uses the same kernel. Default: no
        choice, the move itself."""
        return self

    def settings(self) -> dict[str, float]:
        """What :meth:`settle` chose, stored with the chain (``{}``: nothing)."""
        return {}

    def with_settings(self, stored: dict[str, float]) -> AbstractMove:
        """The move a resumed chain was sampled with, from its stored :meth:`settings`
        (the check is not repeated: the resumed chain is the uninterrupted one)."""
        return self


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
    little wider than its Laplace approximation.

    Where the posterior is far from that approximation (a model that misses physics,
    a parameter against its bound: the shipped logs' baseline model), the independence
    steps are mostly rejected and every one of them is a step the chain does not move:
    at a fixed weight of 0.5 that chain needed 2 350 steps against de-snooker's 1 550.
    So by default (``laplace_weight=None``) the weight is chosen once, before the chain
    starts (:meth:`settle`), from how well the proposal covers the posterior: ``n_check``
    draws from the proposal (seeded), their importance ratios ``p / q``, and the Pareto
    k-hat of those ratios (PSIS, ArviZ's ``psislw``; Vehtari et al. 2024) with their
    relative effective sample size ``(sum w)^2 / (n sum w^2)`` after smoothing
    (:func:`laplace_coverage`). :func:`independence_weight` maps them to the weight:
    0.5 where the proposal is good, down to 0.05 where k-hat says the ratios have no
    usable variance. The choice is stored with the chain; a resumed chain reuses it.
    The convergence rule (50 tau, tau stable) is the same either way.

    Attributes:
        laplace_weight: probability of an independence step [-]; None: chosen before
            sampling (see above).
        nu: degrees of freedom of the t proposal [-].
        scale: factor on the Laplace standard deviations [-].
        de_weight: probability of DE (against snooker) within the other steps [-].
        n_check: proposal draws of the check that chooses the weight [-].
        pareto_khat, ess_fraction: what that check measured (None before it ran, or
            when the weight was given).
    """

    name: ClassVar[str] = "de-laplace"
    uses_snooker: ClassVar[bool] = True
    laplace_weight: float | None = None
    nu: float = 5.0
    scale: float = 1.2
    de_weight: float = 0.8
    n_check: int = 256
    pareto_khat: float | None = None
    ess_fraction: float | None = None

    def __check_init__(self):
        if self.laplace_weight is not None and not 0.0 < self.laplace_weight < 1.0:
            raise ValueError(f"laplace_weight must be in (0, 1), not {self.laplace_weight}")
        if not (self.nu > 0.0 and self.scale > 0.0):
            raise ValueError(f"nu and scale must be positive, not {self.nu}, {self.scale}")
        if self.n_check < 32:
            raise ValueError(f"n_check must be at least 32, not {self.n_check}")

    def settle(self, problem, log_prob, seed):
        if self.laplace_weight is not None:
            return self
        khat, ess = laplace_coverage(
            problem, log_prob, seed=seed, n_draws=self.n_check, nu=self.nu, scale=self.scale
        )
        return dataclasses.replace(
            self, laplace_weight=independence_weight(khat, ess), pareto_khat=khat,
            ess_fraction=ess,
        )  # fmt: skip

    def settings(self):
        if self.laplace_weight is None:
            raise ValueError("the weight is chosen by settle(), which has not run")
        out = {"laplace_weight": float(self.laplace_weight)}
        if self.pareto_khat is not None:
            out |= {"pareto_khat": float(self.pareto_khat),
                    "ess_fraction": float(self.ess_fraction)}  # fmt: skip
        return out

    def with_settings(self, stored):
        # chains from before the choice (2026-11-29 to 2026-12-01) ran at 0.5
        w = float(stored.get("laplace_weight", 0.5))
        if self.laplace_weight is not None and not math.isclose(w, self.laplace_weight):
            raise ValueError(
                f"the stored chain was sampled with laplace_weight {w:g}, this run asks "
                f"for {self.laplace_weight:g}; resume with the same weight"
            )
        return dataclasses.replace(
            self, laplace_weight=w, pareto_khat=stored.get("pareto_khat"),
            ess_fraction=stored.get("ess_fraction"),
        )  # fmt: skip

    def emcee_moves(self, problem):
        if self.laplace_weight is None:
            raise ValueError("the weight is chosen by settle(), which has not run")
        rest = 1.0 - self.laplace_weight
        proposal = _t_proposal(problem.theta_opt, problem.cov_theta, self.nu, self.scale)
        return [
            (emcee.moves.DEMove(), self.de_weight * rest),
            (SnookerUpdate(), (1.0 - self.de_weight) * rest),
            (emcee.moves.MHMove(proposal), self.laplace_weight),
        ]


def laplace_coverage(
    problem: PosteriorProblem,
    log_prob: Callable[[np.ndarray], np.ndarray],
    *,
    seed: int,
    n_draws: int = 256,
    nu: float = 5.0,
    scale: float = 1.2,
) -> tuple[float, float]:
    """How well :class:`LaplaceMove`'s proposal covers the posterior: ``n_draws`` draws
    from it (``numpy`` generator seeded with ``[seed, 1]``), their log importance ratios
    ``log p - log q``, and from those the Pareto k-hat of the ratios' right tail and the
    relative effective sample size ``(sum w)^2 / (n sum w^2)`` of the Pareto-smoothed
    ratios (ArviZ's ``psislw``). A draw whose log-probability is -inf (outside the
    priors' support, or a failed simulation) has ratio 0. Returns ``(khat, ess)``;
    ``(inf, 0)`` when fewer than a quarter of the draws have a finite ratio, and
    ``(-inf, share of finite ratios)`` when the finite ratios are all equal (nothing to
    fit a tail to: the proposal is the posterior, or its draws have collapsed onto one
    point, which the walkers' start then reports)."""
    propose = _t_proposal(problem.theta_opt, problem.cov_theta, nu, scale)
    rng = np.random.default_rng([int(seed), 1])
    # the proposal's draws from emcee's RandomState interface, seeded from rng
    rs = np.random.RandomState(rng.integers(0, 2**31 - 1))
    # proposing from the centre, the proposal's own factor log q(centre) - log q(new)
    # is -log q(new) (log q is 0 at the centre, up to the constant that cancels)
    draws, factor = propose(np.tile(problem.theta_opt, (n_draws, 1)), rs)
    lw = np.asarray(log_prob(draws), dtype=np.float64) + factor
    finite = np.isfinite(lw)
    if finite.sum() < n_draws / 4:
        return math.inf, 0.0
    lw_f = lw[finite] - np.max(lw[finite])
    if np.ptp(lw_f) == 0.0:  # equal ratios: the proposal is the posterior (no tail to fit)
        return -math.inf, float(finite.mean())
    # psislw takes the negative log ratios (its use in LOO: minus the log-likelihood)
    smoothed, khat = array_stats.psislw(-lw_f)
    w = np.zeros(n_draws)
    w[finite] = np.exp(np.asarray(smoothed) - np.max(smoothed))
    ess = float(np.sum(w) ** 2 / (n_draws * np.sum(w * w)))
    khat = float(khat)
    return (khat if np.isfinite(khat) else math.inf), ess


#: :func:`independence_weight`'s settings: the weight where the proposal is good, the
#: least weight, and the k-hat above which the importance ratios have no usable variance.
WEIGHT_GOOD, WEIGHT_LEAST, KHAT_BAD = 0.5, 0.05, 0.7


def independence_weight(khat: float, ess: float) -> float:
    """:class:`LaplaceMove`'s probability of an independence step from the check of its
    proposal (:func:`laplace_coverage`): ``2 ess - 0.1`` within [:data:`WEIGHT_LEAST`,
    :data:`WEIGHT_GOOD`], and :data:`WEIGHT_LEAST` when ``khat`` is at least
    :data:`KHAT_BAD` (the ratios' variance is unusable, so is ``ess``).

    Measured on the 6-dimensional Gaussian of ``tests/test_moves.py`` (20 walkers, the
    proposal's standard deviations f times too wide and too narrow, alternately; tau
    in steps, the mean of two seeds of 6 000 steps; 256 draws in the check):

    | f    | khat  | ess   | w=0  | 0.05 | 0.1  | 0.25 | 0.5  | chosen |
    |------|-------|-------|------|------|------|------|------|--------|
    | 1    | -0.15 | 0.63  | 24.8 | 17.0 | 14.2 | 8.8  | 5.2  | 0.5    |
    | 1.25 | 0.36  | 0.31  | 24.8 | 20.7 | 18.5 | 15.1 | 13.4 | 0.5    |
    | 1.5  | 0.47  | 0.10  | 25.7 | 24.1 | 22.1 | 23.8 | 29.0 | 0.11   |
    | 2    | 0.91  | 0.025 | 24.0 | 25.4 | 26.0 | 29.9 | 42.1 | 0.05   |
    | 3    | 3.8   | 0.004 | 24.5 | 24.8 | 27.1 | 34.9 | 48.5 | 0.05   |

    (w = 0: the DE + snooker mix alone.) The shipped logs' baseline model, which misses
    physics, checks at khat 0.60-0.80 and ess 0.06-0.10 (three seeds): weight 0.05-0.1,
    where a fixed 0.5 had needed 2 350 steps against de-snooker's 1 550."""
    if np.isnan(khat) or khat >= KHAT_BAD:
        return WEIGHT_LEAST
    return float(np.clip(2.0 * ess - 0.1, WEIGHT_LEAST, WEIGHT_GOOD))


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
