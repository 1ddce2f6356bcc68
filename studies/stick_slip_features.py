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
log and of the model are computed by the same function. Since the twelfth sitting the
search is the library's (``jaxlift.StickSlip.starts_from_logs``: the diagnosis's
confirmation refits start from it); this script runs it and the fit on one case. The
``--threshold``/``--with-beta``/``--max-evals`` options of the eleventh sitting are gone:
the library searches the bulk modulus always, with a slip starting from a stuck fork.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.fit import log_simulator, offsets_and_chi2n  # noqa: E402
from jaxlift.model.effects.stick_slip import constant_duty_sections, slip_features  # noqa: E402

SHOWN = ("beta", "cf_con", "cf_in", "cf_out", "d", "dFs", "v_s")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a detection case's folder (fit_1.csv, fit_2.csv, truth.json)")
    ap.add_argument("baseline", help="the case's diagnosis.json (its final_params)")
    args = ap.parse_args()
    case = pathlib.Path(args.case)
    truth = json.loads((case / "truth.json").read_text())["params"]
    base = json.loads(pathlib.Path(args.baseline).read_text())["final_params"]
    logs = [jl.read_log(case / "fit_1.csv"), jl.read_log(case / "fit_2.csv")]
    for lg in logs:
        if lg.speed_mps is None:
            ap.error(f"{lg.name}: the slip features need a speed column (speed_mps)")
    for lg in logs:
        feats = [slip_features(lg.speed_mps[a:b], lg.sample_period).round(4).tolist()
                 for a, b in constant_duty_sections(lg.pwm, lg.sample_period)]  # fmt: skip
        print(f"{lg.name}: features (slips/s, peak m/s, duration s):", feats, flush=True)
    t0 = time.time()
    found = jl.StickSlip.starts_from_logs(logs, base, log_simulator(base, ["stick_slip"], logs))
    if not found:
        print("no section of the logs slips: no start")
        return 0
    start = {**base, **found[0]}
    print("search:", {k: f"{v:.4g}" for k, v in found[0].items()}, f"{time.time() - t0:.0f} s")
    _, chi2n = offsets_and_chi2n(start, ["stick_slip"], logs)
    print("full-simulation chi2/N there:", {k: round(v, 3) for k, v in chi2n.items()}, flush=True)
    fit = jl.fit(logs, effects=["stick_slip"], free="all,effects", init=start, staged=False,
                 n_starts=1, seed=0)  # fmt: skip
    shown = {k: f"{float(fit.params[k]):.4g}" for k in SHOWN}
    print(f"ordinary fit from there: chi2/N {fit.chi2 / fit.n_residuals:.4f},", shown,
          f"{time.time() - t0:.0f} s")  # fmt: skip
    print("truth:                  ", {k: f"{truth[k]:.4g}" for k in SHOWN}, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
