"""The coverage study's report (studies/coverage.py, issue #17) counts what it claims.

The cases are made up here (PIT values and interval flags chosen by hand), so the
expected rates are known without running a fit or a chain."""

import csv
import importlib.util
import json
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def coverage():
    spec = importlib.util.spec_from_file_location(
        "coverage_study", ROOT / "studies" / "coverage.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _case(
    out: pathlib.Path,
    cid: str,
    pits: list[float],
    converged: bool = True,
    seed: int | None = None,
    committed: bool = False,
    fit: tuple[float, float, float] | None = None,
) -> None:
    """One finished case: in a run folder (``cid/result.json``), or as committed
    (``cid.json``); without ``seed`` like the first set's results, which lack it.
    ``fit``: (the fit's value, its standard error, the chain's sd), the same for every
    target; without it, like the cases run before they were recorded."""
    targets = {}
    for k, pit in zip(("beta", "cf_con", "d", "cf_out*cf_in^5"), pits, strict=True):
        targets[k] = {"truth": 1.0, "pit": pit, "in_50": 0.25 <= pit <= 0.75,
                      "in_90": 0.05 <= pit <= 0.95}  # fmt: skip
        if fit is not None:
            targets[k].update(fit_value=fit[0], fit_se=fit[1], sd=fit[2])
    result = {"case_id": cid, "kind": "null", "hidden_effects": [], "steps": {},
              "fit_chi2n": {"fit_1": 1.0}, "converged": converged, "targets": targets}  # fmt: skip
    if seed is not None:
        result["seed"] = seed
    path = out / f"{cid}.json" if committed else out / cid / "result.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result))


def test_report_counts_the_intervals_that_contain_the_truth(coverage, tmp_path):
    out, to = tmp_path / "runs", tmp_path / "report"
    _case(out, "case_000", [0.5, 0.9, 0.99, 0.3])
    _case(out, "case_001", [0.1, 0.5, 0.5, 1.0])
    _case(out, "case_002", [0.6, 0.02, 0.4, 0.7])
    _case(out, "case_003", [0.5, 0.5, 0.5, 0.5], converged=False)  # left out of the rates
    text = coverage.report(out, to)
    with open(to / "coverage.csv", encoding="utf-8") as fh:
        rows = {r["parameter"]: r for r in csv.DictReader(fh)}
    # beta: PIT 0.5, 0.1, 0.6 -> 50 %: 2 of 3, 90 %: 3 of 3; d: 0.99, 0.5, 0.4 -> 2/3, 2/3
    assert rows["beta"]["n"] == "3"
    assert float(rows["beta"]["cover_50"]) == pytest.approx(2 / 3)
    assert float(rows["beta"]["cover_90"]) == pytest.approx(1.0)
    assert float(rows["cf_con"]["cover_90"]) == pytest.approx(2 / 3)
    assert float(rows["d"]["cover_50"]) == pytest.approx(2 / 3)
    assert float(rows["cf_out*cf_in^5"]["cover_90"]) == pytest.approx(2 / 3)
    from scipy import stats  # beta's rms z: PITs 0.5, 0.1, 0.6

    z = stats.norm.ppf([0.5, 0.1, 0.6])
    assert float(rows["beta"]["rms_z"]) == pytest.approx(np.sqrt(np.mean(z**2)))
    assert "case_003 (null): the chain did not reach 50 tau" in text
    for png in ("pit.png", "pit_ecdf.png", "coverage_ecdf.png"):
        assert (to / png).stat().st_size > 5_000


def test_report_pools_sets_and_lists_each(coverage, tmp_path):
    """Two sets (seeds) with the same case ids, one committed and one in a run folder:
    the rates pool all cases, each set's own rates are listed, and a case given twice
    is an error rather than counted twice."""
    first, second, to = tmp_path / "cases", tmp_path / "runs", tmp_path / "report"
    _case(first, "case_000", [0.5, 0.5, 0.5, 0.5], committed=True)  # seed 17 by default
    _case(first, "case_001", [0.9, 0.5, 0.5, 0.5], committed=True)
    _case(second, "case_000", [0.1, 0.5, 0.99, 0.5], seed=18)
    text = coverage.report([first, second], to)
    with open(to / "coverage.csv", encoding="utf-8") as fh:
        rows = {r["parameter"]: r for r in csv.DictReader(fh)}
    # beta: PIT 0.5, 0.9, 0.1 -> 50 %: 1 of 3; d: 0.5, 0.5, 0.99 -> 90 %: 2 of 3
    assert rows["beta"]["n"] == "3"
    assert float(rows["beta"]["cover_50"]) == pytest.approx(1 / 3)
    assert float(rows["d"]["cover_90"]) == pytest.approx(2 / 3)
    assert "Set 17 (2 cases):" in text and "Set 18 (1 cases):" in text
    assert "| 18/case_000 |" in text and "| 17/case_001 |" in text
    _case(tmp_path / "again", "case_000", [0.5] * 4, seed=18)
    with pytest.raises(ValueError, match="the same case appears twice"):
        coverage.report([second, tmp_path / "again"], to)


