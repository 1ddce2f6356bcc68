"""Independent jobs on threads (jaxlift.calibrate.parallel): order, errors, and fits that do not
depend on the number of threads."""

import threading
import time

import jax
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.calibrate.fit import fit
from jaxlift.calibrate.parallel import thread_map


def test_thread_map_keeps_order_and_uses_threads():
    seen = set()

    def job(k):
        time.sleep(0.01 * (5 - k))  # later items finish first
        seen.add(threading.current_thread().name)
        return k * k

    assert list(thread_map(job, range(5), workers=3)) == [0, 1, 4, 9, 16]
    assert any(name.startswith("jaxlift") for name in seen)
    seen.clear()
    assert list(thread_map(job, [2], workers=4)) == [4]  # one item: no pool
    assert seen == {threading.current_thread().name}


def test_thread_map_errors():
    def job(k):
        if k == 2:
            raise KeyError("item 2")
        return k

    it = thread_map(job, range(4), workers=2)
    assert next(it) == 0 and next(it) == 1
    with pytest.raises(KeyError, match="item 2"):
        next(it)
    with pytest.raises(ValueError, match="workers = 0"):
        list(thread_map(job, range(3), workers=0))


def _short_log():
    ts = np.arange(0.0, 5.0 + 0.005, 0.01)
    pwm = np.round(np.interp(ts, [0, 0.5, 1.5, 3, 3.5, 5], [0, 0, 0.5, 0.5, 0.0, 0.0]), 4)
    plant, _ = jl.with_params(jl.Plant(), (), {"beta": 0.6e9, "d": 400.0})
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, 800.0), 0.05)
    sol = jl.simulate(plant, (), inputs, rtol=1e-8)
    return jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(5), name="short")


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_fit_does_not_depend_on_the_number_of_threads():
    log = _short_log()
    kw = dict(free="beta,d", n_starts=2, seed=1)
    one = fit([log], workers=1, **kw)
    two = fit([log], workers=2, **kw)
    assert one.stages[0].start_chi2 == two.stages[0].start_chi2
    assert one.params == two.params and one.chi2 == two.chi2
    assert abs(one.params["beta"] / 0.6e9 - 1) < 0.1  # and it is a fit
