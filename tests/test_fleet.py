"""``jaxlift fleet``: the input tree, job keys, the engine's retries and resumption,
the trend test, the flags, and (slow) the whole command on a small fleet with a
drifting vehicle, killed half way and restarted."""

import datetime
import json
import math
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pyarrow.parquet as pq
import pytest

import jaxlift as jl
from jaxlift.fleet import (
    FleetError,
    discover_jobs,
    fleet_rows,
    laplace_interval,
    pooled_inflation,
    read_table,
    run_jobs,
    trend_test,
    vehicle_flags,
    write_fleet_outputs,
    write_table,
)
from jaxlift.model.sequences import ramped_sequence

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _tree(tmp_path, spec):
    """spec: {vehicle: {date: [file names]}} with tiny placeholder CSVs."""
    for v, dates in spec.items():
        for d, files in dates.items():
            folder = tmp_path / "fleet" / v / d
            folder.mkdir(parents=True)
            for f in files:
                (folder / f).write_text(f"time_s,pwm,height_m,load_kg\n0,0,0,{len(f)}\n")
    return tmp_path / "fleet"


# ------------------------------------------------------------------ input tree
def test_discover_jobs_and_manifest(tmp_path):
    spec = {
        "agv2": {"2026-01-08": ["a.csv", "b.csv", "c.csv"]},
        "agv1": {"2026-01-01": ["x.csv"], "2026-01-15": ["y.csv"]},
    }
    root = _tree(tmp_path, spec)
    (root / "agv2" / "2026-01-08" / "run.toml").write_text('validate = ["b.csv"]\n')
    (root / "agv1" / ".hidden").mkdir()
    jobs = discover_jobs(root)
    assert [j.name for j in jobs] == ["agv1/2026-01-01", "agv1/2026-01-15", "agv2/2026-01-08"]
    j = jobs[2]
    assert [p.name for p in j.fit] == ["a.csv", "c.csv"] and [p.name for p in j.validate] == [
        "b.csv"
    ]
    assert j.date == datetime.date(2026, 1, 8)


@pytest.mark.parametrize(
    "layout, manifest, message",
    [
        ({"v": {"last-week": ["a.csv"]}}, None, "must be an ISO date"),
        ({"v": {"2026-01-01": []}}, None, "no logs"),
        ({"v": {"2026-01-01": ["a.csv"]}}, 'fitt = ["a.csv"]', "unknown key"),
        ({"v": {"2026-01-01": ["a.csv"]}}, 'fit = ["z.csv"]', "'z.csv', which is not a file"),
        ({"v": {"2026-01-01": ["a.csv"]}}, 'fit = ["a.csv"]\nvalidate = ["a.csv"]', "both"),
        ({"v": {"2026-01-01": ["a.csv"]}}, "fit = [", "not valid TOML"),
        ({"v": {"2026-01-01": ["a.csv"]}}, 'fit = "a.csv"', "must be a list"),
    ],
)
def test_bad_trees_are_named(tmp_path, layout, manifest, message):
    root = _tree(tmp_path, layout)
    if manifest is not None:
        (root / "v" / "2026-01-01" / "run.toml").write_text(manifest)
    with pytest.raises(FleetError, match=message) as err:
        discover_jobs(root)
    assert str(root / "v") in str(err.value)


def test_empty_or_missing_fleet(tmp_path):
    with pytest.raises(FleetError, match="not a folder"):
        discover_jobs(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FleetError, match="no <vehicle>/<date>/ run folders"):
        discover_jobs(tmp_path / "empty")


def test_job_key_follows_inputs_settings_and_version(tmp_path):
    root = _tree(tmp_path, {"v": {"2026-01-01": ["a.csv", "b.csv"]}})
    (job,) = discover_jobs(root)
    k = job.key({"job": "fit"}, "1.0")
    assert k == job.key({"job": "fit"}, "1.0")
    assert k != job.key({"job": "diagnose"}, "1.0")
    assert k != job.key({"job": "fit"}, "1.1")
    (root / "v" / "2026-01-01" / "run.toml").write_text('validate = ["b.csv"]\n')
    (job2,) = discover_jobs(root)
    k2 = job2.key({"job": "fit"}, "1.0")
    assert k2 != k  # b.csv changed role
    path = root / "v" / "2026-01-01" / "a.csv"
    path.write_text(path.read_text() + "1,0,0,1\n")
    (job3,) = discover_jobs(root)
    assert job3.key({"job": "fit"}, "1.0") != k2  # a.csv's content changed


