"""Experiment: a stick-slip refit by the prediction-error method (an extended Kalman
filter on the model), then the ordinary fit from where it ends
(studies/DETECTION.md, eleventh sitting).

The least-squares cost of a strong stick-slip is rough because the model's slips drift
in time against the vehicle's and the errors of a whole log's slips add up. A Kalman
filter corrects the model's state at every sample from the measured height and speed
(process noise on the speed and the pressure), so its one-step predictions cannot drift;
the whitened innovations are smooth functions of the parameters. They are fitted by
Levenberg--Marquardt (13 parameters: motor set, dynamic set, ``dFs``, ``v_s``), and the
ordinary full-simulation chi2/N is measured at the end.

Discrete model: each sample interval is integrated by the library's own integrator
(Tsit5, its error control and stability limit) on the library's vector field
(``plant_signals_and_derivative``), duty and load held over the interval; the filter's
transition matrix is the forward-mode Jacobian of that map. (A fixed-step linearly
implicit method, ROS2, was tried first and fails at the onset of a slip: there the
Stribeck term makes the speed locally unstable, ~1 000 /s, and a linearly implicit step
across it flips the sign of the speed.)

    python studies/stick_slip_kalman.py runs/detection/data/case_010 \\
        runs/detection/case_010/diagnosis/diagnosis.json --dfs 1000 --vs 0.01
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.fit import offsets_and_chi2n  # noqa: E402
from jaxlift.model.simulate import DEFAULT_ATOL, DTMAX, error_norm  # noqa: E402
from jaxlift.model.stepping import StabilityLimitedController  # noqa: E402
from jaxlift.model.vector_field import (  # noqa: E402
    canonical_effects,
    initial_state,
    plant_signals_and_derivative,
)

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from stick_slip_shooting import damped_step  # noqa: E402

FREE = ("k1", "k2", "k3", "z1", "z2", "z3", "beta", "cf_con", "cf_in", "cf_out", "d",
        "dFs", "v_s")  # fmt: skip
SHOWN = ("beta", "cf_con", "cf_in", "cf_out", "d", "dFs", "v_s")
MAX_STEPS = 2048  # per sample interval


def held_field(t, y, args):
    plant, effects, u, m = args
    return plant_signals_and_derivative(t, y, plant, effects, u, m)[1]


def interval(plant, effects, u, m, t0, dt, y, atol):
    """``y`` after ``dt`` [s] with duty and load held: the library's integrator (Tsit5,
    error control as in ``simulate``, steps kept inside the stability region)."""
    inner = diffrax.PIDController(rtol=1e-6, atol=atol, dtmax=DTMAX, norm=error_norm)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(held_field), diffrax.Tsit5(), t0=t0, t1=t0 + dt, dt0=None, y0=y,
        args=(plant, effects, u, m),
        stepsize_controller=StabilityLimitedController(inner, held_field, atol),
        max_steps=MAX_STEPS, adjoint=diffrax.ForwardMode(), throw=False,
    )  # fmt: skip
    ok = sol.result == diffrax.RESULTS.successful
    return jnp.where(ok, sol.ys[-1], jnp.nan)


class Data(eqx.Module):
    ts: jax.Array
    pwm: jax.Array
    load: jax.Array
    z: jax.Array  # (N, 2): height, speed
    x0: jax.Array


def innovations(theta, infos, plant0, effects0, data: Data, q, r_diag):
    """Whitened innovations of the EKF on one log, (N-1, 2)."""
    values = {i.name: jl.from_unconstrained(i, theta[k]) for k, i in enumerate(infos)}
    plant, effects = jl.with_params(plant0, effects0, values)
    inputs = jl.Inputs.from_arrays(np.asarray(data.ts), np.asarray(data.pwm),
                                   np.asarray(data.load), data.x0)  # fmt: skip
    y0 = initial_state(plant, effects, inputs)
    n = y0.shape[0]
    scale = jnp.array([1e-3, 1e-3, 1e5] + [1.0] * (n - 3))  # work in scaled states
    atol = jnp.asarray(DEFAULT_ATOL)
    P0 = jnp.diag(jnp.array([1.0, 1.0, 1.0] + [1e-6] * (n - 3)))
    H = jnp.zeros((2, n)).at[0, 0].set(1.0).at[1, 1].set(1.0)
    R = jnp.diag(r_diag / scale[:2] ** 2)
    Q = jnp.diag(q / scale**2)

    def body(carry, k):
        s, P = carry
        t0, dt = data.ts[k], data.ts[k + 1] - data.ts[k]
        u, m = data.pwm[k], data.load[k]

        def phi(ss):
            return interval(plant, effects, u, m, t0, dt, ss * scale, atol) / scale

        s_pred, F = phi(s), jax.jacfwd(phi)(s)
        P_pred = F @ P @ F.T + Q
        e = data.z[k + 1] / scale[:2] - H @ s_pred
        S = H @ P_pred @ H.T + R
        L = jnp.linalg.cholesky(S)
        w = jax.scipy.linalg.solve_triangular(L, e, lower=True)
        K = jnp.linalg.solve(S, H @ P_pred).T
        s_new = s_pred + K @ e
        IKH = jnp.eye(n) - K @ H
        P_new = IKH @ P_pred @ IKH.T + K @ R @ K.T
        return (s_new, P_new), w

    _, ws = jax.lax.scan(body, (y0 / scale, P0), jnp.arange(data.ts.shape[0] - 1))
    return ws


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (its final_params)")
    ap.add_argument("--dfs", type=float, default=1000.0, help="start of dFs [N]")
    ap.add_argument("--vs", type=float, default=0.01, help="start of v_s [m/s]")
    ap.add_argument(
        "--qv",
        default="3e-3,1e-3,3e-4",
        help="process noise of the speed [m/s per sample], one per stage",
    )
    ap.add_argument("--qp", default="3e5,1e5,3e4",
                    help="process noise of the pressure [Pa per sample], per stage")  # fmt: skip
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--start", choices=("baseline", "truth"), default="baseline")
    ap.add_argument("--final-fit", action="store_true", help="then jaxlift's ordinary fit")
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    base = json.loads(pathlib.Path(args.baseline).read_text())["final_params"]
    effects = canonical_effects(jl.make_effects("stick_slip"))
    known = jl.all_param_infos(effects)
    infos = [known[n] for n in FREE]
    init = {k: v for k, v in (truth if args.start == "truth" else base).items() if k in known}
    if args.start == "baseline":
        init.update(dFs=args.dfs, v_s=args.vs)
    plant0, effs0 = jl.with_params(jl.Plant(), effects, init)
    logs = [jl.read_log(case / "fit_1.csv"), jl.read_log(case / "fit_2.csv")]
    mm = jl.MeasurementModel()
    datas = []
    for lg in logs:
        datas.append(Data(jnp.asarray(lg.time_s), jnp.asarray(lg.pwm), jnp.asarray(lg.load_kg),
                          jnp.stack([jnp.asarray(lg.height_m), jnp.asarray(lg.speed_mps)], 1),
                          jnp.asarray(jl.Inputs.from_log(lg).x0)))  # fmt: skip
    sig_v = float(mm.sigma_speed(logs[0].sample_period))
    r_diag = jnp.array([mm.sigma_height**2, sig_v**2])

    @jax.jit
    def res(theta, q):
        return jnp.concatenate([
            innovations(theta, infos, plant0, effs0, d, q, r_diag).ravel() for d in datas
        ])  # fmt: skip

    jac = jax.jit(jax.jacfwd(res))
    t0 = time.time()
    theta = np.array([float(jl.to_unconstrained(i, init[i.name])) for i in infos])
    stages = list(
        zip((float(v) for v in args.qv.split(",")), (float(v) for v in args.qp.split(",")))
    )
    for qv, qp in stages:
        q = jnp.array([0.0, qv**2, qp**2])

        def fun(th, q=q):
            return np.asarray(res(jnp.asarray(th), q))

        r = fun(theta)
        J = np.asarray(jac(jnp.asarray(theta), q))
        print(f"process noise {qv:g} m/s, {qp:g} Pa: PEM chi2/N {r @ r / r.size:.4f} "
              f"(N {r.size}), {time.time() - t0:.0f} s", flush=True)  # fmt: skip
        lam = 1.0
        for it in range(args.iters):
            old = r @ r
            moved, lam = damped_step(fun, theta, r, J, lam)
            if moved is None:
                print("  no step lowers the cost", flush=True)
                break
            theta = moved
            r = fun(theta)
            J = np.asarray(jac(jnp.asarray(theta), q))
            vals = {i.name: float(jl.from_unconstrained(i, theta[k])) for k, i in enumerate(infos)}
            print(f"  {it}: PEM chi2/N {r @ r / r.size:.4f}",
                  {k: f"{vals[k]:.4g}" for k in SHOWN}, f"{time.time() - t0:.0f} s",
                  flush=True)  # fmt: skip
            if old - r @ r < 1e-5 * (r @ r):
                break
    print("truth:", {k: f"{truth[k]:.4g}" for k in SHOWN})
    fitted = {i.name: float(jl.from_unconstrained(i, theta[k])) for k, i in enumerate(infos)}
    vals = {**init, **fitted}
    _, chi2n = offsets_and_chi2n(vals, ["stick_slip"], logs)
    print("full-simulation chi2/N:", {k: round(v, 4) for k, v in chi2n.items()}, flush=True)
    if args.final_fit:
        res_fit = jl.fit(logs, effects=["stick_slip"], free="all,effects", init=vals,
                         staged=False, n_starts=1, seed=0, workers=1)  # fmt: skip
        print("ordinary fit from there: chi2/N", res_fit.chi2 / res_fit.n_residuals,
              {k: f"{float(res_fit.params[k]):.4g}" for k in SHOWN}, f"{time.time() - t0:.0f} s",
              flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
