# ruff: noqa: E402  (float64 must be switched on before anything else imports jax)
"""Benchmark: jaxlift's simulation against SciPy on the same equations, side by side.

Run from the repository root::

    .venv/bin/python benchmarks/bench_simulate.py

Prints a table (each measured number, its target, PASS/MISS) and writes the same text
to ``benchmarks/results_simulate.txt``. See ``benchmarks/README.md``.

The peer is ``tests/scipy_reference.py``: an independent plain-float implementation of
docs/model.md, integrated piecewise between input jumps (restarted at every jump, analytic
Jacobian), by ``solve_ivp(method="LSODA")``; ``odeint`` (ODEPACK's LSODA driven with
less Python per call) is shown as a second, faster SciPy peer for information.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import datetime
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy

import jaxlift as jl
from jaxlift.model.simulate import DTMAX, error_norm
from jaxlift.model.vector_field import initial_state, lift_vector_field

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

import scipy_reference as sr
from _machine import cpu_model
from test_reference import thesis_like_run

RESULTS = HERE / "results_simulate.txt"

#: Accuracy setting shared by jaxlift and the SciPy peers: jaxlift's defaults.
RTOL = 1e-6
ATOL = (1e-7, 1e-7, 1.0)
#: The tight-tolerance reference (scipy LSODA; its own height error is ~1e-9 m).
REF_RTOL, REF_ATOL = 1e-12, (1e-13, 1e-13, 1e-6)
#: Parameters of the run (others nominal).
TRUE = {"beta": 0.5e9}
#: Estimated in the thesis: the forward-mode Jacobian's parameters.
ESTIMATED = ("k1", "k2", "k3", "z1", "z2", "z3", "beta", "cf_con", "cf_in", "cf_out", "d")
N_BATCH = 32
SIGMA_H = 5e-4  # m, height noise of the wire sensor (docs/model.md)
SIGMA_V = float(np.sqrt(1e-7 * 100.0))  # m/s, speed noise at 100 Hz (docs/model.md)

_lines: list[str] = []


def say(text: str = "") -> None:
    print(text, flush=True)
    _lines.append(text)


_spreads: dict[str, list[float]] = {}


def interleaved(fns: dict, reps: dict, rounds: int) -> tuple[dict, dict]:
    """Median wall time of each function, the calls interleaved over ``rounds`` rounds
    (``reps[name]`` calls of each per round), so that a change in the machine's load
    during the benchmark hits the compared timings alike. Returns (medians, results)."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    outs: dict[str, object] = {}
    for _ in range(rounds):
        for name, fn in fns.items():
            for _ in range(reps[name]):
                t0 = time.perf_counter()
                outs[name] = jax.block_until_ready(fn())
                times[name].append(time.perf_counter() - t0)
    _spreads.update(times)
    return {k: statistics.median(v) for k, v in times.items()}, outs


