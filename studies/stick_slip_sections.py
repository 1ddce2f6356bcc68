"""Per section of constant duty: the slip features of a log against jaxlift's model
simulated at the case's true parameters, and how long the fork is stuck in each
(studies/DETECTION.md, fifteenth sitting: the sections the model misses at the truth
are those where the fork never stops).

    python studies/stick_slip_sections.py runs/detection/data/case_089 [more cases]

For each case folder (``fit_1.csv``, ``fit_2.csv``, ``validation.csv``, ``truth.json``
of the detection or coverage generator) it prints every section that slips by the count
or whose cost at the truth exceeds 5: the log's features, the model's, the section's
cost (as in the search), the log's median speed, the share of samples with the fork
stuck (``stuck_share``) and the 10 % quantile of the speed, and ``section_kinds``'s
verdict.
"""

from __future__ import annotations

import json
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.calibrate.fit import log_simulator  # noqa: E402
from jaxlift.model.effects.stick_slip import (  # noqa: E402
    constant_duty_sections,
    section_cost,
    section_kinds,
    slip_features,
    stuck_share,
)


def main(cases: list[str]) -> int:
    for c in cases:
        case = pathlib.Path(c)
        spec = json.loads((case / "truth.json").read_text())
        logs = [jl.read_log(case / n) for n in ("fit_1.csv", "fit_2.csv", "validation.csv")]
        sols = log_simulator(spec["params"], spec["hidden_effects"], logs)({})
        print(f"== {case.name} {spec['hidden_effects']}", "" if sols else "(simulation failed)")
        if not sols:
            continue
        for k, lg in enumerate(logs):
            dt, speed = lg.sample_period, np.asarray(lg.speed_mps)
            secs = constant_duty_sections(lg.pwm, dt)
            for (a, b), kind in zip(secs, section_kinds(speed, dt, secs)):
                f = slip_features(speed[a:b], dt)
                g = slip_features(np.asarray(sols[k].speed)[a:b], dt)
                cost = section_cost(f, g, kind != "still")  # "ignored" counted as slips
                if kind == "still" and cost <= 5:
                    continue
                v = np.convolve(speed[a:b], np.ones(3) / 3, mode="same")
                print(f"  {lg.name[:10]:10s} {a * dt:6.1f} s duty {lg.pwm[a]:.3f} {kind:7s} "
                      f"log {np.round(f, 3)} model at the truth {np.round(g, 3)} cost "
                      f"{cost:8.1f} | median {1e3 * np.median(v):5.1f} mm/s, stuck "
                      f"{stuck_share(speed[a:b]):.2f}, q10 {1e3 * np.quantile(v, 0.1):5.1f} "
                      "mm/s")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
