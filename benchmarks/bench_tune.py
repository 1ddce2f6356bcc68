# ruff: noqa: E402  (float64 must be switched on before anything else imports jax)
"""Benchmark: gain tuning by gradient (jaxlift, Adam through the closed loop) against a
derivative-free optimiser (scipy Nelder--Mead) on the same cost; robust tuning time.

Run from the repository root::

    .venv/bin/python benchmarks/bench_tune.py [--quick]

Both optimisers tune the plain PID's five gains (P, I, D, N, K_aw) in the same log
coordinates (``jaxlift._tuning.GainSpace``), from the thesis PID (K_aw = I/P), on the
same cost (``cost_from_figures`` of the closed-loop run along the thesis-like 110 s
reference at 1000 kg, continuous controller, solver rtol 1e-5) on the plant of the
baseline fit of the shipped logs (``runs/fit_baseline/params.json`` if present, else
its values copied below). Nelder--Mead gets ``NM_EVALS`` cost evaluations (forward
simulations, jitted); Adam gets ``ADAM_STEPS`` value-and-gradient evaluations. We
report each one's best cost and wall time (compilation included, each compiled
once), and the time Adam needed to get below Nelder--Mead's final cost: the target
is "lower cost in <= 1/5 of the time".

Robust tuning: ``ROBUST_STEPS`` Adam steps of mean + CVaR20 over 32 parameter draws
(``vmap``), target <= 5 min on 2 cores; plus one batched cost evaluation of the 32
draws with ``vmap`` against ``lax.map``.

Prints a table and writes it to ``benchmarks/results_tune.txt``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import scipy
from scipy.optimize import minimize

import jaxlift as jl
from jaxlift._closed_loop import simulate_closed_loop, thesis_reference
from jaxlift._control import PID, THESIS_PID
from jaxlift._performance import cost_from_figures, figures
from jaxlift._tuning import (
    GainSpace,
    _run,
    batch_models,
    parameter_draws,
    tune_gains,
)

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


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller budgets (a smoke run)")
    args = ap.parse_args()
    nm_evals, adam_steps, robust_steps = (60, 10, 3) if args.quick else (250, 30, 15)

    plant, effects, source = model()
    ref = thesis_reference(1000.0)
    start = PID().with_gains({**THESIS_PID, "K_aw": THESIS_PID["I"] / THESIS_PID["P"]})
    space = GainSpace.for_controller(start)
    theta0 = space.to_theta(start)

    @jax.jit
    def cost(theta):
        sol = simulate_closed_loop(plant, effects, space.from_theta(theta), ref, rtol=RTOL)
        c = cost_from_figures(figures(sol))
        return jnp.where(sol.ok & jnp.isfinite(c), c, 1e4)

    lines = []

    def out(s=""):
        print(s, flush=True)
        lines.append(s)

    out(f"# bench_tune  {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC")
    out(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; jax "
        f"{jax.__version__}, scipy {scipy.__version__}; model: {source}"
    )
    out(f"# thesis PID (K_aw = I/P) cost on the 110 s reference: {float(cost(theta0)):.4g}")

    # ---------------------------------------------------------------- Nelder-Mead
    t0 = time.perf_counter()
    nm_hist = []

    def f_nm(th):
        v = float(cost(jnp.asarray(th)))
        nm_hist.append((time.perf_counter() - t0, v))
        return v

    res = minimize(
        f_nm,
        theta0,
        method="Nelder-Mead",
        options=dict(maxfev=nm_evals, initial_simplex=None, xatol=1e-4, fatol=1e-6),
    )
    nm_time = time.perf_counter() - t0
    nm_best = min(v for _, v in nm_hist)

    # ---------------------------------------------------------------- Adam
    tr = tune_gains(start, plant, effects, [ref], steps=adam_steps, rtol=RTOL)
    below = [t for t, v in zip(tr.history_s, tr.history, strict=True) if v < nm_best]
    t_beat = below[0] if below else float("inf")
    ratio = t_beat / nm_time
    ok = ratio <= 0.2
    out()
    out("| optimiser | evaluations | best cost | wall time [s] |")
    out("|---|---:|---:|---:|")
    out(f"| scipy Nelder-Mead | {len(nm_hist)} costs | {nm_best:.4g} | {nm_time:.1f} |")
    out(
        f"| jaxlift Adam (grad) | {tr.n_evaluations} value+grad | {tr.best_cost:.4g} | "
        f"{tr.wall_s:.1f} |"
    )
    out(
        f"Adam below Nelder-Mead's final cost after {t_beat:.1f} s = {ratio:.3f} of "
        f"Nelder-Mead's time -> {'PASS' if ok else 'MISS'} (target: lower cost in <= 1/5)"
    )
    out(f"  Nelder-Mead gains: {space.from_theta(jnp.asarray(res.x)).gain_values()}")
    out(f"  Adam gains:        {tr.controller.gain_values()}")
    t_first = tr.history_s[0]
    out(f"  (Adam's first value+grad incl. compile: {t_first:.1f} s; NM's first cost incl. "
        f"compile: {nm_hist[0][0]:.1f} s)")  # fmt: skip

    # ---------------------------------------------------------------- robust, 32 draws
    ds = draws(32, ROOT / "runs" / "bench_tune_fit")
    plants, effs = batch_models(plant, effects, ds.draws)
    run = lambda p, e: _run(tr.controller, p, e, ref, dict(rtol=RTOL), None)[0]
    f_vmap = eqx.filter_jit(eqx.filter_vmap(run))
    f_map = eqx.filter_jit(lambda ps, es: jax.lax.map(lambda pe: run(*pe), (ps, es)))
    timings = {}
    for name, f in (("vmap", f_vmap), ("lax.map", f_map)):
        f(plants, effs).block_until_ready()
        t = time.perf_counter()
        f(plants, effs).block_until_ready()
        timings[name] = time.perf_counter() - t
    out()
    out(f"# robust tuning over 32 draws ({ds.source})")
    out(
        f"batched cost of 32 draws (forward, compiled): vmap {timings['vmap']:.2f} s, "
        f"lax.map {timings['lax.map']:.2f} s"
    )
    rt = tune_gains(
        tr.controller,
        plants,
        effs,
        [ref],
        batched_plants=True,
        robust=True,
        steps=robust_steps,
        rtol=RTOL,
    )
    ok_r = rt.wall_s <= 300
    out(
        f"robust tuning, {robust_steps} Adam steps (mean + CVaR20 over 32 draws, vmap): "
        f"objective {rt.initial_cost:.4g} -> {rt.best_cost:.4g}, wall {rt.wall_s:.0f} s "
        f"-> {'PASS' if ok_r else 'MISS'} (target <= 300 s on 2 cores)"
    )
    if args.quick:
        out("# --quick: smaller budgets; not the reported numbers")
    RESULTS.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
