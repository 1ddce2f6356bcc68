"""What every command shares: float64 at the program's start, and reading logs with
unused columns reported once.
"""

from __future__ import annotations

import sys
import warnings


def cache_dir() -> str | None:
    """Where the command line keeps JAX's persistent compilation cache, or None when
    it is switched off (``JAXLIFT_CACHE=off``). ``JAXLIFT_CACHE=DIR`` chooses the
    folder; the default is ``$XDG_CACHE_HOME/jaxlift/jax`` (``~/.cache/jaxlift/jax``)."""
    import os
    import pathlib

    choice = os.environ.get("JAXLIFT_CACHE", "").strip()
    if choice.lower() in ("off", "0", "no", "false"):
        return None
    if choice:
        return choice
    base = os.environ.get("XDG_CACHE_HOME") or str(pathlib.Path.home() / ".cache")
    return str(pathlib.Path(base) / "jaxlift" / "jax")


def setup_jax() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it
    where = cache_dir()
    if where is not None:
        # compiled simulations, Jacobians and samplers are kept between runs: a second
        # `jaxlift fit` on logs of the same lengths skips most of its compilation
        # (benchmarks/bench_cache.py). Every compilation is cached, however short.
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def read_logs(paths):
    import jaxlift as jl

    logs = []
    for p in paths:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", jl.UnusedColumnsWarning)
            logs.append(jl.read_log(p))
        for w in caught:
            print(f"note: {w.message}", file=sys.stderr)
    return logs