# ------------------------------------------------------------------ engine
@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_engine_retries_records_failures_and_skips_finished(tmp_path):
    import fleet_jobs

    root = _tree(tmp_path, {"a": {"2026-01-01": ["x.csv"], "2026-01-08": ["x.csv"]},
                            "b": {"2026-01-01": ["x.csv"]}})  # fmt: skip
    jobs = discover_jobs(root)
    out = tmp_path / "out"
    run = run_jobs(jobs, out, {"job": "fit"}, workers=2, retries=1, job_fn=fleet_jobs.flaky_job)
    assert run.ran == 3 and not run.failures and len(run.results) == 3
    attempts = sorted(p.read_text() for p in (out / "jobs").rglob("*.attempts"))
    assert attempts == ["2", "2", "2"]  # each failed once, then succeeded on its retry
    # a re-run skips all three
    again = run_jobs(jobs, out, {"job": "fit"}, job_fn=fleet_jobs.flaky_job)
    assert (again.ran, again.skipped, len(again.results)) == (0, 3, 3)
    # other settings: new keys, run again; a job that always fails is recorded, the
    # others finish
    run3 = run_jobs(jobs, out, {"job": "diagnose"}, retries=2, job_fn=fleet_jobs.broken_for_b)
    assert run3.ran == 3 and len(run3.results) == 2
    (fail,) = run3.failures
    assert fail["vehicle"] == "b" and fail["attempts"] == 3
    assert "ValueError: cannot read x.csv" in fail["error"]
    (rec,) = list((out / "failures" / "b").rglob("*.json"))
    assert json.loads(rec.read_text())["error"] == fail["error"]
    rows = fleet_rows(run3.results, run3.failures)
    assert [r["status"] for r in rows] == ["ok", "ok", "failed"]
    flags = vehicle_flags(rows)
    assert flags["b"]["flags"] == ["1 job(s) failed: 2026-01-01"] and not flags["a"]["flags"]


# ------------------------------------------------------------------ trend test
def test_laplace_interval_is_log_normal_and_never_overflows():
    z = 1.6448536269514722  # the 95 % quantile of the standard normal: a 90 % interval
    lo, hi = laplace_interval(2.0, 0.1)
    assert lo == pytest.approx(2.0 * math.exp(-z * 0.05), rel=1e-12)
    assert hi == pytest.approx(2.0 * math.exp(z * 0.05), rel=1e-12)
    # a standard error 1000x the value (exp(1645) overflows): every positive value
    assert laplace_interval(1e-3, 1.0) == (0.0, math.inf)
    assert all(math.isnan(x) for x in laplace_interval(1.0, math.nan))
    assert all(math.isnan(x) for x in laplace_interval(0.0, 1.0))


def test_trend_test_recovers_a_known_slope():
    rng = np.random.default_rng(0)
    days = np.arange(8) * 7.0
    rel_se = 0.02
    truth = 1e9 * 0.9 ** (days / 7)  # -10 %/week
    values = truth * np.exp(rel_se * rng.standard_normal(8))
    t = trend_test(days, values, rel_se * values)
    assert math.exp(t["slope"]) == pytest.approx(0.9, abs=0.01)
    assert t["z"] < -10 and t["p"] < 1e-6 and t["n"] == 8  # Student t, 6 dof


def test_trend_test_false_alarm_rate_own_scatter():
    """Under no trend, the series' own scatter and Student's t give p < 0.05 in at most
    about 5 % of 400 series (binomial: 20 expected, 32 is 2.7 sd above), also when the
    stated errors are 3 times too small."""
    rng = np.random.default_rng(1)
    days = np.arange(6) * 7.0
    for stated in (1.0, 1 / 3):
        hits = 0
        for _ in range(400):
            v = 100.0 * np.exp(0.05 * rng.standard_normal(6))
            hits += trend_test(days, v, stated * 0.05 * v)["p"] < 0.05
        assert hits <= 32, (stated, hits)
    short = trend_test([0, 7], [1.0, 2.0], [0.1, 0.1])
    assert math.isnan(short["p"]) and short["n"] == 2


