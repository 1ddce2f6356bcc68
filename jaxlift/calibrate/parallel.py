"""Independent jobs (least-squares starts, confirmation refits) on all CPU cores.

A fit's time goes into compiled XLA calls (the simulation and its forward-mode
Jacobian), during which JAX releases the GIL, and a single ODE solve runs on one core:
its steps are sequential and its arrays far too small for XLA's intra-op threads. So
independent fits run in Python threads, one per core, and use the cores that one fit
leaves idle. Each job is deterministic on its own, so the results do not depend on
the number of threads (tested); they come back in the order of the inputs.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor


def cpu_cores() -> int:
    """The number of CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def thread_map[T, R](
    fn: Callable[[T], R], items: Sequence[T], workers: int | None = None
) -> Iterator[R]:
    """``map(fn, items)`` on up to ``workers`` threads (default: one per core); results
    are yielded in the order of ``items`` as they become available. ``workers=1`` runs
    in the calling thread. An exception in a job is raised here, at its position."""
    items = list(items)
    n = cpu_cores() if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"workers = {workers}: expected a positive number of threads")
    n = min(n, len(items))
    if n <= 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="jaxlift") as pool:
        futures = [pool.submit(fn, it) for it in items]
        try:
            for f in futures:
                yield f.result()
        finally:
            for f in futures:  # an early exit (exception, closed generator): stop the rest
                f.cancel()
