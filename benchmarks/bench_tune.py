# ruff: noqa: E402  (float64 must be switched on before anything else imports jax)
"""Benchmark: gain tuning by derivatives through the closed loop (jaxlift) against a
derivative-free optimiser (scipy Nelder--Mead) on the same cost; robust tuning time.

Run from the repository root::

    .venv/bin/python benchmarks/bench_tune.py [--quick]

Problem: the plain PID's five gains (P, I, D, N, K_aw) in the same log coordinates
(``jaxlift.control.gains.GainSpace``), from the thesis PID (K_aw = I/P), on the same cost
(``tuning_cost``: ``cost_from_figures`` of the closed-loop run along the thesis-like
110 s reference at 1000 kg, continuous controller, solver rtol 1e-5) on the plant of
the baseline fit of the shipped logs (``runs/fit_baseline/params.json`` if present,
else its values copied below). Then the scheduled PID (18 stage gains + N) on the
500 and 1500 kg references.

Protocol (the same for every optimiser): each runs *to its own convergence* from the
same start, compiled before the clock starts (compile times measured and reported
separately; they are paid once per problem shape and process):

- scipy Nelder--Mead on the jitted cost (one forward simulation per evaluation):
  ``xatol`` 1e-3 (log gains: 0.1 %), ``fatol`` 1e-4 (absolute; the cost is ~1),
  at most ``NM_MAXFEV`` evaluations (plain) / ``NM_MAXFEV_SCHED`` (scheduled);
- jaxlift ``tune_gains`` (default: Levenberg--Marquardt on the residual vector, its
  Jacobian by forward mode; stops when a Gauss--Newton step would gain < 0.1 % or the
  best has improved by < 0.1 % over 5 evaluations), at most 40 evaluations;
- for reference, L-BFGS and Adam on the same cost and forward-mode gradient (60 and 30
  evaluations).

Reported: each one's final cost and wall time. The target "lower cost in <= 1/5 of the
time" is judged as the issue states it: both run on the same cost to their own
convergence; LM's final cost is lower and its whole wall time is <= 1/5 of
Nelder--Mead's. Also shown: the time LM needed to get below Nelder--Mead's final cost,
against (a) Nelder--Mead's total time and (b) the time Nelder--Mead needed to first
get within 0.1 % of its own final cost (a stricter reading, which credits Nelder--Mead
with a stopping point it cannot know; information, with its own PASS/MISS); and
Nelder--Mead's best cost within LM's wall time (the same-wall-time view).

Robust tuning: LM on mean + CVaR20 over 32 parameter draws (``lax.map``), from the
nominal-tuned and from the starting gains (``tune_multistart``, as ``jaxlift tune``
does), compile and both starts included, target <= 5 min on 2 cores; plus one batched
cost evaluation of the 32 draws with ``vmap`` against ``lax.map``.

The machine has 2 cores and may be shared: the load average is recorded at the start
of each part; timings under load are pessimistic (both sides slow down, but not
necessarily by the same factor).

Prints a table and writes it to ``benchmarks/results_tune.txt``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import scipy
from _machine import cpu_model
from scipy.optimize import minimize

import jaxlift as jl
from jaxlift.control.closed_loop import simulate_closed_loop
from jaxlift.control.controller import PID, THESIS_PID, ScheduledPID
from jaxlift.control.cost import FAILED_COST, _run, tuning_cost
from jaxlift.control.draws import batch_models, parameter_draws
from jaxlift.control.gains import GainSpace
from jaxlift.control.optimisers import LBFGS, Adam, LevenbergMarquardt
from jaxlift.control.reference import thesis_reference
from jaxlift.control.tune import tune_gains, tune_multistart

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results_tune.txt"
FIT = ROOT / "runs" / "fit_baseline"
# the baseline fit of the shipped logs (used when runs/fit_baseline is absent)
BASELINE_FIT = {
    "k1": 2.0449, "k2": 1.9493, "k3": 1.8037, "z1": -2.5701, "z2": -3.2924, "z3": -4.4186,
    "beta": 4.0428e8, "cf_con": 7.5e-6, "cf_in": 13.502, "cf_out": 768.37, "d": 556.99,
}  # fmt: skip
STDERR = {"beta": 0.8e8, "d": 80.0, "cf_out": 120.0, "cf_in": 0.5, "k1": 0.03, "k2": 0.03}
RTOL = 1e-5
NM_MAXFEV = 2000
NM_MAXFEV_SCHED = 6000


def model():
    if (FIT / "params.json").exists():
        plant, effects = jl.load_model(FIT / "params.json")
        return plant, effects, str(FIT / "params.json")
    plant, _ = jl.with_params(jl.Plant(), (), BASELINE_FIT)
    return plant, (), "baseline-fit values (copied)"


def draws(n, tmp: Path):
    if (FIT / "metrics.json").exists():
        return parameter_draws(n, 0, fit_dir=FIT)
    tmp.mkdir(parents=True, exist_ok=True)
    jl.save_params_json(tmp / "params.json", BASELINE_FIT)
    (tmp / "metrics.json").write_text(__import__("json").dumps({"stderr": STDERR}))
    return parameter_draws(n, 0, fit_dir=tmp)


NOTES = """
## notes (measured separately from this script, same plant, 2026-11-23)
- The cost is a sum of squares: every figure in cost_from_figures is an RMS or a mean,
  so jaxlift.control.cost.tuning_residuals writes it as one residual vector (error samples,
  band-passed error, the same on the steady samples, 10 ms duty rate on the moving
  samples, the two post-shift offsets, the noise amplification; sum(r^2) equals
  tuning_cost to 1e-12, tests/test_tuning.py). LM (jaxlift/calibrate/lm.py) on it with the
  forward-mode Jacobian is now the default of tune_gains.
