"""When what is missing is none of the candidates: the remaining error against the
sensor-noise floor (``remaining_misfit``), and held-out logs that cannot judge a model
because they visit heights the fit never saw (``usable_heldout``)."""

import jax
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.calibrate.diagnose import (
    MIN_EXCESS,
    lifted_stages,
    remaining_misfit,
    usable_heldout,
)
from jaxlift.calibrate.fit import fit
from jaxlift.model.sequences import ramped_sequence

SECTIONS = [(0.0, 2.0), (0.5, 5.0), (0.25, 6.0), (0.0, 3.0), (0.6, 5.0), (0.0, 3.0)]


def _log(x0, load=900.0, seed=0, effects=(), values=None, sections=SECTIONS, name=None):
    plant, effs = jl.with_params(jl.Plant(), jl.make_effects(effects), dict(values or {}))
    ts, pwm = ramped_sequence(sections, ramp_s=0.5)
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
    sol = jl.simulate(plant, effs, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
    assert bool(sol.ok)
    name = name or f"x0_{x0:g}_{load:.0f}kg"
    return jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(seed), name=name)


def test_lifted_stages_and_usable_heldout():
    mid = _log(2.0)  # lifts from 2.0 m: stage 2, then 3
    bottom = _log(0.0, name="from_the_stop")  # lifts from the stop through stage 1
    assert lifted_stages(mid) == {2, 3}
    assert 1 in lifted_stages(bottom)
    keep, excluded = usable_heldout([mid], [bottom, _log(1.8, seed=1, name="mid2")])
    assert [lg.name for lg in keep] == ["mid2"]
    assert "stage(s) 1" in excluded["from_the_stop"]
    keep, excluded = usable_heldout([bottom, mid], [_log(0.0, seed=2, name="b2")])
    assert [lg.name for lg in keep] == ["b2"] and not excluded


@pytest.mark.slow
def test_remaining_misfit_is_significant_only_for_a_model_that_misses_something():
    """A 200 ms input delay hidden: the baseline leaves an error far above the noise,
    on fitted and held-out logs; the model with the delay leaves none."""
    hidden = {"tau_d": 0.2}
    logs = [_log(1.0, m, s, ("input_delay",), hidden) for m, s in ((500.0, 1), (1500.0, 2))]
    held = [_log(1.0, 1000.0, 3, ("input_delay",), hidden)]
    wrong = fit(logs, staged=False, n_starts=1)
    m = remaining_misfit(wrong, held)
    assert m.significant and m.chi2n - 1 > MIN_EXCESS and m.z > 3 and m.heldout_z > 3, m
    right = fit(logs, effects=["input_delay"], init=hidden, free="all,effects", n_starts=1)
    m = remaining_misfit(right, held)
    assert not m.significant and abs(m.chi2n - 1) < 0.05 and abs(m.heldout_chi2n - 1) < 0.05, m