def test_pooled_inflation_restores_the_false_alarm_rate():
    """A fleet of 400 stable vehicles whose stated errors are 3 times too small: the
    uninflated z test alarms on most of them; with the fleet's pooled inflation the rate
    is about 5 % (at most 32 of 400), and the factor is about 3."""
    rng = np.random.default_rng(2)
    days = np.arange(8) * 7.0
    series = [100.0 * np.exp(0.03 * rng.standard_normal(8)) for _ in range(400)]
    tests = [trend_test(days, v, 0.01 * v) for v in series]
    factor = pooled_inflation(tests)
    assert factor == pytest.approx(3.0, rel=0.1)
    naive = sum(trend_test(days, v, 0.01 * v, inflation=1.0)["p"] < 0.05 for v in series)
    pooled = sum(trend_test(days, v, 0.01 * v, inflation=factor)["p"] < 0.05 for v in series)
    assert naive > 150 and pooled <= 32, (naive, pooled)


def _row(v, d, verdict="none", beta=1e9, cf=50.0, status="ok"):
    return {"vehicle": v, "date": d, "status": status, "verdict": verdict,
            "beta": beta, "beta_se": 0.01 * beta, "cf_con": cf, "cf_con_se": 1.0,
            "d": 300.0, "d_se": 10.0, "air": 0.003, "air_lo": 0.002,
            "air_hi": 0.004}  # fmt: skip


def _four_vehicles():
    """A stable vehicle, one losing bulk modulus, one gaining friction, one whose
    cylinder starts leaking in the third week."""
    dates = [f"2026-01-{d:02d}" for d in (1, 8, 15, 22)]
    rows = [_row("stable", d, beta=1e9 * (1 + 0.005 * (-1) ** i)) for i, d in enumerate(dates)]
    rows += [_row("airy", d, beta=1e9 * 0.85**i) for i, d in enumerate(dates)]
    rows += [_row("sticky", d, cf=50.0 * 1.3**i) for i, d in enumerate(dates)]
    rows += [_row("leaky", d, verdict="leakage" if i >= 2 else "none") for i, d in enumerate(dates)]
    return rows


def test_flags_from_rows():
    f = vehicle_flags(_four_vehicles())
    assert f["stable"]["flags"] == [] and f["leaky"]["flags"] == [
        "new effect since 2026-01-15: leakage"
    ]
    assert len(f["airy"]["flags"]) == 1 and f["airy"]["flags"][0].startswith("air content rising")
    assert len(f["sticky"]["flags"]) == 1 and "friction rising" in f["sticky"]["flags"][0]


