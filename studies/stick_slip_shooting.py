"""Experiment: a multiple-shooting refit of stick-slip, to test whether it reaches the
optimum where the full-simulation refit stagnates (studies/DETECTION.md, "Stick-slip
from nominal").

Each fitted log is cut into windows of ``--window`` seconds. Every window is simulated
from a free start state (height, speed, pressure): the measurement residuals inside
the window, plus continuity residuals between the end of one window and the start of
the next. The free parameters are the motor set, the dynamic set and the stick-slip
pair (``dFs``, ``v_s``), on jaxlift's unconstrained scale, and the window starts (in
mm, cm/s and bar). The start states begin at the measured height and speed and at the
pressure of a full simulation of the starting model; ``--starts-only N`` first moves
only the starts for N iterations. Levenberg--Marquardt (Nielsen's damping rule) on the
block-structured Jacobian: each window's forward-mode Jacobian covers the physical
parameters and its own start only. At the end, the full-simulation chi2/N at the
shooting parameters (initial-height offsets refitted) says whether the result is an
optimum of the ordinary fit.

    python studies/stick_slip_shooting.py runs/detection/data/case_010 \\
        runs/detection/case_010/diagnosis/diagnosis.json --window 1 --dfs 1700 \\
        --vs 0.0035 --start truth --starts-only 15

``--start baseline`` starts from the diagnosis's baseline fit (``final_params`` of a
``none``/``unexplained`` diagnosis of the case), ``--start truth`` from the case's true
parameters with the baseline's bulk modulus (the start at which the full refit was
measured to stagnate), ``--exact`` with the true bulk modulus too (with ``--starts-only``
as large as ``--iters``: how well the window starts alone are found at the truth).
This is research code: the window simulations use jaxlift's private vector field and
step-size controllers.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.experiment import FAILED_RESIDUAL, make_experiments  # noqa: E402
from jaxlift.calibrate.fit import offsets_and_chi2n  # noqa: E402
from jaxlift.model.simulate import DEFAULT_ATOL, DTMAX, error_norm  # noqa: E402
from jaxlift.model.stepping import (  # noqa: E402
    JumpStepSizeController,
    StabilityLimitedController,
)
from jaxlift.model.vector_field import canonical_effects, lift_vector_field  # noqa: E402

FREE = ("k1", "k2", "k3", "z1", "z2", "z3", "beta", "cf_con", "cf_in", "cf_out", "d",
        "dFs", "v_s")  # fmt: skip
SHOWN = ("beta", "cf_con", "cf_in", "cf_out", "d", "dFs", "v_s")
#: units of the window starts in theta, and the scales of the continuity residuals:
#: height [m], speed [m/s], pressure [Pa]
START_UNITS = np.array([1e-3, 1e-2, 1e5])
CONTINUITY = np.array([1e-3, 1e-2, 1e5])


class Shooting:
    """The multiple-shooting least-squares problem of one case."""

    def __init__(self, logs, init: dict, window: float):
        self.effects = canonical_effects(jl.make_effects("stick_slip"))
        known = jl.all_param_infos(self.effects)
        self.infos = [known[n] for n in FREE]
        self.plant, self.effs = jl.with_params(jl.Plant(), self.effects, init)
        self.blocks = []
        for exp in make_experiments(logs):
            ts = np.asarray(exp.inputs.ts)
            n, nw = len(ts), int(round(window / (ts[1] - ts[0])))
            first = np.arange(0, n - 1, nw)
            idx = first[:, None] + np.arange(nw + 1)[None, :]
            mask = idx[:, :-1] <= n - 1  # the last window is padded with its last sample
            idx = np.minimum(idx, n - 1)
            y = np.asarray(exp.y)[:2].T
            self.blocks.append(dict(exp=exp, first=first, idx=jnp.asarray(idx), mask=mask,
                                    ym=jnp.asarray(y[idx[:, :-1]]),
                                    sig=jnp.asarray(np.asarray(exp.sigma)[:2])))  # fmt: skip
        self.phys0 = np.array([float(jl.to_unconstrained(i, init[i.name])) for i in self.infos])
        self.starts0 = []
        for b in self.blocks:
            sol = jl.simulate(self.plant, self.effs, b["exp"].inputs, stability_limit=False)
            x = np.maximum(np.asarray(b["exp"].y)[0], 0.0) + 1e-6
            v = np.asarray(b["exp"].y)[1]
            p = np.asarray(sol.ys)[:, 2]
            s = np.stack([x, v, p], axis=1)[b["first"]] / START_UNITS
            self.starts0.append(s)
        self.n_phys = len(self.phys0)
        self._res = jax.jit(self._window_residuals)
        self._jac = jax.jit(self._window_jacobians)

    # ------------------------------------------------------------ window simulations
    def _simulate(self, phys, s, t_idx, inputs):
        values = {i.name: jl.from_unconstrained(i, phys[k]) for k, i in enumerate(self.infos)}
        plant, effs = jl.with_params(self.plant, self.effs, values)
        ts = inputs.ts[t_idx]
        atol = jnp.asarray(DEFAULT_ATOL)
        inner = diffrax.PIDController(rtol=1e-6, atol=atol, dtmax=DTMAX, norm=error_norm)
        inner = StabilityLimitedController(inner, lift_vector_field, atol)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lift_vector_field), diffrax.Tsit5(), t0=ts[0], t1=ts[-1],
            dt0=None, y0=s * jnp.asarray(START_UNITS), args=(plant, effs, inputs),
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=JumpStepSizeController(inner, inputs.jump_ts),
            max_steps=50_000, adjoint=diffrax.ForwardMode(), throw=False,
        )  # fmt: skip
        return jnp.where(sol.result == diffrax.RESULTS.successful, sol.ys, jnp.nan)

    def _one(self, phys, s, t_idx, ym, sig, inputs):
        ys = self._simulate(phys, s, t_idx, inputs)
        r = (ys[:-1, :2] - ym) / sig
        return jnp.concatenate([r.reshape(-1), ys[-1] / jnp.asarray(CONTINUITY)])

    def _window_residuals(self, phys, S, idx, ym, sig, inputs):
        return jax.vmap(lambda s, i, y: self._one(phys, s, i, y, sig, inputs))(S, idx, ym)

    def _window_jacobians(self, phys, S, idx, ym, sig, inputs):
        def one(s, i, y):
            f = lambda ph, st: self._one(ph, st, i, y, sig, inputs)  # noqa: E731
            return f(phys, s), *jax.jacfwd(f, argnums=(0, 1))(phys, s)

        return jax.vmap(one)(S, idx, ym)

    # ------------------------------------------------------------ the whole problem
    def pack(self, phys, starts) -> np.ndarray:
        return np.concatenate([phys, *[s.reshape(-1) for s in starts]])

    def unpack(self, theta):
        out, o = [], self.n_phys
        for s in self.starts0:
            out.append(theta[o : o + s.size].reshape(s.shape))
            o += s.size
        return theta[: self.n_phys], out

    def residuals(self, theta, jacobian: bool = False):
        phys, starts = self.unpack(theta)
        rs, Js, o, n_th, P = [], [], self.n_phys, len(theta), self.n_phys
        link = np.diag(START_UNITS / CONTINUITY)
        for b, s in zip(self.blocks, starts):
            K, nw = b["ym"].shape[:2]
            args = (jnp.asarray(phys), jnp.asarray(s), b["idx"], b["ym"], b["sig"],
                    b["exp"].inputs)  # fmt: skip
            if jacobian:
                out, Jp, Jw = (np.asarray(a) for a in self._jac(*args))
            else:
                out = np.asarray(self._res(*args))
            m = np.repeat(b["mask"], 2, axis=1)
            end = out[:, 2 * nw :]
            rs += [out[:, : 2 * nw][m], (end[:-1] - s[1:] @ link).reshape(-1)]
            if jacobian:
                Jm = np.zeros((K, 2 * nw, n_th))
                Jm[:, :, :P] = Jp[:, : 2 * nw]
                Jc = np.zeros((K - 1, 3, n_th))
                Jc[:, :, :P] = Jp[:-1, 2 * nw :]
                for k in range(K):
                    Jm[k, :, o + 3 * k : o + 3 * k + 3] = Jw[k, : 2 * nw]
                    if k < K - 1:
                        Jc[k, :, o + 3 * k : o + 3 * k + 3] = Jw[k, 2 * nw :]
                        Jc[k, :, o + 3 * k + 3 : o + 3 * k + 6] = -link
                Js += [Jm[m], Jc.reshape(-1, n_th)]
            o += s.size
        r = np.concatenate(rs)
        return (r, np.concatenate(Js)) if jacobian else r

    def physical(self, theta) -> dict[str, float]:
        return {i.name: float(jl.from_unconstrained(i, theta[k])) for k, i in enumerate(self.infos)}


def damped_step(residuals, theta, r, J, lam: float, act=None):
    """One accepted Levenberg step from ``theta`` (residuals ``r``, Jacobian ``J``) over
    the columns ``act`` (default all), with absolute damping ``lam`` updated by
    Nielsen's rule: ``(new theta, new lam)``, or ``(None, lam)`` when no step lowers
    chi2. ``residuals(theta)`` marks a failed evaluation by a non-finite residual or one
    of jaxlift's ``FAILED_RESIDUAL``."""
    act = np.ones(len(theta), bool) if act is None else act
    Ja = J[:, act]
    g, A = Ja.T @ r, Ja.T @ Ja
    nu, old = 2.0, r @ r
    while lam < 1e12:
        step = np.zeros(len(theta))
        step[act] = np.linalg.solve(A + lam * np.eye(int(act.sum())), -g)
        rn = residuals(theta + step)
        failed = not np.all(np.isfinite(rn)) or np.any(rn == FAILED_RESIDUAL)
        new = np.inf if failed else rn @ rn
        if new < old:
            rho = (old - new) / max(-2 * step[act] @ g - step[act] @ A @ step[act], 1e-300)
            return theta + step, lam * max(1 / 3, 1 - (2 * rho - 1) ** 3)
        lam, nu = lam * nu, nu * 2
    return None, lam


