"""The fleet's results as one tidy table, and which vehicles are changing.

Trend test (per vehicle and tracked parameter, stated in docs/fleet.md): a weighted
least-squares line through the log of the estimates against time, weights
``1 / se_log^2`` from each job's standard error. Job errors from a least-squares fit
understate the real scatter (model error, loads, sequences), so the slope's standard
error is inflated by the square root of the reduced chi-square about the lines,
pooled over the fleet (the median over vehicles, :func:`pooled_inflation`; at least 5
vehicles), then a two-sided z test; a smaller fleet uses each series' own scatter and
Student's t with ``n - 2`` degrees of freedom. a vehicle is flagged when ``p < alpha / m``
(Bonferroni over the ``m`` = vehicles × parameters tests of the fleet, ``alpha`` =
0.05 family-wise), and at least three dates are needed. Direction decides the
message: bulk modulus falling = air content rising (bleed soon); Coulomb friction or
viscous damping rising (service the mast).
"""

from __future__ import annotations

import csv
import datetime
import math
import pathlib
from collections.abc import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy import stats

from .job import TRACKED
from .manifest import FleetError

#: name -> (what, unit, scale to the unit, direction that needs service, message)
TRACKED_INFO = {
    "beta": ("bulk modulus", "GPa", 1e-9, -1, "air content rising: bleed the system soon"),
    "cf_con": ("Coulomb friction", "N", 1.0, +1, "friction rising: service the mast"),
    "d": ("viscous damping", "N·s/m", 1.0, +1, "damping rising: service the mast"),
}
ALPHA = 0.05
MIN_DATES = 3

#: the table's columns, in order (see docs/fleet.md)
COLUMNS = [
    "vehicle", "date", "status", "verdict", "effects", "chi2n", "baseline_chi2n",
    *[f"{n}{s}" for n in TRACKED for s in ("", "_lo", "_hi", "_se")],
    "air", "air_lo", "air_hi", "alpha0", "p_mean_pa", "interval", "wall_s", "error",
    "job_key",
    "jaxlift_version",
]  # fmt: skip


def fleet_rows(results: Sequence[dict], failures: Sequence[dict] = ()) -> list[dict]:
    """One row per job (finished or failed), sorted by vehicle and date."""
    rows = []
    for rec in [*results, *failures]:
        row = {c: rec.get(c) for c in COLUMNS}
        row["effects"] = "+".join(rec.get("effects", []) or [])
        row["status"] = rec.get("status", "ok")
        row["error"] = rec.get("error", "")
        rows.append(row)
    return sorted(rows, key=lambda r: (r["vehicle"], r["date"]))


#: the table's text columns (the others but ``date`` are numbers)
TEXT_COLUMNS = {"vehicle", "status", "verdict", "effects", "interval", "error", "job_key",
                "jaxlift_version"}  # fmt: skip


