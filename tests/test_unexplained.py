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


@pytest.mark.slow
def test_a_law_outside_the_eight_is_unexplained_not_named(tmp_path):
    """A quadratic (turbulent) drag hidden, not among the candidates, diagnosed from
    nominal values by the CLI: the final verdict is ``unexplained``, and an effect
    added on the way is reported as a possible stand-in, with the small share of the
    model error it explains. (With the law as a user effect the diagnosis names it:
    ``test_user_effects.py``.)"""
    import json
    import subprocess
    import sys

    import test_user_effects as ue

    from jaxlift.model.effects import EFFECTS

    drag = tmp_path / "drag.py"
    drag.write_text(ue.DRAG_FILE)
    jl.load_effect_file(drag)  # only to make the logs
    try:
        logs = [ue._log(tmp_path / f"d{m:.0f}.csv", m, s, x0=x0)
                for m, s, x0 in ((500.0, 3, 0.0), (1600.0, 4, 1.0))]  # fmt: skip
        held = ue._log(tmp_path / "held.csv", 1000.0, 5, x0=0.0)
    finally:
        EFFECTS.pop("turbulent_drag")
    out = tmp_path / "diag"
    # at most one effect added (two diagnosis steps): the CI's time. Before a candidate
    # had to remove 25 % of the error (MIN_SHARE), the iteration added stand-ins that
    # each explained a few per cent (measured: hose compliance 21 %, then a mast mode
    # 5 %), still ending `unexplained`
    argv = ["diagnose", *logs, "--validate", held, "--max-effects", "1", "--out", str(out)]
    # in its own process, as a user runs it (and without the test session's memory)
    proc = subprocess.run([sys.executable, "-m", "jaxlift", *argv], capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["final_verdict"] == "unexplained", (d["verdicts"], d["final_verdict"])
    misfit = d["remaining_misfit"]
    assert misfit["significant"] and misfit["chi2n"] > 1.2 and misfit["heldout_chi2n"] > 1.2
    for step in d["steps"]:  # whatever was added explains little of the error
        if step["explained_share"] is not None:
            assert step["explained_share"] < 0.5, step["verdict"]
            assert step["verdict"] in " ".join(d["reasons"])
    # the shape (--shape auto: estimated when unexplained): the drag is a force; a law
    # is printed only for a signal the data need
    shape = d["missing_shape"]
    assert shape["needed"]["force"], shape["evidence"]
    for sig, needed in shape["needed"].items():
        said = f"missing {sig} (needed" if needed else f"missing {sig}: not needed"
        assert said in proc.stdout, proc.stdout[-2000:]
