"""Stand-in fleet jobs for the engine's tests (importable by Dask's worker processes:
``tests/`` is on their path). They do no modelling: they test the engine's retries,
failure records and skipping, not jaxlift's physics."""

import json
import pathlib


def ok_job(job, settings, job_dir):
    d = pathlib.Path(job_dir)
    d.mkdir(parents=True, exist_ok=True)
    rec = {"vehicle": job.vehicle, "date": job.date.isoformat(), "status": "ok",
           "verdict": "none", "effects": []}  # fmt: skip
    (d / "result.json").write_text(json.dumps(rec))
    return rec


def flaky_job(job, settings, job_dir):
    """Fails on its first attempt for every job (a marker file counts attempts)."""
    marker = pathlib.Path(job_dir).with_suffix(".attempts")
    marker.parent.mkdir(parents=True, exist_ok=True)
    n = int(marker.read_text()) if marker.exists() else 0
    marker.write_text(str(n + 1))
    if n == 0:
        raise RuntimeError("transient failure (first attempt)")
    return ok_job(job, settings, job_dir)


def broken_for_b(job, settings, job_dir):
    """Always fails for vehicle ``b``."""
    if job.vehicle == "b":
        raise ValueError(f"cannot read {job.fit[0].name}")
    return ok_job(job, settings, job_dir)
