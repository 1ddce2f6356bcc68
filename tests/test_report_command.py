"""``jaxlift report``: stages reused or redone as their inputs say, one self-contained
page, and the whole command from nominal values on logs with known truth."""

from __future__ import annotations

import dataclasses
import json
import re

import arviz as az
import numpy as np
import pytest
import xarray as xr
from test_posterior import TRUTH, synthetic_logs

import jaxlift as jl
from jaxlift.model.sequences import ramped_sequence
from jaxlift.posterior.sampler import auto_walkers
from jaxlift.report.document import Report
from jaxlift.workflows.report import (
    FULL,
    QUICK,
    STAGE_FILE,
    ReportBudget,
    _run_stage,
    log_digest,
    run_report,
    stage_keys,
)

#: Short runs (28.5 s, 100 Hz) that determine beta and d from nominal starts: fast and
#: slow sections and holds; one log starts on the bottom stop. (The 26 s stage-1 runs of
#: test_posterior do not: from nominal values the fit finds a second optimum with
#: beta 3.2 GPa and d 8.6 kN s/m, chi2/N 1.02 and 1.20.)
SECTIONS = [(0.0, 2.5), (0.45, 5.0), (0.2, 8.0), (0.0, 3.0), (0.4, 6.0), (0.0, 4.0)]


