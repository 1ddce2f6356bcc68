"""Fleet study: are the fleet's flags right, and how does `jaxlift fleet` scale?

    python studies/fleet_study.py generate --fleet runs/fleet/data [--vehicles 8 --weeks 4]
    python studies/fleet_study.py run      --fleet runs/fleet/data --out runs/fleet/out
    python studies/fleet_study.py evaluate --fleet runs/fleet/data --out runs/fleet/out
    python studies/fleet_study.py scaling  --fleet runs/fleet/data --out runs/fleet/scaling
    python studies/fleet_study.py merge    --earlier OLD/fleet.csv --out NEW [NEW ...] --into DIR

``generate`` writes a synthetic fleet (``studies/fleet_generator.py``: the detection
study's independent generator, vehicles drifting by construction). ``run`` is the
user's command (``jaxlift fleet``, resumable). ``evaluate`` compares the flags with
the truth: every drifting vehicle flagged with the right reason, no stable vehicle
flagged, the new effect named on the week it appears; it writes
``studies/results/fleet_study.md``. ``scaling`` measures jobs per hour with 1 and 2
local workers on the same jobs, and the engine's own overhead per job (trivial jobs
through the same engine), into ``studies/results/fleet_scaling.md`` (which
``evaluate`` includes). ``merge`` replaces the rows of an earlier run's table by those
of a newer run of some of its vehicles (e.g. jobs re-run on a fixed library) and writes
the flags and the report of the merged table with the library's own functions; the
evaluation then lists which jaxlift version made how many rows.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "studies" / "results"
EXPECT = {
    "air": "air content rising",
    "friction": "friction rising",
    "new_effect": "new effect since",
}


def cmd_generate(a) -> int:
    return subprocess.call([sys.executable, str(ROOT / "studies" / "fleet_generator.py"),
                            "--out", a.fleet, "--vehicles", str(a.vehicles),
                            "--weeks", str(a.weeks), "--seed", str(a.seed)])  # fmt: skip


def cmd_run(a) -> int:
    return subprocess.call([sys.executable, "-m", "jaxlift", "fleet", a.fleet, "--out", a.out,
                            "--workers", str(a.workers)])  # fmt: skip


def cmd_evaluate(a) -> int:
    truth = json.loads((pathlib.Path(a.fleet) / "fleet_truth.json").read_text())
    flags = json.loads((pathlib.Path(a.out) / "flags.json").read_text())
    import pyarrow.parquet as pq

    table = pq.read_table(pathlib.Path(a.out) / "fleet.parquet").to_pylist()
    start = truth["start"]
    lines = ["# Fleet study: results", ""]
    lines.append(
        f"Synthetic fleet of {len(truth['vehicles'])} vehicles × {truth['n_weeks']} weeks "
        f"(`studies/fleet_generator.py`, seed in `fleet_truth.json`; weeks from {start}), "
        f"{len(table)} jobs, diagnosed by `jaxlift fleet` from nominal values "
        f"({sum(r['status'] != 'ok' for r in table)} failed)."
    )
    lines += ["", "| vehicle | truth | flags | right? |", "|---|---|---|---|"]
    tally = {"drifting": [0, 0], "stable": [0, 0]}
    for v in truth["vehicles"]:
        got = flags["flagged"].get(v["vehicle"], [])
        kind = v["kind"]
        if kind == "stable":
            ok = not got
            tally["stable"][0] += ok
            tally["stable"][1] += 1
        else:
            want = EXPECT[kind]
            ok = any(f.startswith(want) for f in got) and all(f.startswith(want) for f in got)
            if kind == "new_effect":
                import datetime

                week = datetime.date.fromisoformat(start) + datetime.timedelta(
                    weeks=v["new_effect_week"]
                )
                ok = ok and any(f"since {week.isoformat()}: leakage" in f for f in got)
            tally["drifting"][0] += ok
            tally["drifting"][1] += 1
        desc = (
            kind
            if kind != "new_effect"
            else f"new_effect (leakage from week {v['new_effect_week']})"
        )
        lines.append(
            f"| {v['vehicle']} | {desc} | {'; '.join(got) or '–'} | {'yes' if ok else '**no**'} |"
        )
    d, s = tally["drifting"], tally["stable"]
    lines += [
        "",
        f"- Drifting vehicles flagged with the right reason (and no other): {d[0]} of {d[1]}.",
        f"- Stable vehicles flagged: {s[1] - s[0]} of {s[1]} (false-alarm rate "
        f"{(s[1] - s[0]) / max(s[1], 1):.0%}).",
    ]
    times = sorted(r["wall_s"] for r in table if r["wall_s"] == r["wall_s"])
    if times:
        lines.append(
            f"- Time per job (inside the worker): median {times[len(times) // 2]:.0f} s, "
            f"max {times[-1]:.0f} s."
        )
    stable = [v["vehicle"] for v in truth["vehicles"] if v["kind"] == "stable"]
    zs = [abs(t["z"]) for v in stable for t in flags["tests"][v].values() if t["z"] == t["z"]]
    infl = {
        name: sorted({round(t["inflation"], 2) for v in flags["tests"].values()
                      for n, t in v.items() if n == name and t["inflation"] == t["inflation"]})
        for name in ("beta", "cf_con", "d")
    }  # fmt: skip
    if zs:
        lines.append(
            f"- Stable vehicles: largest |z| of any trend test {max(zs):.1f} (the Bonferroni "
            f"threshold at alpha 0.05 over {3 * len(truth['vehicles'])} tests is |z| "
            f"{_z_threshold(3 * len(truth['vehicles'])):.2f}); inflation of the stated "
            f"errors, pooled over the fleet: {infl}."
        )
    verdicts = {}
    for r in table:
        verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
    lines.append(f"- Verdicts over all jobs: {verdicts}.")
    versions = {}
    for r in table:
        versions[r["jaxlift_version"]] = versions.get(r["jaxlift_version"], 0) + 1
    lines.append(
        "- jaxlift version of the jobs (a failed job records none): "
        + ", ".join(f"`{v or '-'}` {n}" for v, n in sorted(versions.items(), key=str))
        + "."
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    if (RESULTS / "fleet_scaling.md").exists():
        lines += ["", (RESULTS / "fleet_scaling.md").read_text()]
    (RESULTS / "fleet_study.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def cmd_merge(a) -> int:
    """The earlier table with the newer runs' rows in place of its own (same vehicle
    and date; a newer row for a job the earlier table lacks is added), then the
    flags, table and report of the merged rows. The newer runs must not share a job."""
    from jaxlift.fleet import read_table, write_fleet_outputs

    earlier = read_table(a.earlier)
    newer = [r for out in a.out for r in read_table(pathlib.Path(out) / "fleet.parquet")]
    replaced = {(r["vehicle"], r["date"]) for r in newer}
    if len(replaced) < len(newer):
        raise SystemExit(f"the runs in --out {' '.join(a.out)} share a vehicle and date")
    kept = [r for r in earlier if (r["vehicle"], r["date"]) not in replaced]
    rows = sorted(kept + newer, key=lambda r: (r["vehicle"], r["date"]))
    info = {"ran": len(newer), "skipped": len(kept),
            "failed": sum(r["status"] != "ok" for r in rows)}  # fmt: skip
    write_fleet_outputs(rows, a.into, {**info, "jobs": len(rows)})
    print(f"{len(kept)} rows from {a.earlier}, {len(newer)} from {' '.join(a.out)}: "
          f"wrote {a.into}")  # fmt: skip
    return 0


def _z_threshold(m: int, alpha: float = 0.05) -> float:
    from scipy import stats

    return float(stats.norm.isf(alpha / m / 2))


def _trivial(job, settings, job_dir):
    return {"vehicle": job.vehicle, "date": job.date.isoformat(), "status": "ok"}


def cmd_scaling(a) -> int:
    """Jobs per hour with 1 and 2 workers on the first N jobs (fresh output folders),
    and the engine's overhead per job with trivial jobs."""
    sys.path.insert(0, str(ROOT / "studies"))
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxlift.fleet import discover_jobs, run_jobs

    jobs = discover_jobs(a.fleet)[: a.jobs]
    out = pathlib.Path(a.out)
    rows = []
    for workers in (1, 2):
        t0 = time.perf_counter()
        run = run_jobs(jobs, out / f"w{workers}", workers=workers)
        wall = time.perf_counter() - t0
        rows.append((workers, len(jobs), wall, 3600 * run.ran / wall))
        print(rows[-1], flush=True)
    trivial = discover_jobs(a.fleet)
    over = []
    for workers in (1, 2):
        t0 = time.perf_counter()
        run_jobs(trivial, out / f"trivial{workers}_{time.time_ns()}", workers=workers,
                 job_fn=_trivial)  # fmt: skip
        over.append((workers, len(trivial), time.perf_counter() - t0))
        print(over[-1], flush=True)
    lines = ["## Scaling (this machine: 2 cores)", "",
             "| workers | jobs | wall [s] | jobs per hour |", "|---:|---:|---:|---:|"]  # fmt: skip
    lines += [f"| {w} | {n} | {t:.0f} | {r:.0f} |" for w, n, t, r in rows]
    lines += ["", "Engine overhead (trivial jobs through the same engine, cluster start "
              "included):", ""]  # fmt: skip
    lines += [f"- {w} worker(s): {n} jobs in {t:.1f} s ({1000 * t / n:.0f} ms per job)"
              for w, n, t in over]  # fmt: skip
    with open(RESULTS / "fleet_scaling.md", "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate")
    g.add_argument("--fleet", default="runs/fleet/data")
    g.add_argument("--vehicles", type=int, default=8)
    g.add_argument("--weeks", type=int, default=4)
    g.add_argument("--seed", type=int, default=0)
    g.set_defaults(func=cmd_generate)
    r = sub.add_parser("run")
    r.add_argument("--fleet", default="runs/fleet/data")
    r.add_argument("--out", default="runs/fleet/out")
    r.add_argument("--workers", type=int, default=2)
    r.set_defaults(func=cmd_run)
    e = sub.add_parser("evaluate")
    e.add_argument("--fleet", default="runs/fleet/data")
    e.add_argument("--out", default="runs/fleet/out")
    e.set_defaults(func=cmd_evaluate)
    m = sub.add_parser("merge")
    m.add_argument("--earlier", required=True, help="an earlier run's fleet.csv")
    m.add_argument("--out", required=True, nargs="+", help="the newer runs' output folders")
    m.add_argument("--into", required=True, help="where the merged outputs go")
    m.set_defaults(func=cmd_merge)
    s = sub.add_parser("scaling")
    s.add_argument("--fleet", default="runs/fleet/data")
    s.add_argument("--out", default="runs/fleet/scaling")
    s.add_argument("--jobs", type=int, default=4)
    s.set_defaults(func=cmd_scaling)
    a = p.parse_args(argv)
    return a.func(a)


if __name__ == "__main__":
    sys.exit(main())
