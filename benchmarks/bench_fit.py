# ruff: noqa: E402  (float64 must be switched on before anything else imports jax)
"""Benchmark: the baseline fit of two logs, jaxlift against SciPy, time to converge.

Run from the repository root::

    .venv/bin/python benchmarks/bench_fit.py [--quick]

Prints a table (each measured number, its target, PASS/MISS) and writes the same text
to ``benchmarks/results_fit.txt``. See ``benchmarks/README.md``.

Both sides fit the 11 baseline parameters the thesis estimates to the same two
synthetic logs (made by jaxlift at the known truth of ``tests/test_fit.py``), from the
same start, in the same unconstrained coordinates (jaxlift's ``to_unconstrained``),
with the same residuals (height / 0.5 mm, speed / sigma_v; both simulations start from
the log's mean initial-hold height). jaxlift: ``jaxlift.calibrate.fit.fit`` (optimistix
Levenberg--Marquardt, forward-mode Jacobian through diffrax). The peer:
``scipy.optimize.least_squares`` (trust-region reflective, 2-point finite-difference
Jacobian) driving ``tests/scipy_reference.py`` (``solve_ivp`` LSODA, integration
restarted at every input jump, analytic ODE Jacobian), both simulators at jaxlift's
default accuracy.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse
import datetime
import math
import os
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import diffrax
import equinox as eqx
import numpy as np
import optimistix as optx
import scipy
from scipy.optimize import least_squares

import jaxlift as jl
from jaxlift.calibrate.experiment import FAILED_RESIDUAL, make_experiments
from jaxlift.calibrate.fit import fit
from jaxlift.calibrate.problem import Problem as _Problem
from jaxlift.model.build import all_param_infos
from jaxlift.model.sequences import THESIS_LIKE_SECTIONS, ramped_sequence

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

import scipy_reference as sr
from _machine import cpu_model
from test_fit import TRUTH, _synthetic_logs

RESULTS = HERE / "results_fit.txt"

#: The fitted parameters (thesis 2.3.2: the motor set and the dynamic set).
NAMES = ("k1", "k2", "k3", "z1", "z2", "z3", "beta", "cf_con", "cf_in", "cf_out", "d")
#: The start: truth times a fixed factor, 10-20 % off in each parameter. The gains are
#: lowered, not raised: at the truth the fork already climbs to 4.32 m of the 4.5 m
#: mast, and the SciPy peer (no end stops) cannot simulate a run that leaves the mast.
START_FACTOR = dict(
    k1=0.88, k2=1.12, k3=0.85, z1=1.15, z2=0.85, z3=1.20,
    beta=1.20, cf_con=0.85, cf_in=1.10, cf_out=0.83, d=1.15,
)  # fmt: skip
#: Accuracy of both simulators: jaxlift's defaults (``fit`` uses them).
SIM_RTOL, SIM_ATOL = 1e-6, (1e-7, 1e-7, 1.0)
#: SciPy: relative finite-difference step in the unconstrained coordinates (chosen by
#: comparing finite-difference columns against jaxlift's exact forward-mode Jacobian at
#: the start: see README); unit variable scale (the coordinates are logs and logits, so a
#: unit step is a relative change: jaxlift's LM does not rescale them either;
#: ``x_scale="jac"`` was tried and wandered off: see README); SciPy's default tolerances.
DIFF_STEP = 1e-3
X_SCALE = 1.0
FTOL = XTOL = GTOL = 1e-8
#: "Equal cost": SciPy counts as having reached jaxlift's optimum once its chi2 is
#: within this much of the chi2 that SciPy's own simulator gives at jaxlift's optimum.
CHI2_TOL = 0.1
#: Wall-time caps of the SciPy fit [s] (full run, --quick).
SCIPY_CAP_S, SCIPY_CAP_QUICK_S = 600.0, 150.0
#: The logs: loads [kg] and noise seeds of tests/test_fit.py; sample period [s] (--quick).
LOADS, SEEDS = (500.0, 1500.0), (11, 12)
QUICK_DT = 0.04

_lines: list[str] = []


def say(text: str = "") -> None:
    print(text, flush=True)
    _lines.append(text)


def _load() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def fmt_t(s: float) -> str:
    return f"{s * 1e3:7.0f} ms" if s < 1.0 else f"{s:7.1f} s "


def make_logs(dt: float) -> list[jl.Log]:
    """The two synthetic logs. At 100 Hz these are exactly ``tests/test_fit.py``'s;
    ``--quick`` makes the same runs sampled at a lower rate (same sequence, seeds and
    noise model; the speed noise follows the sample rate as in docs/model.md)."""
    if dt == 0.01:
        return _synthetic_logs(TRUTH)
    plant, _ = jl.with_params(jl.Plant(), (), TRUTH)
    ts, pwm = ramped_sequence(THESIS_LIKE_SECTIONS, dt=dt)
    logs = []
    for load, seed in zip(LOADS, SEEDS, strict=True):
        inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), 0.02)
        sol = jl.simulate(plant, (), inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
        key = jax.random.key(seed)
        logs.append(
            jl.to_log(sol, inputs, jl.MeasurementModel(), key, name=f"synthetic_{load:.0f}")
        )
    return logs


# ------------------------------------------------------------------ the SciPy side
class _Capped(Exception):
    """Raised from the residual function when the SciPy fit has used its wall time."""


class ScipyProblem:
    """The same residuals as jaxlift's fit, from ``scipy_reference.simulate_scipy``.

    ``theta`` is in jaxlift's unconstrained coordinates (the same ``ParamInfo``
    transforms). Every evaluation is recorded (time, chi2, theta), including those
    ``least_squares`` makes for its finite differences (so "best chi2 so far" may
    credit SciPy with a point it has not stepped to: in SciPy's favour).
    """

    def __init__(self, logs, experiments, infos, cap_s: float = math.inf):
        self.infos = infos
        self.runs = []
        for log, exp in zip(logs, experiments, strict=True):
            x0 = jl.initial_height(log)
            assert abs(x0 - float(exp.inputs.x0)) < 1e-15
            sigma = np.asarray(exp.sigma)
            self.runs.append((log, x0, sigma[0], sigma[1]))
        self.cap_s = cap_s
        self.t0 = None
        self.record: list[tuple[float, float, np.ndarray]] = []
        self.durations: list[float] = []
        self.failures = 0

    def values(self, theta) -> dict[str, float]:
        """The physical parameters; ``theta`` ends with each log's initial-height offset
        [mm], estimated with them as in jaxlift's fit."""
        p = len(self.infos)
        assert len(theta) == p + len(self.runs)
        return {
            info.name: float(jl.from_unconstrained(info, float(th)))
            for info, th in zip(self.infos, theta[:p], strict=True)
        }

    def residuals(self, theta) -> np.ndarray:
        vals = self.values(theta)
        offsets = 1e-3 * np.asarray(theta[len(self.infos) :], dtype=float)
        out = []
        for (log, x0, s_h, s_v), dx0 in zip(self.runs, offsets, strict=True):
            x0 = x0 + dx0
            try:
                sim = sr.simulate_scipy(
                    vals, log.time_s, log.pwm, log.load_kg, x0, "LSODA", SIM_RTOL, SIM_ATOL
                )
            except RuntimeError:  # solver failure or the fork left the mast
                self.failures += 1
                out.append(np.full(2 * log.n, FAILED_RESIDUAL))
                continue
            out.append((sim["height"] - log.height_m) / s_h)
            out.append((sim["speed"] - log.speed_mps) / s_v)
        return np.concatenate(out)

    def __call__(self, theta) -> np.ndarray:
        """The residual function handed to ``least_squares`` (timed, recorded, capped)."""
        if self.t0 is None:
            self.t0 = time.perf_counter()
        if time.perf_counter() - self.t0 > self.cap_s:
            raise _Capped
        t1 = time.perf_counter()
        r = self.residuals(theta)
        t2 = time.perf_counter()
        self.durations.append(t2 - t1)
        self.record.append((t2 - self.t0, float(r @ r), np.array(theta, dtype=float)))
        return r

    def best(self) -> tuple[float, np.ndarray]:
        _, chi2, theta = min(self.record, key=lambda rec: rec[1])
        return chi2, theta

    def time_to(self, chi2_level: float) -> float | None:
        """Seconds from the start until an evaluation first had chi2 <= ``chi2_level``."""
        for t, chi2, _ in self.record:
            if chi2 <= chi2_level:
                return t
        return None


# ------------------------------------------------------------------ main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"logs sampled at {1 / QUICK_DT:.0f} Hz instead of 100 Hz (4x fewer samples "
        f"and input jumps), SciPy capped at {SCIPY_CAP_QUICK_S:.0f} s (smoke run)",
    )
    args = ap.parse_args()
    cap_s = SCIPY_CAP_QUICK_S if args.quick else SCIPY_CAP_S
    # keep the table readable: LSODA's notes on hard trial points (counted failures are
    # reported; a warning is not a failure)
    warnings.filterwarnings("ignore", message="lsoda: ", category=UserWarning)

    say(
        f"jaxlift fit benchmark{' (--quick)' if args.quick else ''} -- "
        f"{datetime.datetime.now():%Y-%m-%d %H:%M}"
    )
    say(
        f"python {platform.python_version()}, jax {jax.__version__}, diffrax "
        f"{diffrax.__version__}, optimistix {optx.__version__}, equinox {eqx.__version__}, "
        f"scipy {scipy.__version__}, numpy {np.__version__}"
    )
    say(
        f"machine: {cpu_model()}, {os.cpu_count()} CPU cores, "
        f"jax devices {[d.platform for d in jax.devices()]}"
    )
    say(f"load average at start (1, 5, 15 min): {_load()}")

    # ------------------------------------------------------------ data and start
    logs = make_logs(QUICK_DT if args.quick else 0.01)
    experiments = make_experiments(logs)
    n_res = sum(e.n_residuals for e in experiments)
    start = {k: TRUTH[k] * START_FACTOR[k] for k in NAMES}
    infos = all_param_infos(())
    say(
        f"data: {len(logs)} synthetic logs from jaxlift at the truth of tests/test_fit.py "
        f"(thesis-like sequence, {', '.join(f'{lg.load_kg[0]:.0f}' for lg in logs)} kg, "
        f"{logs[0].time_s[-1]:.0f} s at {1 / logs[0].sample_period:.0f} Hz, {logs[0].n} samples "
        f"each; docs/model.md sensor noise, seeds 11, 12; no hidden effect); {n_res} residuals "
        "(height, speed)"
    )
    say(
        f"fitted: {len(NAMES)} parameters ({', '.join(NAMES)}) and each log's initial-height "
        "offset, in jaxlift's unconstrained "
        f"coordinates ({', '.join(sorted({infos[n].transform for n in NAMES}))}); start = "
        "truth x (" + ", ".join(f"{START_FACTOR[n]:.2f}" for n in NAMES) + ")"
    )
    say(
        f"simulators: rtol {SIM_RTOL:g}, atol (x, v, p) {SIM_ATOL}; jaxlift Tsit5, SciPy "
        "solve_ivp LSODA restarted at every input jump (tests/scipy_reference.py)"
    )
    say(
        "jaxlift: fit(free='all', staged=False, n_starts=1): jaxlift's Levenberg-Marquardt "
        "(jaxlift/calibrate/lm.py: residuals at trial points, forward-mode Jacobian at accepted "
        "ones, stop when the Gauss-Newton decrease < 0.01 s^2)"
    )
    say(
        f"scipy:   least_squares(method='trf', jac='2-point', diff_step={DIFF_STEP:g}, "
        f"x_scale={X_SCALE:g}, ftol=xtol=gtol={FTOL:g}), wall time capped at {cap_s:.0f} s"
    )

    # ------------------------------------------------------------ jaxlift: fit()
    t0 = time.perf_counter()
    res = fit(logs, free="all", init=start, staged=False, n_starts=1)
    t_fit = time.perf_counter() - t0
    stage = res.stages[0]
    theta_jl_vals = {n: res.params[n] for n in NAMES}

    # ------------------------------------------------------------ jaxlift: LM alone
    # fit()'s residuals and Jacobian are jitted once per problem structure, so a second
    # identical call reuses the compiled code: its LM stage is the compile-excluded time.
    t0 = time.perf_counter()
    res2 = fit(logs, free="all", init=start, staged=False, n_starts=1)
    t_fit2 = time.perf_counter() - t0
    t_lm = res2.stages[0].wall_s
    steps_lm = res2.stages[0].num_steps
    lm_agrees = abs(res2.chi2 - res.chi2) < 1e-9 * res.chi2
    # optimistix's Levenberg--Marquardt on the same problem (fit(solver=OptimistixLM())),
    # for reference: compiled afresh on each call
    t0 = time.perf_counter()
    res_ox = fit(logs, free="all", init=start, staged=False, n_starts=1, method="optimistix")
    t_ox = time.perf_counter() - t0

    plant0, _ = jl.with_params(jl.Plant(), (), start)
    problem = _Problem(plant0, (), tuple(experiments), NAMES, tuple(infos[n] for n in NAMES))
    theta0 = problem.to_theta(start)

    def chi2_jaxlift(values, x0_mm=None) -> float:
        r = problem.residuals_at(problem.to_theta(values, x0_mm))
        return float(r @ r)

    load_mid = _load()

    # ------------------------------------------------------------ SciPy
    sp = ScipyProblem(logs, experiments, tuple(infos[n] for n in NAMES), cap_s=cap_s)
    x0 = np.asarray(theta0)
    t0 = time.perf_counter()
    try:
        ls = least_squares(
            sp,
            x0,
            jac="2-point",
            method="trf",
            x_scale=X_SCALE,
            diff_step=DIFF_STEP,
            ftol=FTOL,
            xtol=XTOL,
            gtol=GTOL,
            max_nfev=1000,
        )
        capped = False
        sp_msg = ls.message
        sp_iters = f"{ls.nfev} trial points, {ls.njev} Jacobians"
        chi2_sp, theta_sp = 2.0 * float(ls.cost), np.asarray(ls.x)
    except _Capped:
        capped = True
        sp_msg = f"stopped at the {cap_s:.0f} s cap"
        sp_iters = "-"
        chi2_sp, theta_sp = sp.best()
    t_sp = time.perf_counter() - t0
    n_sims = len(sp.record)
    sp_vals = sp.values(theta_sp)

    # ------------------------------------------------------------ cross-evaluation
    chi2_start_jl = chi2_jaxlift(start)
    chi2_start_sp = sp.record[0][1]
    x0_jl = [1e3 * res.x0_offsets[e.name] for e in experiments]  # mm
    x0_sp = np.asarray(theta_sp)[len(NAMES) :]
    th_jl = np.asarray(problem.to_theta(theta_jl_vals, x0_jl))
    chi2_sp_at_jl = float(np.sum(sp.residuals(th_jl) ** 2))
    chi2_jl_at_sp = chi2_jaxlift(sp_vals, x0_sp)
    chi2_sp_at_truth = float(np.sum(sp.residuals(np.asarray(problem.to_theta(TRUTH))) ** 2))
    chi2_jl_at_truth = chi2_jaxlift(TRUTH)
    level = chi2_sp_at_jl + CHI2_TOL
    t_reach = sp.time_to(level)

    say()
    say(f"chi2 = sum of squared scaled residuals, N = {n_res}")
    say(f"  {'point':34s} {'jaxlift sim':>14s} {'scipy sim':>14s}")
    say(f"  {'start':34s} {chi2_start_jl:14.6g} {chi2_start_sp:14.6g}")
    say(f"  {'truth':34s} {chi2_jl_at_truth:14.3f} {chi2_sp_at_truth:14.3f}")
    say(f"  {'jaxlift optimum':34s} {res.chi2:14.3f} {chi2_sp_at_jl:14.3f}")
    say(f"  {'scipy end point':34s} {chi2_jl_at_sp:14.3f} {chi2_sp:14.3f}")
    say(
        f"  (each column is one simulator's chi2; the two simulators differ by ~um, so the "
        f"same point can differ by ~1 in chi2 between columns; SciPy is measured against "
        f"its own column: it has reached jaxlift's optimum at chi2 <= "
        f"{chi2_sp_at_jl:.3f} + {CHI2_TOL:g})"
    )
    say(
        f"jaxlift: {stage.message}, {stage.num_steps} LM steps; chi2/N {res.chi2 / n_res:.4f}; "
        f"second (compiled) call {'agrees' if lm_agrees else 'DISAGREES'} "
        f"(chi2 {res2.chi2:.3f}, {steps_lm} steps)"
    )
    say(
        f"optimistix LM (fit(method='optimistix'), for reference): {res_ox.stages[0].message}, "
        f"{res_ox.stages[0].num_steps} steps, chi2 {res_ox.chi2:.3f}, fit() {t_ox:.1f} s, "
        f"LM stage {res_ox.stages[0].wall_s:.1f} s incl compile"
    )
    say(
        f"scipy:   {sp_msg}; {sp_iters}; {n_sims} residual evaluations "
        f"({2 * n_sims} simulations, median {statistics.median(sp.durations):.2f} s per "
        f"evaluation of both logs, {sp.failures} failed simulations); best chi2/N "
        f"{chi2_sp / n_res:.4f}"
    )
    marks = []
    for extra in (1000.0, 100.0, 10.0, 1.0, CHI2_TOL):
        t = sp.time_to(chi2_sp_at_jl + extra)
        marks.append(f"+{extra:g}: " + (f"{t:.0f} s" if t is not None else "not reached"))
    say("scipy's time to chi2 <= (jaxlift's optimum, scipy sim) + ...: " + "; ".join(marks))

    # ------------------------------------------------------------ table
    def row(num, what, a, b, value, target, status):
        say(f"{num:3s} {what:50s} {a:>10s} {b:>10s} {value:>9s} {target:>8s}  {status}")

    say()
    say("timings: wall time of one run each (not interleaved; see the load averages)")
    say(
        f"{'#':3s} {'measurement':50s} {'jaxlift':>10s} {'scipy':>10s} {'value':>9s} "
        f"{'target':>8s}  status"
    )
    say("-" * 100)
    # scipy's time to jaxlift's optimum: measured; or, if it was capped first, a lower
    # bound; or, if it stopped (converged) above it, never (jaxlift reaches a lower cost)
    never = t_reach is None and not capped
    t_sp_eq = t_reach if t_reach is not None else t_sp
    bound = "" if t_reach is not None else ">="
    sp_col = fmt_t(t_reach) if t_reach is not None else ("never" if never else f">{t_sp:.0f} s")

    def ratio_row(num, what, t_jl, target):
        r = math.inf if never else t_sp_eq / t_jl
        if target is None:
            status = "info"
        elif r >= target:
            status = "PASS"
        else:
            status = "MISS" if t_reach is not None else "OPEN (capped: only a lower bound)"
        tg = "-" if target is None else f">= {target:g}x"
        value = "inf" if never else f"{bound}{r:.1f}x"
        row(num, what, fmt_t(t_jl), sp_col, value, tg, status)

    row(
        "1",
        "fit() total: compile + LM + error analysis",
        fmt_t(t_fit),
        "",
        f"{t_fit:.1f} s",
        "<= 60 s",
        "PASS" if t_fit <= 60.0 else "MISS",
    )
    ratio_row("2", "time to the optimum: LM stage of fit(), incl compile", stage.wall_s, 20)
    ratio_row("2b", "time to the optimum: LM stage, compiled (2nd call)", t_lm, 20)
    ratio_row("2c", "time to the optimum: fit() total", t_fit, None)
    row(
        "3",
        "final chi2/N (own simulator)",
        f"{res.chi2 / n_res:.5f}",
        f"{chi2_sp / n_res:.5f}",
        f"{chi2_sp - chi2_sp_at_jl:+.2f}",
        f">= -{CHI2_TOL:g}",
        "PASS" if chi2_sp - chi2_sp_at_jl >= -CHI2_TOL else "MISS",
    )
    say("-" * 100)
    say(
        f"row 2: scipy = time until its chi2 first reached jaxlift's optimum (+{CHI2_TOL:g}); "
        "jaxlift = until its converged result. Row 3 value: scipy's final chi2 minus "
        "jaxlift's optimum, both in scipy's simulator (PASS: jaxlift's cost is equal or "
        "lower)."
    )
    say(
        f"jaxlift: fit() {t_fit:.1f} s = LM stage {stage.wall_s:.1f} s (compile + "
        f"{stage.num_steps} accepted steps) + error analysis {t_fit - stage.wall_s:.1f} s; "
        f"second call (compiled): fit() {t_fit2:.1f} s, LM {t_lm:.1f} s"
    )
    say(f"scipy: total wall time of the least_squares call {t_sp:.1f} s")

    # ------------------------------------------------------------ parameters
    say()
    say("parameters recovered (relative error vs truth; jaxlift stderr AR(1)-inflated)")
    say(
        f"  {'name':8s} {'truth':>11s} {'start':>11s} {'jaxlift':>11s} {'err':>8s} "
        f"{'stderr':>9s} {'scipy':>11s} {'err':>8s}"
    )
    for n in NAMES:
        tv, jv, sv = TRUTH[n], res.params[n], sp_vals[n]
        say(
            f"  {n:8s} {tv:11.5g} {start[n]:11.5g} {jv:11.5g} {jv / tv - 1:+8.2%} "
            f"{res.stderr[n]:9.2g} {sv:11.5g} {sv / tv - 1:+8.2%}"
        )

    def prod(v):
        return v["cf_out"] * v["cf_in"] ** 5

    say(
        f"  {'cf_out*cf_in^5':14s} {prod(TRUTH):11.4g} {prod(start):11.4g} "
        f"{prod(res.params):11.4g} {prod(res.params) / prod(TRUTH) - 1:+8.2%} "
        f"{'':9s} {prod(sp_vals):11.4g} {prod(sp_vals) / prod(TRUTH) - 1:+8.2%}"
    )
    if res.undetermined:
        say(f"  jaxlift names as undetermined: {', '.join(sorted(res.undetermined))}")
    say()
    say(f"load average after jaxlift (1, 5, 15 min): {load_mid}")
    say(f"load average at end (1, 5, 15 min): {_load()}  (> 1 per core: shared machine, noisy)")

    if args.quick:  # a smoke run: the results file keeps the last full run
        print(f"\n--quick: {RESULTS.name} not written")
    else:
        RESULTS.write_text("\n".join(_lines) + "\n", encoding="utf-8")
        print(f"\nwritten to {RESULTS}")


if __name__ == "__main__":
    main()
