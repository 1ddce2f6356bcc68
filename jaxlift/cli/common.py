"""What every command shares: float64 at the program's start, and reading logs with
unused columns reported once.
"""

from __future__ import annotations

import sys
import warnings


def setup_jax() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)  # a program's start: the place to do it


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
