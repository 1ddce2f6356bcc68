"""Does gain scheduling by load pay its way? (issue #18)

Plain PID against the gain-scheduled PID of docs/control.md (one PID per stage, each
gain linear in the load), both tuned the way ``jaxlift tune`` tunes by default -- the
loop as deployed (sampled every 10 ms, duty held, the speed sensor's noise averaged
over seeds) -- on the shipped logs' true model (``data/truth.json``), at the loads
300, 1 000 and 2 000 kg, then evaluated with noise seeds the tuning never saw at eight
loads from 300 to 2 000 kg along the whole 110 s reference.

Recommendation rule (stated before the run): the simpler plain PID, unless the
scheduled one lowers the mean cost over the evaluation loads by at least 10 % *and*
that difference is larger than 2 standard errors of the paired per-load, per-seed
differences.

    .venv/bin/python studies/gain_scheduling.py [--out studies/results/gain_scheduling]
        [--quick]

Writes ``gain_scheduling.md`` (tables, the recommendation), ``gain_scheduling.json`` and
``gain_scheduling.png`` (figures against load) under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxlift as jl  # noqa: E402
from jaxlift.control.controller import THESIS_PID  # noqa: E402
from jaxlift.control.cost import tuning_cost  # noqa: E402
from jaxlift.control.tune import tune_gains  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent.parent
TUNE_LOADS = (300.0, 1000.0, 2000.0)
EVAL_LOADS = (300.0, 500.0, 750.0, 1000.0, 1250.0, 1500.0, 1750.0, 2000.0)
TUNE_SEEDS = (0, 1)
EVAL_SEEDS = (100, 101, 102)
MIN_GAIN = 0.10  # the scheduled PID must be at least this much better to be recommended


def evaluate(ctrl, plant, effects, loads, seeds, time_scale):
    """Per load and seed: tuning cost (NaN for a failed run: solver failure or the fork
    out of the mast's range), tracking and oscillation RMS [mm/s] (of the run as far
    as it went)."""
    rows = []
    for m in loads:
        ref = jl.thesis_reference(m, time_scale=time_scale)
        for s in seeds:
            sol = jl.simulate_closed_loop(
                plant, effects, ctrl, ref, sampled=True, T_c=0.01, noise_seed=s
            )
            ok = bool(sol.ok)
            f = jl.closed_loop_figures(sol).as_dict()
            rows.append(
                dict(
                    load_kg=m,
                    seed=s,
                    ok=ok,
                    cost=float(tuning_cost(ctrl, plant, sol)) if ok else float("nan"),
                    tracking_mmps=f["tracking_rms_mmps"],
                    osc_mmps=f["osc_rms_mmps"],
                    effort=f["effort_per_s"],
                )
            )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "studies/results/gain_scheduling"))
    ap.add_argument("--quick", action="store_true", help="a 25 %% reference, 5 steps")
    ap.add_argument("--steps", type=int, default=30)
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    time_scale = 0.25 if args.quick else 1.0
    steps = 5 if args.quick else args.steps

    plant, effects, _ = jl.calibrated_model(str(ROOT / "data/truth.json"), None)
    refs = [jl.thesis_reference(m, time_scale=time_scale) for m in TUNE_LOADS]
    thesis = jl.PID().with_gains({**THESIS_PID, "K_aw": 15.0})
    results = {}
    for kind, start in (("plain", thesis), ("scheduled", jl.ScheduledPID.from_pid(thesis))):
        t0 = time.perf_counter()
        res = tune_gains(
            start, plant, effects, refs, sampled=True, T_c=0.01, noise_seeds=TUNE_SEEDS,
            steps=steps, progress=True,
        )  # fmt: skip
        wall = time.perf_counter() - t0
        print(f"{kind}: cost {res.initial_cost:.4g} -> {res.best_cost:.4g} in {wall:.0f} s "
              f"({res.n_evaluations} evaluations; {res.message})", flush=True)  # fmt: skip
        rows = evaluate(res.controller, plant, effects, EVAL_LOADS, EVAL_SEEDS, time_scale)
        results[kind] = dict(
            gains=res.controller.gain_values(),
            tune_cost=res.best_cost,
            tune_wall_s=wall,
            evaluations=res.n_evaluations,
            start_note=res.start_note,
            rows=rows,
        )
    thesis_pid = jl.PID().with_gains(THESIS_PID)  # as the thesis ran it: no anti-windup
    results["thesis"] = dict(
        gains=thesis_pid.gain_values(),
        rows=evaluate(thesis_pid, plant, effects, EVAL_LOADS, EVAL_SEEDS, time_scale),
    )

    def arr(kind, key):
        return np.array([r[key] for r in results[kind]["rows"]], dtype=float)

    diff = arr("scheduled", "cost") - arr("plain", "cost")
    mean_plain = float(np.nanmean(arr("plain", "cost")))
    mean_sched = float(np.nanmean(arr("scheduled", "cost")))
    gain = 1.0 - mean_sched / mean_plain
    se = float(np.nanstd(diff, ddof=1) / np.sqrt(np.sum(np.isfinite(diff))))
    clearly = gain >= MIN_GAIN and -np.nanmean(diff) > 2 * se
    recommendation = (
        f"scheduled PID: it lowers the mean cost by {100 * gain:.1f} % "
        f"(paired difference {np.nanmean(diff):.3g} +- {se:.2g})"
        if clearly
        else f"plain PID: the scheduled PID changes the mean cost by {-100 * gain:+.1f} % "
        f"(paired difference {np.nanmean(diff):.3g} +- {se:.2g} per run), short of "
        f"'at least {100 * MIN_GAIN:.0f} % lower and beyond 2 standard errors'; the "
        "simpler controller is recommended"
    )
    results["summary"] = dict(
        mean_cost_plain=mean_plain,
        mean_cost_scheduled=mean_sched,
        improvement=gain,
        paired_se=se,
        recommend_scheduled=bool(clearly),
        recommendation=recommendation,
        time_scale=time_scale,
        tune_loads=TUNE_LOADS,
        eval_loads=EVAL_LOADS,
        tune_seeds=TUNE_SEEDS,
        eval_seeds=EVAL_SEEDS,
    )
    (out / "gain_scheduling.json").write_text(json.dumps(results, indent=1, default=str))

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for kind, style in (("thesis", "k:"), ("plain", "C0-o"), ("scheduled", "C1-s")):
        for a, key, label in zip(
            ax, ("cost", "tracking_mmps", "osc_mmps"),
            ("tuning cost [-]", "tracking RMS [mm/s]", "oscillation RMS [mm/s]"),
        ):  # fmt: skip
            y = arr(kind, key).reshape(len(EVAL_LOADS), len(EVAL_SEEDS))
            ok = np.isfinite(y).any(axis=1)
            mean = np.array([np.nanmean(r) if f else np.nan for r, f in zip(y, ok)])
            a.plot(EVAL_LOADS, mean, style, label=kind)
            a.set_xlabel("load [kg]")
            a.set_ylabel(label)
            a.grid(alpha=0.3)
    ax[0].set_yscale("log")
    ax[0].legend()
    for m in TUNE_LOADS:
        for a in ax:
            a.axvline(m, color="0.8", lw=0.8, zorder=0)
    fig.suptitle("Plain vs gain-scheduled PID, sampled 10 ms with sensor noise "
                 "(grey lines: tuning loads)")  # fmt: skip
    fig.tight_layout()
    fig.savefig(out / "gain_scheduling.png", dpi=110)

    lines = [
        "# Plain vs gain-scheduled PID over the loads 300-2 000 kg",
        "",
        f"Generated by `studies/gain_scheduling.py{' --quick' if args.quick else ''}` on "
        f"{time.strftime('%Y-%m-%d')}. Model: `data/truth.json` (the shipped logs' true "
        "model). Both tuned as `jaxlift tune` does by default (sampled 10 ms, duty held, "
        f"sensor noise averaged over seeds {list(TUNE_SEEDS)}; from the thesis PID with "
        f"K_aw = 15) at {', '.join(f'{m:g}' for m in TUNE_LOADS)} kg; evaluated with "
        f"seeds {list(EVAL_SEEDS)} at {', '.join(f'{m:g}' for m in EVAL_LOADS)} kg "
        f"(reference time scale {time_scale:g}).",
        "",
        f"**Recommendation: {recommendation}.**",
        "",
        "| gains | tuning cost | tuning time [s] | evaluations |",
        "|---|---|---|---|",
    ]
    for kind in ("plain", "scheduled"):
        r = results[kind]
        lines.append(f"| {kind} | {r['tune_cost']:.4g} | {r['tune_wall_s']:.0f} | "
                     f"{r['evaluations']} |")  # fmt: skip
    lines += ["", "Mean over the evaluation seeds, per load (thesis: the thesis PID P 20, "
              "I 300, D 2, N 100, no anti-windup; `failed`: runs, of "
              f"{len(EVAL_SEEDS)}, that failed -- the fork left the mast's range; their "
              "cost is left out, tracking and oscillation are of the run as far as it "
              "went):", "",
              "| load [kg] | " + " | ".join(
                  f"{k} cost | {k} failed | {k} track [mm/s] | {k} osc [mm/s]"
                  for k in ("thesis", "plain", "scheduled")) + " |",
              "|---" * 13 + "|"]  # fmt: skip
    for i, m in enumerate(EVAL_LOADS):
        cells = []
        for kind in ("thesis", "plain", "scheduled"):
            ok = np.array([r["ok"] for r in results[kind]["rows"]]).reshape(
                len(EVAL_LOADS), len(EVAL_SEEDS)
            )[i]
            for key in ("cost", "failed", "tracking_mmps", "osc_mmps"):
                if key == "failed":
                    cells.append(str(int(np.sum(~ok))))
                    continue
                y = arr(kind, key).reshape(len(EVAL_LOADS), len(EVAL_SEEDS))[i]
                cells.append(f"{np.mean(y[np.isfinite(y)]):.3g}" if np.isfinite(y).any() else "-")
        lines.append(f"| {m:g} | " + " | ".join(cells) + " |")
    lines += ["", "![figures against load](gain_scheduling.png)", "",
              "Gains: " + "; ".join(
                  f"{k}: " + ", ".join(f"{n} {v:.3g}" for n, v in results[k]["gains"].items())
                  for k in ("plain", "scheduled"))]  # fmt: skip
    (out / "gain_scheduling.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'gain_scheduling.md'}: {recommendation}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
