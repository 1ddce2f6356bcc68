"""The optimisers the tuner can use, as objects: pass one to
:func:`jaxlift.tune_gains` as ``optimiser=``.

- :class:`LevenbergMarquardt` (default): on the cost written as a sum of squares, with
  its forward-mode Jacobian through the closed loop (one tangent per gain). Measured
  on the 110 s reference (``benchmarks/results_tune.txt``): converges in about 10
  evaluations where L-BFGS on the same cost stalls.
- :class:`LBFGS`: ``scipy.optimize.minimize(method="L-BFGS-B", jac=True)`` driven by
  the JAX value and gradient.
- :class:`Adam`: optax's Adam on the log gains.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx

Gradient = Literal["auto", "forward", "reverse"]


class LevenbergMarquardt(eqx.Module):
    """Levenberg--Marquardt on the tuning residuals.

    Attributes:
        ftol: stop when a full Gauss--Newton step would lower the objective by less than
            this fraction of it.
        trials: how a trial point is evaluated: ``"jacobian"`` (with the Jacobian: one
            compiled function, and an accepted trial needs no second simulation; best
            when compilation dominates, few gains), ``"residuals"`` (a plain simulation,
            the Jacobian only where a step is accepted: a rejected trial then costs one
            simulation instead of ``1 + n_gains`` tangents, for a second compilation) or
            ``"auto"``: ``"jacobian"`` up to 8 gains, else ``"residuals"``.
    """

    ftol: float = 1e-3
    trials: Literal["auto", "jacobian", "residuals"] = "auto"


class LBFGS(eqx.Module):
    """L-BFGS-B (SciPy) on the cost and its JAX gradient.

    Attributes:
        gradient: ``"forward"`` (``jax.jacfwd`` with ``diffrax.ForwardMode``; one tangent
            per gain: measured 4.5x a simulation for the plain PID's 5 gains),
            ``"reverse"`` (``RecursiveCheckpointAdjoint``; cost independent of the
            number of gains, more to compile) or ``"auto"``: forward up to 8 gains.
    """

    gradient: Gradient = "auto"


class Adam(eqx.Module):
    """optax's Adam on the log gains.

    Attributes:
        learning_rate: step in log-gain units.
        gradient: as for :class:`LBFGS`.
    """

    learning_rate: float = 0.08
    gradient: Gradient = "auto"