- Why L-BFGS stalls (it did at 1.225 in the previous run, at 1.163 after 60 evaluations
  here): the Gauss-Newton Hessian 2 J^T J of the cost in log gains has eigenvalues
  4e-4 ... 14 at the thesis gains (condition 3.5e4; K_aw is nearly flat) and 9e-4 ...
  577 near the optimum (6e5), and the cost is rough at the 0.1-1 % level (the valve's
  saturation, the adaptive steps changing with the gains). L-BFGS's curvature pairs and
  Wolfe line search break down on that: after 3 evaluations it is at 1.227, then it
  tries 22.9 and two failed runs and creeps; where it stopped, the Gauss-Newton model
  still predicts a 6 % decrease. Gauss-Newton takes the scale from J^T J itself.
- LM's first two trial points from the thesis gains fail (the undamped Gauss-Newton
  step lowers K_aw, the flat direction, by e^11). Each costs a Jacobian evaluation. A
  start damping option in jaxlift/calibrate/lm.py would save them (not changed here: another
  session's file); a trust region of 1 in log gains, tried, made the path worse (1.139
  after 26 evaluations instead of 1.095): the cost has several basins.
- Per evaluation, Nelder-Mead's cost is one 110 s simulation (12-25 ms, depending on
  the load); LM's Jacobian is 5 tangents (~8x) for the plain PID and, for the scheduled
  PID, 11 tangents per load (the loop at one load sees the 19 coordinates only through
  its 9 stage gains + N + K_aw; measured 1.6 s against 2.25 s per Jacobian with 19
  tangents). Nelder-Mead gets within 0.1 % of its final cost long before its own
  stopping test fires (plain: after ~1/3 of its evaluations), hence the two readings.
- Compile: LM compiles one function for 5 gains (residuals + Jacobian at every trial
  point); for more than 8 gains it also compiles a plain simulation for the trial points
  (a rejected trial then costs one simulation). The compile times above were taken at
  load 6-8 and vary by 2-3x with the load.
- Robust vs nominal (tests/test_tuning.py: 14 s reference, wide draws, beta +-30 %),
  measured with this working tree over 208 held-out draws (13 blocks of 16), tuned at
  rtol 1e-6: worst case 30.9 -> 29.6, mean 3.47 -> 3.31, 71 % of the draws better, the
  worst case lower in every block (ratios 0.90-1.00); the nominal-tuned gains remain
  better on the nominal plant (2.29 vs 2.33). A real, modest (~5 %) effect: the
  earlier test's ~3 % was of that size. Tuned at rtol 1e-5 instead, LM found nominal
  gains whose cost was 2.55 at 1e-5 and 2.90 at 1e-6 (it exploited the integration
  error on the short reference), which inflated the robust gain to ~10 %; the test now
  tunes at the tolerance it evaluates at. (On the 110 s reference the LM gains cost
  1.098 at rtol 1e-5, 1e-6 and 1e-7 alike.) The robust tuning runs from the
  nominal-tuned and from the starting gains (tune_multistart): with the previous
  step-size control at rtol 1e-5, the start at the nominal-tuned gains stayed in their
  basin (11.2 -> 11.0) where the other reached 7.5.