def test_clopper_pearson_matches_the_binomial_tails(coverage):
    from scipy import stats

    lo, hi = coverage.clopper_pearson(45, 50)
    # the defining property: each end leaves 2.5 % in its tail
    assert stats.binom.sf(44, 50, lo) == pytest.approx(0.025, rel=1e-6)
    assert stats.binom.cdf(45, 50, hi) == pytest.approx(0.025, rel=1e-6)
    assert coverage.clopper_pearson(0, 10)[0] == 0.0
    assert coverage.clopper_pearson(10, 10)[1] == 1.0


def test_width_ratio_from_the_pits(coverage):
    """The width ratio: rms of Phi^-1(PIT), by hand on four cases; its chi-square
    interval's ends leave 2.5 % each; a truth beyond every draw counts as 3.09 standard
    deviations; and on made-up posteriors 1.3 times too narrow (a fixed seed) the
    estimate's interval holds 1.3 and not 1, while calibrated ones give an interval
    around 1."""
    from scipy import stats

    pits = stats.norm.cdf([1.0, -1.0, 2.0, -2.0])
    s, lo, hi = coverage.width_ratio(pits)
    assert s == pytest.approx(2.5**0.5, rel=1e-12)
    assert stats.chi2.sf(10.0 / lo**2, 4) == pytest.approx(0.025, rel=1e-9)
    assert stats.chi2.cdf(10.0 / hi**2, 4) == pytest.approx(0.025, rel=1e-9)
    s, _, _ = coverage.width_ratio([0.0, 1.0])
    assert s == pytest.approx(stats.norm.ppf(0.999), rel=1e-12)
    rng = np.random.default_rng(20261205)
    s, lo, hi = coverage.width_ratio(stats.norm.cdf(1.3 * rng.standard_normal(400)))
    assert lo < 1.3 < hi and lo > 1.0
    s, lo, hi = coverage.width_ratio(rng.uniform(size=400))
    assert lo < 1.0 < hi
    assert all(np.isnan(coverage.width_ratio([])))


def test_target_estimates_by_hand(coverage, tmp_path):
    """The fit's targets and standard errors: the product's by the delta method on its
    logarithm, computed by hand; a parameter without a standard error (None, as
    metrics.json writes one the data do not determine) does not spoil the product; read
    from a fit folder's metrics.json, and {} without one."""
    params = {"beta": 5e8, "cf_con": 20.0, "d": 400.0, "cf_in": 2.0, "cf_out": 3.0}
    free = ["beta", "cf_in", "cf_out", "d"]
    stderr = {"beta": None, "cf_in": 0.1, "cf_out": 0.3, "d": 40.0}
    corr = [[1.0, 0.2, 0.1, 0.0], [0.2, 1.0, -0.5, 0.0], [0.1, -0.5, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0]]  # fmt: skip
    val, se = coverage.target_estimates(params, stderr, corr, free)
    # var(log P) = (5 * 0.1 / 2)^2 + (0.3 / 3)^2 + 2 (5 / 2)(1 / 3)(-0.5)(0.1)(0.3)
    #            = 0.0625 + 0.01 - 0.025 = 0.0475
    assert val["cf_out*cf_in^5"] == pytest.approx(96.0)
    assert se["cf_out*cf_in^5"] == pytest.approx(96.0 * 0.0475**0.5, rel=1e-12)
    assert se["d"] == 40.0 and np.isnan(se["beta"]) and np.isnan(se["cf_con"])
    metrics = {"params": params, "stderr": stderr,
               "correlation": {"names": free, "matrix": corr}}  # fmt: skip
    (tmp_path / "fit").mkdir()
    (tmp_path / "fit" / "metrics.json").write_text(json.dumps(metrics))
    est = coverage._fit_estimates(tmp_path)
    assert est["cf_out*cf_in^5"]["se"] == pytest.approx(96.0 * 0.0475**0.5, rel=1e-12)
    assert est["d"] == {"value": 400.0, "se": 40.0}
    assert coverage._fit_estimates(tmp_path / "elsewhere") == {}


