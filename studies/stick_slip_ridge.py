"""Experiment: refits from points along the ridge of equal slip features
(studies/DETECTION.md, twenty-eighth sitting).

Where the fitted logs slip in one section of constant duty only, its three features
(slips per second, median peak speed, median duration) do not fix the breakaway force
``dFs`` and the Stribeck speed ``v_s`` together: they are matched as well along a line
in the two. The library's slip-feature search (``jaxlift.StickSlip.starts_from_logs``)
ends somewhere on it, and a least-squares refit reaches the optimum only from a start
within a few per cent of it. This script:

1. fits the baseline (no effect) from nominal values, as the diagnosis does;
2. runs the library's search and takes its first start;
3. walks the ridge through it (``jaxlift.model.effects.stick_slip.ridge_starts``,
   since the twenty-ninth sitting in the library): for each Stribeck speed of a ladder
   of 13 rungs over 2-30 mm/s (ratio 1.25), outwards both ways, the breakaway force
   that matches the features best (bounded Brent on its log, within a factor 1.6 of
   the neighbour's; the other parameters at the start's), until a rung's features cost
   exceeds the start's by 9;
4. refits every parameter from the search's start and from each rung (one start each,
   as the diagnosis's confirmation refits), and prints each refit's chi2/N on the
   fitted logs and on the held-out log (``validation.csv``).

With ``--at-truth`` it only evaluates the stick-slip model at the case's truth, and at
the truth with some values changed to those of the best refit, on the fitted and the
held-out logs (each log at its own fitted initial-height offset): whether the held-out
log is right to reject that refit.

    python studies/stick_slip_ridge.py DATA/case_093     # a folder of the generator
    python studies/stick_slip_ridge.py DATA/case_093 --at-truth
    python studies/stick_slip_ridge.py DATA/case_093 --swap

With ``--swap`` it goes on from the best refit (the lowest chi2/N on the fitted logs):
it refits the baseline and the stick-slip model with the held-out log among the fitted
ones, once with all three logs and once for each fitted log left out and predicted
(each model from its own earlier fit): whether stick-slip explains all three logs with
one set of values, which the held-out check alone cannot say.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it


from jaxlift.calibrate.diagnose import _heldout_chi2  # noqa: E402
from jaxlift.calibrate.fit import fit, log_simulator, offsets_and_chi2n  # noqa: E402
from jaxlift.model.effects import stick_slip as ss  # noqa: E402
from jaxlift.model.log import read_log  # noqa: E402

# case_093's best refit (the run without --at-truth): d 78 N*s/m, v_s 7.97 mm/s, dFs 600.9 N
CHANGES = {
    "truth": {},
    "d 78": {"d": 78.0},
    "v_s 7.97 mm/s": {"v_s": 0.00797},
    "d 78, v_s 7.97 mm/s": {"d": 78.0, "v_s": 0.00797},
    "d 78, v_s 7.97 mm/s, dFs 600.9 N": {"d": 78.0, "v_s": 0.00797, "dFs": 600.9},
}


def features_cost(logs, run):
    """The search's features cost in its first reading (``READINGS[0]``), and the number
    of sections that reading matches as slipping."""
    objective, kinds = ss.features_objective(logs, run)
    reading = {k: [ss.READINGS[0].get(x, x) for x in ks] for k, ks in kinds.items()}
    n_slipping = sum(x == "slips" for xs in reading.values() for x in xs)
    return (lambda values: objective(values, reading)), n_slipping


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", type=pathlib.Path, help="a case folder of detection_generator.py")
    ap.add_argument("--at-truth", action="store_true", help="only evaluate at the truth")
    ap.add_argument("--swap", action="store_true", help="then refit with the held-out log")
    a = ap.parse_args()
    logs = [read_log(a.case / "fit_1.csv"), read_log(a.case / "fit_2.csv")]
    held = [read_log(a.case / "validation.csv")]
    truth = json.loads((a.case / "truth.json").read_text())["params"]
    if a.at_truth:
        for label, change in CHANGES.items():
            p = {**truth, **change}
            fitted = offsets_and_chi2n(p, ["stick_slip"], logs)[1]
            out = offsets_and_chi2n(p, ["stick_slip"], held)[1]
            fitted_txt = ", ".join(f"{k} {v:.3f}" for k, v in fitted.items())
            out_txt = ", ".join(f"{v:.3f}" for v in out.values())
            print(f"{label}: chi2/N {fitted_txt}; held-out {out_txt}", flush=True)
        return
    t = time.perf_counter()
    base = fit(logs, free="all", staged=True, n_starts=2, seed=0)
    held_base = _heldout_chi2(base.params, (), held)
    print(
        f"baseline: chi2/N {base.chi2 / base.n_residuals:.4g}, held-out {held_base:.4g} "
        f"({time.perf_counter() - t:.0f} s)"
    )
    run = log_simulator(base.params, ["stick_slip"], logs)
    found = ss.slip_feature_search(logs, base.params, run)
    if not found:
        print("the search reads no start from these logs")
        return
    cost, n_slipping = features_cost(logs, run)
    print(f"sections matched as slipping in the first reading: {n_slipping}")
    starts, refits = [found[0], *ss.ridge_starts(logs, run, found[0])], []
    for st in starts:
        t = time.perf_counter()
        r = fit(logs, effects=["stick_slip"], free="all,effects", init={**base.params, **st},
                staged=False, n_starts=1, seed=0, workers=1)  # fmt: skip
        p = r.params
        print(
            f"start dFs {st['dFs']:7.1f} N, v_s {st['v_s'] * 1e3:5.2f} mm/s (features cost "
            f"{cost(st):.3g}): chi2/N {r.chi2 / r.n_residuals:.4g}, held-out "
            f"{_heldout_chi2(r.params, r.effects, held):.4g}; dFs {p['dFs']:.1f} N, v_s "
            f"{p['v_s'] * 1e3:.2f} mm/s, d {p['d']:.0f} N*s/m ({time.perf_counter() - t:.0f} s)",
            flush=True,
        )
        refits.append(r)
    print("truth: " + ", ".join(f"{k} {truth[k]:.4g}" for k in ("dFs", "v_s", "d", "beta")))
    if a.swap:
        best = min(refits, key=lambda r: r.chi2 / r.n_residuals)
        swap(logs, held, base, best)


def swap(logs, held, base, best) -> None:
    """Refit the baseline and the stick-slip model with the held-out log among the
    fitted ones (all three; then each fitted log left out and predicted)."""
    names = ["fit_1", "fit_2", "validation"]
    every = [*logs, *held]
    for model, start in (("baseline", base), ("stick_slip", best)):
        effects = list(start.effects)
        free = "all,effects" if effects else "all"
        t = time.perf_counter()
        r = fit(every, effects=effects, free=free, init=start.params, staged=False,
                n_starts=1, seed=0, workers=1)  # fmt: skip
        per_log = offsets_and_chi2n(r.params, effects, every)[1]
        txt = ", ".join(f"{n} {v:.3f}" for n, v in zip(names, per_log.values()))
        print(f"{model} on all three logs: chi2/N {txt} ({time.perf_counter() - t:.0f} s)")
        for out in (0, 1):
            t = time.perf_counter()
            on = [lg for i, lg in enumerate(every) if i != out]
            r = fit(on, effects=effects, free=free, init=start.params, staged=False,
                    n_starts=1, seed=0, workers=1)  # fmt: skip
            print(
                f"{model} fitted without {names[out]}: chi2/N {r.chi2 / r.n_residuals:.4g}, "
                f"{names[out]} predicted {_heldout_chi2(r.params, effects, [every[out]]):.4g} "
                f"({time.perf_counter() - t:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
