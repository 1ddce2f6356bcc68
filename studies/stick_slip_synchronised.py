"""Experiment: a stick-slip refit through simulations pulled towards the data
(``jaxlift.Nudging``), at decreasing gains, then the ordinary simulation
(studies/DETECTION.md, seventh sitting).

At each gain of ``--gains`` (1/s, the last normally 0: the model itself), a
Levenberg--Marquardt fit of the motor set, the dynamic set and the stick-slip pair
(``dFs``, ``v_s``) on jaxlift's unconstrained scale, with plain (absolute) damping
starting at 1 and Nielsen's update, at most ``--iters`` accepted steps, each gain
starting where the previous one ended. The initial-height offsets are not fitted. At
the end, the full-simulation chi2/N (offsets fitted) at the parameters reached.

    python studies/stick_slip_synchronised.py runs/detection/data/case_010 \\
        runs/detection/case_010/diagnosis/diagnosis.json --dfs 1000 --vs 0.01

The residuals and Jacobians are those of the fit's own problem
(``jaxlift.calibrate.problem.Problem`` with ``nudge_gain``).
``jaxlift.fit(..., synchronise=...)`` does the same with jaxlift's own
Levenberg--Marquardt loop (damping scaled by the Jacobian, 30 trial steps per gain,
offsets fitted): on the case above it did *not* reach the optimum (DETECTION.md), so
the path through the gains matters.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.experiment import make_experiments  # noqa: E402
from jaxlift.calibrate.fit import offsets_and_chi2n  # noqa: E402
from jaxlift.calibrate.problem import Problem  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from stick_slip_shooting import damped_step  # noqa: E402

FREE = ("k1", "k2", "k3", "z1", "z2", "z3", "beta", "cf_con", "cf_in", "cf_out", "d",
        "dFs", "v_s")  # fmt: skip
SHOWN = ("beta", "cf_con", "cf_in", "cf_out", "d", "dFs", "v_s")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (its final_params)")
    ap.add_argument("--dfs", type=float, default=1000.0, help="start of dFs [N]")
    ap.add_argument("--vs", type=float, default=0.01, help="start of v_s [m/s]")
    ap.add_argument("--gains", default="10,3,1,0.3,0.1,0", help="pull gains [1/s]")
    ap.add_argument("--iters", type=int, default=15, help="accepted steps per gain")
    ap.add_argument("--start", choices=("baseline", "truth"), default="baseline",
                    help="truth: the true parameters with the baseline's bulk modulus")  # fmt: skip
    ap.add_argument("--reset", action="store_true", help="cf_con 10 N, d 300 N·s/m")
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    base = json.loads(pathlib.Path(args.baseline).read_text())["final_params"]
    effects = jl.make_effects("stick_slip")
    known = jl.all_param_infos(effects)
    infos = [known[n] for n in FREE]
    init = {k: v for k, v in (truth if args.start == "truth" else base).items() if k in known}
    init.update(dFs=args.dfs, v_s=args.vs, beta=base["beta"])
    if args.reset:
        init.update(cf_con=10.0, d=300.0)
    plant0, effs0 = jl.with_params(jl.Plant(), effects, init)
    logs = [jl.read_log(case / "fit_1.csv"), jl.read_log(case / "fit_2.csv")]
    # the fit's own least-squares problem (no initial-height offsets), pulled at each gain
    problem = Problem(plant0, effs0, tuple(make_experiments(logs)), FREE, tuple(infos),
                      sim_max_steps=400_000, fit_x0=False)  # fmt: skip

    def evaluate(phys, gain, jacobian=False):
        pulled = dataclasses.replace(problem, nudge_gain=gain)
        return pulled.jacobian_at(phys) if jacobian else pulled.residuals_at(phys)

    t0 = time.time()
    phys = np.array([float(jl.to_unconstrained(i, init[i.name])) for i in infos])
    for gain in (float(g) for g in args.gains.split(",")):
        r, J = evaluate(phys, gain, jacobian=True)
        print(f"gain {gain:g}/s: start chi2/N {r @ r / r.size:.3f}, {time.time() - t0:.0f} s",
              flush=True)  # fmt: skip
        lam = 1.0
        for it in range(args.iters):
            old = r @ r
            moved, lam = damped_step(lambda th: evaluate(th, gain), phys, r, J, lam)  # noqa: B023
            if moved is None:
                print("  no step lowers chi2", flush=True)
                break
            phys = moved
            r, J = evaluate(phys, gain, jacobian=True)
            vals = {i.name: float(jl.from_unconstrained(i, phys[k])) for k, i in enumerate(infos)}
            print(f"  {it}: chi2/N {r @ r / r.size:.4f}",
                  {k: f"{vals[k]:.4g}" for k in SHOWN}, f"{time.time() - t0:.0f} s",
                  flush=True)  # fmt: skip
            if old - r @ r < 1e-4 * (r @ r):
                break
    print("truth:", {k: f"{truth[k]:.4g}" for k in SHOWN})
    vals = {
        **init,
        **{i.name: float(jl.from_unconstrained(i, phys[k])) for k, i in enumerate(infos)},
    }
    _, chi2n = offsets_and_chi2n(vals, ["stick_slip"], logs)
    print("full-simulation chi2/N:", {k: round(v, 4) for k, v in chi2n.items()}, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