def levenberg_marquardt(problem: Shooting, theta, iters: int, starts_only: int, t0: float):
    r, J = problem.residuals(theta, jacobian=True)
    print(f"start: chi2/N {r @ r / r.size:.3f} (N = {r.size}), {time.time() - t0:.0f} s",
          flush=True)  # fmt: skip
    lam = 1.0
    for it in range(iters):
        act = np.ones(len(theta), bool)
        act[: problem.n_phys] = it >= starts_only
        old = r @ r
        moved, lam = damped_step(problem.residuals, theta, r, J, lam, act)
        if moved is None:
            print("no step lowers chi2: stopped", flush=True)
            break
        theta = moved
        r, J = problem.residuals(theta, jacobian=True)
        shown = {k: f"{v:.4g}" for k, v in problem.physical(theta).items() if k in SHOWN}
        print(f"{it}: chi2/N {r @ r / r.size:.3f}, damping {lam:.1e}, {shown}, "
              f"{time.time() - t0:.0f} s", flush=True)  # fmt: skip
        if it >= starts_only and old - r @ r < 1e-5 * (r @ r):
            break
    return theta


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (its final_params)")
    ap.add_argument("--window", type=float, default=1.0, help="window length [s]")
    ap.add_argument("--dfs", type=float, default=1000.0, help="start of dFs [N]")
    ap.add_argument("--vs", type=float, default=0.01, help="start of v_s [m/s]")
    ap.add_argument("--start", choices=("baseline", "truth"), default="baseline")
    ap.add_argument("--reset", action="store_true", help="cf_con 10 N, d 300 N·s/m")
    ap.add_argument("--exact", action="store_true",
                    help="with --start truth: the true bulk modulus too")  # fmt: skip
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--starts-only", type=int, default=0)
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    base = json.loads(pathlib.Path(args.baseline).read_text())["final_params"]
    known = jl.all_param_infos(jl.make_effects("stick_slip"))
    init = {k: v for k, v in (truth if args.start == "truth" else base).items() if k in known}
    init.update(dFs=args.dfs, v_s=args.vs)
    if not args.exact:
        init.update(beta=base["beta"])
    if args.reset:
        init.update(cf_con=10.0, d=300.0)
    logs = [jl.read_log(case / "fit_1.csv"), jl.read_log(case / "fit_2.csv")]
    t0 = time.time()
    problem = Shooting(logs, init, args.window)
    theta = problem.pack(problem.phys0, problem.starts0)
    theta = levenberg_marquardt(problem, theta, args.iters, args.starts_only, t0)
    print("truth:", {k: f"{truth[k]:.4g}" for k in SHOWN})
    values = {**init, **problem.physical(theta)}
    _, chi2n = offsets_and_chi2n(values, ["stick_slip"], logs)
    print("full-simulation chi2/N at the shooting parameters:",
          {k: round(v, 3) for k, v in chi2n.items()}, flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
