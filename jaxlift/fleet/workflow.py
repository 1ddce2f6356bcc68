"""``jaxlift fleet`` as a function: discover the jobs, run them on Dask, write the
table and the fleet report."""

from __future__ import annotations

import json
import pathlib
from collections.abc import Callable

from ..report.fleet import fleet_report
from .engine import run_jobs
from .manifest import discover_jobs
from .trends import METHOD, TRACKED_INFO, fleet_rows, vehicle_flags, write_table


def run_fleet(
    fleet_dir: str | pathlib.Path,
    out_dir: str | pathlib.Path,
    *,
    settings: dict | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    retries: int = 2,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
    job_fn: Callable | None = None,
) -> dict:
    """Run (or resume) the fleet under ``fleet_dir``; write ``out_dir/fleet.parquet``,
    ``fleet.csv``, ``flags.json``, ``report.md``/``report.html`` and ``figures/``.
    Returns a summary (jobs run, skipped, failed; flagged vehicles)."""
    out = pathlib.Path(out_dir)
    jobs = discover_jobs(fleet_dir)
    kw = {} if job_fn is None else {"job_fn": job_fn}
    run = run_jobs(jobs, out, settings, workers=workers, scheduler=scheduler, retries=retries,
                   progress=progress, progress_bar=progress_bar, **kw)  # fmt: skip
    rows = fleet_rows(run.results, run.failures)
    info = {"ran": run.ran, "skipped": run.skipped, "failed": len(run.failures)}
    return write_fleet_outputs(rows, out, {**info, "jobs": len(jobs)})


def write_fleet_outputs(rows: list[dict], out_dir: str | pathlib.Path, info: dict) -> dict:
    """From the table's rows (:func:`~jaxlift.fleet.fleet_rows`): write the table, the
    flags (``flags.json``) and the fleet report into ``out_dir``; return the summary
    (``info``, e.g. jobs run/skipped/failed, and the flags and trend tests)."""
    out = pathlib.Path(out_dir)
    write_table(rows, out)
    flags = vehicle_flags(rows)
    fleet_report(flags, out, info, TRACKED_INFO, METHOD)
    summary = {
        **info,
        "flagged": {v: f["flags"] for v, f in flags.items() if f["flags"]},
        "notes": {v: f["notes"] for v, f in flags.items() if f["notes"]},
        "tests": {v: f["tests"] for v, f in flags.items()},
    }
    (out / "flags.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