def write_table(rows: Sequence[dict], out_dir: str | pathlib.Path) -> list[pathlib.Path]:
    """``fleet.parquet`` (typed columns; dates as dates) and ``fleet.csv`` beside it."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for c in COLUMNS:
        vals = [r.get(c) for r in rows]
        if c == "date":
            arrays[c] = pa.array([datetime.date.fromisoformat(v) for v in vals], pa.date32())
        elif c in TEXT_COLUMNS:
            arrays[c] = pa.array([None if v is None else str(v) for v in vals], pa.string())
        else:
            arrays[c] = pa.array([math.nan if v is None else float(v) for v in vals], pa.float64())
    pq.write_table(pa.table(arrays), out / "fleet.parquet")
    with open(out / "fleet.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({c: "" if r.get(c) is None else r.get(c) for c in COLUMNS})
    return [out / "fleet.parquet", out / "fleet.csv"]


def read_table(path: str | pathlib.Path) -> list[dict]:
    """The rows of a fleet table written by :func:`write_table` (``fleet.parquet`` or
    ``fleet.csv``), as :func:`fleet_rows` makes them: dates as ISO strings, numbers as
    floats (a missing one NaN), a missing text "" and a failed job's verdict None. With
    :func:`~jaxlift.fleet.write_fleet_outputs` it lets an earlier run's table be
    combined with a newer run's (docs/fleet.md, "After an upgrade"). Raises
    :class:`~jaxlift.fleet.FleetError` naming the file (and row and column) when it is
    not such a table."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FleetError(f"{path}: no such file (expected a fleet.parquet or fleet.csv)")
    if path.suffix == ".parquet":
        try:
            table = pq.read_table(path)
        except (OSError, ValueError) as err:  # pyarrow's: not Parquet, truncated, ...
            raise FleetError(f"{path}: not a readable Parquet file ({err})") from None
        names, recs = table.column_names, table.to_pylist()
    else:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            names, recs = reader.fieldnames or [], list(reader)
    missing = [c for c in COLUMNS if c not in names]
    if missing:
        raise FleetError(f"{path}: column(s) {missing} missing; expected {COLUMNS}")
    rows = []
    for i, rec in enumerate(recs, start=2):  # CSV: row 1 is the header
        row = {}
        for c in COLUMNS:
            v = rec[c]
            if c == "date":
                row[c] = v.isoformat() if isinstance(v, datetime.date) else str(v)
            elif c in TEXT_COLUMNS:
                row[c] = None if c == "verdict" and v in ("", None) else ("" if v is None else v)
            else:
                try:
                    row[c] = math.nan if v in ("", None) else float(v)
                except ValueError:
                    raise FleetError(
                        f"{path}, row {i}, column {c!r}: {v!r} is not a number"
                    ) from None
        try:
            datetime.date.fromisoformat(row["date"])
        except ValueError:
            raise FleetError(
                f"{path}, row {i}, column 'date': {row['date']!r} is not a date (YYYY-MM-DD)"
            ) from None
        rows.append(row)
    return rows


def trend_test(
    days: Sequence[float],
    values: Sequence[float],
    ses: Sequence[float],
    inflation: float | None = None,
) -> dict:
    """Slope per week of ``log(value)`` (relative change per week) by weighted least
    squares, its standard error, z and the two-sided p-value (module docstring).

    ``inflation``: the factor on the stated standard errors, estimated from the whole
    fleet (:func:`pooled_inflation`); the p-value is then normal. Without it the
    series' own scatter sets the factor (``sqrt(max(1, chi2_red))``) and the p-value
    is Student's t with ``n - 2`` degrees of freedom, valid whatever the scale of the
    stated errors (but weak with few dates). Estimates without a finite positive value
    and standard error are left out; fewer than :data:`MIN_DATES` gives ``p = nan``."""
    nan = {"slope": math.nan, "se": math.nan, "z": math.nan, "p": math.nan,
           "inflation": math.nan, "chi2_red": math.nan}  # fmt: skip
    t = np.asarray(days, float) / 7.0
    v, se = np.asarray(values, float), np.asarray(ses, float)
    ok = np.isfinite(v) & np.isfinite(se) & (v > 0) & (se > 0)
    n = int(ok.sum())
    if n < MIN_DATES:
        return {"n": n, **nan}
    t, y, s = t[ok], np.log(v[ok]), se[ok] / v[ok]
    w = 1.0 / s**2
    tm = np.sum(w * t) / np.sum(w)
    sxx = np.sum(w * (t - tm) ** 2)
    if sxx <= 0:
        return {"n": n, **nan}
    slope = float(np.sum(w * (t - tm) * y) / sxx)
    icpt = float(np.sum(w * y) / np.sum(w) - slope * tm)
    chi2r = float(np.sum(w * (y - icpt - slope * t) ** 2) / (n - 2))
    own = inflation is None
    infl = math.sqrt(max(1.0, chi2r)) if own else float(inflation)
    se_slope = infl / math.sqrt(sxx)
    z = slope / se_slope
    p = float(2 * stats.t.sf(abs(z), n - 2)) if own else math.erfc(abs(z) / math.sqrt(2.0))
    return {"n": n, "slope": slope, "se": se_slope, "z": z, "p": p, "inflation": infl,
            "chi2_red": chi2r}  # fmt: skip


