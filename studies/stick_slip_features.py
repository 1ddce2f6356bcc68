"""Experiment: a stick-slip refit started from a search on per-cycle features
(studies/DETECTION.md, eleventh sitting).

A least-squares fit of a strong stick-slip stagnates unless it starts very near the
optimum (its surface is rough: every slip's timing moves with every parameter). The
slips' *statistics per cycle* do not depend on their timing, can be read from a noisy
log, and (unlike the section statistics of the ninth sitting) tell the breakaway force
from the Stribeck speed. So:

1. In each section of constant duty (at least 5 s) of each fitted log: the number of
   slips per second, the median peak speed and the median duration of a slip (a slip:
   a run of samples above ``--threshold``, the speed smoothed over 3 samples).
2. A grid over ``dFs`` and ``v_s`` (Coulomb friction and damping at their nominal
   values, everything else at the baseline fit), then Nelder--Mead over ``dFs``,
   ``v_s``, ``d``, ``cf_con`` (and ``beta`` with ``--with-beta``), both on the features'
   squared relative errors (3 % for frequency and peak, 10 % for duration; a section
   without slips in the log asks for none in the model).
3. jaxlift's ordinary fit (all 13 parameters, one start) from the best point.

    python studies/stick_slip_features.py runs/detection/data/case_045 \\
        runs/detection/case_045/diagnosis/diagnosis.json

The simulations are jaxlift's (``jaxlift.simulate``, no noise); the features of the
log and of the model are computed by the same function.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import numpy as np  # noqa: E402
import scipy.optimize as so  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.fit import offsets_and_chi2n  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from stick_slip_moments import sections as section_ranges  # noqa: E402

SHOWN = ("beta", "cf_con", "cf_in", "cf_out", "d", "dFs", "v_s")
#: relative errors the features are weighed by: frequency, peak speed, duration
REL = np.array([0.03, 0.03, 0.10])
MIN_SECTION_S = 5.0
DFS_GRID = (100.0, 200.0, 400.0, 700.0, 1000.0, 1500.0, 2200.0, 3000.0)  # N
VS_GRID = (0.002, 0.003, 0.0045, 0.007, 0.01, 0.015, 0.02)  # m/s


def features(speed: np.ndarray, idx: np.ndarray, dt: float, threshold: float) -> np.ndarray:
    """(slips per second, median peak speed [m/s], median slip duration [s]) of a section."""
    v = np.convolve(speed, np.ones(3) / 3, mode="same")[idx]
    up = v > threshold
    starts = np.nonzero(up[1:] & ~up[:-1])[0] + 1
    rate = starts.size / (idx.size * dt)
    if starts.size < 3:
        return np.array([rate, 0.0, 0.0])
    peaks, durations = [], []
    for s in starts:
        e = s
        while e < v.size and up[e]:
            e += 1
        peaks.append(v[s:e].max())
        durations.append((e - s) * dt)
    return np.array([rate, np.median(peaks), np.median(durations)])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (its final_params)")
    ap.add_argument("--threshold", type=float, default=0.012, help="slip speed [m/s]")
    ap.add_argument("--with-beta", action="store_true", help="search beta too")
    ap.add_argument("--max-evals", type=int, default=150, help="Nelder-Mead evaluations")
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    base = json.loads(pathlib.Path(args.baseline).read_text())["final_params"]
    effects = jl.make_effects("stick_slip")
    known = jl.all_param_infos(effects)
    start = {k: v for k, v in base.items() if k in known}
    start.update(cf_con=known["cf_con"].nominal, d=known["d"].nominal)
    logs = [jl.read_log(case / "fit_1.csv"), jl.read_log(case / "fit_2.csv")]
    for lg in logs:
        if lg.speed_mps is None:
            ap.error(f"{lg.name}: the slip features need a speed column (speed_mps)")
    inputs = [jl.Inputs.from_log(lg) for lg in logs]
    # each section of constant, positive duty of at least MIN_SECTION_S, whole
    secs = [
        [np.arange(a, b) for a, b in section_ranges(lg, min_s=MIN_SECTION_S, skip_s=0.0)]
        for lg in logs
    ]
    measured = [
        [features(lg.speed_mps, i, lg.sample_period, args.threshold) for i in ss]
        for lg, ss in zip(logs, secs)
    ]
    print("the logs' features (slips/s, peak m/s, duration s):",
          [[np.round(f, 4).tolist() for f in fs] for fs in measured], flush=True)  # fmt: skip

    def cost(values) -> float:
        plant, effs = jl.with_params(jl.Plant(), effects, values)
        c = 0.0
        for lg, inp, ss, fs in zip(logs, inputs, secs, measured):
            sol = jl.simulate(plant, effs, inp)
            if not bool(sol.ok):
                return np.inf
            v = np.asarray(sol.speed)
            for idx, f in zip(ss, fs):
                g = features(v, idx, lg.sample_period, args.threshold)
                if f[0] * MIN_SECTION_S >= 3:  # the log slips here
                    c += float(np.sum(((g - f) / (REL * f)) ** 2))
                else:  # no slips in the log: none in the model (0.1 /s as one sigma)
                    c += float((g[0] / 0.1) ** 2)
        return c

    t0 = time.time()
    print(f"cost at the truth: {cost({k: truth[k] for k in known}):.1f}", flush=True)
    grid = []
    for dfs, vs in itertools.product(DFS_GRID, VS_GRID):
        grid.append((cost({**start, "dFs": dfs, "v_s": vs}), dfs, vs))
    grid.sort()
    print("grid, best three (cost, dFs, v_s):", grid[:3], f"{time.time() - t0:.0f} s", flush=True)
    names = ["dFs", "v_s", "d", "cf_con"] + (["beta"] if args.with_beta else [])
    x0 = np.log([grid[0][1], grid[0][2], start["d"], start["cf_con"]]
                + ([start["beta"]] if args.with_beta else []))  # fmt: skip
    simplex = np.vstack([x0, x0 + 0.15 * np.eye(len(names))])
    res = so.minimize(
        lambda x: cost({**start, **dict(zip(names, np.exp(x)))}), x0, method="Nelder-Mead",
        options=dict(maxfev=args.max_evals, initial_simplex=simplex, xatol=0.01, fatol=0.5),
    )  # fmt: skip
    found = {**start, **dict(zip(names, np.exp(res.x)))}
    shown = {k: f"{found[k]:.4g}" for k in names}
    print(f"Nelder-Mead: cost {res.fun:.1f} after {res.nfev} simulations,", shown,
          f"{time.time() - t0:.0f} s", flush=True)  # fmt: skip
    _, chi2n = offsets_and_chi2n(found, ["stick_slip"], logs)
    print("full-simulation chi2/N there:", {k: round(v, 3) for k, v in chi2n.items()}, flush=True)
    fit = jl.fit(logs, effects=["stick_slip"], free="all,effects", init=found, staged=False,
                 n_starts=1, seed=0)  # fmt: skip
    shown = {k: f"{float(fit.params[k]):.4g}" for k in SHOWN}
    print(f"ordinary fit from there: chi2/N {fit.chi2 / fit.n_residuals:.4f},", shown,
          f"{time.time() - t0:.0f} s")  # fmt: skip
    print("truth:                  ", {k: f"{truth[k]:.4g}" for k in SHOWN}, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
