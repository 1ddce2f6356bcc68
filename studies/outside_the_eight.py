"""Study: laws outside the eight candidate effects, hidden alone and beside one of the
eight, and null cases, each diagnosed by the call a user makes
(``jaxlift diagnose fit_1.csv fit_2.csv --validate validation.csv --shape always``,
from nominal values). Measured per case: the final verdict (``unexplained`` is right
for a law outside the eight; a confident name of one of the eight alone is wrong), the
signal the shape estimate calls dominant, the correlation of the estimated signal with
what the final model lacks (``tests/outside_laws.missing_targets``: from the true and
the fitted model's vector fields), and the law's leading term where the library has it.

The logs are made by jaxlift's own simulator (the laws are user effects:
``tests/outside_laws.py``), with a pressure channel; truth drawn around nominal
(beta 0.5-1.4 GPa, Coulomb friction and damping within ±30 %), loads 300-1800 kg,
three styles of input sequence, starts on the bottom stop or mid-mast. Resumable: a
case whose ``result.json`` exists is not run again::

    python studies/outside_the_eight.py run --out runs/outside
    python studies/outside_the_eight.py report --out runs/outside --to studies/results/outside

After a change of the shape estimate alone (``jaxlift/calibrate/shape.py``), ``reshape``
estimates the shape again on each finished case's final model, as its diagnosis left it
(the final parameters and effects from ``diagnosis.json``; each fitted log's
initial-height offset estimated again under that model, the fit's nuisance parameter),
into a copy of the run, and scores it the same way; the verdicts are the diagnosis's::

    python studies/outside_the_eight.py reshape --out runs/outside --into runs/outside_reshaped
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import outside_laws  # noqa: E402

sys.path.insert(0, str(ROOT / "studies"))
from detection_power import _jaxlift_commit  # noqa: E402  (the commit of the jaxlift the cases import)

import jaxlift as jl  # noqa: E402
from jaxlift.model.sequences import ramped_sequence  # noqa: E402

#: Law, its size parameter, the range of sizes (log-uniform), the signal that carries
#: it, the library term that leads (None: not in the library).
LAWS = {
    "seal_friction": ("mu", (2e-5, 1.2e-4), "force", "p sign(v)"),
    "early_relief": ("k", (4e-13, 3e-12), "flow", None),
    "duty_saturation": ("u_sat", (0.5, 0.35), "flow", None),
}
#: One of the eight beside a law (pairs), at a size the diagnosis finds (docs).
BESIDE = {"leakage": {"C_L": 1.5e-13}, "stick_slip": {"dFs": 300.0, "v_s": 0.008}}


def _sequence(style: str, rng: np.random.Generator) -> list[tuple[float, float]]:
    if style == "thesis-like":
        return [(0.0, 2.0), (0.5, 5.0), (0.25, 6.0), (0.0, 3.0), (0.6, 5.0), (0.0, 3.0),
                (0.35, 6.0), (0.0, 2.0)]  # fmt: skip
    if style == "random steps":
        out = [(0.0, 1.5)]
        for _ in range(int(rng.integers(5, 9))):
            out.append((float(rng.uniform(0.2, 0.65)), float(rng.uniform(2.0, 5.0))))
            if rng.uniform() < 0.4:
                out.append((0.0, float(rng.uniform(1.0, 2.5))))
        return [*out, (0.0, 2.0)]
    # slow ramps: long, low duty
    return [(0.0, 2.0), (0.22, 10.0), (0.3, 8.0), (0.0, 2.0), (0.26, 10.0), (0.0, 2.0)]


def cases(seed: int = 20261124) -> list[dict]:
    """The seeded list of cases: each law at 3 sizes alone, each law beside one of the
    eight, and 3 null cases."""
    rng = np.random.default_rng(seed)
    out = []
    for law, (_, (lo, hi), _, _) in LAWS.items():
        for q in (0.15, 0.5, 0.85):
            size = float(np.exp(np.log(lo) + q * (np.log(hi) - np.log(lo))))
            out.append({"law": law, "size": size, "beside": None})
    for law, beside in zip(LAWS, ("leakage", "stick_slip", "leakage")):
        lo, hi = LAWS[law][1]
        out.append({"law": law, "size": float(np.sqrt(lo * hi)), "beside": beside})
    out += [{"law": None, "size": None, "beside": None} for _ in range(3)]
    styles = ("thesis-like", "random steps", "slow ramps")
    for k, c in enumerate(out):
        c["case_id"] = f"case_{k:03d}"
        c["truth"] = {
            "beta": float(np.exp(rng.uniform(np.log(0.5e9), np.log(1.4e9)))),
            "cf_con": float(jl.Plant().cf_con * rng.uniform(0.7, 1.3)),
            "d": float(jl.Plant().d * rng.uniform(0.7, 1.3)),
        }
        c["logs"] = [
            {"name": name, "load": float(rng.uniform(300, 1800)),
             "x0": 0.0 if rng.uniform() < 0.4 else float(rng.uniform(0.3, 2.0)),
             "style": styles[int(rng.integers(0, 3))], "seed": int(rng.integers(2**31))}
            for name in ("fit_1", "fit_2", "validation")
        ]  # fmt: skip
    return out


def _model(case: dict):
    plant = jl.with_params(jl.Plant(), (), case["truth"])[0]
    law = None
    effects = []
    if case["law"] is not None:
        cls = outside_laws.LAWS[case["law"]]
        law = cls(**{LAWS[case["law"]][0]: case["size"]})
    if case["beside"] is not None:
        effects = list(jl.make_effects([case["beside"]], BESIDE[case["beside"]]))
    return plant, effects, law


def _inputs(spec: dict) -> jl.Inputs:
    rng = np.random.default_rng(spec["seed"])
    ts, pwm = ramped_sequence(_sequence(spec["style"], rng), ramp_s=0.5)
    return jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, spec["load"]), spec["x0"])


def write_case(case: dict, case_dir: pathlib.Path) -> None:
    case_dir.mkdir(parents=True, exist_ok=True)
    plant, effects, law = _model(case)
    allfx = (*effects, *([law] if law is not None else []))
    for spec in case["logs"]:
        path = case_dir / f"{spec['name']}.csv"
        if path.exists():
            continue
        inputs = _inputs(spec)
        sol = jl.simulate(plant, allfx, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
        log = jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(spec["seed"] % 2**31),
                        with_pressure=True, name=spec["name"])  # fmt: skip
        jl.write_log(path, log)
    (case_dir / "case.json").write_text(json.dumps(case, indent=1))


def evaluate(case: dict, diag_dir: pathlib.Path) -> dict:
    """The shape's correlation with the missing signal, per case (pooled over the
    fitted logs), and the law's leading term."""
    d = json.loads((diag_dir / "diagnosis.json").read_text())
    out = {
        "final_verdict": d["final_verdict"],
        "found": [v for v in d["verdicts"] if v not in d["dropped"]],
        "baseline_chi2n": d["steps"][0]["base_chi2"] / d["steps"][0]["n_residuals"],
        "heldout_chi2n_final": d["errors_by_step"][-1],
    }
    shape = d.get("missing_shape") or {}
    if "laws" not in shape:
        return {**out, "shape": shape.get("failed", "none")}
    plant, effects, law = _model(case)
    out.update(dominant=shape["dominant"], needed=shape["needed"], evidence=shape["evidence"],
               shares=shape["shares"],
               leading={k: v["leading"] for k, v in shape["laws"].items()},
               laws={k: v["law"] for k, v in shape["laws"].items()})  # fmt: skip
    if law is None:
        return out
    signal = LAWS[case["law"]][2]
    import csv

    rows = list(csv.DictReader(open(diag_dir / "missing_shape.csv", encoding="utf-8")))
    targets, ests = [], []
    for spec in case["logs"][:2]:
        r = [row for row in rows if row["log"] == spec["name"]]
        arr = {k: np.array([float(x[k]) for x in r]) for k in r[0] if k != "log"}
        F, Q = outside_laws.missing_targets(
            law, d["final_params"], d["final_effects"], _inputs(spec), arr["time_s"],
            arr["height_m"], arr["speed_mps"], arr["pressure_pa"], true_plant=plant,
            base_effects=tuple(effects),
        )  # fmt: skip
        targets.append(F if signal == "force" else Q)
        ests.append(arr["force_N"] if signal == "force" else arr["flow_m3s"])
    t, e = np.concatenate(targets), np.concatenate(ests)
    out["correlation"] = float(np.corrcoef(t, e)[0, 1]) if np.std(e) > 0 else 0.0
    out["signal"] = signal
    # the law of the signal that carries the hidden law, from the estimate as written
    # (every 5th sample of the fitted logs, as MissingShape.laws), with the terms the
    # data cannot tell from the leading one (Law.alternatives)
    fitted = [row for row in rows if row["log"] in {sp["name"] for sp in case["logs"][:2]}]
    col = {k: np.array([float(x[k]) for x in fitted[::5]]) for k in fitted[0] if k != "log"}
    states = {"t": col["time_s"] - col["time_s"].min(), "x": col["height_m"],
              "v": col["speed_mps"], "p": col["pressure_pa"], "a": col["accel_mps2"],
              "u": col["pwm"]}  # fmt: skip
    y, sd = (col["force_N"], col["force_sd_N"]) if signal == "force" else (
        col["flow_m3s"], col["flow_sd_m3s"])  # fmt: skip
    law_fit = jl.explain(y, states, name=signal, unit=jl.MissingShape.UNITS[signal],
                         weights=1.0 / sd**2)  # fmt: skip
    out["law_leading"], out["law_alternatives"] = law_fit.leading, law_fit.alternatives
    term = LAWS[case["law"]][3]
    out["term_named"] = None if term is None else term in {law_fit.leading, *law_fit.alternatives}
    return out


