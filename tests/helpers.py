"""Test helpers: tree comparison, finite-difference gradient checks, short logs."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def tree_allclose(x, y, *, rtol=1e-7, atol=0.0) -> bool:
    """True if two pytrees have the same structure and all array leaves are close."""
    if jax.tree_util.tree_structure(eqx.filter(x, eqx.is_array)) != jax.tree_util.tree_structure(
        eqx.filter(y, eqx.is_array)
    ):
        return False
    xs = jax.tree_util.tree_leaves(eqx.filter(x, eqx.is_array))
    ys = jax.tree_util.tree_leaves(eqx.filter(y, eqx.is_array))
    return all(
        a.shape == b.shape and bool(jnp.allclose(a, b, rtol=rtol, atol=atol))
        for a, b in zip(xs, ys)
    )


def head(log, n: int, name: str = "short"):
    """The first ``n`` samples of a :class:`jaxlift.Log`, every column it has (extra
    ones too): a short log for tests whose claim does not need the whole run."""
    from jaxlift import Log

    def cut(a):
        return None if a is None else a[:n]

    return Log(
        time_s=cut(log.time_s), pwm=cut(log.pwm), height_m=cut(log.height_m),
        load_kg=cut(log.load_kg), speed_mps=cut(log.speed_mps),
        pressure_pa=cut(log.pressure_pa), extra={k: cut(v) for k, v in log.extra.items()},
        name=name,
    )  # fmt: skip


def finite_difference_grad(f, x: np.ndarray, rel_step: float = 1e-6) -> np.ndarray:
    """Central finite-difference gradient of a scalar function ``f`` of a 1-D array."""
    x = np.asarray(x, dtype=np.float64)
    g = np.zeros_like(x)
    for i in range(x.size):
        h = rel_step * max(abs(x[i]), 1e-3)
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        g[i] = (float(f(xp)) - float(f(xm))) / (2 * h)
    return g


def assert_grad_matches_fd(f, x, *, rtol=1e-4, atol=0.0, rel_step=1e-6):
    """Check ``jax.grad(f)(x)`` against central finite differences."""
    x = np.asarray(x, dtype=np.float64)
    g_ad = np.asarray(jax.grad(f)(jnp.asarray(x)))
    g_fd = finite_difference_grad(f, x, rel_step=rel_step)
    np.testing.assert_allclose(g_ad, g_fd, rtol=rtol, atol=atol)
    return g_ad, g_fd


class count_traces:
    """Context manager: how many times jitted functions whose name contains ``name``
    were traced inside the block (JAX's monitoring events; a call served by the jit
    cache traces nothing), ``.n`` after the block."""

    def __init__(self, name: str):
        self.name, self.n = name, 0

    def _listener(self, event: str, duration: float, **kwargs) -> None:
        if event == "/jax/core/compile/jaxpr_trace_duration" and self.name in str(
            kwargs.get("fun_name", "")
        ):
            self.n += 1

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self._listener)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._listener)
        return False