- The simulation code was being changed by another session while this ran (the
  stability-limited step control in _closed_loop.py / _stepping.py, then uncommitted,
  since committed as cd2f7e2); the tables and the robust-vs-nominal numbers are for
  that code; the Gauss-Newton eigenvalues, the trust-region trial and the rtol-1e-5
  robust numbers were measured earlier, the last two before it (the thesis cost at
  rtol 1e-6 moved from 4.092987 to 4.092966 with it).
"""


def _load() -> str:
    a, b, c = os.getloadavg()
    return f"load average {a:.1f} / {b:.1f} / {c:.1f} (1/5/15 min)"


def nelder_mead(cost, theta0, maxfev):
    """Nelder--Mead to its own convergence; returns (history [(t, cost)], x, wall)."""
    t0 = time.perf_counter()
    hist = []

    def f(th):
        v = float(cost(jnp.asarray(th)))
        hist.append((time.perf_counter() - t0, v))
        return v

    res = minimize(
        f,
        theta0,
        method="Nelder-Mead",
        options=dict(maxfev=maxfev, xatol=1e-3, fatol=1e-4, adaptive=len(theta0) > 8),
    )
    return hist, res, time.perf_counter() - t0


def compare(out, nm_hist, nm_time, tr, label):
    """The comparison lines (see the module docstring)."""
    nm_best = min(v for _, v in nm_hist)
    near = [t for t, v in nm_hist if v <= nm_best * (1 + 1e-3)][0]
    below = [t for t, v in zip(tr.history_s, tr.history, strict=True) if v < nm_best]
    t_beat = below[0] if below else float("inf")
    ra, rb = t_beat / nm_time, t_beat / near
    rw = tr.wall_s / nm_time
    lower = tr.best_cost < nm_best
    out(
        f"{label}: final cost {tr.best_cost:.4g} vs Nelder-Mead's {nm_best:.4g}, wall time "
        f"{tr.wall_s:.2f} s = {rw:.3f} of Nelder-Mead's {nm_time:.1f} s "
        f"-> {'PASS' if rw <= 0.2 and lower else 'MISS'} (the target as the issue states "
        "it: each on the same cost to its own convergence, lower cost in <= 1/5 of the time)"
    )
    out(
        f"  below Nelder-Mead's final cost after {t_beat:.2f} s: (a) {ra:.3f} of "
        f"Nelder-Mead's total time, (b) {rb:.3f} of the time Nelder-Mead needed to get "
        f"within 0.1 % of its final cost ({near:.1f} s) -> stricter reading (b): "
        f"{'PASS' if rb <= 0.2 and lower else 'MISS'} (Nelder-Mead cannot know it is "
        "that close; information)"
    )
    nm_at = [v for t, v in nm_hist if t <= tr.wall_s]
    out(
        f"  same wall time: in {label}'s {tr.wall_s:.2f} s Nelder-Mead reached "
        f"{min(nm_at) if nm_at else float('nan'):.4g} ({len(nm_at)} evaluations; "
        f"{label}: {tr.best_cost:.4g})"
    )
    return rb


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller budgets (a smoke run)")
    args = ap.parse_args()
    q = args.quick
    nm_maxfev, nm_maxfev_s = (100, 200) if q else (NM_MAXFEV, NM_MAXFEV_SCHED)
    lm_evals, lbfgs_evals, adam_steps, robust_evals = (8, 8, 5, 3) if q else (40, 60, 30, 15)

    lines = []

    def out(s=""):
        print(s, flush=True)
        lines.append(s)

    plant, effects, source = model()
    ref = thesis_reference(1000.0)
    start = PID().with_gains({**THESIS_PID, "K_aw": THESIS_PID["I"] / THESIS_PID["P"]})
    space = GainSpace.for_controller(start)
    theta0 = space.to_theta(start)

    @jax.jit
    def cost(theta):
        ctrl = space.from_theta(theta)
        sol = simulate_closed_loop(plant, effects, ctrl, ref, rtol=RTOL)
        c = tuning_cost(ctrl, plant, sol)
        return jnp.where(sol.ok & jnp.isfinite(c), c, FAILED_COST)

    out(f"# bench_tune  {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC")
    busy = os.getloadavg()[0] > 1.5
    out(
        f"# {_load()} at the start"
        + ("; the cores are shared with other jobs: timings are pessimistic" if busy else "")
    )
    out(
        f"# {cpu_model()}, {os.cpu_count()} cores; jax "
        f"{jax.__version__}, scipy {scipy.__version__}; model: {source}"
    )
    out("# protocol: every optimiser runs to its own convergence from the same start,")
    out("# compiled code on both sides, compile timed separately (see the module docstring)")

    # ---------------------------------------------------------------- compile first
    t = time.perf_counter()
    c0 = float(cost(jnp.asarray(theta0)))
    nm_compile = time.perf_counter() - t
    out(f"# thesis PID (K_aw = I/P) cost on the 110 s reference: {c0:.4g}")
    compile_s = {}
    optimisers = {"lm": LevenbergMarquardt(), "lbfgs": LBFGS(), "adam": Adam()}
    for method, optimiser in optimisers.items():
        t = time.perf_counter()
        tune_gains(start, plant, effects, [ref], steps=1, rtol=RTOL, optimiser=optimiser)
        compile_s[method] = time.perf_counter() - t

    # ---------------------------------------------------------------- plain PID
    out()
    out(f"## plain PID (5 log-gains), 1000 kg; {_load()}")
    nm_hist, nm_res, nm_time = nelder_mead(cost, theta0, nm_maxfev)
    runs = {
        "lm": tune_gains(start, plant, effects, [ref], steps=lm_evals, rtol=RTOL),
        "lbfgs": tune_gains(
            start, plant, effects, [ref], steps=lbfgs_evals, rtol=RTOL, optimiser=LBFGS()
        ),
        "adam": tune_gains(
            start, plant, effects, [ref], steps=adam_steps, rtol=RTOL, optimiser=Adam()
        ),
    }
    out("| optimiser | evaluations | final cost | wall time [s] | compile [s] | stopped |")
    out("|---|---:|---:|---:|---:|---|")
    out(
        f"| scipy Nelder-Mead (forward sims) | {len(nm_hist)} costs | {nm_res.fun:.4g} | "
        f"{nm_time:.1f} | {nm_compile:.1f} | {nm_res.message} |"
    )
    labels = {
        "lm": "jaxlift LM (residuals + fwd-mode Jacobian)",
        "lbfgs": "jaxlift L-BFGS (fwd-mode grad)",
        "adam": "jaxlift Adam (fwd-mode grad)",
    }
    for method, tr in runs.items():
        out(
            f"| {labels[method]} | {evals(tr)} | {tr.best_cost:.4g} | "
            f"{tr.wall_s:.2f} | {compile_s[method]:.1f} | {tr.message or 'budget'} |"
        )
    out(
        "(compile: the jitted cost for Nelder-Mead; one tune_gains call with a budget of 1 "
        "for the others -- L-BFGS and Adam share one compiled value-and-gradient)"
    )
    compare(out, nm_hist, nm_time, runs["lm"], "LM")
    compare(out, nm_hist, nm_time, runs["lbfgs"], "L-BFGS")
    out(f"  LM history: {[round(v, 4) for v in runs['lm'].history]}")
    out(f"  L-BFGS history: {[round(v, 4) for v in runs['lbfgs'].history]}")
    out(f"  Nelder-Mead gains: {fmt(space.from_theta(jnp.asarray(nm_res.x)).gain_values())}")
    out(f"  LM gains:          {fmt(runs['lm'].controller.gain_values())}")
    out(f"  L-BFGS gains:      {fmt(runs['lbfgs'].controller.gain_values())}")

    # ---------------------------------------------------------------- scheduled (19 gains)
    refs2 = [thesis_reference(m) for m in (500.0, 1500.0)]
    sched0 = ScheduledPID.from_pid(start)
    sspace = GainSpace.for_controller(sched0, [n for n in GainSpace.for_controller(sched0).names
                                               if n != "K_aw"])  # fmt: skip
    stheta0 = sspace.to_theta(sched0)

    @jax.jit
    def cost2(theta):
        cs = []
        for r in refs2:
            ctrl = sspace.from_theta(theta)
            sol = simulate_closed_loop(plant, effects, ctrl, r, rtol=RTOL)
            c = tuning_cost(ctrl, plant, sol)
            cs.append(jnp.where(sol.ok & jnp.isfinite(c), c, FAILED_COST))
        return jnp.mean(jnp.stack(cs))

    t = time.perf_counter()
    cost2(jnp.asarray(stheta0)).block_until_ready()
    nm2_compile = time.perf_counter() - t
    t = time.perf_counter()
    tune_gains(sched0, plant, effects, refs2, names=sspace.names, steps=1, rtol=RTOL)
    s_compile = time.perf_counter() - t
    out()
    out(
        f"## scheduled PID (18 stage gains + N = {len(sspace.names)} log-gains), "
        f"500 + 1500 kg; {_load()}"
    )
    nm2, nm2_res, nm2_time = nelder_mead(cost2, stheta0, nm_maxfev_s)
    ts2 = tune_gains(sched0, plant, effects, refs2, names=sspace.names, steps=lm_evals, rtol=RTOL)
    out("| optimiser | evaluations | final cost | wall time [s] | compile [s] | stopped |")
    out("|---|---:|---:|---:|---:|---|")
    out(
        f"| scipy Nelder-Mead (adaptive) | {len(nm2)} costs | {nm2_res.fun:.4g} | "
        f"{nm2_time:.1f} | {nm2_compile:.1f} | {nm2_res.message} |"
    )
    out(
        f"| jaxlift LM (fwd-mode Jacobian, 19 tangents) | {evals(ts2)} "
        f"| {ts2.best_cost:.4g} | {ts2.wall_s:.2f} | {s_compile:.1f} | {ts2.message} |"
    )
    compare(out, nm2, nm2_time, ts2, "LM")
    out(f"  LM history: {[round(v, 4) for v in ts2.history]}")

    # ---------------------------------------------------------------- robust, 32 draws
    ds = draws(32, ROOT / "runs" / "bench_tune_fit")
    plants, effs = batch_models(plant, effects, ds.draws)
    nominal = runs["lm"].controller
    run = lambda p, e: _run(nominal, p, e, ref, dict(rtol=RTOL), None)[0]  # noqa: E731
    f_vmap = eqx.filter_jit(eqx.filter_vmap(run))
    f_map = eqx.filter_jit(lambda ps, es: jax.lax.map(lambda pe: run(*pe), (ps, es)))
    timings = {}
    for name, f in (("vmap", f_vmap), ("lax.map", f_map)):
        f(plants, effs).block_until_ready()
        t = time.perf_counter()
        f(plants, effs).block_until_ready()
        timings[name] = time.perf_counter() - t
    out()
    out(f"## robust tuning over 32 draws ({ds.source}); {_load()}")
    out(
        f"batched cost of 32 draws (forward, compiled): vmap {timings['vmap']:.2f} s, "
        f"lax.map {timings['lax.map']:.2f} s"
    )
    rt = tune_multistart(
        [nominal, start],
        plants,
        effs,
        [ref],
        batched_plants=True,
        robust=True,
        steps=robust_evals,
        rtol=RTOL,
    )
    ok_r = rt.wall_s <= 300
    out(
        f"robust tuning as `jaxlift tune` does it: LM from the nominal-tuned and from the "
        f"starting gains, at most {robust_evals} evaluations each (mean + CVaR20 over 32 "
        f"draws, lax.map, forward-mode Jacobian, compile included): objective "
        f"{rt.best_cost:.4g} ({rt.message}); {rt.n_evaluations} evaluations in all, wall "
        f"{rt.wall_s:.0f} s -> {'PASS' if ok_r else 'MISS'} (target <= 300 s on 2 cores)"
    )
    out(f"  robust gains: {fmt(rt.controller.gain_values())}")
    out(f"# {_load()} at the end")
    if args.quick:
        out("# --quick: smaller budgets; not the reported numbers")
    lines.append(NOTES.strip("\n"))
    RESULTS.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0


def evals(tr) -> str:
    n, d = tr.n_evaluations, tr.n_with_derivatives
    if d is None or d == n:
        return f"{n} value+derivative"
    return f"{d} value+derivative, {n - d} values"


def fmt(gains: dict) -> str:
    return "{" + ", ".join(f"{k}: {float(v):.4g}" for k, v in gains.items()) + "}"


if __name__ == "__main__":
    sys.exit(main())