def run_case(case: dict, out: pathlib.Path, time_limit: float) -> dict:
    case_dir = out / case["case_id"]
    if (case_dir / "result.json").exists():
        return json.loads((case_dir / "result.json").read_text())
    write_case(case, case_dir)
    argv = [sys.executable, "-P", "-m", "jaxlift", "diagnose", str(case_dir / "fit_1.csv"),
            str(case_dir / "fit_2.csv"), "--validate", str(case_dir / "validation.csv"),
            "--shape", "always", "--out", str(case_dir / "diagnosis")]  # fmt: skip
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=time_limit,
                              check=False)  # fmt: skip
        rc, tail = proc.returncode, proc.stderr[-2000:]
    except subprocess.TimeoutExpired:
        rc, tail = None, f"stopped at the study's limit of {time_limit:.0f} s"
    res = {"case_id": case["case_id"], "law": case["law"], "size": case["size"],
           "beside": case["beside"], "exit_code": rc,
           "wall_s": time.perf_counter() - t0, "commit": _jaxlift_commit()}  # fmt: skip
    if rc == 0:
        res.update(evaluate(case, case_dir / "diagnosis"))
    else:
        res["crash"] = tail
    (case_dir / "result.json").write_text(json.dumps(res, indent=1, default=float))
    return res


