"""Priors on the sampled parameters: log-normal and uniform, explicit and physical, with
the Jacobian of the unconstrained transform.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float
from scipy.stats import norm

from ..model.constants import BETA_OIL
from ..model.params import ParameterError, ParamInfo


# ------------------------------------------------------------------ priors
class LogNormal(eqx.Module):
    """Log-normal prior: ``log(x) ~ Normal(log(median), log(factor))``.

    ``median`` is in the parameter's unit; ``factor`` is the multiplicative one-sigma
    spread (``factor = 3``: 68 % of the prior mass within ``median / 3 … median * 3``).
    Truncated to the parameter's bounds (the normalising constant is irrelevant for
    MCMC). ``reason`` says why this prior."""

    median: float
    factor: float
    reason: str = ""

    def log_pdf(self, x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        """Log-density at ``x`` (physical units), up to a constant; ``-inf`` for x <= 0."""
        s = math.log(self.factor)
        xs = jnp.where(x > 0, x, 1.0)
        z = (jnp.log(xs) - math.log(self.median)) / s
        lp = -0.5 * z**2 - jnp.log(xs) - math.log(s) - 0.5 * math.log(2 * math.pi)
        return jnp.where(x > 0, lp, -jnp.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws (physical units)."""
        return self.median * np.exp(math.log(self.factor) * rng.standard_normal(n))

    def quantiles(self, q: ArrayLike) -> np.ndarray:
        """Quantiles (physical units, untruncated)."""

        return self.median * np.exp(math.log(self.factor) * norm.ppf(np.asarray(q)))

    def describe(self, unit: str = "") -> str:
        return f"log-normal, median {self.median:.4g} {unit}, x/÷ {self.factor:g} (1 sigma)"


class Uniform(eqx.Module):
    """Uniform prior on ``[lower, upper]`` (physical units); ``reason`` says why."""

    lower: float
    upper: float
    reason: str = ""

    def log_pdf(self, x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        inside = (x >= self.lower) & (x <= self.upper)
        return jnp.where(inside, -math.log(self.upper - self.lower), -jnp.inf)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.uniform(self.lower, self.upper, n)

    def quantiles(self, q: ArrayLike) -> np.ndarray:
        return self.lower + (self.upper - self.lower) * np.asarray(q)

    def describe(self, unit: str = "") -> str:
        return f"uniform on [{self.lower:.4g}, {self.upper:.4g}] {unit}"


Prior = LogNormal | Uniform

#: The priors of the dynamic set and of the noise factors (physical units).
DEFAULT_PRIORS: dict[str, Prior] = {
    "beta": LogNormal(
        BETA_OIL, 3.0, "ideal oil (1.4 GPa) as the centre; air, hoses and seals can only "
        "soften it, by up to an order of magnitude in practice: x/÷ 3"
    ),
    "cf_con": LogNormal(10.0, 10.0, "Coulomb friction of the cylinder seals, nominal 10 N; "
                        "a few N to a few hundred N: x/÷ 10"),
    "cf_in": LogNormal(16.0, 3.0, "speed scale of the fifth-power friction, nominal 16 s/m; "
                       "only cf_out * cf_in^5 is seen in the data, so this prior decides "
                       "how the product is split: x/÷ 3"),
    "cf_out": LogNormal(545.0, 10.0, "fifth-power friction coefficient, nominal 545 N: "
                        "x/÷ 10"),
    "d": LogNormal(300.0, 10.0, "viscous damping, nominal 300 N s/m: x/÷ 10"),
    "noise_height": LogNormal(1.0, 2.0, "factor on the height noise scale: x/÷ 2 around 1"),
    "noise_speed": LogNormal(1.0, 2.0, "factor on the speed noise scale: x/÷ 2 around 1"),
    "noise_pressure": LogNormal(1.0, 2.0, "factor on the pressure noise scale: x/÷ 2"),
}  # fmt: skip


def default_prior(info: ParamInfo) -> Prior:
    """The prior of a parameter: :data:`DEFAULT_PRIORS` where listed; an effect parameter
    log-normal around its typical size ``info.scale`` (its nominal is the nesting value
    0) x/÷ 10; another positive parameter log-normal around its nominal x/÷ 2; a
    parameter with two finite bounds and a logit transform uniform on its bounds."""
    if info.name in DEFAULT_PRIORS:
        return DEFAULT_PRIORS[info.name]
    if info.nesting is not None and info.scale is not None and info.nominal == info.nesting:
        return LogNormal(
            float(info.scale), 10.0, f"effect parameter: around its typical size "
            f"{info.scale:g} {info.unit}, x/÷ 10 (the nesting value {info.nesting:g} "
            "is approached, not excluded)"
        )  # fmt: skip
    if info.transform == "log" and info.nominal > 0:
        return LogNormal(float(info.nominal), 2.0, "around the nominal value, x/÷ 2")
    if math.isfinite(info.lower) and math.isfinite(info.upper):
        return Uniform(float(info.lower), float(info.upper), "uniform on the bounds")
    raise ParameterError(f"parameter {info.name!r}: no default prior; give one")


def log_abs_det_jac(info: ParamInfo, theta: Float[Array, ""]) -> Float[Array, ""]:
    """``log |d x / d theta|`` of :func:`from_unconstrained`."""
    if info.transform == "log":
        return theta
    if info.transform == "logit":
        return math.log(info.upper - info.lower) - jax.nn.softplus(-theta) - jax.nn.softplus(theta)
    return jnp.zeros_like(theta)


def prior_to_json(p: Prior) -> dict:
    d = {"kind": type(p).__name__}
    d.update({f.name: getattr(p, f.name) for f in dataclasses.fields(p)})
    return d


def prior_from_json(d: Mapping) -> Prior:
    d = dict(d)
    cls = {"LogNormal": LogNormal, "Uniform": Uniform}[d.pop("kind")]
    return cls(**d)
