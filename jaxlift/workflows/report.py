"""``jaxlift report`` as a function: from a vehicle's logs to one report.

Four stages, each in a folder of its own below ``out_dir`` and each the job of one
command:

1. ``fit/``: the baseline model fitted from nominal values (``jaxlift fit``): where
   it fails;
2. ``diagnose/``: which physical effects are missing (``jaxlift diagnose``, iterated
   until ``none``, ``undecided`` or ``unexplained``), from that fit;
3. ``posterior/``: the posterior of the diagnosed model (``jaxlift posterior``,
   marginal over the motor set and the offsets), with the air-in-the-oil call;
4. ``tune/``: PID gains tuned on the diagnosed model (``jaxlift tune``: nominal and
   robust over the posterior's draws, sampled loop with noise) and their robustness.

Then ``report.html`` (self-contained: every figure embedded) opens with the summary a
service engineer acts on, followed by each stage's own report; ``summary.json`` holds
the summary's numbers.

**Resumable.** Each finished stage leaves ``stage.json`` with a key: the SHA-256 of
the logs' contents (and their roles), the settings, the package version and the keys
of the stages it depends on. A second run reuses every stage whose key is unchanged
and redoes the others (and everything after them). A stage that failed or was
interrupted has no ``stage.json`` and is redone.

**Quick** (``quick=True``): a small budget (about 3 min on 2 cores). The fit uses one
start per stage; the diagnosis is the score screen only (the candidates ranked, none
confirmed by a refit: no verdict); the uncertainty is the fit's Laplace approximation
(its standard errors, which already include the motor set and the offsets), no MCMC;
the tuning is nominal only, on one noise seed, with no robust tuning or robustness
report. The report says so at the top.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pathlib
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from importlib.metadata import version
from typing import Any

import numpy as np

from ..calibrate.diagnose import NOT_AN_EFFECT, screen_effects
from ..calibrate.fit import fit
from ..model.build import all_param_infos, make_effects, with_params
from ..model.inputs import Inputs
from ..model.log import Log
from ..model.params import save_params_json
from ..model.plant import Plant
from ..posterior.air import air_content, air_verdict, mean_pressure
from ..posterior.moves import MOVES
from ..report.document import Report, json_safe
from .diagnose import run_diagnose
from .fit import run_fit
from .posterior import run_posterior
from .tune import run_tune

#: The stages, in order.
STAGES = ("fit", "diagnose", "posterior", "tune")
#: The report's sections, one per stage, in order (the summary refers to them by title).
SECTION_TITLES = {
    "fit": "1. The baseline model against the logs: where it fails",
    "diagnose": "2. Which physical effect is missing",
    "posterior": "3. How sure: the posterior of the diagnosed model",
    "tune": "4. Gains for the lift controller",
}
STAGE_FILE = "stage.json"


@dataclasses.dataclass(frozen=True)
class ReportBudget:
    """How much work each stage does (:data:`FULL` and :data:`QUICK`)."""

    fit_starts: int = 4  # starts per fit stage
    diagnose: str = "iterate"  # "iterate" (confirmed verdicts) or "screen" (ranking only)
    diagnose_starts: int = 2
    max_effects: int = 3
    posterior: str = "mcmc"  # "mcmc" (emcee, to 50 tau) or "laplace" (the fit's errors)
    posterior_max_steps: int = 20_000
    # ensemble size: "auto" (auto_walkers: 20 for 8 sampled parameters) or a number. The
    # chain runs to 50 tau in steps whatever the ensemble, so the stage's time grows
    # with it; 20 walkers give ~1 300-1 500 effective samples per parameter on the
    # shipped logs' final model (de-laplace), 32 (`jaxlift posterior`'s default) more in
    # 1.6x the time
    posterior_walkers: int | str = "auto"
    # the emcee proposal (jaxlift.posterior.moves.MOVES; the default): DE and snooker
    # updates mixed with independence proposals from the Laplace approximation; on the
    # shipped logs' final model 500 steps to 50 tau (tau 7.0) against 1 650 (tau 32.2)
    # with de-snooker, the same means (0.07 sd) and standard deviations (6 %)
    posterior_move: str = "de-laplace"
    noise_seeds: int = 4  # speed-noise seeds of the tuning cost
    tune_steps: int = 30  # LM evaluations per tuning
    robust_draws: int = 16  # 0: no robust tuning
    eval_draws: int = 100  # held-out draws of the robustness report (0: none)

    def __post_init__(self):
        if self.posterior_move not in MOVES:
            raise ValueError(
                f"posterior_move must be one of {', '.join(MOVES)}, not {self.posterior_move!r}"
            )


FULL = ReportBudget()
QUICK = ReportBudget(
    fit_starts=1, diagnose="screen", posterior="laplace", noise_seeds=1, tune_steps=10,
    robust_draws=0, eval_draws=0,
)  # fmt: skip


# ------------------------------------------------------------------ stage bookkeeping


def log_digest(log: Log) -> str:
    """SHA-256 of a log's contents (name, sample period and every column), so that a
    changed log is noticed whether or not it came from a file."""
    h = hashlib.sha256(log.name.encode())
    for col in ("time_s", "pwm", "height_m", "load_kg", "speed_mps", "pressure_pa"):
        a = getattr(log, col, None)
        h.update(col.encode())
        if a is not None:
            h.update(np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes())
    return h.hexdigest()


def _key(payload: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def _finished(folder: pathlib.Path, key: str) -> dict | None:
    """The stored result of a stage finished with this key, else None."""
    try:
        record = json.loads((folder / STAGE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("key") != key:
        return None
    return record.get("result")


def _run_stage(
    folder: pathlib.Path,
    key: str,
    job: Callable[[pathlib.Path], dict],
    say: Callable[[str], None],
    timings: dict[str, float],
) -> dict:
    name = folder.name
    done = _finished(folder, key)
    if done is not None:
        say(f"[{name}] finished before with the same inputs and settings: reused")
        timings[name] = 0.0
        return done
    if folder.exists():  # another run's results (other inputs or settings): redo
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    say(f"[{name}] running ...")
    t0 = time.perf_counter()
    result = json_safe(job(folder))
    wall = time.perf_counter() - t0
    timings[name] = wall
    record = {"key": key, "wall_s": wall, "result": result}
    (folder / STAGE_FILE).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    say(f"[{name}] done in {wall:.0f} s")
    return result


def stage_keys(
    fit_logs: Sequence[Log], validate_logs: Sequence[Log], budget: ReportBudget, seed: int
) -> dict[str, str]:
    """Each stage's key: the logs' contents and roles, the budget, the seed, the
    package version, and the keys of the stages before it (a changed fit redoes
    everything after it)."""
    base = {
        "jaxlift": version("jaxlift"),
        "fit_logs": [log_digest(lg) for lg in fit_logs],
        "validate_logs": [log_digest(lg) for lg in validate_logs],
        "budget": dataclasses.asdict(budget),
        "seed": int(seed),
    }
    keys: dict[str, str] = {}
    for name in STAGES:
        keys[name] = _key({**base, "stage": name, "before": [keys[s] for s in keys]})
    return keys


# ------------------------------------------------------------------ the stages


def _model(values: Mapping[str, float], effects: Sequence[str]):
    """Plant and effects of a diagnosed model (its parameter values, its effects)."""
    effs = make_effects(effects)
    infos = all_param_infos(effs)
    return with_params(Plant(), effs, {k: v for k, v in values.items() if k in infos})


def _fit_stage(fit_logs, validate_logs, budget: ReportBudget, seed: int, say, keep: dict):
    def job(folder: pathlib.Path) -> dict:
        result, metrics = run_fit(
            fit_logs, validate_logs, n_starts=budget.fit_starts, seed=seed, out_dir=folder,
            progress=say,
        )  # fmt: skip
        keep["fit"] = result  # handed to the diagnosis in this run
        return {
            "converged": bool(result.converged),
            "undetermined": list(result.undetermined),
            "logs": metrics["logs"],
            "params": result.params,
            "stderr": result.stderr,
        }

    return job


def _diagnose_stage(fit_logs, validate_logs, budget: ReportBudget, seed: int, say, keep: dict):
    def job(folder: pathlib.Path) -> dict:
        base = keep.get("fit")
        if budget.diagnose == "screen":
            if base is None:
                base = fit(fit_logs, n_starts=budget.fit_starts, seed=seed, progress=say)
            ranking = screen_effects(base, fit_logs)
            rows = [
                {"effect": s.effect, "score z": s.z, "p (screen)": s.p_value,
                 "predicted size": s.predicted_value, "parameter": s.parameter,
                 "failure": s.failure or ""}
                for s in ranking
            ]  # fmt: skip
            rep = Report("Candidate effects, screened (quick: not confirmed)")
            rep.text(
                "Score test of every candidate effect at the baseline fit (no refit; "
                "autocorrelation-corrected). A large `z` says the data pull towards "
                "that effect; it is **not** a verdict: on the shipped logs the hidden "
                "stick-slip ranks second by score and only the confirming refits (the "
                "full report) name it. Run without `--quick` for the verdict."
            )
            rep.table(rows, floatfmt=".3g")
            rep.write(folder)
            (folder / "diagnosis.json").write_text(json.dumps(json_safe(rows), indent=1) + "\n")
            return {
                "mode": "screen", "final_verdict": "not confirmed (quick)", "verdicts": [],
                "final_effects": [], "final_params": base.params, "ranking": rows,
                "reasons": [], "undecided_between": [],
                "final_stderr": base.stderr,
            }  # fmt: skip
        steps = run_diagnose(
            fit_logs, validate_logs, out_dir=folder, iterate=True,
            max_effects=budget.max_effects, n_starts=budget.diagnose_starts, seed=seed,
            base=base, progress=say,
        )  # fmt: skip
        data = json.loads((folder / "diagnosis.json").read_text(encoding="utf-8"))
        evidence = []
        for d in steps:
            if d.verdict in NOT_AN_EFFECT:
                continue
            s = next((r for r in d.ranking if r.effect == d.verdict), None)
            if s is not None:
                evidence.append(
                    {"effect": s.effect, "delta_bic": s.delta_bic,
                     "heldout_before": s.heldout_chi2_before,
                     "heldout_after": s.heldout_chi2_after,
                     "fitted": s.fitted_params, "stderr": s.fitted_stderr,
                     "dropped_later": s.effect in data["dropped"]}
                )  # fmt: skip
        final = steps[-1].winner_fit if steps[-1].winner_fit is not None else steps[-1].base_fit
        return {
            "mode": "iterate",
            "final_verdict": data["final_verdict"],
            "verdicts": data["verdicts"],
            "dropped": data["dropped"],
            "final_effects": data["final_effects"],
            "final_params": data["final_params"],
            "final_stderr": final.stderr,
            "reasons": data["reasons"],
            "undecided_between": data["undecided_between"],
            "errors_by_step": data["errors_by_step"],
            "evidence": evidence,
        }

    return job


def _posterior_stage(fit_logs, diag: dict, budget: ReportBudget, seed: int, say, bar: bool):
    def job(folder: pathlib.Path) -> dict:
        if budget.posterior == "laplace":
            return _laplace_stage(fit_logs, diag, folder, seed)
        res = run_posterior(
            fit_logs, folder, effects=diag["final_effects"], params=diag["final_params"],
            n_walkers=budget.posterior_walkers, max_steps=budget.posterior_max_steps,
            move=MOVES[budget.posterior_move](), seed=seed, progress=say, progress_bar=bar,
        )  # fmt: skip
        return {
            "mode": "mcmc",
            "converged": res["converged"],
            "steps": res["steps"],
            "tau_max": max(res["tau"].values()) if res["tau"] else None,
            "summary": res["summary"],
            "air": res["air"],
            "effects": res["effects"],
        }

    return job


def _laplace_stage(fit_logs, diag: dict, folder: pathlib.Path, seed: int) -> dict:
    """The quick stage's uncertainty: a normal approximation from the fit's standard
    errors (the least squares' Gauss--Newton covariance, AR(1)-inflated), the air call
    from its bulk modulus draws."""
    values, se = diag["final_params"], diag["final_stderr"]
    effects = diag["final_effects"]
    plant, effs = _model(values, effects)
    p_mean = mean_pressure(
        plant, effs, [Inputs.from_log(lg) for lg in fit_logs], [lg.name for lg in fit_logs]
    )
    rng = np.random.default_rng(seed)
    beta = values["beta"] + se.get("beta", 0.0) * rng.standard_normal(20_000)
    beta = beta[beta > 0]
    air = air_verdict(air_content(beta, p_mean), p_mean, "hose_compliance" in effects)
    air["text"] += " (Laplace approximation from the fit, quick mode: not sampled.)"
    rows = [
        {"parameter": k, "mean": values[k], "sd": se[k],
         "HDI 5 %": values[k] - 1.645 * se[k], "HDI 95 %": values[k] + 1.645 * se[k]}
        for k in se
    ]  # fmt: skip
    rep = Report("Uncertainty of the calibrated parameters (quick: Laplace)")
    rep.text(
        "Normal approximation at the least-squares optimum: the fit's standard errors "
        "(Gauss-Newton covariance of all free parameters, so the motor set and the "
        "initial-height offsets are accounted for; inflated for the residuals' AR(1) "
        "autocorrelation). No Markov chain was run: the full report samples the "
        "posterior."
    )
    rep.table(rows, floatfmt=".4g", caption="value ± sd; 90 % interval value ± 1.645 sd")
    rep.heading("Air in the oil")
    rep.text(air["text"])
    rep.write(folder)
    return {"mode": "laplace", "converged": None, "summary": rows, "air": air,
            "effects": effects}  # fmt: skip


def _tune_stage(fit_logs, diag: dict, post_dir, budget: ReportBudget, seed: int, say):
    def job(folder: pathlib.Path) -> dict:
        plant, effs = _model(diag["final_params"], diag["final_effects"])
        params_path = folder / "model_params.json"
        save_params_json(params_path, diag["final_params"],
                         comment="the diagnosed model (jaxlift report)")  # fmt: skip
        run = run_tune(
            fit_logs, plant, effs, folder, params_path=str(params_path),
            posterior_dir=post_dir, sampled=True,
            noise_seeds=range(budget.noise_seeds) if budget.noise_seeds else None,
            steps=budget.tune_steps, robust_draws=budget.robust_draws,
            eval_draws=budget.eval_draws, seed=seed, progress=say,
        )  # fmt: skip
        return {
            "chosen": run.chosen_name,
            "gains": run.chosen.gain_values(),
            "rows": run.rows,
            "robust_verdict": run.robustness.get("robust_vs_nominal"),
            "notes": run.notes,
            "draws": None if run.draws is None else run.draws.source,
        }

    return job


# ------------------------------------------------------------------ the whole job


def run_report(
    fit_logs: Sequence[Log],
    validate_logs: Sequence[Log] = (),
    *,
    out_dir: str | pathlib.Path,
    quick: bool = False,
    budget: ReportBudget | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
) -> dict:
    """Fit → diagnosis → posterior → tuning on ``fit_logs`` (``validate_logs`` held
    out), each stage resumable, and one self-contained ``out_dir/report.html``
    opening with the summary. Returns the summary (also ``summary.json``), with
    ``stage_wall_s``: each stage's seconds in this run (0: reused).

    ``quick``: the small budget (:data:`QUICK`; see the module docstring);
    ``budget``: another one (:class:`ReportBudget`; overrides ``quick``; the summary
    counts it as quick when it screens only);
    ``seed``: of the fits' random starts, the posterior and the parameter draws."""
    if not fit_logs:
        raise ValueError("jaxlift report needs at least one log to fit")
    say = progress or (lambda _line: None)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    budget = budget if budget is not None else QUICK if quick else FULL
    quick = budget.diagnose == "screen" or budget.posterior == "laplace"
    keys = stage_keys(fit_logs, validate_logs, budget, seed)
    keep: dict = {}
    timings: dict[str, float] = {}
    fit_res = _run_stage(
        out / "fit", keys["fit"], _fit_stage(fit_logs, validate_logs, budget, seed, say, keep),
        say, timings,
    )  # fmt: skip
    diag = _run_stage(
        out / "diagnose", keys["diagnose"],
        _diagnose_stage(fit_logs, validate_logs, budget, seed, say, keep), say, timings,
    )  # fmt: skip
    post = _run_stage(
        out / "posterior", keys["posterior"],
        _posterior_stage(fit_logs, diag, budget, seed, say, progress_bar), say, timings,
    )  # fmt: skip
    post_dir = out / "posterior" if post["mode"] == "mcmc" else None
    tune = _run_stage(
        out / "tune", keys["tune"], _tune_stage(fit_logs, diag, post_dir, budget, seed, say),
        say, timings,
    )  # fmt: skip
    summary = summarise(fit_res, diag, post, tune, quick=quick)
    summary["stage_wall_s"] = timings
    rep = Report("jaxlift report: " + ", ".join(lg.name for lg in fit_logs))
    write_summary(rep, summary, [lg.name for lg in validate_logs])
    for name in STAGES:
        rep.include(Report.read(out / name), title=SECTION_TITLES[name])
    rep.write(out)
    (out / "summary.json").write_text(json.dumps(json_safe(summary), indent=1) + "\n")
    say(f"wrote {out / 'report.html'} (self-contained), {out / 'summary.json'}")
    return summary


# ------------------------------------------------------------------ the summary


def _held_out_chi2(fit_res: dict) -> tuple[float | None, float | None]:
    ok = [m for m in fit_res["logs"].values() if "failed" not in m["before"]
          and "failed" not in m["after"]]  # fmt: skip
    rows = [m for m in ok if m["role"] == "held_out"] or ok
    if not rows:
        return None, None
    before = float(np.mean([m["before"]["chi2_per_sample"] for m in rows]))
    after = float(np.mean([m["after"]["chi2_per_sample"] for m in rows]))
    return before, after


def summarise(fit_res: dict, diag: dict, post: dict, tune: dict, *, quick: bool) -> dict:
    """The report's summary from the stages' results: verdict and confidence, the air
    call, the recommended gains against the current (thesis) ones."""
    nominal_chi2, baseline_chi2 = _held_out_chi2(fit_res)
    final_chi2 = None
    if diag.get("errors_by_step"):
        last = diag["errors_by_step"][-1]
        held = [v for k, v in last.items() if "(held-out)" in k]
        fitted = [v for k, v in last.items() if "(fit)" in k]
        final_chi2 = float(np.mean(held or fitted))
    costs = {r["gains"]: r["nominal_cost"] for r in tune["rows"]}
    current = costs.get("thesis PID")
    chosen = costs.get(tune["chosen"])
    beta = next((r for r in post["summary"] if r.get("parameter") == "beta"), None)
    return {
        "quick": quick,
        "verdict": diag["final_verdict"],
        "missing_effects": [v for v in diag["verdicts"] if v not in diag.get("dropped", [])],
        "evidence": diag.get("evidence", []),
        "reasons": diag["reasons"],
        "undecided_between": diag["undecided_between"],
        "screen": diag.get("ranking"),
        "chi2_nominal": nominal_chi2,
        "chi2_baseline": baseline_chi2,
        "chi2_final": final_chi2,
        "fit_converged": fit_res["converged"],
        "posterior_mode": post["mode"],
        "posterior_converged": post["converged"],
        "beta": beta,
        "air": post["air"],
        "gains": tune["gains"],
        "gains_name": tune["chosen"],
        "cost_current": current,
        "cost_recommended": chosen,
        "robust_verdict": tune.get("robust_verdict"),
    }


def gain_order(name: str) -> tuple[int, str]:
    """P, I, D, N, K_aw first (the controller's order), then the rest by name."""
    order = ("P", "I", "D", "N", "K_aw")
    return (order.index(name), "") if name in order else (len(order), name)


def _fmt(x: float | None, spec: str = ".3g") -> str:
    return "–" if x is None or not math.isfinite(x) else format(x, spec)


def write_summary(rep: Report, s: dict, held_out: Sequence[str]) -> None:
    """The summary section at the top of the report."""
    rep.heading("Summary")
    if s["quick"]:
        rep.text(
            "**Quick report** (`--quick`): the candidates are screened, not confirmed "
            "(no verdict); the uncertainty is the fit's normal approximation, not a "
            "sampled posterior; the gains are tuned on the nominal model only. Run "
            "without `--quick` before acting on it."
        )
    judged = "held-out" if held_out else "fitted"
    lines = []
    v = s["verdict"]
    if s["screen"]:  # screened only, not confirmed
        top = [r for r in s["screen"] or [] if not r.get("failure")][:3]
        lines.append(
            "**Missing physics (not confirmed):** the score screen ranks "
            + ", ".join(f"`{r['effect']}` (z {_fmt(r['score z'], '.1f')})" for r in top)
            + " highest."
        )
    elif s["missing_effects"]:
        ev = "; ".join(
            f"`{e['effect']}`: BIC {_fmt(e['delta_bic'], '+.0f')}, held-out chi2/N "
            f"{_fmt(e['heldout_before'])} → {_fmt(e['heldout_after'])}, "
            + ", ".join(
                f"{k} = {_fmt(val, '.3g')} ± {_fmt((e['stderr'] or {}).get(k), '.2g')}"
                for k, val in (e["fitted"] or {}).items()
            )
            for e in s["evidence"]
            if not e["dropped_later"]
        )
        lines.append(
            f"**Missing physics:** {', '.join(f'**{x}**' for x in s['missing_effects'])} "
            f"(added in this order; then **{v}**). Evidence: {ev}."
        )
    else:
        lines.append(f"**Missing physics:** **{v}**.")
    if v in ("undecided", "unexplained") and not s["screen"]:
        lines.append(f"**{v.capitalize()}:** " + "; ".join(s["reasons"]) + ".")
    lines.append(
        f"**Model error** ({judged} logs, chi2 per sample, 1 = sensor noise): nominal "
        f"model {_fmt(s['chi2_nominal'])}, baseline fitted {_fmt(s['chi2_baseline'])}"
        + (f", diagnosed model {_fmt(s['chi2_final'])}" if s["chi2_final"] is not None else "")
        + "."
    )
    if s["air"]:
        b = s["beta"] or {}
        gpa = [None if b.get(k) is None else b[k] / 1e9 for k in ("mean", "HDI 5 %", "HDI 95 %")]
        lines.append(
            f"**Air in the oil:** {s['air']['text']} Bulk modulus {_fmt(gpa[0], '.4g')} GPa, "
            f"90 % interval {_fmt(gpa[1], '.4g')}–{_fmt(gpa[2], '.4g')}"
            f" GPa ({'sampled posterior' if s['posterior_mode'] == 'mcmc' else 'Laplace'}"
            + (
                ", chain NOT converged: treat as indicative"
                if s["posterior_converged"] is False
                else ""
            )
            + "; conditional on the diagnosed model being right)."
        )
    g = s["gains"]
    better = (
        f"; cost {_fmt(s['cost_recommended'], '.4g')} against {_fmt(s['cost_current'], '.4g')} "
        f"for the current (thesis) gains, {_fmt(s['cost_current'] / s['cost_recommended'], '.1f')}"
        "× lower (sampled 10 ms loop with sensor noise)"
        if s["cost_current"] and s["cost_recommended"]
        else ""
    )
    lines.append(
        f"**Recommended gains** ({s['gains_name']}, `tune/gains.json`): "
        + ", ".join(f"{k} = {_fmt(g[k], '.4g')}" for k in sorted(g, key=gain_order))
        + better
        + "."
    )
    if s.get("robust_verdict"):
        rv = s["robust_verdict"]
        short = rv.get("short")  # the per-case figures are in the tuning section
        lines.append(
            "**Robust or nominal?** "
            + (
                f"{short[0].upper()}{short[1:]} Per case: section “{SECTION_TITLES['tune']}”."
                if short
                else rv["text"]
            )
        )
    rep.text("\n".join(f"- {x}" for x in lines))
