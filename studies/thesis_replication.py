# ruff: noqa: E402  (float64 must be switched on before anything else imports jax)
"""Replication of the thesis's controller results (figures 3.9--3.14) on the
calibrated model of the shipped data.

Usage (from the repository root)::

    # the calibrated model: a least-squares fit of the shipped logs, e.g.
    jaxlift fit data/lift_500kg.csv data/lift_1500kg.csv \\
        --validate data/validation_1000kg.csv --out runs/fit_baseline
    # (the shipped data hide stick-slip and hose compliance: add
    #  --effects stick_slip,hose_compliance --out runs/fit_sh for the full model)
    .venv/bin/python studies/thesis_replication.py --params runs/fit_baseline/params.json \\
        --out runs/thesis_replication

Writes ``report.md``/``report.html`` and ``figures/*.png`` to ``--out``. ``--quick``
shortens the noisy runs (a smoke test). Every number in the report is computed here;
the "Where we disagree" paragraphs compare them with the thesis's statements.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse
import pathlib
import sys
import time
import warnings

import jaxlift as jl
from jaxlift.control.closed_loop import SampledFilterWarning, simulate_closed_loop
from jaxlift.control.controller import PID, THESIS_PI, THESIS_PID, THESIS_PID_NOISE, ScheduledPID
from jaxlift.control.cost import tuning_cost
from jaxlift.control.performance import figures
from jaxlift.control.reference import Reference
from jaxlift.control.reference import thesis_reference as make_ref
from jaxlift.control.stability import stability_table
from jaxlift.control.tune import tune_gains
from jaxlift.report.document import Report
from jaxlift.report.tuning import plot_response

FIG_KEYS = [
    "tracking_rms_mmps",
    "osc_rms_mmps",
    "osc_stage1_mmps",
    "osc_stage2_mmps",
    "osc_stage3_mmps",
    "osc_sustained_mmps",
    "shift1_offset_mmps",
    "shift2_offset_mmps",
    "effort_per_s",
    "shut_share_pct",
]


def run(plant, effects, ctrl, ref, **kw):
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SampledFilterWarning)
        sol = simulate_closed_loop(plant, effects, ctrl, ref, **kw)
    row = figures(sol).as_dict()
    row["cost"] = float(tuning_cost(ctrl, plant, sol))
    row["ok"] = bool(sol.ok)
    row["sim_s"] = time.perf_counter() - t
    row["steps"] = int(sol.num_steps)
    return sol, row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--params", required=True, help="calibrated parameters (jaxlift fit)")
    ap.add_argument("--effects", default=None, help="effects (default: those in --params)")
    ap.add_argument("--out", default="runs/thesis_replication")
    ap.add_argument("--quick", action="store_true", help="small tuning budget (smoke test)")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    plant, effects = jl.load_model(args.params, args.effects)
    names = [e.name for e in effects] or ["none"]
    rep = Report("Thesis replication: the lift controller (figures 3.9-3.14)")
    rep.text(
        f"Model: `{args.params}` (effects: {', '.join(names)}). Reference: the thesis-like "
        "sequence of docs/control.md (110 s, fast 0.09 m/s and slow 0.025 m/s sections in every "
        "stage, both stage shifts crossed), 1000 kg unless said otherwise. Continuous "
        "controller unless said otherwise. Figures of good as in `jaxlift.control.performance`."
    )
    ref = make_ref(1000.0)
    pid = PID().with_gains(THESIS_PID)
    pi = PID().with_gains(THESIS_PI)

    # ------------------------------------------------ 3.9 / 3.10: PI diverges, PID not
    print("3.9/3.10: PI and PID ...", flush=True)
    s_pi, r_pi = run(plant, effects, pi, ref)
    s_pid, r_pid = run(plant, effects, pid, ref)
    rep.heading("PI diverging at height (3.9) and PID removing it (3.10)")
    rep.table(
        [dict(gains="PI 20/120", **r_pi), dict(gains="PID 20/300/2/100", **r_pid)],
        columns=["gains", *FIG_KEYS, "cost", "ok"],
    )
    plot_response([("PI", s_pi), ("PID", s_pid)], figdir / "pi_vs_pid.png", "PI vs PID, 1000 kg")
    rep.figure(figdir / "pi_vs_pid.png", "PI (20/120) against PID (20/300/2/100)")
    st_pi = stability_table(plant, effects, pi, 1000.0)
    st_pid = stability_table(plant, effects, pid, 1000.0)
    rows = [
        dict(
            point=a["point"],
            x_m=a["x_m"],
            v_ref_mps=a["v_ref_mps"],
            PI_max_real=a["max_real_per_s"],
            PI_freq_hz=a["freq_hz"],
            PID_max_real=b["max_real_per_s"],
            PID_freq_hz=b["freq_hz"],
        )
        for a, b in zip(st_pi, st_pid, strict=True)
    ]
    rep.table(rows, caption="Eigenvalue with the largest real part [1/s] and its frequency")
    slow_pi = [r for r in st_pi if r["v_ref_mps"] < 0.05]
    growth = slow_pi[-1]["max_real_per_s"] - slow_pi[0]["max_real_per_s"]
    rep.text(
        f"**Finding.** PI is unstable at slow speed at every height (max real part "
        f"{min(r['max_real_per_s'] for r in slow_pi):.2f} to "
        f"{max(r['max_real_per_s'] for r in slow_pi):.2f} 1/s, "
        f"{slow_pi[0]['freq_hz']:.1f} Hz at the bottom falling to "
        f"{slow_pi[-1]['freq_hz']:.1f} Hz at the top) and stable at fast speed; the "
        f"oscillation RMS per stage is {r_pi['osc_stage1_mmps']:.1f} / "
        f"{r_pi['osc_stage2_mmps']:.1f} / {r_pi['osc_stage3_mmps']:.1f} mm/s. "
        f"PID removes it everywhere (sustained oscillation {r_pid['osc_sustained_mmps']:.2f} "
        "mm/s, all eigenvalues in the left half plane)."
    )
    rep.text(
        "**Where we disagree.** The thesis saw decaying oscillations low and diverging ones "
        "high (3.9b/c). In this model the PI loop's growth rate barely depends on height "
        f"(change {growth:+.2f} 1/s from bottom to top at slow speed): the larger volume "
        "lowers the hydraulic frequency but, with the friction law's negative slope at low "
        "speed dominating the damping, does not make the loop much less stable. What does "
        "grow with height is the amplitude of the limit cycle around the closed valve. The "
        "instability is a slow-speed one (the friction law makes the hydraulic mode lightly "
        "damped only at low speed), which the thesis attributed to height."
    )

    # ------------------------------------------------ 3.10c / 3.11: offset, anti-windup
    print("3.10c/3.11: stage-shift offset and anti-windup ...", flush=True)
    rows = []
    sols = []
    for m in (1000.0, 1500.0):
        for k_aw in (0.0, THESIS_PID["I"] / THESIS_PID["P"]):
            ctrl = pid.with_gains({"K_aw": k_aw})
            s, r = run(plant, effects, ctrl, make_ref(m))
            rows.append(dict(load_kg=m, K_aw=k_aw, **r))
            if m == 1000.0:
                sols.append((f"K_aw = {k_aw:g}", s))
    slow = Reference.from_sections(
        [(0.0, 1.0), (0.09, 3.0), (0.02, 8.0), (0.0, 2.0)], m_load=1500.0, x0=1.35, ramp_s=0.2
    )
    for k_aw in (0.0, 15.0):
        s, r = run(plant, effects, pid.with_gains({"K_aw": k_aw}), slow)
        rows.append(dict(load_kg="1500, slow-down at shift", K_aw=k_aw, **r))
        if k_aw == 0.0:
            s_slow0 = s
        else:
            s_slow1 = s
    rep.heading("Offset after a stage shift (3.10c) and anti-windup (3.11)")
    rep.table(
        rows,
        columns=["load_kg", "K_aw", "shift1_offset_mmps", "shift2_offset_mmps", "tracking_rms_mmps",
                 "shut_share_pct", "cost"],
    )  # fmt: skip
    plot_response(
        [("K_aw = 0", s_slow0), ("K_aw = 15", s_slow1)],
        figdir / "anti_windup.png",
        "slow-down just before the first stage shift, 1500 kg",
    )
    rep.figure(figdir / "anti_windup.png", "Windup at u = 0 when slowing down at a shift")
    r0 = [r for r in rows[:4] if r["K_aw"] == 0.0]
    big = max(abs(r[k]) for r in r0 for k in ("shift1_offset_mmps", "shift2_offset_mmps"))
    rep.text(
        "**Finding / where we disagree.** On the thesis-like reference the error 1.5-4.5 s "
        "after a shift is small with or without anti-windup (largest |offset| "
        f"{big:.2f} mm/s at 1000 and 1500 kg): the stall at "
        "the shift is short (the pressure climbs in a fraction of a second) and the "
        "duty does not saturate long enough to wind up. The offset of thesis figure "
        "3.10c appears here when the lift slows down at the shift: the valve shuts while the "
        "fork runs on (overdamped at 0.09 m/s) and the integral winds down; then K_aw = I/P "
        f"takes the offset from {rows[-2]['shift1_offset_mmps']:.2f} to "
        f"{rows[-1]['shift1_offset_mmps']:.2f} mm/s. This agrees with docs/control.md's "
        "independent simulation (anti-windup mainly cures windup at u = 0 when slowing down)."
    )

    # ------------------------------------------------ 3.12: scheduled vs plain
    print("3.12: scheduled vs plain (gradient-tuned, same budget) ...", flush=True)
    steps = 4 if args.quick else 15
    short = [make_ref(m, time_scale=1.0) for m in (500.0, 1500.0)]
    start = pid.with_gains({"K_aw": 15.0})
    t_plain = tune_gains(start, plant, effects, short, steps=steps, progress=True)
    t_sched = tune_gains(
        ScheduledPID.from_pid(start), plant, effects, short, steps=steps, progress=True
    )
    rows = []
    for name, ctrl in (
        ("thesis PID", pid),
        ("plain PID, tuned", t_plain.controller),
        ("scheduled PID, tuned", t_sched.controller),
    ):
        for m in (500.0, 1000.0, 1500.0):
            _, r = run(plant, effects, ctrl, make_ref(m))
            rows.append(dict(gains=name, load_kg=m, **r))
    rep.heading("Scheduled vs plain PID (3.12)")
    rep.text(
        f"Both tuned by derivatives (Levenberg-Marquardt) from the thesis PID (K_aw = 15) "
        f"on 500 and 1500 kg with the same budget (at most {steps} evaluations); 1000 kg "
        "is held out. Tuning cost: plain "
        f"{t_plain.initial_cost:.3g} -> {t_plain.best_cost:.3g}, scheduled "
        f"{t_sched.initial_cost:.3g} -> {t_sched.best_cost:.3g}."
    )
    rep.table(
        rows, columns=["gains", "load_kg", "tracking_rms_mmps", "osc_rms_mmps",
                       "osc_sustained_mmps", "effort_per_s", "cost"],
    )  # fmt: skip
    change = t_sched.best_cost / t_plain.best_cost - 1
    rep.text(
        f"**Finding.** With the same budget the scheduled PID's tuned cost is "
        f"{100 * change:+.0f} % against the plain PID's"
        + (
            " -- no real gain from scheduling, as in the thesis (3.12: 'marginal'): the load "
            "and stage dependence of this plant is too weak to pay for the extra freedom "
            "within this budget."
            if abs(change) < 0.2
            else (
                " -- worse: the scheduled PID contains the plain one (G_m = 0, equal "
                "stages), so this is the optimiser not converging within the budget in 20 "
                "dimensions (it started at the plain PID's point), not a property of "
                "scheduling. Within this budget scheduling gains nothing -- in line with the "
                "thesis's 'marginal' (3.12)."
                if change > 0
                else " -- a clear gain, unlike the thesis's 'marginal' (3.12)."
            )
        )
    )

    # ------------------------------------------------ 3.13 / 3.14: noise
    print("3.13/3.14: noise ...", flush=True)
    rows = []
    runs = []
    for label, g in (("PID 20/300/2/100", THESIS_PID), ("PID 20/300/3/N=1e4", THESIS_PID_NOISE)):
        ctrl = PID().with_gains(g)
        for form, kw in (("continuous", {}), ("sampled 10 ms", dict(sampled=True))):
            s, r = run(plant, effects, ctrl, ref, noise_seed=0, **kw)
            rows.append(dict(gains=label, form=form, **r))
            if form == "continuous":
                runs.append((label, s))
    _, r_clean = run(plant, effects, pid, ref)
    rep.heading("Noise amplified by D and a larger filter N (3.13, 3.14)")
    rep.table(
        rows,
        columns=["gains", "form", "tracking_rms_mmps", "osc_rms_mmps", "osc_sustained_mmps",
                 "effort_per_s", "shut_share_pct", "height_error_mm", "ok", "steps", "sim_s"],
    )  # fmt: skip
    plot_response(runs, figdir / "noise.png", "with sensor noise (seed 0), continuous controller")
    rep.figure(figdir / "noise.png", "Noise: N = 100 against N = 10000 (continuous)")
    a, _, c, d = rows
    rep.text(
        f"**Finding.** Without noise the thesis PID has effort {r_clean['effort_per_s']:.2f} "
        f"1/s; with noise, D = 2, N = 100 makes u bang between 0 and 1 (effort "
        f"{a['effort_per_s']:.0f} 1/s, valve shut {a['shut_share_pct']:.0f} % of the moving "
        f"time, tracking {a['tracking_rms_mmps']:.1f} mm/s): 3.13 reproduced. N = 10000 "
        f"(3.14) in continuous time gives tracking {c['tracking_rms_mmps']:.1f} mm/s and "
        f"shut {c['shut_share_pct']:.0f} % (it took {c['steps']} solver steps: the filter "
        f"makes the loop stiff, 'the simulation took longer'). Once the controller runs at "
        f"100 Hz it is the worst choice (sampled: tracking {d['tracking_rms_mmps']:.1f} mm/s, "
        f"height error {d['height_error_mm']:.0f} mm, run ok: {d['ok']}) -- N T_c = 100, "
        "the filter is meaningless on the clock; the thesis could not see this (4.1.4)."
    )
    md, html = rep.write(out)
    print(f"wrote {md}, {html}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
