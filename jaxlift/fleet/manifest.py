"""The fleet's input tree: ``DIR/<vehicle>/<date>/`` folders of logs, each one job.

A run folder holds the logs of one vehicle's test runs on one day, and optionally a
manifest ``run.toml`` that says which logs are fitted and which are held out::

    fit = ["lift_500kg.csv", "lift_1200kg.csv"]   # fitted (default: every log file)
    validate = ["lift_800kg.csv"]                 # held out (default: none)

``<date>`` is an ISO date (``2026-11-23``); the vehicle folder's name is the vehicle's
id. Loads and input sequences may differ from run to run: each log carries its own
(docs/data.md). Files and folders whose names start with ``.`` or ``_`` are ignored.
See docs/fleet.md.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import pathlib
import tomllib
from importlib.metadata import version

MANIFEST = "run.toml"
#: The files a run folder's logs are (CSV, Parquet or MDF, docs/data.md).
LOG_SUFFIXES = (".csv", ".parquet", ".pq", ".mf4", ".mdf")
_KEYS = {"fit", "validate"}


class FleetError(ValueError):
    """A fleet folder that cannot be read as one (the message names the path)."""


@dataclasses.dataclass(frozen=True)
class FleetJob:
    """One vehicle on one date: the logs to fit and those held out."""

    vehicle: str
    date: datetime.date
    folder: pathlib.Path
    fit: tuple[pathlib.Path, ...]
    validate: tuple[pathlib.Path, ...]

    @property
    def name(self) -> str:
        return f"{self.vehicle}/{self.date.isoformat()}"

    def key(self, settings: dict, version: str) -> str:
        """Hash of what decides the job's result: the bytes of every log (and of its
        role), the job settings and ``version`` (:func:`code_version`: jaxlift's version
        and a hash of its source). A re-run skips a job whose key has a finished
        result; a changed log, setting or code runs it again."""
        h = hashlib.sha256()
        h.update(json.dumps({"settings": settings, "version": version}, sort_keys=True).encode())
        for role, paths in (("fit", self.fit), ("validate", self.validate)):
            for p in paths:
                h.update(f"{role}:{p.name}:".encode())
                h.update(hashlib.sha256(p.read_bytes()).digest())
        return h.hexdigest()[:20]


def code_version() -> str:
    """jaxlift's version and the SHA-256 (first 12 hex digits) of its source files, so
    that a development install's changes count as a new version."""
    h = hashlib.sha256()
    pkg = pathlib.Path(__file__).resolve().parents[1]
    for p in sorted(pkg.rglob("*.py")):
        h.update(p.relative_to(pkg).as_posix().encode())
        h.update(p.read_bytes())
    return f"{version('jaxlift')}+src.{h.hexdigest()[:12]}"


def _visible(p: pathlib.Path) -> bool:
    return not p.name.startswith((".", "_"))


def _read_manifest(folder: pathlib.Path) -> tuple[tuple, tuple]:
    csvs = sorted(p for p in folder.iterdir() if p.suffix.lower() in LOG_SUFFIXES and _visible(p))
    path = folder / MANIFEST
    if not path.exists():
        if not csvs:
            raise FleetError(f"{folder}: no logs (*.csv, *.parquet, *.mf4) in this run folder")
        return tuple(csvs), ()
    try:
        spec = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise FleetError(f"{path}: not valid TOML: {err}") from None
    unknown = set(spec) - _KEYS
    if unknown:
        raise FleetError(f"{path}: unknown key(s) {sorted(unknown)}; expected {sorted(_KEYS)}")
    roles = {}
    for key in _KEYS:
        names = spec.get(key, [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise FleetError(f"{path}: {key!r} must be a list of file names, got {names!r}")
        paths = []
        for n in names:
            p = folder / n
            if not p.is_file():
                raise FleetError(f"{path}: {key} names {n!r}, which is not a file in {folder}")
            paths.append(p)
        roles[key] = tuple(paths)
    if "fit" not in spec:
        held = set(roles["validate"])
        roles["fit"] = tuple(p for p in csvs if p not in held)
    both = set(roles["fit"]) & set(roles["validate"])
    if both:
        raise FleetError(f"{path}: {sorted(p.name for p in both)} both fitted and held out")
    if not roles["fit"]:
        raise FleetError(f"{path}: no log to fit")
    return roles["fit"], roles["validate"]


def discover_jobs(root: str | pathlib.Path) -> list[FleetJob]:
    """Every ``<vehicle>/<date>`` run folder under ``root``, sorted by vehicle and date.

    Raises :class:`FleetError` naming the folder or file when the tree is not a fleet:
    a date folder whose name is not an ISO date, a run folder without logs, a manifest
    with unknown keys or missing files."""
    root = pathlib.Path(root)
    if not root.is_dir():
        raise FleetError(f"{root}: not a folder (expected <vehicle>/<date>/ folders of logs)")
    jobs = []
    for vdir in sorted(p for p in root.iterdir() if p.is_dir() and _visible(p)):
        for ddir in sorted(p for p in vdir.iterdir() if p.is_dir() and _visible(p)):
            try:
                date = datetime.date.fromisoformat(ddir.name)
            except ValueError:
                raise FleetError(
                    f"{ddir}: a run folder's name must be an ISO date (YYYY-MM-DD), "
                    f"got {ddir.name!r}"
                ) from None
            fit, val = _read_manifest(ddir)
            jobs.append(FleetJob(vdir.name, date, ddir, fit, val))
    if not jobs:
        raise FleetError(f"{root}: no <vehicle>/<date>/ run folders found")
    return jobs
