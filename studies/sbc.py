"""Simulation-based calibration (SBC; Talts et al. 2018) of jaxlift's sampler on a cheap
surrogate problem: does the sampling machinery itself give calibrated posteriors?

The coverage study (``studies/coverage.py``) runs the whole chain fit -> posterior on
the lift model, minutes per data set. When it misses, the miss may come from the model
(linearised nuisances, the AR(1) likelihood, priors) or from the sampler (its start
around the least-squares optimum, the DE-snooker move, the stop at 50 tau, the burn-in
and thinning of ``posterior_samples``). SBC separates the two: on a problem whose
posterior is exactly the one the sampler targets, with the truth drawn *from the prior*,
the rank of the truth among the posterior draws is uniform if and only if the sampler
is right (for every parameter; Talts et al.). Anything non-uniform is the sampler's.

The surrogate is the lift's dominant physics in closed form: the step response of a
damped second-order system (the hydraulic mode), ``y(t) = K (1 - e^{-z w t} (cos(w_d t)
+ z w / w_d sin(w_d t)))``, ``w_d = w sqrt(1 - z^2)``, observed for 4 s at 50 Hz with
AR(1) noise (rho 0.6, innovation sd 0.02, known) -- the likelihood the lift's posterior
uses. Three parameters in unconstrained coordinates: ``log w`` (frequency, prior
N(log 2 pi 2 Hz, 0.3)), ``logit z`` (damping ratio, N(logit 0.1, 0.5)), ``log K`` (gain,
N(0, 0.1)). The sampler is the production one: ``sample_posterior`` (walkers started
around the MAP from its Laplace covariance, the default move, stopped at 50 tau) and
``posterior_samples`` (burn 3 tau, thin 0.5 tau); from its draws ``L = 99`` are taken at
random (seeded) and the truth's rank among them recorded.

Resumable (one JSON per replicate)::

    python studies/sbc.py run --out runs/sbc --n 200
    python studies/sbc.py report --out runs/sbc --to studies/results/sbc

``--move`` picks the proposal (default: ``sample_posterior``'s, ``de-laplace``: the DE
moves mixed with independence proposals from the Laplace approximation); the results
of ``de-laplace`` are in ``studies/results/sbc``, those of ``de-snooker`` (with
jaxlift's snooker update) in ``studies/results/sbc_de_snooker``. The results before
2026-11-29 were of ``de-snooker`` with emcee's biased snooker update, which this
3-parameter check did not detect (a 3-dimensional Gaussian's standard deviations come
out about 2 % short with that mix; 200 replicates resolve some 10 %).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import optimize, stats  # noqa: E402

from jaxlift.posterior.moves import DEFAULT_MOVE, MOVES  # noqa: E402
from jaxlift.posterior.sampler import posterior_samples, sample_posterior  # noqa: E402

NAMES = ("log_w", "logit_z", "log_K")
PRIOR_MEAN = np.array([math.log(2 * math.pi * 2.0), math.log(0.1 / 0.9), 0.0])
PRIOR_SD = np.array([0.3, 0.5, 0.1])
T = np.arange(0.0, 4.0, 0.02)
RHO, SIGMA = 0.6, 0.02
L_DRAWS = 99
N_WALKERS = 16


def response(theta: jnp.ndarray) -> jnp.ndarray:
    w, z, k = jnp.exp(theta[0]), jax.nn.sigmoid(theta[1]), jnp.exp(theta[2])
    wd = w * jnp.sqrt(1.0 - z**2)
    decay = jnp.exp(-z * w * T)
    return k * (1.0 - decay * (jnp.cos(wd * T) + z * w / wd * jnp.sin(wd * T)))


def _log_post_one(theta, y):
    r = y - response(theta)
    e = r[1:] - RHO * r[:-1]  # AR(1) innovations; the first residual stationary
    s0 = SIGMA / math.sqrt(1.0 - RHO**2)
    ll = -0.5 * jnp.sum((e / SIGMA) ** 2) - 0.5 * (r[0] / s0) ** 2
    lp = -0.5 * jnp.sum(((theta - PRIOR_MEAN) / PRIOR_SD) ** 2)
    out = ll + lp
    return jnp.where(jnp.isfinite(out), out, -jnp.inf)


_batch = jax.jit(jax.vmap(_log_post_one, in_axes=(0, None)))
_one = jax.jit(_log_post_one)
_grad = jax.jit(jax.grad(_log_post_one))
_hess = jax.jit(jax.hessian(_log_post_one))


@dataclasses.dataclass
class SurrogateProblem:
    """What ``sample_posterior`` and ``posterior_samples`` read of a posterior problem:
    the dimension, the optimum and covariance that start the walkers, and the map to
    reported coordinates (here the unconstrained ones themselves)."""

    theta_opt: np.ndarray
    cov_theta: np.ndarray

    @property
    def ndim(self) -> int:
        return self.theta_opt.size

    def to_physical(self, theta) -> dict[str, np.ndarray]:
        theta = np.asarray(theta)
        return {n: theta[..., i] for i, n in enumerate(NAMES)}


def replicate(i: int, out: pathlib.Path, move: str = DEFAULT_MOVE) -> dict:
    rng = np.random.default_rng(10_000 + i)
    truth = PRIOR_MEAN + PRIOR_SD * rng.standard_normal(3)
    e = SIGMA * rng.standard_normal(T.size)
    noise = np.empty(T.size)
    noise[0] = e[0] / math.sqrt(1.0 - RHO**2)
    for k in range(1, T.size):
        noise[k] = RHO * noise[k - 1] + e[k]
    y = np.asarray(response(jnp.asarray(truth))) + noise
    yj = jnp.asarray(y)
    opt = optimize.minimize(
        lambda th: -float(_one(jnp.asarray(th), yj)),
        PRIOR_MEAN,
        jac=lambda th: -np.asarray(_grad(jnp.asarray(th), yj)),
        method="BFGS",
    )
    cov = np.linalg.inv(-np.asarray(_hess(jnp.asarray(opt.x), yj)))
    cov = 0.5 * (cov + cov.T)
    problem = SurrogateProblem(np.asarray(opt.x), cov)
    chain = out / f"chain_{i:04d}.h5"
    chain.unlink(missing_ok=True)
    t0 = time.perf_counter()
    run = sample_posterior(
        problem, chain, n_walkers=N_WALKERS, max_steps=20_000, seed=i, move=MOVES[move](),
        log_prob=lambda th: np.asarray(_batch(jnp.asarray(th), yj)),
    )  # fmt: skip
    draws, _, thin = posterior_samples(problem, chain, run.tau)
    pool = np.stack([draws[n].ravel() for n in NAMES], axis=1)
    pick = rng.choice(pool.shape[0], size=L_DRAWS, replace=False)
    ranks = (pool[pick] < truth).sum(axis=0)
    chain.unlink()
    return {
        "replicate": i, "truth": truth.tolist(), "map": opt.x.tolist(),
        "ranks": ranks.tolist(), "converged": run.converged, "steps": run.iteration,
        "tau_max": float(np.max(run.tau)), "pool": int(pool.shape[0]), **thin,
        "move": run.move, "acceptance": run.acceptance,
        "wall_s": time.perf_counter() - t0,
        # central-interval coverage from the whole pool (not only the L draws)
        "in50": [bool(np.quantile(pool[:, j], 0.25) <= truth[j] <= np.quantile(pool[:, j], 0.75))
                 for j in range(3)],
        "in90": [bool(np.quantile(pool[:, j], 0.05) <= truth[j] <= np.quantile(pool[:, j], 0.95))
                 for j in range(3)],
    }  # fmt: skip


def cmd_run(args) -> None:
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i in range(args.n):
        path = out / f"rep_{i:04d}.json"
        if path.exists():
            continue
        rec = replicate(i, out, args.move)
        path.write_text(json.dumps(rec) + "\n")
        print(f"rep {i}: ranks {rec['ranks']} steps {rec['steps']} "
              f"({rec['wall_s']:.1f} s)", flush=True)  # fmt: skip


def _binom_ci(k: int, n: int) -> tuple[float, float]:
    """95 % Clopper-Pearson interval of a proportion."""
    lo = stats.beta.ppf(0.025, k, n - k + 1) if k > 0 else 0.0
    hi = stats.beta.ppf(0.975, k + 1, n - k) if k < n else 1.0
    return float(lo), float(hi)


def cmd_report(args) -> None:
    out, to = pathlib.Path(args.out), pathlib.Path(args.to)
    to.mkdir(parents=True, exist_ok=True)
    recs = [json.loads(p.read_text()) for p in sorted(out.glob("rep_*.json"))]
    n = len(recs)
    if n == 0:
        sys.exit(f"{out}: no replicates yet (run first)")
    ranks = np.array([r["ranks"] for r in recs])  # (n, 3), each in 0..L
    bins = 10
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2), constrained_layout=True)
    rows = []
    for j, name in enumerate(NAMES):
        counts = np.histogram(ranks[:, j], bins=bins, range=(0, L_DRAWS + 1))[0]
        expected = n / bins
        chi2 = float(np.sum((counts - expected) ** 2 / expected))
        p = float(stats.chi2.sf(chi2, bins - 1))
        ax = axes[j]
        ax.bar(np.arange(bins), counts, width=0.9, color="C0")
        lo, hi = stats.binom.ppf([0.005, 0.995], n, 1 / bins)
        ax.axhspan(lo, hi, color="0.85", zorder=0, label="99 % band, uniform")
        ax.axhline(expected, color="0.4", lw=0.8)
        ax.set_title(f"{name}: chi2 p = {p:.2f}", fontsize=9)
        ax.set_xlabel(f"rank of the truth among {L_DRAWS} draws (binned)")
        k50 = sum(r["in50"][j] for r in recs)
        k90 = sum(r["in90"][j] for r in recs)
        rows.append((name, p, k50, _binom_ci(k50, n), k90, _binom_ci(k90, n)))
    axes[0].set_ylabel("replicates")
    axes[0].legend(fontsize=7)
    fig.savefig(to / "sbc_ranks.png", dpi=110)
    wall = np.median([r["wall_s"] for r in recs])
    conv = sum(r["converged"] for r in recs)
    moves = sorted({r.get("move", "de-snooker") for r in recs})
    steps = np.median([r["steps"] for r in recs])
    taus = np.median([r["tau_max"] for r in recs])
    lines = [
        "# Simulation-based calibration of the sampler (surrogate problem)",
        "",
        f"{n} replicates (truth drawn from the prior, seeds 10000 + i); {conv} of {n} "
        f"chains reached 50 tau; median {wall:.1f} s per replicate on this machine, "
        f"median {steps:.0f} steps and max tau {taus:.1f} steps; move {', '.join(moves)}. "
        f"Method and surrogate: `studies/sbc.py`.",
        "",
        "| parameter | rank uniformity (chi2, 10 bins) p | 50 % interval covers | "
        "95 % CI | 90 % interval covers | 95 % CI |",
        "|---|---:|---:|---|---:|---|",
    ]
    for name, p, k50, c50, k90, c90 in rows:
        lines.append(
            f"| `{name}` | {p:.2f} | {k50}/{n} ({k50 / n:.0%}) | {c50[0]:.0%}-{c50[1]:.0%} | "
            f"{k90}/{n} ({k90 / n:.0%}) | {c90[0]:.0%}-{c90[1]:.0%} |"
        )
    lines += ["", "![SBC rank histograms](sbc_ranks.png)", ""]
    (to / "sbc.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--out", default="runs/sbc")
    r.add_argument("--n", type=int, default=200)
    r.add_argument("--move", default=DEFAULT_MOVE, choices=sorted(MOVES), help="emcee proposal")
    r.set_defaults(func=cmd_run)
    p = sub.add_parser("report")
    p.add_argument("--out", default="runs/sbc")
    p.add_argument("--to", default="studies/results/sbc")
    p.set_defaults(func=cmd_report)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
