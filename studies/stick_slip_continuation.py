"""Experiment: a stick-slip refit by continuation in the breakaway force
(studies/DETECTION.md, eighth sitting).

``dFs`` is held at a rising, log-spaced sequence of values; at each, every other
parameter of the model with stick-slip (the Stribeck speed ``v_s`` included) is
refitted by ``jaxlift.fit`` from the optimum of the value before, starting from the
baseline's fit. Then ``dFs`` is freed too, from the best point of the path::

    python studies/stick_slip_continuation.py runs/detection/data/case_010 \\
        runs/detection/case_010/diagnosis/diagnosis.json --dfs 30,3000 --steps 9

The idea: if the optimum at a fixed breakaway force moves continuously with it, the
path leads from the baseline (``dFs`` = 0) to the optimum. Measured on case_010, it does
not (the Coulomb friction and the damping keep carrying the breakaway force, and the
fit gets worse as ``dFs`` grows).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import jaxlift as jl  # noqa: E402

SHOWN = ("v_s", "cf_con", "d", "beta")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (final_params, no effect)")
    ap.add_argument("--dfs", default="30,3000", help="first and last dFs held [N]")
    ap.add_argument("--steps", type=int, default=9, help="values of dFs on the path")
    ap.add_argument("--vs", type=float, default=0.005, help="start of v_s [m/s]")
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    logs = [jl.read_log(str(case / f"fit_{k}.csv")) for k in (1, 2)]
    diag = json.loads(pathlib.Path(args.baseline).read_text())
    if diag["final_effects"]:
        raise SystemExit(f"{args.baseline}: the final model has effects {diag['final_effects']}")
    print("truth", {k: truth.get(k) for k in ("dFs", *SHOWN)}, flush=True)
    lo, hi = (float(v) for v in args.dfs.split(","))
    init = {**diag["final_params"], "v_s": args.vs}
    path = []
    for k in range(args.steps):
        dfs = math.exp(math.log(lo) + k * (math.log(hi) - math.log(lo)) / max(args.steps - 1, 1))
        init["dFs"] = dfs
        t0 = time.perf_counter()
        res = jl.fit(logs, effects=["stick_slip"], free="all,v_s", init=init, staged=False,
                     n_starts=1, seed=0, workers=1)  # fmt: skip
        chi2n = res.chi2 / res.n_residuals
        if math.isfinite(chi2n):
            init = dict(res.params)
            path.append((chi2n, dict(res.params)))
        shown = {n: round(float(res.params[n]), 4) for n in SHOWN}
        print(f"dFs {dfs:8.1f} N: chi2/N {chi2n:9.4f} {shown} "
              f"{time.perf_counter() - t0:.0f} s", flush=True)  # fmt: skip
    chi2n, best = min(path, key=lambda cp: cp[0])
    res = jl.fit(logs, effects=["stick_slip"], free="all,effects", init=best, staged=False,
                 n_starts=1, seed=0, workers=1)  # fmt: skip
    shown = {n: round(float(res.params[n]), 4) for n in ("dFs", *SHOWN)}
    print(f"dFs freed from the best of the path: chi2/N {res.chi2 / res.n_residuals:.4f} {shown}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
