"""Parameter draws for robust tuning: a hand-written parameter file (or the nominal
model) never silently skips the robust part: it gets draws from stated spreads."""

import json

import numpy as np

import jaxlift as jl
from jaxlift.control.draws import STATED_SPREADS


def _values():
    plant, effects = jl.with_params(
        jl.Plant(), jl.make_effects(["hose_compliance"]), {"beta": 6e8, "C_h": 1.2e-12}
    )
    return {k: float(v) for k, v in jl.model_params(plant, effects).items()}


def test_stated_spreads_without_posterior_or_fit():
    values = _values()
    a = jl.parameter_draws(400, 3, values=values, effects=["hose_compliance"])
    b = jl.parameter_draws(400, 3, values=values, effects=["hose_compliance"])
    assert a.draws == b.draws  # the same seed, the same numbers
    assert a.source.startswith("stated spreads") and "beta x/÷ 1.22" in a.source
    beta = np.log([d["beta"] for d in a.draws])
    assert abs(np.std(beta) - STATED_SPREADS["beta"]) < 0.03
    assert abs(np.mean(beta) - np.log(6e8)) < 0.05
    ch = np.array([d["C_h"] for d in a.draws])
    assert ch.min() < 1.2e-12 < ch.max()  # the effect's size varies too
    assert {d["k1"] for d in a.draws} == {values["k1"]}  # the rest is held


def test_a_hand_written_parameter_file_gets_stated_spreads(tmp_path):
    (tmp_path / "params.json").write_text(json.dumps({"beta": 5e8, "d": 420.0}))
    draws = jl.parameter_draws(16, 0, fit_dir=tmp_path)
    assert "metrics.json not found" in draws.source and "stated spreads" in draws.source
    assert len(draws.draws) == 16
    assert 3e8 < np.median([d["beta"] for d in draws.draws]) < 8e8


def test_a_parameter_file_of_another_name_gets_stated_spreads(tmp_path):
    """Issue #18: `jaxlift tune ... --params truth.json` looked for a fit's params.json
    beside it, found none, and skipped robust tuning and the report. Now: stated
    spreads around the model's values, and the source says why."""
    (tmp_path / "truth.json").write_text(json.dumps({"beta": 5e8, "d": 420.0}))
    values = _values()
    draws = jl.parameter_draws(8, 0, fit_dir=tmp_path, values=values, effects=["hose_compliance"])
    assert "params.json not found" in draws.source and "stated spreads" in draws.source
    assert len(draws.draws) == 8
    assert 3e8 < np.median([d["beta"] for d in draws.draws]) < 1.2e9
