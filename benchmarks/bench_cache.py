"""Benchmark: JAX's persistent compilation cache on the README's main job.

Run from the repository root::

    .venv/bin/python benchmarks/bench_cache.py [--diagnose]

Runs ``jaxlift fit data/lift_500kg.csv data/lift_1500kg.csv --validate
data/validation_1000kg.csv`` three times, each in a fresh process as a user would:
with the cache switched off (``JAXLIFT_CACHE=off``), then twice with a new, empty
cache folder (the first run fills it, the second reads it). Prints the wall times,
the ratio first/second (target >= 3) and the ratio off/second, and writes the same
text to ``benchmarks/results_cache.txt``. ``--diagnose`` adds the same for
``jaxlift diagnose --once`` on the same logs (minutes each).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import cpu_model

ROOT = Path(__file__).resolve().parent.parent
LOGS = ["data/lift_500kg.csv", "data/lift_1500kg.csv"]
HELD = ["--validate", "data/validation_1000kg.csv"]


def timed(argv: list[str], cache: str, out: Path) -> float:
    env = dict(os.environ, JAXLIFT_CACHE=cache)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "jaxlift", *argv, "--out", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(argv)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return wall


def measure(name: str, argv: list[str], work: Path) -> list[str]:
    cache = work / f"cache_{name}"
    off = timed(argv, "off", work / f"{name}_off")
    first = timed(argv, str(cache), work / f"{name}_1")
    second = timed(argv, str(cache), work / f"{name}_2")
    size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file()) / 1e6
    ratio = first / second
    return [
        f"{name}: cache off {off:.1f} s; with the cache: first {first:.1f} s, "
        f"second {second:.1f} s; first/second {ratio:.2f} (target >= 3: "
        f"{'PASS' if ratio >= 3 else 'MISS'}); off/second {off / second:.2f}; "
        f"cache {size:.0f} MB",
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--diagnose", action="store_true", help="also diagnose --once (minutes)")
    args = ap.parse_args()
    lines = [
        f"# bench_cache {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, "
        f"{cpu_model()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        lines += measure("fit", ["fit", *LOGS, *HELD], work)
        if args.diagnose:
            lines += measure("diagnose --once", ["diagnose", *LOGS, *HELD, "--once"], work)
    text = "\n".join(lines) + "\n"
    print(text, end="")
    (ROOT / "benchmarks" / "results_cache.txt").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