def reshape_case(case: dict, out: pathlib.Path, into: pathlib.Path) -> dict | None:
    """The shape estimated again on the final model of a finished case of ``out``, into
    ``into`` (see the module docstring); None if the case has not finished there."""
    src = out / case["case_id"]
    if not (src / "result.json").exists():
        return None
    dst = into / case["case_id"]
    if (dst / "result.json").exists():
        return json.loads((dst / "result.json").read_text())
    from jaxlift.calibrate.fit import estimate_x0_offsets
    from jaxlift.calibrate.shape import estimate_missing_shape
    from jaxlift.report.document import Report, json_safe
    from jaxlift.report.shape import shape_section, write_shape_csv

    res = json.loads((src / "result.json").read_text())
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    (dst / "result.json").unlink()
    if res.get("exit_code") == 0:
        diag = dst / "diagnosis"
        d = json.loads((diag / "diagnosis.json").read_text())
        logs = [jl.read_log(dst / f"{n}.csv") for n in ("fit_1", "fit_2")]
        params, effects = d["final_params"], d["final_effects"]
        final = jl.FitResult.__new__(jl.FitResult)  # only the model and offsets are read
        final.model = jl.Model.build(effects, params)
        final.effects = list(effects)
        final.x0_offsets = estimate_x0_offsets(params, effects, logs)
        t0 = time.perf_counter()
        try:
            est = estimate_missing_shape(final, logs)
        except jl.SimulationError as err:
            d["missing_shape"] = {"failed": str(err)}
        else:
            rep = Report("shape only")
            d["missing_shape"] = shape_section(rep, est, diag / "figures")
            write_shape_csv(est, diag / "missing_shape.csv")
        (diag / "diagnosis.json").write_text(json.dumps(json_safe(d), indent=2))
        res = {k: v for k, v in res.items() if k not in ("correlation", "signal", "term_named")}
        res.update(evaluate(case, diag))
        res.update(shape_commit=_jaxlift_commit(), shape_wall_s=time.perf_counter() - t0)
    (dst / "result.json").write_text(json.dumps(res, indent=1, default=float))
    return res


def correct(r: dict) -> bool:
    """Right: ``unexplained`` for a law (alone, or with its companion found too);
    ``none`` (or the companion alone) for a null case."""
    if r.get("exit_code") != 0:
        return False
    if r["law"] is None:
        return r["final_verdict"] != "unexplained" and not r["found"]
    return r["final_verdict"] == "unexplained"


def _size(v) -> str:
    return "" if v is None else f"{v:.3g}"


