# ruff: noqa: E402  (float64 and the CPU device count must be set before jax is used)
"""Benchmark: the posterior's log-probability on a GPU against the same machine's CPU.

For a machine with an NVIDIA GPU and JAX's CUDA plugin. Run from the repository root,
twice, as two processes (JAX picks its platform once per process)::

    JAX_PLATFORMS=cpu python benchmarks/bench_gpu.py --platform cpu --out cpu.json
    python benchmarks/bench_gpu.py --platform gpu --out gpu.json --compare cpu.json

Problem: the one of ``bench_posterior.py`` (a): the two shipped 130 s logs, the baseline
model, the default sampled set ``beta, cf_con, cf_in, cf_out, d`` and AR(1) likelihood.
The set-up (least-squares re-fit, Laplace covariance) runs on the CPU in both processes,
so that both evaluate the same walkers. Then the log-probability of batches of walkers
drawn around the optimum (seed 0) is timed:

- ``cpu``: ``jax.lax.map`` split across one XLA CPU device per core (what ``jaxlift
  posterior`` does), and on one core;
- ``gpu``: ``jax.vmap`` over the batch on the GPU (every walker steps until the slowest
  one finishes; ``lax.map`` would run them one after the other).

Prints evaluations per second per batch size; with ``--compare`` also the largest
relative difference between the GPU's and the CPU's log-densities (float64 on both).
"""

from __future__ import annotations

import os

import jax

jax.config.update("jax_enable_x64", True)
N_CORES = len(os.sched_getaffinity(0))
jax.config.update("jax_num_cpu_devices", N_CORES)

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

import jaxlift as jl
from jaxlift.posterior.likelihood import make_log_prob
from jaxlift.posterior.problem import prepare_posterior

ROOT = Path(__file__).resolve().parent.parent


def say(text: str) -> None:
    print(text, flush=True)


def setup():
    """The posterior problem of ``bench_posterior.py``, set up on the CPU."""
    logs = [jl.read_log(ROOT / "data" / f) for f in ("lift_500kg.csv", "lift_1500kg.csv")]
    truth = jl.load_params_json(ROOT / "data" / "truth.json", jl.all_param_infos("all"))
    base = {k: v for k, v in truth.items() if k in jl.all_param_infos(())}
    with jax.default_device(jax.devices("cpu")[0]):
        return prepare_posterior(logs, params=base)


def rate(f, th: np.ndarray, rounds: int) -> dict:
    """First call (compilation included) and the best of ``rounds`` timed calls."""
    t0 = time.perf_counter()
    vals = f(th)
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(rounds):
        t0 = time.perf_counter()
        f(th)
        best = min(best, time.perf_counter() - t0)
    return {"first_s": first, "best_s": best, "evals_per_s": th.shape[0] / best,
            "values": vals.tolist()}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--platform", choices=("cpu", "gpu"), required=True)
    ap.add_argument("--batches", default="16,128,1024", help="batch sizes, comma-separated")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", required=True, help="JSON of the timings and log-densities")
    ap.add_argument("--compare", help="the CPU run's JSON: compare the log-densities")
    args = ap.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    dev = jax.devices()[0]
    say(f"# bench_gpu --platform {args.platform}: python {sys.version.split()[0]}, jax "
        f"{jax.__version__}, {platform.machine()}, {N_CORES} cores, default device "
        f"{dev.device_kind} ({dev.platform})")  # fmt: skip
    t0 = time.perf_counter()
    problem = setup()
    say(f"set-up on the CPU: {time.perf_counter() - t0:.0f} s; sampled {', '.join(problem.names)}")
    rng = np.random.default_rng(0)
    th_all = rng.multivariate_normal(problem.theta_opt, problem.cov_theta, size=max(batches))
    out = {"platform": args.platform, "device": dev.device_kind, "cores": N_CORES, "runs": {}}
    if args.platform == "cpu":
        modes = {f"map, {N_CORES} CPU devices": make_log_prob(problem, batch="map")}
        modes["map, 1 CPU device"] = make_log_prob(problem, batch="map", devices=1)
    else:
        modes = {"vmap, 1 GPU": make_log_prob(problem, batch="vmap", devices=1)}
    for label, f in modes.items():
        for b in batches:
            if label.endswith("1 CPU device") and b > 16:
                continue  # ~30 ms per walker and core: the rate does not depend on b
            r = rate(f, th_all[:b], args.rounds)
            out["runs"][f"{label}, batch {b}"] = r
            say(f"  {label:24s} batch {b:5d}: {r['evals_per_s']:8.1f} evals/s (best "
                f"{r['best_s']:.3f} s; first call incl. compile {r['first_s']:.1f} s)")  # fmt: skip
    if args.compare:
        ref = json.loads(Path(args.compare).read_text())
        cpu_vals = max((r["values"] for r in ref["runs"].values()), key=len)
        for key, r in out["runs"].items():
            n = min(len(cpu_vals), len(r["values"]))
            a, b = np.asarray(cpu_vals[:n]), np.asarray(r["values"][:n])
            both = np.isfinite(a) & np.isfinite(b)
            rel = np.max(np.abs(a[both] - b[both]) / np.abs(a[both])) if both.any() else np.nan
            one = int((np.isfinite(a) ^ np.isfinite(b)).sum())
            say(f"  {key}: log-density vs the CPU's, {n} walkers: max relative difference "
                f"{rel:.2e}; finite on both {both.sum()}, on one only {one}")  # fmt: skip
            out["runs"][key]["max_rel_diff_vs_cpu"] = float(rel)
    Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