def pooled_inflation(tests: Sequence[dict], min_series: int = 5) -> float | None:
    """The fleet's factor on the stated standard errors of one parameter: from the
    median reduced chi-square of the per-vehicle trend lines (robust to the few
    vehicles that do not follow a line), divided by the median of a chi-square
    variable per degree of freedom at the typical series length, and never below 1.
    None with fewer than ``min_series`` series (then each series uses its own scatter)."""
    good = [t for t in tests if math.isfinite(t.get("chi2_red", math.nan))]
    if len(good) < min_series:
        return None
    k = int(np.median([t["n"] - 2 for t in good]))
    ratio = float(np.median([t["chi2_red"] for t in good])) / (stats.chi2.median(k) / k)
    return math.sqrt(max(1.0, ratio))


def _is_effect(verdict: str | None) -> bool:
    return bool(verdict) and verdict not in ("none", "not searched", "undecided")


def vehicle_flags(rows: Sequence[dict], alpha: float = ALPHA) -> dict[str, dict]:
    """Per vehicle: its latest row, the trend tests, and the flags (reasons for
    attention). Flags: a significant trend in the service direction (module
    docstring), a significant trend the other way (reported, not a service call), an
    effect that appears on a date after dates without one, an effect already present
    on the first date, failed jobs."""
    by_vehicle: dict[str, list[dict]] = {}
    for r in rows:
        by_vehicle.setdefault(r["vehicle"], []).append(r)
    m = max(1, len(by_vehicle) * len(TRACKED))

    def series(rs, name):
        ok = [r for r in rs if r["status"] == "ok"]
        d0 = datetime.date.fromisoformat(ok[0]["date"]) if ok else None
        days = [(datetime.date.fromisoformat(r["date"]) - d0).days for r in ok]
        return days, [r[name] for r in ok], [r[f"{name}_se"] for r in ok]

    inflation = {
        name: pooled_inflation([trend_test(*series(rs, name)) for rs in by_vehicle.values()])
        for name in TRACKED
    }
    out = {}
    for veh, rs in sorted(by_vehicle.items()):
        rs = sorted(rs, key=lambda r: r["date"])
        ok = [r for r in rs if r["status"] == "ok"]
        flags, notes, tests = [], [], {}
        if ok:
            for name in TRACKED:
                what, _unit, _scale, direction, message = TRACKED_INFO[name]
                tt = trend_test(*series(rs, name), inflation=inflation[name])
                tests[name] = tt
                if math.isfinite(tt["p"]) and tt["p"] < alpha / m:
                    pct = 100 * (math.exp(tt["slope"]) - 1)
                    text = f"{what} {pct:+.1f} %/week (z {tt['z']:.1f}, p {tt['p']:.1e})"
                    if np.sign(tt["slope"]) == direction:
                        flags.append(f"{message}: {text}")
                    else:
                        notes.append(f"{what} changing: {text}")
            first_effect = next((i for i, r in enumerate(ok) if _is_effect(r["verdict"])), None)
            if first_effect is not None:
                r = ok[first_effect]
                if first_effect > 0:
                    flags.append(f"new effect since {r['date']}: {r['verdict']}")
                else:
                    flags.append(f"effect present from the first date ({r['date']}): "
                                 f"{r['verdict']}")  # fmt: skip
        failed = [r for r in rs if r["status"] != "ok"]
        if failed:
            flags.append(f"{len(failed)} job(s) failed: " + ", ".join(r["date"] for r in failed))
        out[veh] = {"rows": rs, "latest": ok[-1] if ok else None, "tests": tests,
                    "flags": flags, "notes": notes}  # fmt: skip
    return out


#: How a vehicle is flagged, for the report.
METHOD = (
    "A trend is a weighted least-squares line through the log of a parameter's estimates "
    "against time (weights from each job's standard error). Least-squares errors "
    "understate the scatter from week to week, so they are inflated by the square root "
    "of the reduced chi-square about the lines, pooled over the fleet (median over "
    "vehicles; at least 5), and the slope is tested with a two-sided z test; a smaller "
    "fleet uses each vehicle's own scatter and Student's t with n - 2 degrees of freedom. "
    f"Bonferroni's correction over all vehicles and parameters (family-wise alpha "
    f"= {ALPHA}); at least {MIN_DATES} dates. Bulk modulus falling means air content "
    "rising. An effect found on a date after dates without one is flagged as new. "
    "Intervals are 90 %: by default from the Laplace approximation at the least-squares "
    "optimum (standard errors inflated for the residuals' autocorrelation); with "
    "`--posterior mcmc` the sampled posterior's HDI (column `interval` says which)."
)