def first_call(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - t0, out


def _load() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def fmt_t(s: float) -> str:
    return f"{s * 1e3:8.1f} ms" if s < 1.0 else f"{s:8.2f} s "


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


def main() -> None:
    ts, pwm, load, x0 = thesis_like_run()
    inputs = jl.Inputs.from_arrays(ts, pwm, load, x0)
    plant, _ = jl.with_params(jl.Plant(), (), TRUE)
    params = {k: float(v) for k, v in jl.model_params(plant).items()}

    say(f"jaxlift simulate benchmark -- {datetime.datetime.now():%Y-%m-%d %H:%M}")
    say(
        f"python {platform.python_version()}, jax {jax.__version__}, diffrax "
        f"{diffrax.__version__}, equinox {eqx.__version__}, scipy {scipy.__version__}, "
        f"numpy {np.__version__}"
    )
    say(
        f"machine: {cpu_model()}, {os.cpu_count()} CPU cores, "
        f"jax devices {[d.platform for d in jax.devices()]}"
    )
    say(f"load average at start (1, 5, 15 min): {_load()}")
    say(f"accuracy setting for all timed solvers: rtol = {RTOL:g}, atol (x, v, p) = {ATOL}")

    # ------------------------------------------------------------ reference
    t0 = time.perf_counter()
    ref = sr.simulate_scipy(params, ts, pwm, load, x0, "LSODA", REF_RTOL, REF_ATOL)
    t_ref = time.perf_counter() - t0
    say(
        f"run: {ts[-1]:.0f} s at 100 Hz ({ts.size} samples, {inputs.jump_ts.size} input jumps: "
        f"1 s ramps change pwm at every sample), {load[0]:.0f} kg, beta = {TRUE['beta']:.2g} Pa, "
        f"others nominal; height {x0:.2f} -> {ref['height'].max():.2f} m (both stage shifts)"
    )
    say(f"reference: scipy LSODA rtol {REF_RTOL:g} ({t_ref:.1f} s, {ref['nfev']} rhs calls)")

    # ------------------------------------------------------------ 1. one run
    @eqx.filter_jit
    def forward(plant, inputs):
        sol = jl.simulate(plant, (), inputs, rtol=RTOL, atol=ATOL)
        return sol.ys, sol.num_steps, sol.ok

    c_fwd, _ = first_call(lambda: forward(plant, inputs))

    @eqx.filter_jit
    def forward_clip(plant, inputs):
        """The same solve with diffrax's ClipStepSizeController(jump_ts=...), which
        jaxlift used before JumpStepSizeController (jaxlift/model/stepping.py)."""
        atol = jnp.asarray(ATOL)
        pid = diffrax.PIDController(rtol=RTOL, atol=atol, dtmax=DTMAX, norm=error_norm)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lift_vector_field),
            diffrax.Tsit5(),
            t0=inputs.ts[0],
            t1=inputs.ts[-1],
            dt0=None,
            y0=initial_state(plant, (), inputs),
            args=(plant, (), inputs),
            saveat=diffrax.SaveAt(ts=inputs.ts),
            stepsize_controller=diffrax.ClipStepSizeController(pid, jump_ts=inputs.jump_ts),
            max_steps=200_000,
            throw=False,
        )
        return sol.ys, sol.stats["num_steps"]

    c_clip, _ = first_call(lambda: forward_clip(plant, inputs))

    def run_scipy(p, method):
        return sr.simulate_scipy(p, ts, pwm, load, x0, method, RTOL, ATOL)

    med, outs = interleaved(
        {
            "jl": lambda: forward(plant, inputs),
            "ivp": lambda: run_scipy(params, "LSODA"),
            "clip": lambda: forward_clip(plant, inputs),
            "ode": lambda: run_scipy(params, "odeint"),
        },
        {"jl": 5, "ivp": 1, "clip": 5, "ode": 1},
        rounds=3,
    )
    t_jl, t_ivp, t_ode, t_clip = med["jl"], med["ivp"], med["ode"], med["clip"]
    ys_jl, steps_jl, ok_jl = outs["jl"]
    ys_clip, steps_clip = outs["clip"]
    r_ivp, r_ode = outs["ivp"], outs["ode"]
    assert bool(ok_jl), "jaxlift failed on the benchmark run"

    say()
    say("accuracy of the timed single runs against the reference")
    say(f"  {'solver':38s} {'max|dh| [m]':>12s} {'max|dv| [m/s]':>14s}  work")
    acc_rows = (
        ("jaxlift Tsit5 (default settings)", ys_jl[:, 0], ys_jl[:, 1], f"{int(steps_jl)} steps"),
        ("scipy solve_ivp LSODA", r_ivp["height"], r_ivp["speed"], f"{r_ivp['nfev']} rhs calls"),
        ("scipy odeint LSODA", r_ode["height"], r_ode["speed"], f"{r_ode['nfev']} rhs calls"),
    )
    for name, h, v, work in acc_rows:
        say(
            f"  {name:38s} {max_abs(h, ref['height']):12.2e} "
            f"{max_abs(v, ref['speed']):14.2e}  {work}"
        )
    say(
        f"  jaxlift's JumpStepSizeController vs diffrax's ClipStepSizeController (same run): "
        f"{int(steps_jl)} vs {int(steps_clip)} steps, max |dy| {max_abs(ys_jl, ys_clip):.1e}"
    )

    # ------------------------------------------------------------ 2. batch of 32
    rng = np.random.default_rng(2024)
    batch = {
        "beta": rng.uniform(0.3e9, 1.2e9, N_BATCH),
        "cf_con": rng.uniform(5.0, 40.0, N_BATCH),
        "d": rng.uniform(150.0, 1000.0, N_BATCH),
        "k1": rng.uniform(1.75, 2.05, N_BATCH),
    }
    batch_j = {k: jnp.asarray(v) for k, v in batch.items()}

    @eqx.filter_jit
    def forward_batch(plant, values, inputs):
        def one(v):
            p, _ = jl.with_params(plant, (), v)
            sol = jl.simulate(p, (), inputs, rtol=RTOL, atol=ATOL)
            return sol.ys[:, 0], sol.num_steps, sol.ok

        return eqx.filter_vmap(one)(values)

    @eqx.filter_jit
    def forward_map(plant, values, inputs):  # the same batch, one member after the other
        def one(v):
            p, _ = jl.with_params(plant, (), v)
            return jl.simulate(p, (), inputs, rtol=RTOL, atol=ATOL).ys[:, 0]

        return jax.lax.map(one, values)

    c_batch, _ = first_call(lambda: forward_batch(plant, batch_j, inputs))
    c_map, _ = first_call(lambda: forward_map(plant, batch_j, inputs))

    def scipy_batch(method):
        hs = []
        for i in range(N_BATCH):
            p = dict(params, **{k: float(v[i]) for k, v in batch.items()})
            hs.append(run_scipy(p, method)["height"])
        return np.array(hs)

    # vmap 2x, 32 solve_ivp runs, lax.map 2x, vmap 2x, 32 odeint runs, lax.map 2x
    med, outs = interleaved(
        {
            "b_jl": lambda: forward_batch(plant, batch_j, inputs),
            "b_ivp": lambda: scipy_batch("LSODA"),
            "b_map": lambda: forward_map(plant, batch_j, inputs),
            "b_jl2": lambda: forward_batch(plant, batch_j, inputs),
            "b_ode": lambda: scipy_batch("odeint"),
            "b_map2": lambda: forward_map(plant, batch_j, inputs),
        },
        {"b_jl": 2, "b_ivp": 1, "b_map": 2, "b_jl2": 2, "b_ode": 1, "b_map2": 2},
        rounds=1,
    )
    t_batch = statistics.median([med["b_jl"], med["b_jl2"]])
    t_map = statistics.median([med["b_map"], med["b_map2"]])
    h_map = outs["b_map"]
    t_batch_ivp, t_batch_ode = med["b_ivp"], med["b_ode"]
    h_batch, steps_batch, ok_batch = outs["b_jl"]
    h_batch_ivp, h_batch_ode = outs["b_ivp"], outs["b_ode"]
    assert bool(jnp.all(ok_batch)), "jaxlift failed on a batch member"
    say()
    say(
        f"batch of {N_BATCH} parameter sets (beta, cf_con, d, k1 varied): max |dh| between "
        f"jaxlift and scipy over all members {max_abs(h_batch, h_batch_ivp):.2e} m "
        f"(solve_ivp), {max_abs(h_batch, h_batch_ode):.2e} m (odeint); vmap vs lax.map "
        f"{max_abs(h_batch, h_map):.1e} m; jaxlift steps "
        f"{int(jnp.min(steps_batch))}..{int(jnp.max(steps_batch))} (the vmapped solve runs "
        "until its slowest member is done)"
    )

    # ------------------------------------------------------------ 3. gradients
    # synthetic data from the true parameters, misfit evaluated at a perturbed point
    noise = np.random.default_rng(7)
    h_data = jnp.asarray(ref["height"] + SIGMA_H * noise.standard_normal(ts.size))
    v_data = jnp.asarray(ref["speed"] + SIGMA_V * noise.standard_normal(ts.size))
    start = {k: jnp.asarray(v) for k, v in jl.model_params(jl.Plant()).items()}
    start["beta"] = jnp.asarray(0.6e9)
    start["d"] = jnp.asarray(400.0)

    def residuals(values, plant, inputs, adjoint=None):
        p, _ = jl.with_params(plant, (), values)
        sol = jl.simulate(p, (), inputs, rtol=RTOL, atol=ATOL, adjoint=adjoint)
        return jnp.concatenate([(sol.height - h_data) / SIGMA_H, (sol.speed - v_data) / SIGMA_V])

    def misfit(values, plant, inputs):
        return jnp.sum(residuals(values, plant, inputs) ** 2)

    misfit_jit = eqx.filter_jit(misfit)
    grad_jit = eqx.filter_jit(jax.grad(misfit))

    def misfit_fwd(values, plant, inputs):  # the same misfit, differentiable in forward mode
        r = residuals(values, plant, inputs, adjoint=diffrax.ForwardMode())
        return jnp.sum(r**2)

    grad_fwd_jit = eqx.filter_jit(jax.jacfwd(misfit_fwd))

    c_mis, _ = first_call(lambda: misfit_jit(start, plant, inputs))
    c_grad, _ = first_call(lambda: grad_jit(start, plant, inputs))
    c_gfwd, _ = first_call(lambda: grad_fwd_jit(start, plant, inputs))

    est0 = jnp.stack([start[k] for k in ESTIMATED])

    @eqx.filter_jit
    def jac_fwd(theta, plant, inputs):
        def res(th):
            values = dict(start, **{k: th[i] for i, k in enumerate(ESTIMATED)})
            return residuals(values, plant, inputs, adjoint=diffrax.ForwardMode())

        return res(theta), jax.jacfwd(res)(theta)

    c_jac, _ = first_call(lambda: jac_fwd(est0, plant, inputs))
    med, outs = interleaved(
        {
            "mis": lambda: misfit_jit(start, plant, inputs),
            "grad": lambda: grad_jit(start, plant, inputs),
            "gfwd": lambda: grad_fwd_jit(start, plant, inputs),
            "jac": lambda: jac_fwd(est0, plant, inputs),
        },
        {"mis": 3, "grad": 1, "gfwd": 1, "jac": 1},
        rounds=5,
    )
    t_mis, t_grad, t_gfwd, t_jac = med["mis"], med["grad"], med["gfwd"], med["jac"]
    chi2, g_rev, (r0, jac) = outs["mis"], outs["grad"], outs["jac"]
    g_fwd_all = outs["gfwd"]
    g_rel_all = max(
        abs(float(g_fwd_all[k]) - float(g_rev[k])) / (abs(float(g_rev[k])) + 1e-300) for k in start
    )
    g_fwd = 2.0 * jac.T @ r0  # gradient of sum(r^2) from the forward-mode Jacobian
    g_rev_est = jnp.stack([g_rev[k] for k in ESTIMATED])
    g_rel = float(jnp.max(jnp.abs(g_fwd - g_rev_est) / (jnp.abs(g_rev_est) + 1e-300)))
    say()
    say(
        f"gradients at a perturbed point (beta 0.6e9, d 400; chi2 = {float(chi2):.4g}) w.r.t. "
        f"all {len(start)} baseline parameters: forward mode (jax.jacfwd with "
        "diffrax.ForwardMode(), what jaxlift uses for fitting, "
        f"~{len(ESTIMATED)}-{len(start)} parameters) and reverse mode (jax.grad, default "
        f"RecursiveCheckpointAdjoint); they agree to a max relative difference of "
        f"{g_rel_all:.1e} over all {len(start)} entries; the forward-mode Jacobian "
        f"{tuple(jac.shape)} w.r.t. the {len(ESTIMATED)} estimated ones gives 2 J^T r equal "
        f"to the reverse-mode gradient to {g_rel:.1e} (at rtol {RTOL:g} the solves of the "
        "different modes need not take identical steps, so gradients can differ at the "
        "tolerance level; see README)"
    )

    # ------------------------------------------------------------ table
    def row(num, what, a, b, value, target, ok):
        status = "info" if ok is None else ("PASS" if ok else "MISS")
        say(f"{num:3s} {what:46s} {a:>11s} {b:>11s} {value:>9s} {target:>8s}  {status}")

    say()
    say("timings: medians after compile; the compared runs interleaved (scipy batch: 32 runs once)")
    say(
        f"{'#':3s} {'measurement':46s} {'jaxlift':>11s} {'peer':>11s} {'value':>9s} "
        f"{'target':>8s}  status"
    )
    say("-" * 100)
    r1 = t_ivp / t_jl
    row(
        "1",
        "one 130 s run vs solve_ivp LSODA",
        fmt_t(t_jl),
        fmt_t(t_ivp),
        f"{r1:.0f}x",
        ">= 50x",
        r1 >= 50,
    )
    r1b = t_ode / t_jl
    row("1b", "one 130 s run vs odeint LSODA", fmt_t(t_jl), fmt_t(t_ode), f"{r1b:.0f}x", "-", None)
    r1c = t_clip / t_jl
    row(
        "1c",
        "  (diffrax ClipStepSizeController / jaxlift's)",
        fmt_t(t_jl),
        fmt_t(t_clip),
        f"{r1c:.2f}x",
        "-",
        None,
    )
    r2 = t_batch_ivp / t_batch
    row(
        "2",
        f"batch of {N_BATCH} (filter_vmap) vs {N_BATCH} solve_ivp runs",
        fmt_t(t_batch),
        fmt_t(t_batch_ivp),
        f"{r2:.0f}x",
        ">= 200x",
        r2 >= 200,
    )
    r2b = t_batch_ode / t_batch
    row(
        "2b",
        f"batch of {N_BATCH} (filter_vmap) vs {N_BATCH} odeint runs",
        fmt_t(t_batch),
        fmt_t(t_batch_ode),
        f"{r2b:.0f}x",
        "-",
        None,
    )
    r2c = t_batch_ivp / t_map
    row(
        "2c",
        f"batch of {N_BATCH} (jax.lax.map) vs {N_BATCH} solve_ivp runs",
        fmt_t(t_map),
        fmt_t(t_batch_ivp),
        f"{r2c:.0f}x",
        ">= 200x",
        r2c >= 200,
    )
    row(
        "",
        "  (vmap batch per member / one unbatched run)",
        fmt_t(t_batch / N_BATCH),
        fmt_t(t_jl),
        f"{t_batch / N_BATCH / t_jl:.2f}x",
        "-",
        None,
    )
    r3 = t_gfwd / t_mis
    row(
        "3",
        f"grad, {len(start)} params, forward mode / one forward",
        fmt_t(t_gfwd),
        fmt_t(t_mis),
        f"{r3:.1f}x",
        "<= 4x",
        r3 <= 4,
    )
    r3b = t_grad / t_mis
    row(
        "3b",
        "same gradient, reverse mode (jax.grad) / forward",
        fmt_t(t_grad),
        fmt_t(t_mis),
        f"{r3b:.1f}x",
        "-",
        None,
    )
    r4 = t_jac / t_mis
    row(
        "4",
        f"jacfwd (ForwardMode), {len(ESTIMATED)} params / one forward",
        fmt_t(t_jac),
        fmt_t(t_mis),
        f"{r4:.1f}x",
        "-",
        None,
    )
    say("-" * 100)
    spread = {"jl": "jaxlift one run", "clip": "same with ClipStepSizeController"}
    spread.update(ivp="solve_ivp one run", mis="jaxlift misfit")
    spread.update(gfwd="forward-mode grad", grad="reverse grad", jac="forward Jacobian")
    say(
        "spread (min / median / max, n): "
        + "; ".join(
            f"{label} {min(_spreads[k]) * 1e3:.0f} / {statistics.median(_spreads[k]) * 1e3:.0f}"
            f" / {max(_spreads[k]) * 1e3:.0f} ms, {len(_spreads[k])}"
            for k, label in spread.items()
        )
    )
    say(
        f"compile (first call incl. tracing): forward {c_fwd:.1f} s (with "
        f"ClipStepSizeController {c_clip:.1f} s), batch vmap {c_batch:.1f} s, "
        f"batch lax.map {c_map:.1f} s, misfit {c_mis:.1f} s, reverse grad {c_grad:.1f} s, "
        f"forward-mode grad {c_gfwd:.1f} s, forward Jacobian {c_jac:.1f} s"
    )
    say(f"reference run (scipy LSODA rtol {REF_RTOL:g}): {t_ref:.1f} s")
    say(f"load average at end (1, 5, 15 min): {_load()}  (> 1 per core: shared machine, noisy)")

    RESULTS.write_text("\n".join(_lines) + "\n", encoding="utf-8")
    print(f"\nwritten to {RESULTS}")


if __name__ == "__main__":
    main()