def clean_logs(seeds, loads, x0s):
    """Logs simulated at TRUTH (no hidden effect) with docs/model.md's sensor noise."""
    import jax

    plant, _ = jl.with_params(jl.Plant(), (), TRUTH)
    ts, pwm = ramped_sequence(SECTIONS, ramp_s=0.5)
    out = []
    for load, seed, x0 in zip(loads, seeds, x0s, strict=True):
        inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
        sol = jl.simulate(plant, (), inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
        key = jax.random.key(seed)
        out.append(jl.to_log(sol, inputs, jl.MeasurementModel(), key, name=f"run{load:.0f}"))
    return out


def _png(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\1" * 16)
    return path


# ------------------------------------------------------------------ the machinery


def test_a_stage_is_reused_only_with_its_key_and_redone_after_a_failure(tmp_path):
    calls = []

    def job(folder):
        calls.append(folder.name)
        (folder / "out.txt").write_text("x")
        return {"value": len(calls)}

    timings = {}
    folder = tmp_path / "fit"
    assert _run_stage(folder, "k1", job, lambda _: None, timings) == {"value": 1}
    assert _run_stage(folder, "k1", job, lambda _: None, timings) == {"value": 1}
    assert calls == ["fit"] and timings["fit"] == 0.0  # reused
    (folder / "stale.txt").write_text("from the run with key k1")
    assert _run_stage(folder, "k2", job, lambda _: None, timings) == {"value": 2}
    assert not (folder / "stale.txt").exists()  # the other key's results are gone

    def failing(folder):
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        _run_stage(folder, "k3", failing, lambda _: None, timings)
    assert not (folder / STAGE_FILE).exists()  # not finished: redone next time
    assert _run_stage(folder, "k3", job, lambda _: None, timings) == {"value": 3}


def test_stage_keys_follow_logs_roles_budget_and_seed():
    a, b = synthetic_logs(seeds=(3, 4))
    keys = stage_keys([a], [b], FULL, 0)
    assert stage_keys([a], [b], FULL, 0) == keys  # deterministic
    assert log_digest(a) != log_digest(b)
    height = np.array(a.height_m)
    height[100] += 1e-6  # one sample, a micrometre
    changed = dataclasses.replace(a, height_m=height)
    k = stage_keys([changed], [b], FULL, 0)
    assert all(k[s] != keys[s] for s in keys)  # a changed log redoes every stage
    assert all(stage_keys([b], [a], FULL, 0)[s] != keys[s] for s in keys)  # roles
    assert all(stage_keys([a], [b], FULL, 1)[s] != keys[s] for s in keys)
    k = stage_keys([a], [b], dataclasses.replace(FULL, tune_steps=5), 0)
    assert all(k[s] != keys[s] for s in keys)


def test_included_reports_keep_their_figures_embedded(tmp_path):
    fig = _png(tmp_path / "stage" / "figures" / "a.png")
    part = Report("Stage one")
    part.heading("Inner")
    part.text("some **text**")
    part.figure(fig, "a figure")
    part.write(tmp_path / "stage")
    fig.parent.joinpath("unrelated.png").write_bytes(b"")
    whole = Report("Whole").include(Report.read(tmp_path / "stage"), title="1. Stage")
    md, html = whole.write(tmp_path / "whole")
    text = open(html, encoding="utf-8").read()
    assert "<h2>1. Stage</h2>" in text and "<h3>Inner</h3>" in text
    assert text.count("data:image/png;base64,") == 1
    assert "../stage/figures/a.png" in open(md, encoding="utf-8").read()
    with pytest.raises(FileNotFoundError):
        Report.read(tmp_path / "nowhere")


# ------------------------------------------------------------------ the whole job


def _sections(html: str) -> list[str]:
    return re.findall(r"<h2>(.*?)</h2>", html)


def _assert_self_contained(html: str) -> None:
    srcs = re.findall(r'<img src="([^"]*)"', html)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs), srcs[:3]


@pytest.mark.slow
def test_report_from_nominal_on_clean_logs_resumes_without_redoing(tmp_path):
    """The full path (iterated diagnosis, emcee posterior, nominal and robust tuning)
    on a small budget: two short logs of known truth without a hidden effect (one
    starting on the bottom stop), a third held out. From nominal values the diagnosis
    must say ``none``; a second run with nothing changed reuses every stage."""
    fit_logs = clean_logs((3, 4), (500.0, 1400.0), (0.0, 0.7))  # one on the bottom stop
    (held,) = clean_logs((5,), (1000.0,), (0.3,))
    budget = ReportBudget(
        fit_starts=2, diagnose="iterate", diagnose_starts=1, max_effects=1,
        posterior="mcmc", posterior_max_steps=150, noise_seeds=1, tune_steps=3,
        robust_draws=2, eval_draws=3,
    )  # fmt: skip
    s = run_report(fit_logs, [held], out_dir=tmp_path, budget=budget)
    assert s["verdict"] == "none", s["reasons"]
    assert s["missing_effects"] == []
    assert s["chi2_baseline"] < 1.3  # the baseline is the true model class
    assert s["posterior_mode"] == "mcmc" and s["air"]["verdict"] in (
        "indicated",
        "not indicated",
        "undecided",
    )
    assert s["beta"]["HDI 5 %"] < s["beta"]["mean"] < s["beta"]["HDI 95 %"]
    assert abs(s["beta"]["mean"] / TRUTH["beta"] - 1) < 0.02
    assert set(s["gains"]) == {"P", "I", "D", "N", "K_aw"}
    assert s["cost_recommended"] < s["cost_current"]  # better than the thesis gains
    html = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert _sections(html)[:5] == [
        "Summary",
        "1. The baseline model against the logs: where it fails",
        "2. Which physical effect is missing",
        "3. How sure: the posterior of the diagnosed model",
        "4. Gains for the lift controller",
    ]
    _assert_self_contained(html)
    assert html.index("Summary") < html.index("<img")  # opens with the summary
    assert all(s["stage_wall_s"][k] > 0 for k in ("fit", "diagnose", "posterior", "tune"))
    stored = json.loads((tmp_path / "summary.json").read_text())
    assert stored["verdict"] == "none"
    # the posterior's DataTree weighs models (az.loo) without touching the chain file
    tree = xr.open_datatree(tmp_path / "posterior" / "posterior.nc", engine="h5netcdf")
    assert {"posterior", "prior", "observed_data", "posterior_predictive", "log_likelihood"} <= set(
        tree.children
    )
    assert np.isfinite(az.loo(tree).elpd)
    # the report's ensemble is the "auto" one (FULL's too): 16 walkers for the baseline's
    # five sampled parameters, not the command's 32
    post = json.loads((tmp_path / "posterior" / "posterior.json").read_text())
    assert FULL.posterior_walkers == budget.posterior_walkers == "auto"
    assert post["n_walkers"] == auto_walkers(len(post["sampled"])) == 16
    # and its proposal mixes in independence steps from the Laplace approximation
    assert post["move"] == FULL.posterior_move == budget.posterior_move == "de-laplace"

    again = run_report(fit_logs, [held], out_dir=tmp_path, budget=budget)
    assert again["stage_wall_s"] == {"fit": 0.0, "diagnose": 0.0, "posterior": 0.0, "tune": 0.0}
    assert again["gains"] == s["gains"] and again["verdict"] == s["verdict"]


@pytest.mark.slow
def test_report_command_quick_on_log_files(tmp_path, capsys):
    """``jaxlift report --quick`` on CSV files, as a user runs it (in this process, so
    that it reuses what the test above compiled): exit 0, the page, the quick caveat, a
    resumed second run; and a clear error for a missing file."""
    from jaxlift.cli.main import main

    logs = clean_logs((7, 8), (600.0, 1500.0), (0.2, 0.0))
    paths = []
    for lg in logs:
        paths.append(tmp_path / f"{lg.name}.csv")
        jl.write_log(paths[-1], lg)
    out = tmp_path / "report"
    cmd = ["report", *map(str, paths), "--quick", "--out", str(out)]
    assert main(cmd) == 0
    first = capsys.readouterr()
    assert "recommended gains: P = " in first.out
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "Quick report" in html and "not confirmed" in html
    _assert_self_contained(html)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["posterior_mode"] == "laplace" and summary["quick"]
    # the screen's ranking, not a verdict; the Laplace interval holds the truth
    assert summary["verdict"] == "not confirmed (quick)"
    lo, hi = summary["beta"]["HDI 5 %"], summary["beta"]["HDI 95 %"]
    assert lo < TRUTH["beta"] < hi, (lo, hi)
    assert (out / "provenance.json").exists()
    assert main(cmd) == 0
    second = capsys.readouterr()
    assert second.out.count("finished before with the same inputs") == 4
    assert main(["report", str(tmp_path / "nope.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "nope.csv" in err and "Traceback" not in err


def test_quick_is_smaller_than_full():
    assert QUICK.diagnose == "screen" and QUICK.posterior == "laplace"
    assert FULL.diagnose == "iterate" and FULL.posterior == "mcmc"
    assert np.all([QUICK.robust_draws == 0, QUICK.eval_draws == 0])