def test_report_separates_the_fit_from_the_chain(coverage, tmp_path):
    """Cases that recorded the fit's standard errors get the table of the fit's own z
    and the chain's width over the fit's; cases without them are left out of it, and a
    set with none has no such table."""
    out, to = tmp_path / "runs", tmp_path / "report"
    _case(out, "case_000", [0.5] * 4, fit=(1.5, 0.5, 0.45))  # z = +1, sd / se 0.9
    _case(out, "case_001", [0.5] * 4, fit=(0.7, 0.1, 0.11))  # z = -3, sd / se 1.1
    _case(out, "case_002", [0.5] * 4)  # run before the fit's errors were recorded
    text = coverage.report(out, to)
    rows = [ln for ln in text.splitlines() if ln.startswith("| d | 2 |")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    # rms sqrt((1 + 9) / 2) = 2.24, its interval from chi-square on 2 degrees of
    # freedom, mean -1, median of 0.9 and 1.1 = 1.0
    from scipy import stats

    lo, hi = (np.sqrt(10.0 / stats.chi2.ppf(q, 2)) for q in (0.975, 0.025))
    assert cells[2:] == ["2.24", f"[{lo:.2f}, {hi:.2f}]", "-1.00", "1.00", "0.90-1.10"]
    _case(tmp_path / "old", "case_000", [0.5] * 4)
    assert "The fit and the chain apart" not in coverage.report(tmp_path / "old", to)


def test_refit_adds_the_fit_only_where_it_is_the_recorded_one(coverage, tmp_path, monkeypatch):
    """``refit`` gives committed records the fit's estimates where a new fit reproduces
    the recorded chi2/N (within 1e-3), leaves the others as they were, skips records
    that have them; the report then reads the chain's sd from the 90 % interval
    (width / 3.29) for records that did not store it."""
    records, out = tmp_path / "cases", tmp_path / "runs"
    records.mkdir()
    for cid in ("case_000", "case_001"):
        targets = {k: {"truth": 1.0, "pit": 0.5, "in_50": True, "in_90": True,
                       "interval_90": [0.9, 1.1 + 2 * 1.6448536269514722 * 0.05]}
                   for k in ("beta", "cf_con", "d", "cf_out*cf_in^5")}  # fmt: skip
        rec = {"case_id": cid, "seed": 18, "kind": "null", "hidden_effects": [],
               "steps": {"fit": {"rc": 0, "tail": ""}}, "fit_chi2n": {"fit_1": 1.0},
               "converged": True, "targets": targets}  # fmt: skip
        (records / f"{cid}.json").write_text(json.dumps(rec))
    new_chi2 = {"case_000": 1.0002, "case_001": 1.01}  # the second: another fit
    calls = []

    def fake_fit(spec, data, where):
        calls.append(spec["case_id"])
        fit = where / spec["case_id"] / "fit"
        fit.mkdir(parents=True, exist_ok=True)
        metrics = {
            "logs": {"fit_1": {"role": "fitted",
                               "after": {"chi2_per_sample": new_chi2[spec["case_id"]]}}},
            "params": {"beta": 1.3, "cf_con": 1.3, "d": 1.3, "cf_in": 1.0, "cf_out": 1.3},
            "stderr": {"beta": 0.1, "cf_con": 0.1, "d": 0.1, "cf_in": 1e-9, "cf_out": 0.1},
            "correlation": {"names": ["beta", "cf_con", "d", "cf_in", "cf_out"],
                            "matrix": np.eye(5).tolist()},
        }  # fmt: skip
        (fit / "metrics.json").write_text(json.dumps(metrics))
        return [], {"rc": 0, "tail": ""}

    monkeypatch.setattr(coverage, "_fit_case", fake_fit)
    monkeypatch.setattr(coverage, "_library", lambda: "abc1234")
    monkeypatch.setattr(coverage, "cases", lambda seed: [
        {"case_id": c, "hidden_effects": []} for c in ("case_000", "case_001")])  # fmt: skip
    lines = list(coverage.refit(records, 18, out))
    assert [ln.split(":")[0] for ln in lines] == ["case_000", "case_001"]
    assert "estimates added" in lines[0] and "left without" in lines[1]
    r0 = json.loads((records / "case_000.json").read_text())
    r1 = json.loads((records / "case_001.json").read_text())
    assert r0["fit_estimates_from"] == {"library": "abc1234", "fit_chi2n": {"fit_1": 1.0002}}
    assert r0["targets"]["d"]["fit_value"] == 1.3 and r0["targets"]["d"]["fit_se"] == 0.1
    assert "fit_estimates_from" not in r1 and "fit_se" not in r1["targets"]["d"]
    calls.clear()
    assert [ln.split(":")[0] for ln in coverage.refit(records, 18, out)] == ["case_001"]
    # the chain's sd from the interval: (0.2 + 2 * 1.645 * 0.05) / 3.29 = 0.1108; over
    # the fit's 0.1: 1.11; the fit's z = (1.3 - 1) / 0.1 = 3
    text = coverage.report(records, tmp_path / "report")
    row = next(ln for ln in text.splitlines() if ln.startswith("| d | 1 |"))
    cells = [c.strip() for c in row.split("|")]
    assert cells[3] == "3.00" and cells[5] == "+3.00" and cells[6] == "1.11"


def test_collect_copies_finished_cases_with_their_library_and_step(coverage, tmp_path):
    """``collect`` copies each finished case of a run folder as a committed record with
    the library and the posterior's nuisance step and failed check points added; an
    unfinished case (no result.json) is not copied; a record with no library and none
    given is an error that names the file."""
    runs, to = tmp_path / "runs", tmp_path / "cases"
    _case(runs, "case_000", [0.5, 0.5, 0.5, 0.5], seed=18)
    _case(runs, "case_001", [0.5, 0.5, 0.5, 0.5], seed=18)
    (runs / "case_002" / "posterior").mkdir(parents=True)  # a chain still running
    settings = {"problem": {"nuisance_steps": 1,
                            "ls_info": {"nuisance_check": {"failed": ["d +1 sd"]}}}}  # fmt: skip
    (runs / "case_001" / "posterior").mkdir()
    (runs / "case_001" / "posterior" / "posterior_settings.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match="case_000/result.json"):
        list(coverage.collect(runs, to))
    lines = list(coverage.collect(runs, to, library="abc1234"))
    assert [ln.split(":")[0] for ln in lines] == ["case_000", "case_001"]
    assert sorted(p.name for p in to.iterdir()) == ["case_000.json", "case_001.json"]
    r0 = json.loads((to / "case_000.json").read_text())
    r1 = json.loads((to / "case_001.json").read_text())
    assert r0["library"] == "abc1234" and "nuisance_steps" not in r0
    assert r1["nuisance_steps"] == 1 and r1["nuisance_check_failed"] == ["d +1 sd"]
    assert r1["targets"] == json.loads((runs / "case_001" / "result.json").read_text())["targets"]


def test_compare_sets_each_case_beside_its_earlier_record(coverage, tmp_path):
    """``compare``: a row per case of the new records, PIT and 90 % verdict earlier ->
    now; the counts over the new records alone and merged with the earlier records of
    the cases not re-run."""
    earlier, now = tmp_path / "earlier", tmp_path / "now"
    _case(earlier, "case_000", [0.97, 0.5, 0.5, 0.5], committed=True)
    _case(earlier, "case_001", [0.5, 0.01, 0.5, 0.5], committed=True)
    _case(earlier, "case_002", [0.5, 0.5, 0.99, 0.3], committed=True)
    _case(now, "case_000", [0.94, 0.5, 0.5, 0.96], committed=True)
    _case(now, "case_003", [0.5, 0.5, 0.5, 0.5], committed=True)  # no earlier record
    text = coverage.compare(earlier, now)
    row0 = next(ln for ln in text.splitlines() if ln.startswith("| case_000 |"))
    cells = [c.strip() for c in row0.split("|")[1:-1]]
    assert cells[4] == "0.970 → 0.940 (**out** → in)"
    assert cells[7] == "0.500 → 0.960 (in → **out**)"
    row3 = next(ln for ln in text.splitlines() if ln.startswith("| case_003 |"))
    assert row3.split("|")[5].strip() == "0.500 (in)"
    assert "case_001" not in text.split("\n\n")[0] and "case_002" not in text.split("\n\n")[0]
    # now alone: 2 cases, every target in but the product of case_000; merged with
    # case_001 (cf_con out) and case_002 (d out): 4 cases
    assert "these records (2 cases): beta 2, cf_con 2, d 2, cf_out*cf_in^5 1;" in text
    assert "for the rest (4 cases): beta 4, cf_con 3, d 3, cf_out*cf_in^5 3;" in text


# ~145 s (two runs of a study script): out of CI's time since 2026-12-04; the study
# scripts' shared pieces stay checked above. Run with -m extended.
@pytest.mark.extended
def test_stderr_montecarlo_runs_and_is_reproducible(capsys):
    """studies/stderr_montecarlo.py (the Monte Carlo check of the standard errors quoted
    in docs/statistics.md): a short run prints one row per parameter, and the same
    seeds give the same numbers."""
    spec = importlib.util.spec_from_file_location(
        "stderr_montecarlo", ROOT / "studies" / "stderr_montecarlo.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    tables = []
    for _ in range(2):
        assert mod.main(["own", "--draws", "2"]) == 0
        out = capsys.readouterr().out
        tables.append([ln for ln in out.splitlines() if ln.startswith("| ")])
    assert tables[0] == tables[1]
    rows = {ln.split("|")[1].strip(): ln for ln in tables[0][1:]}
    assert set(rows) == {"beta", "cf_con", "d", "cf_out*cf_in^5"}
    for ln in rows.values():
        assert "nan" not in ln and "/2 (expected" in ln
