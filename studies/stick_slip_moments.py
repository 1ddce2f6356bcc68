"""Experiment: a stick-slip pre-fit on statistics of the speed that do not depend on
the slips' timing (studies/DETECTION.md, ninth sitting), then a synchronised fit.

The least-squares cost of a stick-slip log is rugged because a model that slips a
little earlier or later than the vehicle is charged for every sample in between. The
speed's *statistics* in each long constant-duty section do not depend on that timing:
its quantiles (in units of the speed noise), its RMS, the centroid and band powers of
its spectrum (0.2--5 Hz) and the share of time it is near zero. The simulated speed
gets the log's noise added (one fixed draw, so the cost is a deterministic function of
the parameters). Steps:

1. a grid over ``dFs``, ``v_s``, ``d``, ``cf_con`` (the baseline's bulk modulus);
2. a local least-squares refinement (scipy, finite differences on the log scale) of
   those four and ``beta`` from the best grid points;
3. ``jaxlift.fit(..., synchronise=...)`` from the best refined point.

    python studies/stick_slip_moments.py runs/detection/data/case_010 \\
        runs/detection/case_010/diagnosis/diagnosis.json

Measured on case_010 (DETECTION.md): the statistics find the right kind of model
(a breakaway force of about 1 kN, small damping and Coulomb friction) but not the
point: ``dFs`` and ``v_s`` lie on a ridge of equal statistics, and the synchronised
fit from there does not reach the optimum.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402
import scipy.optimize as so  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.fit import estimate_x0_offsets, offsets_and_chi2n  # noqa: E402
from jaxlift.model.effects.stick_slip import constant_duty_sections  # noqa: E402

NAMES = ("dFs", "v_s", "d", "cf_con", "beta")
QUANTILES = (0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95)
BANDS_HZ = ((0.2, 0.5), (0.5, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 3.0), (3.0, 5.0))
GRID = {
    "dFs": (100, 300, 1000, 3000),
    "v_s": (0.002, 0.005, 0.01, 0.03),
    "d": (100, 300, 1000, 3000),
    "cf_con": (10, 100, 300),
}
LOWER = np.log([1.0, 1e-4, 1.0, 0.1, 1e8])
UPPER = np.log([1e5, 0.2, 1e5, 1e4, 5e9])


def sections(log: jl.Log, min_s: float = 3.0, skip_s: float = 1.0) -> list[tuple[int, int]]:
    """Sample ranges of the constant, positive-duty sections at least ``min_s`` long,
    without their first ``skip_s`` (the start transient)."""
    skip = int(skip_s / float(log.sample_period))
    ranges = constant_duty_sections(np.asarray(log.pwm), float(log.sample_period), min_s)
    return [(a + skip, b) for a, b in ranges]


def statistics(speeds, secs, dt: float, sig_v: float) -> np.ndarray:
    """The timing-free statistics of each section (weighted by its length)."""
    f = []
    for v, ranges in zip(speeds, secs):
        for a, b in ranges:
            w = v[a:b]
            sc = np.sqrt((b - a) / 1000.0)
            c = w - w.mean()
            P = np.abs(np.fft.rfft(c * np.hanning(len(c)))) ** 2
            fr = np.fft.rfftfreq(len(c), dt)
            m = (fr > 0.2) & (fr < 5.0)
            tot = np.sum(P[m])
            f += list(np.quantile(w, QUANTILES) / sig_v * sc)
            f.append(10.0 * np.sum(fr[m] * P[m]) / tot * sc)
            f += [
                10.0 * np.sqrt(np.sum(P[(fr >= lo) & (fr < hi)]) / tot) * sc for lo, hi in BANDS_HZ
            ]
            f.append(np.sqrt(np.mean(c**2)) / sig_v * sc)
            f.append(10.0 * np.mean(w < 2e-3) * sc)
    return np.asarray(f)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (final_params, no effect)")
    ap.add_argument("--refine", type=int, default=3, help="grid points refined")
    ap.add_argument("--gains", default="10,3,1,0.3,0.1", help="synchronised fit's gains [1/s]")
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    base = json.loads(pathlib.Path(args.baseline).read_text())["final_params"]
    logs = [jl.read_log(str(case / f"fit_{k}.csv")) for k in (1, 2)]
    offsets = estimate_x0_offsets(base, [], logs)
    effects = jl.make_effects("stick_slip")
    known = jl.all_param_infos(effects)
    sig_v = float(jl.MeasurementModel().sigmas(logs[0].sample_period)["speed_mps"])
    dt = float(logs[0].sample_period)
    secs = [sections(lg) for lg in logs]
    noise = [np.random.default_rng(k).normal(0.0, sig_v, lg.n) for k, lg in enumerate(logs)]
    measured = statistics([np.asarray(lg.speed_mps) for lg in logs], secs, dt, sig_v)

    def params_of(th):
        return {**base, **{n: float(np.exp(x)) for n, x in zip(NAMES, th)}}

    def cost_vector(th):
        plant, effs = jl.with_params(
            jl.Plant(), effects, {k: v for k, v in params_of(th).items() if k in known}
        )
        speeds = []
        for lg, nz in zip(logs, noise):
            inputs = jl.Inputs.from_log(lg)
            inputs = eqx.tree_at(lambda i: i.x0, inputs, inputs.x0 + offsets.get(lg.name, 0.0))
            sol = jl.simulate(plant, effs, inputs, stability_limit=False)
            if not bool(sol.ok):
                return np.full(measured.shape, 1e3)  # a failed simulation: far off
            speeds.append(np.asarray(sol.speed) + nz)
        return statistics(speeds, secs, dt, sig_v) - measured

    def cost(th):
        return float(np.sum(cost_vector(th) ** 2))

    print(f"statistics: {measured.size} over {sum(map(len, secs))} sections", flush=True)
    print(f"cost at the truth {cost(np.log([truth[n] for n in NAMES])):.4g}", flush=True)
    t0 = time.perf_counter()
    rows = sorted(
        (cost(np.log([*point, base["beta"]])), point) for point in itertools.product(*GRID.values())
    )
    print(f"grid: {len(rows)} points in {time.perf_counter() - t0:.0f} s", flush=True)
    best = None
    for c, point in rows[: args.refine]:
        th0 = np.log([*point, base["beta"]])
        r = so.least_squares(cost_vector, th0, diff_step=0.03, max_nfev=80, bounds=(LOWER, UPPER))
        p = params_of(r.x)
        chi2n = offsets_and_chi2n(p, ["stick_slip"], logs)[1]
        print(
            f"grid {dict(zip(GRID, point))} cost {c:.4g} -> refined cost {2 * r.cost:.4g}: "
            + ", ".join(f"{n} {p[n]:.4g} (truth {truth[n]:.4g})" for n in NAMES)
            + f"; chi2/N {', '.join(f'{v:.3g}' for v in chi2n.values())}",
            flush=True,
        )
        if best is None or r.cost < best[0]:
            best = (r.cost, p)
    gains = tuple(float(g) for g in args.gains.split(","))
    t0 = time.perf_counter()
    res = jl.fit(
        logs,
        effects="stick_slip",
        init={k: v for k, v in best[1].items() if k in known},
        synchronise=gains,
        n_starts=1,
        staged=False,
    )
    print(
        f"synchronised fit from the best: chi2/N {res.chi2 / res.n_residuals:.4g} in "
        f"{time.perf_counter() - t0:.0f} s; "
        + ", ".join(f"{n} {res.params[n]:.4g} (truth {truth[n]:.4g})" for n in NAMES),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