def _right(r: dict) -> str:
    """yes / no, or "inactive" for a law the logs never brought into play (baseline
    chi2/N below 1.1: e.g. a relief valve that the loads never crack)."""
    if r["law"] and r.get("exit_code") == 0 and r.get("baseline_chi2n", 2.0) < 1.1:
        return "inactive" + (" (none)" if r["final_verdict"] == "none" else "")
    return "yes" if correct(r) else "no"


def cmd_run(args) -> int:
    out = pathlib.Path(args.out)
    for case in cases():
        if args.only and case["case_id"] not in args.only:
            continue
        r = run_case(case, out, args.time_limit)
        print(case["case_id"], case["law"], r.get("final_verdict"), r.get("correlation"),
              r.get("leading"), f"{r['wall_s']:.0f} s", flush=True)  # fmt: skip
    return 0


def cmd_reshape(args) -> int:
    out, into = pathlib.Path(args.out), pathlib.Path(args.into)
    for case in cases():
        if args.only and case["case_id"] not in args.only:
            continue
        r = reshape_case(case, out, into)
        if r is not None:
            print(case["case_id"], case["law"], r.get("correlation"),
                  f"{r.get('shape_wall_s', 0.0):.0f} s", flush=True)  # fmt: skip
    return 0


def cmd_report(args) -> int:
    out = pathlib.Path(args.out)
    to = pathlib.Path(args.to)
    (to / "cases").mkdir(parents=True, exist_ok=True)
    results = []
    for case in cases():
        p = out / case["case_id"] / "result.json"
        if p.exists():
            r = json.loads(p.read_text())
            if args.rescore and r.get("exit_code") == 0:  # the targets computed again
                r.update(evaluate(case, out / case["case_id"] / "diagnosis"))
                p.write_text(json.dumps(r, indent=1, default=float))
            results.append(r)
            (to / "cases" / f"{case['case_id']}.json").write_text(json.dumps(r, indent=1))
    lines = ["# Laws outside the eight: diagnosis and shape", "",
             f"{len(results)} of {len(cases())} cases done.", "",
             "| case | law | size | beside | baseline chi2/N | final verdict | found | "
             "dominant | correlation | leading term | right | time [s] | commit |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in results:
        lead = r.get("law_leading") or (r.get("leading") or {}).get(
            r.get("signal") or r.get("dominant") or "", ""
        )
        if r.get("law_alternatives"):
            lead += " (≈ " + ", ".join(r["law_alternatives"]) + ")"
        lines.append(
            f"| {r['case_id']} | {r['law'] or 'null'} | {_size(r['size'])} | {r['beside'] or ''}"
            f" | {r.get('baseline_chi2n', float('nan')):.3g} | {r.get('final_verdict', 'crash')}"
            f" | {', '.join(r.get('found', [])) or '—'} | {r.get('dominant', '')}"
            f" | {r.get('correlation', float('nan')):.3f} | {lead}"
            f" | {_right(r)} | {r['wall_s']:.0f} | {r.get('commit', 'not recorded')}"
            + (f" (shape: {r['shape_commit']})" if "shape_commit" in r else "")
            + " |"
        )
    laws = [r for r in results if r["law"]]
    nulls = [r for r in results if not r["law"]]
    big = [r for r in laws if r.get("baseline_chi2n", 0) >= 2.0]
    lines += ["",
              f"- laws at baseline chi2/N >= 2: `unexplained` in "
              f"{sum(correct(r) for r in big)} of {len(big)}; shape correlation >= 0.9 in "
              f"{sum(r.get('correlation', 0) >= 0.9 for r in big)} of {len(big)}",
              f"- leading term named (the hidden law's term, or one the data cannot tell "
              f"from it), where the library has it: "
              f"{sum(bool(r.get('term_named')) for r in big if r.get('term_named') is not None)}"
              f" of {sum(r.get('term_named') is not None for r in big)}",
              f"- null cases: `unexplained` in "
              f"{sum(r.get('final_verdict') == 'unexplained' for r in nulls)} of {len(nulls)}",
              ""]  # fmt: skip
    (to / "outside_the_eight.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--out", required=True)
    r.add_argument("--only", nargs="*", default=[])
    r.add_argument("--time-limit", type=float, default=1800.0)
    r.set_defaults(func=cmd_run)
    s = sub.add_parser("reshape")
    s.add_argument("--out", required=True)
    s.add_argument("--into", required=True)
    s.add_argument("--only", nargs="*", default=[])
    s.set_defaults(func=cmd_reshape)
    q = sub.add_parser("report")
    q.add_argument("--out", required=True)
    q.add_argument("--to", required=True)
    q.add_argument(
        "--rescore",
        action="store_true",
        help="evaluate the finished cases again (after a change of the targets)",
    )
    q.set_defaults(func=cmd_report)
    args = p.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