def test_a_table_read_back_gives_the_same_flags_and_can_be_merged(tmp_path):
    """read_table inverts write_table (Parquet and CSV): the flags from the rows read
    back are those from the rows written; an earlier table with a failed job, merged
    with a newer run's row for that job, is flagged as if the job had never failed."""
    failed = {"vehicle": "stable", "date": "2026-01-29", "status": "failed",
              "error": "OverflowError: math range error"}  # fmt: skip
    rows = fleet_rows([*_four_vehicles()], [failed])
    write_table(rows, tmp_path / "old")
    want = vehicle_flags(rows)
    assert want["stable"]["flags"] == ["1 job(s) failed: 2026-01-29"]
    for name in ("fleet.parquet", "fleet.csv"):
        back = read_table(tmp_path / "old" / name)
        assert [(r["vehicle"], r["date"], r["status"], r["verdict"]) for r in back] == [
            (r["vehicle"], r["date"], r["status"], r["verdict"]) for r in rows
        ]
        got = vehicle_flags(back)
        assert {v: (f["flags"], f["notes"]) for v, f in got.items()} == {
            v: (f["flags"], f["notes"]) for v, f in want.items()
        }
        for v in want:
            for p, t in want[v]["tests"].items():
                assert got[v]["tests"][p]["z"] == pytest.approx(t["z"], rel=1e-12, nan_ok=True)
    # the failed job re-run (e.g. on a fixed library) replaces the earlier row
    newer = fleet_rows([_row("stable", "2026-01-29", beta=1e9)])
    merged = [r for r in read_table(tmp_path / "old" / "fleet.csv") if r["status"] == "ok"]
    summary = write_fleet_outputs(merged + newer, tmp_path / "merged",
                                  {"ran": 1, "skipped": len(merged), "failed": 0})  # fmt: skip
    assert "stable" not in summary["flagged"]
    assert set(summary["flagged"]) == {"airy", "sticky", "leaky"}
    assert len(read_table(tmp_path / "merged" / "fleet.parquet")) == len(rows)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("cf_con_se,", "cf_con_sd,", 1), "column(s) ['cf_con_se'] missing"),
        (lambda t: t.replace("2026-01-08", "8 Jan 2026", 1), "row 3, column 'date'"),
        (lambda t: t.replace(",50.0,", ",fifty,", 1), "row 2, column 'cf_con': 'fifty'"),
    ],
)
def test_a_bad_table_is_named(tmp_path, edit, message):
    write_table(fleet_rows(_four_vehicles()), tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text(edit((tmp_path / "fleet.csv").read_text()))
    with pytest.raises(FleetError, match=re.escape(f"{bad}") + ".*" + re.escape(message)):
        read_table(bad)


def test_a_file_that_is_no_table_is_named(tmp_path):
    with pytest.raises(FleetError, match="no such file"):
        read_table(tmp_path / "fleet.parquet")
    junk = tmp_path / "fleet.parquet"
    junk.write_text("not parquet")
    with pytest.raises(FleetError, match="not a readable Parquet file"):
        read_table(junk)
    empty = tmp_path / "fleet.csv"
    empty.write_text("")
    with pytest.raises(FleetError, match=r"column\(s\) \['vehicle', 'date'"):
        read_table(empty)


# ------------------------------------------------------------------ the command
SECTIONS = [(0.0, 2.5), (0.45, 5.0), (0.2, 8.0), (0.0, 3.0), (0.4, 6.0), (0.0, 4.0)]


def _write_fleet(root, betas_by_vehicle, seed0=0):
    ts, pwm = ramped_sequence(SECTIONS, ramp_s=0.5)
    start = datetime.date(2026, 3, 2)
    for vi, (vehicle, betas) in enumerate(betas_by_vehicle.items()):
        for w, beta in enumerate(betas):
            folder = root / vehicle / (start + datetime.timedelta(weeks=w)).isoformat()
            folder.mkdir(parents=True)
            plant, effects = jl.with_params(jl.Plant(), [], {"beta": beta, "cf_con": 40.0})
            for k, (load, x0) in enumerate([(500.0 + 100 * w, 0.0), (1400.0, 0.7)]):
                inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
                sol = jl.simulate(plant, effects, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
                key = jax.random.key(seed0 + 100 * vi + 10 * w + k)
                log = jl.to_log(sol, inputs, jl.MeasurementModel(), key, name=f"run{k}")
                jl.write_log(folder / f"run{k}.csv", log)


def _fleet_cmd(fleet, out, workers):
    env = {**os.environ, "JAXLIFT_CACHE": "off"}
    return [sys.executable, "-m", "jaxlift", "fleet", str(fleet), "--out", str(out),
            "--workers", str(workers), "--starts", "1"], env  # fmt: skip


@pytest.mark.slow
def test_fleet_command_killed_and_resumed_flags_the_drifting_vehicle(tmp_path):
    """The user's command in Dask's local mode: a stable vehicle and one whose bulk
    modulus falls 30 % a week, four weeks each. The run is killed (SIGKILL to its
    process group, workers included) after two jobs; the second run redoes none of
    them, finishes the rest, and flags only the drifting vehicle."""
    fleet, out = tmp_path / "fleet", tmp_path / "out"
    _write_fleet(fleet, {"steady": [1.1e9] * 4, "airy": [1.2e9 * 0.7**w for w in range(4)]})
    cmd, env = _fleet_cmd(fleet, out, workers=1)
    proc = subprocess.Popen(cmd, env=env, cwd=tmp_path, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 600
    while len(list(out.rglob("result.json"))) < 2:
        assert proc.poll() is None, "the first run ended before it was killed"
        assert time.monotonic() < deadline
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(1.0)
    first = {p: p.read_bytes() for p in out.rglob("result.json")}
    assert 2 <= len(first) < 8
    cmd, env = _fleet_cmd(fleet, out, workers=2)
    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"8 job(s): {len(first)} finished before (skipped), {8 - len(first)} to run" in (
        done.stdout
    )
    for p, content in first.items():
        assert p.read_bytes() == content  # not redone
    assert len(list(out.rglob("result.json"))) == 8
    table = pq.read_table(out / "fleet.parquet").to_pylist()
    assert len(table) == 8 and {r["status"] for r in table} == {"ok"}
    assert {r["verdict"] for r in table} == {"none"}  # nothing is missing from these logs
    for r in table:  # the fitted bulk modulus is the truth's, within its interval
        truth = (
            1.1e9
            if r["vehicle"] == "steady"
            else 1.2e9 * 0.7 ** ((r["date"] - datetime.date(2026, 3, 2)).days // 7)
        )
        assert r["beta_lo"] <= truth * 1.02 and truth * 0.98 <= r["beta_hi"], r
    flags = json.loads((out / "flags.json").read_text())
    assert list(flags["flagged"]) == ["airy"]
    assert flags["flagged"]["airy"][0].startswith("air content rising")
    assert (out / "report.html").exists() and (out / "figures" / "vehicle_airy.png").exists()


def test_engine_runs_on_a_cluster_given_its_scheduler_address(tmp_path):
    """``scheduler=``: the same jobs on a cluster that was started elsewhere (here a
    separate local cluster, reached only through its address)."""
    import fleet_jobs
    from dask.distributed import LocalCluster

    root = _tree(tmp_path, {"a": {"2026-01-01": ["x.csv"]}, "b": {"2026-01-01": ["x.csv"]}})
    with LocalCluster(n_workers=1, threads_per_worker=1, dashboard_address=":0") as cluster:
        run = run_jobs(discover_jobs(root), tmp_path / "out", scheduler=cluster.scheduler_address,
                       job_fn=fleet_jobs.ok_job)  # fmt: skip
        assert run.ran == 2 and len(run.results) == 2 and not run.failures
        # the cluster is not ours: it is still up after the run
        assert cluster.status.name == "running"


@pytest.mark.slow
def test_a_job_with_the_sampled_posterior(tmp_path):
    """``posterior: mcmc`` (``jaxlift fleet --posterior mcmc``): the job samples the
    final model's posterior and the row carries its mean and 90 % HDI (a short chain:
    the test checks the plumbing, the coverage study the intervals)."""
    from jaxlift.fleet.job import run_job

    _write_fleet(tmp_path / "fleet", {"v1": [0.9e9]})
    (job,) = discover_jobs(tmp_path / "fleet")
    settings = {"job": "fit", "n_starts": 1, "posterior": "mcmc", "posterior_max_steps": 300}
    rec = run_job(job, settings, tmp_path / "job")
    assert rec["interval"] == "mcmc" and rec["posterior_steps"] <= 300
    post = json.loads((tmp_path / "job" / "posterior" / "posterior.json").read_text())
    beta = next(r for r in post["summary"] if r["parameter"] == "beta")
    assert (rec["beta_lo"], rec["beta"], rec["beta_hi"]) == (
        beta["HDI 5 %"],
        beta["mean"],
        beta["HDI 95 %"],
    )
    assert rec["beta_lo"] < 0.9e9 * 1.01 and 0.9e9 * 0.99 < rec["beta_hi"]
    assert rec["air_lo"] <= rec["air"] <= rec["air_hi"]
    row = fleet_rows([rec])[0]
    assert row["interval"] == "mcmc"


def test_the_table_keeps_text_columns_as_text(tmp_path):
    """Every text column of the fleet table is written as text (measured: the new
    ``interval`` column was cast to float and ``jaxlift fleet`` ended with exit 2)."""
    from jaxlift.fleet.trends import COLUMNS, write_table

    rec = {c: 1.0 for c in COLUMNS}
    rec.update(vehicle="v1", date="2026-03-02", status="ok", verdict="none", effects="",
               interval="laplace", error=None, job_key="k", jaxlift_version="0")  # fmt: skip
    write_table(fleet_rows([rec]), tmp_path)
    (row,) = pq.read_table(tmp_path / "fleet.parquet").to_pylist()
    assert row["interval"] == "laplace" and row["verdict"] == "none" and row["beta"] == 1.0
