"""The emcee sampler: initial walkers, moves, the HDF5 chain with resume, and the
convergence rule (chain longer than 50 autocorrelation times).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable

import emcee
import numpy as np
from jaxtyping import ArrayLike, Float
from tqdm.auto import tqdm

from .likelihood import EmceeLogProb, make_log_prob
from .moves import MOVES, AbstractMove, LaplaceMove
from .problem import PosteriorProblem

# ------------------------------------------------------------------ the chain file
#: How long an access to the chain file waits for another process's lock on it (HDF5
#: locks a file while it is open: a reader such as h5py, ArviZ or a second ``jaxlift
#: posterior`` that opens the chain while it runs) before giving up [s].
LOCK_WAIT_S = 120.0


class ChainFileLocked(RuntimeError):
    """The chain's HDF5 file stayed locked by another process for :data:`LOCK_WAIT_S`;
    the steps written before are kept, and the same call resumes from them."""


class _ChainBackend(emcee.backends.HDFBackend):
    """emcee's HDF5 backend, patient with locks: emcee opens the file for every step it
    stores, and HDF5 refuses (``BlockingIOError``, errno 11) while another process has it
    open; a chain must not die of someone looking at it (a coverage run's chain did, of
    a script reading its progress). Waits with growing pauses up to
    :data:`LOCK_WAIT_S`, then raises :class:`ChainFileLocked` naming the file."""

    def open(self, mode="r"):
        waited, pause = 0.0, 0.05
        while True:
            try:
                return super().open(mode)
            except BlockingIOError as exc:
                if waited >= LOCK_WAIT_S:
                    raise ChainFileLocked(
                        f"{self.filename}: the chain file stayed locked by another process "
                        f"for {waited:.0f} s (a program reading it while the chain runs: "
                        "open it with h5py.File(path, 'r', locking=False), or wait); the "
                        "steps stored so far are kept, and running the same command again "
                        "resumes from them"
                    ) from exc
                time.sleep(pause)
                waited += pause
                pause = min(2 * pause, 2.0)


# ------------------------------------------------------------------ sampling
@dataclasses.dataclass
class SamplerRun:
    """Where an emcee run stands.

    Attributes:
        path: the HDF5 chain.
        iteration: steps in the chain.
        tau: integrated autocorrelation time of each coordinate [steps] (emcee,
            ``tol=0``: an estimate even on a short chain).
        converged: chain longer than ``tau_factor`` x max tau with tau stable.
        resumed_from: steps that were already in the chain when this run began.
        acceptance: mean acceptance fraction.
        wall_s: wall time of this run [s]; n_evals: log-probability evaluations.
        tau_history: ``(iteration, max tau)`` at each check.
        move: the name of the emcee proposal (:data:`~jaxlift.posterior.moves.MOVES`).
        n_devices: devices the walkers were split across.
        move_settings: what the move chose before sampling
            (:meth:`~jaxlift.posterior.moves.AbstractMove.settings`; de-laplace: its
            independence weight and the check it came from).
    """

    path: str
    iteration: int
    tau: np.ndarray
    converged: bool
    resumed_from: int
    acceptance: float
    wall_s: float
    n_evals: int
    tau_history: list[tuple[int, float]]
    tau_factor: float
    n_walkers: int
    move: str = "stretch"
    n_devices: int = 1
    move_settings: dict = dataclasses.field(default_factory=dict)


#: Stored with every new chain: which snooker update its moves use. Chains without it
#: that use a snooker move were sampled with emcee's biased one and are not resumed.
SNOOKER_REVISION = "ter Braak & Vrugt 2008 (jaxlift.posterior.moves.SnookerUpdate)"

#: The fewest walkers :func:`auto_walkers` gives.
MIN_AUTO_WALKERS = 16


def auto_walkers(ndim: int) -> int:
    """An ensemble size for ``ndim`` sampled coordinates: ``2 ndim + 4``, at least
    :data:`MIN_AUTO_WALKERS`, rounded up to a multiple of 4 (each half of the ensemble
    splits evenly across two devices).

    Why not more: with the differential-evolution moves the autocorrelation time in
    *steps* does not depend on the ensemble size (measured on an 8-dimensional
    Gaussian, the report's posterior's size, three seeds each: tau 32.3, 32.0, 29.8,
    29.2 and 29.6 steps with 16, 20, 24, 32 and 48 walkers; the shipped logs' posterior
    with 32 walkers: 30.6), so the chain must be 50 tau long whatever the ensemble and
    the time to convergence grows in proportion to it. What more walkers buy is
    effective samples, about ``walkers x (50 - 3)`` per parameter at convergence
    (burn-in of 3 tau discarded): 940 with 20 walkers, above the 400 that ArviZ asks of
    a summary's interval ends. Why not fewer: emcee needs at least ``2 ndim``, and the
    DE move's differences of the other half's walkers span that half's affine hull
    only, so a half of ``ndim`` walkers would be on the edge."""
    if ndim < 1:
        raise ValueError(f"ndim must be positive, not {ndim}")
    n = max(MIN_AUTO_WALKERS, 2 * int(ndim) + 4)
    return -(-n // 4) * 4


def _initial_coords(problem: PosteriorProblem, n_walkers: int, seed: int, f) -> np.ndarray:
    """Walkers drawn around the least-squares optimum from its covariance (seeded);
    draws with -inf log-probability are redrawn (up to 20 rounds)."""
    rng = np.random.default_rng(seed)
    cov = problem.cov_theta
    coords = rng.multivariate_normal(problem.theta_opt, cov, size=n_walkers, method="eigh")
    for _ in range(20):
        lp = EmceeLogProb(f, max(n_walkers // 2, 1))(coords)
        bad = ~np.isfinite(lp)
        if not bad.any():
            _check_independent(problem, coords)
            return coords
        coords[bad] = rng.multivariate_normal(
            problem.theta_opt, 0.25 * cov, size=int(bad.sum()), method="eigh"
        )
    raise ValueError(
        "could not start the walkers: the log-probability is -inf around the least-squares "
        "optimum (solver failures or prior support); check the calibration"
    )


def _check_independent(problem: PosteriorProblem, coords: np.ndarray) -> None:
    """emcee's own test of the starting ensemble (its stretch and snooker moves never
    leave the walkers' affine hull), with a message that says where the covariance
    came from and how it is broken."""
    if emcee.ensemble.walkers_independent(coords):
        return
    sd = np.sqrt(np.maximum(np.diag(problem.cov_theta), 0.0))
    raise ValueError(
        "could not start the walkers: the Laplace covariance at the least-squares optimum "
        "is degenerate (standard deviations in the unconstrained coordinates: "
        + ", ".join(f"{n} {v:.3g}" for n, v in zip(problem.names, sd))
        + "), so the walkers are not linearly independent. The Jacobian there is not "
        "trustworthy (a simulation whose sensitivities exploded, or a parameter at a "
        "bound); check the calibration"
    )


def sample_posterior(
    problem: PosteriorProblem,
    chain_path: str | os.PathLike,
    *,
    n_walkers: int = 32,
    max_steps: int = 20_000,
    seed: int = 0,
    chunk: int = 50,
    tau_factor: float = 50.0,
    batch: str = "map",
    move: AbstractMove | None = None,
    devices: int | None = None,
    log_prob: Callable | None = None,
    progress: bool | Callable[[int], None] = False,
) -> SamplerRun:
    """Run (or resume) emcee's ensemble sampler into an HDF5 file until converged.

    Args:
        problem: from :func:`prepare_posterior`.
        chain_path: HDF5 file (emcee ``HDFBackend``, group ``mcmc``). If it holds steps,
            the run resumes from the last one: emcee stores its random state with every
            step, so an interrupted and resumed run gives the same chain, bit for bit,
            as an uninterrupted one with the same seed.
        n_walkers: ensemble size (even, > 2 x number of sampled coordinates).
        max_steps: step limit (total, including resumed steps); reaching it first
            means "not converged".
        seed: seeds the initial walkers (numpy ``Generator``) and emcee's random state.
        chunk: steps between convergence checks (at absolute multiples of ``chunk``).
        tau_factor: converged when steps > ``tau_factor`` x max tau and every tau
            changed by less than 5 % since the previous check.
        batch: how the log-probability goes over the walkers (:func:`make_log_prob`).
        move: the emcee proposal (:mod:`jaxlift.posterior.moves`; None:
            ``LaplaceMove()``), stored with the chain by name: a resumed chain must use
            the move it was started with.
        devices: devices the walkers are split across (:func:`make_log_prob`).
        log_prob: a ready :func:`make_log_prob` function (saves a compile).
        progress: show a tqdm progress bar (``True``), or a callable called with the
            iteration after each step (may raise to stop the run).

    Returns:
        A :class:`SamplerRun`.
    """

    ndim = problem.ndim
    if n_walkers < 2 * ndim or n_walkers % 2:
        raise ValueError(f"n_walkers must be even and at least {2 * ndim}, not {n_walkers}")
    move = LaplaceMove() if move is None else move
    if not isinstance(move, AbstractMove):
        known = ", ".join(c.__name__ + "()" for c in MOVES.values())
        raise TypeError(f"move must be a jaxlift move ({known}), not {move!r}")
    f = log_prob or make_log_prob(problem, batch=batch, devices=devices)
    lp_fn = EmceeLogProb(f, n_walkers // 2)
    backend = _ChainBackend(os.fspath(chain_path), name="mcmc")
    start = backend.iteration if os.path.exists(chain_path) and backend.initialized else 0
    if start > 0:
        with backend.open() as fh:  # chains from before the choice: the stretch move
            stored_move = str(fh["mcmc"].attrs.get("jaxlift_move", "stretch"))
            snooker = str(fh["mcmc"].attrs.get("jaxlift_snooker", ""))
            stored_settings = json.loads(str(fh["mcmc"].attrs.get("jaxlift_move_settings", "{}")))
        if stored_move != move.name:
            raise ValueError(
                f"{chain_path}: the stored chain was run with the {stored_move!r} move, "
                f"this run asks for {move.name!r}; resume with the same move"
            )
        if move.uses_snooker and snooker != SNOOKER_REVISION:
            raise ValueError(
                f"{chain_path}: the stored chain was sampled with emcee's DESnookerMove, "
                "which does not converge to the posterior (its intervals come out too "
                "narrow; jaxlift.posterior.moves.SnookerUpdate); delete the file to start "
                "a new chain"
            )
        if backend.shape != (n_walkers, ndim):
            raise ValueError(
                f"{chain_path}: the stored chain has {backend.shape} (walkers, parameters), "
                f"this run asks for {(n_walkers, ndim)}"
            )
        state = backend.get_last_sample()  # coords, log_prob and emcee's random state
        if state.random_state is None:
            raise ValueError(f"{chain_path}: the chain has no stored random state")
        move = move.with_settings(stored_settings)
    else:
        # choices the move makes before sampling (de-laplace: its independence weight,
        # from a seeded check of its proposal), made once and stored with the chain
        move = move.settle(problem, lp_fn, seed)
        backend.reset(n_walkers, ndim)
        with backend.open("a") as fh:
            fh["mcmc"].attrs["jaxlift_move"] = move.name
            fh["mcmc"].attrs["jaxlift_snooker"] = SNOOKER_REVISION
            fh["mcmc"].attrs["jaxlift_move_settings"] = json.dumps(move.settings())
        coords = _initial_coords(problem, n_walkers, seed, f)
        state = emcee.State(coords, random_state=np.random.RandomState(seed).get_state())
    moves = move.emcee_moves(problem)
    sampler = emcee.EnsembleSampler(
        n_walkers, ndim, lp_fn, vectorize=True, backend=backend, moves=moves
    )
    it = start
    t0 = time.perf_counter()
    bar = tqdm(total=max_steps, initial=it, desc="MCMC", unit="step", disable=progress is not True)
    tau = np.full(ndim, np.nan)
    tau_prev = None
    history: list[tuple[int, float]] = []
    converged = False
    try:
        if it > 0:
            tau, converged, tau_prev = _check(backend, it, tau_factor, None)
        while it < max_steps and not converged:
            n = min(chunk - it % chunk, max_steps - it)
            for st in sampler.sample(
                state, iterations=n, store=True, skip_initial_state_check=it > 0
            ):
                state = st
                it += 1
                bar.update(1)
                if callable(progress):
                    progress(it)
            tau, converged, tau_prev = _check(backend, it, tau_factor, tau_prev)
            history.append((it, float(np.max(tau))))
            bar.set_postfix(tau=f"{np.max(tau):.0f}", need=f"{tau_factor * np.max(tau):.0f}")
    finally:
        bar.close()
    acc = float(np.mean(backend.accepted / max(backend.iteration, 1)))
    return SamplerRun(
        path=os.fspath(chain_path),
        iteration=it,
        tau=tau,
        converged=converged,
        resumed_from=start,
        acceptance=acc,
        wall_s=time.perf_counter() - t0,
        n_evals=lp_fn.n_evals,
        tau_history=history,
        tau_factor=tau_factor,
        n_walkers=n_walkers,
        move=move.name,
        n_devices=getattr(f, "n_devices", 1),
        move_settings=move.settings(),
    )


def _check(backend, it, tau_factor, tau_prev):
    with np.errstate(invalid="ignore"):  # a walker that has not moved yet: tau NaN
        tau = np.asarray(backend.get_autocorr_time(tol=0), dtype=float)
    stable = tau_prev is not None and bool(np.all(np.abs(tau - tau_prev) < 0.05 * tau))
    converged = bool(np.all(np.isfinite(tau)) and it > tau_factor * np.max(tau) and stable)
    return tau, converged, tau


def chain_status(chain_path: str | os.PathLike, tau_factor: float = 50.0) -> dict:
    """Steps, tau and convergence of a stored chain (read-only)."""

    b = _ChainBackend(os.fspath(chain_path), name="mcmc", read_only=True)
    it = b.iteration
    tau = np.asarray(b.get_autocorr_time(tol=0), dtype=float)
    return {"iteration": it, "tau": tau, "enough": bool(it > tau_factor * np.max(tau))}


def posterior_samples(
    problem: PosteriorProblem,
    chain_path: str | os.PathLike,
    tau: Float[ArrayLike, " P"],
    *,
    burn_factor: float = 3.0,
    thin_factor: float = 0.5,
) -> tuple[dict[str, np.ndarray], np.ndarray, dict]:
    """Physical samples from the stored chain, burn-in discarded and thinned.

    Burn-in: ``burn_factor`` x max tau steps (at most half the chain); thinning every
    ``thin_factor`` x min tau steps. Returns ``({name: (walkers, draws)}, log_prob
    (walkers, draws), {"burn": .., "thin": ..})``."""

    b = _ChainBackend(os.fspath(chain_path), name="mcmc", read_only=True)
    tau = np.asarray(tau, dtype=float)
    it = b.iteration
    burn = int(min(math.ceil(burn_factor * np.nanmax(tau)), it // 2))
    thin = max(1, int(thin_factor * np.nanmin(tau)))
    chain = b.get_chain(discard=burn, thin=thin)  # (draws, walkers, P)
    lp = b.get_log_prob(discard=burn, thin=thin)
    phys = problem.to_physical(np.swapaxes(chain, 0, 1))
    return phys, np.swapaxes(lp, 0, 1), {"burn": burn, "thin": thin}
