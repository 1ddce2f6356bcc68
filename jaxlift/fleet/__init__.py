"""A fleet of vehicles: one job per vehicle and date, run on Dask; trends and flags."""

from .engine import FleetRun, run_jobs
from .job import DEFAULT_SETTINGS, TRACKED, laplace_interval, run_job
from .manifest import FleetError, FleetJob, discover_jobs
from .trends import (
    fleet_rows,
    pooled_inflation,
    read_table,
    trend_test,
    vehicle_flags,
    write_table,
)
from .workflow import run_fleet, write_fleet_outputs

__all__ = [
    "DEFAULT_SETTINGS",
    "TRACKED",
    "FleetError",
    "FleetJob",
    "FleetRun",
    "discover_jobs",
    "fleet_rows",
    "laplace_interval",
    "pooled_inflation",
    "read_table",
    "run_job",
    "run_fleet",
    "run_jobs",
    "trend_test",
    "vehicle_flags",
    "write_fleet_outputs",
    "write_table",
]
