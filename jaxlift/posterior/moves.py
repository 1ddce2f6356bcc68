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

A move's :attr:`~AbstractMove.name` is stored with the chain: a chain resumes only
with the move it was started with.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import emcee
import equinox as eqx


class AbstractMove(eqx.Module):
    """An emcee proposal with a stable name (stored with the chain)."""

    name: ClassVar[str]

    @abc.abstractmethod
    def emcee_moves(self):
        """emcee's ``moves`` argument."""


class DESnookerMove(AbstractMove):
    """Differential evolution mixed with the DE snooker move (emcee's suggested mix);
    the default."""

    name: ClassVar[str] = "de-snooker"
    de_weight: float = 0.8

    def emcee_moves(self):
        return [
            (emcee.moves.DEMove(), self.de_weight),
            (emcee.moves.DESnookerMove(), 1.0 - self.de_weight),
        ]


class DEMove(AbstractMove):
    """Differential evolution alone."""

    name: ClassVar[str] = "de"

    def emcee_moves(self):
        return emcee.moves.DEMove()


class StretchMove(AbstractMove):
    """emcee's own default, the affine-invariant stretch move."""

    name: ClassVar[str] = "stretch"

    def emcee_moves(self):
        return emcee.moves.StretchMove()


class KDEMove(AbstractMove):
    """A Gaussian KDE of the complementary half of the ensemble as the proposal."""

    name: ClassVar[str] = "kde"

    def emcee_moves(self):
        return emcee.moves.KDEMove()


#: The moves by name (the command line's ``--move`` and stored chains use the names).
MOVES: dict[str, type[AbstractMove]] = {
    cls.name: cls for cls in (DESnookerMove, DEMove, StretchMove, KDEMove)
}
DEFAULT_MOVE = DESnookerMove.name
