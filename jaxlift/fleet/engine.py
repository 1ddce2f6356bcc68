"""Run fleet jobs on Dask (``dask.distributed``): a local cluster of worker processes
by default, or an existing cluster at a scheduler address, with the same code.

Why Dask and not Ray: the jobs are coarse (minutes each) and independent, and need
nothing from an engine but processes, bounded retries and results as they finish.
Dask's ``LocalCluster`` gives that with no set-up on one machine and ``Client(address)``
on a cluster; it is pure Python (a small install) and starts in about a second, where
Ray brings a runtime of its own (raylet, object store, dashboard) for features the
fleet does not use. See docs/fleet.md.

Resumability: every job writes ``result.json`` into its own folder, keyed by the hash
of its inputs, settings and the jaxlift version (:meth:`FleetJob.key`), last and
atomically. A re-run skips every job whose key has a result, so killing a run loses
at most the jobs in flight. The output folder must be reachable by the workers (on a
cluster: a shared file system).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import pathlib
import traceback
from collections.abc import Callable, Sequence

from dask.distributed import Client, LocalCluster, as_completed
from tqdm.auto import tqdm

from .job import DEFAULT_SETTINGS, run_job, write_json
from .manifest import FleetJob, code_version


@dataclasses.dataclass
class FleetRun:
    """What a run did: results (``result.json`` records) of every finished job (those
    of earlier runs included), failures of this run, and how many jobs were skipped
    as already finished."""

    results: list[dict]
    failures: list[dict]
    skipped: int
    ran: int


def job_dir(out: pathlib.Path, job: FleetJob, key: str) -> pathlib.Path:
    return out / "jobs" / job.vehicle / job.date.isoformat() / key


def run_jobs(
    jobs: Sequence[FleetJob],
    out_dir: str | pathlib.Path,
    settings: dict | None = None,
    *,
    workers: int = 1,
    scheduler: str | None = None,
    retries: int = 2,
    job_fn: Callable = run_job,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
) -> FleetRun:
    """Run every job not finished before, on a local Dask cluster of ``workers``
    processes (one thread each), or on the cluster whose scheduler is at
    ``scheduler`` (``tcp://host:8786``). A job that raises is retried ``retries``
    times, then recorded in ``out_dir/failures/`` with its error and traceback, and
    the run goes on. ``job_fn(job, settings, job_dir)`` is the job (default
    :func:`~jaxlift.fleet.job.run_job`)."""
    say = progress or (lambda _s: None)
    out = pathlib.Path(out_dir)
    settings = {**DEFAULT_SETTINGS, **(settings or {})}
    ver = code_version()
    todo, results = [], []
    for job in jobs:
        key = job.key(settings, ver)
        res = job_dir(out, job, key) / "result.json"
        if res.exists():
            results.append(json.loads(res.read_text()) | {"job_key": key})
        else:
            todo.append((job, key))
    skipped = len(results)
    say(f"{len(jobs)} job(s): {skipped} finished before (skipped), {len(todo)} to run")
    failures: list[dict] = []
    if not todo:
        return FleetRun(results, failures, skipped, 0)

    if scheduler:
        client, cluster = Client(scheduler), None
    else:
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True,
            dashboard_address=":0", silence_logs=logging.ERROR,
        )  # fmt: skip
        client = Client(cluster)
    say(f"engine: Dask, {'scheduler ' + scheduler if scheduler else f'{workers} local worker(s)'}")
    try:
        futures = {}
        for job, key in todo:
            d = job_dir(out, job, key)
            fut = client.submit(
                job_fn, job, settings, str(d), key=f"{job.name}#{key}", retries=retries,
                pure=False,
            )  # fmt: skip
            futures[fut] = (job, key)
        bar = None
        if progress_bar:
            bar = tqdm(total=len(futures), desc="fleet", unit="job")
        for fut in as_completed(futures):
            job, key = futures[fut]
            d = job_dir(out, job, key)
            if fut.status == "finished":
                rec = fut.result()
                if not (d / "result.json").exists():  # a worker without the shared folder
                    d.mkdir(parents=True, exist_ok=True)
                    write_json(d / "result.json", rec)
                results.append(rec | {"job_key": key})
                say(f"{job.name}: {rec.get('verdict')} ({rec.get('wall_s', 0):.0f} s)")
            else:
                exc = fut.exception()
                tb = "".join(traceback.format_exception(exc))
                fail = {
                    "vehicle": job.vehicle,
                    "date": job.date.isoformat(),
                    "job_key": key,
                    "status": "failed",
                    "attempts": retries + 1,
                    "error": f"{type(exc).__name__}: {exc}",
                    "traceback": tb[-4000:],
                    "folder": str(job.folder),
                }
                fdir = out / "failures" / job.vehicle / job.date.isoformat()
                fdir.mkdir(parents=True, exist_ok=True)
                write_json(fdir / f"{key}.json", fail)
                failures.append(fail)
                say(f"{job.name}: FAILED after {retries + 1} attempt(s): {fail['error']}")
            if bar is not None:
                bar.update()
        if bar is not None:
            bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return FleetRun(results, failures, skipped, len(todo))
