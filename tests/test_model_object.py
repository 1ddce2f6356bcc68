"""The model as one object: built once from names and values, then derived from."""

import jax.numpy as jnp
import pytest
from helpers import head, tree_allclose

import jaxlift as jl


def test_build_is_the_names_and_values_path():
    values = {"beta": 6e8, "dFs": 120.0, "C_h": 1e-12}
    m = jl.Model.build("stick_slip,hose_compliance", values)
    plant, effects = jl.with_params(
        jl.Plant(), jl.make_effects(["stick_slip", "hose_compliance"]), values
    )
    assert tree_allclose((m.plant, m.effects), (plant, effects))
    assert m.effect_names == ("stick_slip", "hose_compliance")  # registry order
    assert float(m.values()["beta"]) == 6e8 and float(m.values()["dFs"]) == 120.0
    assert set(m.param_infos()) == set(jl.all_param_infos(effects))


def test_with_effect_keeps_every_value_and_adds_the_new_one():
    m = jl.Model.build(["hose_compliance"], {"beta": 5e8, "C_h": 2e-12})
    m2 = m.with_effect("leakage", {"C_L": 3e-13})
    assert m2.effect_names == ("leakage", "hose_compliance")
    v = m2.values()
    assert float(v["beta"]) == 5e8 and float(v["C_h"]) == 2e-12 and float(v["C_L"]) == 3e-13
    assert m.effect_names == ("hose_compliance",)  # the original is unchanged


def test_with_values_and_errors():
    m = jl.Model.build((), {"d": 400.0})
    assert float(m.with_values({"d": 500.0}).values()["d"]) == 500.0
    with pytest.raises(jl.ParameterError, match="C_h"):
        m.with_values({"C_h": 1e-12})  # hose compliance is not switched on
    with pytest.raises(ValueError, match="unknown effect"):
        jl.Model.build(["air_in_oil"])


def test_fit_result_carries_the_calibrated_model():
    log = jl.read_log("data/lift_500kg.csv")
    short = head(log, 1500)
    res = jl.fit([short], free="beta,d", n_starts=1, solver=jl.LM(max_steps=3))
    assert res.model.effect_names == ()
    assert jnp.allclose(res.model.plant.beta, res.params["beta"])
    assert jnp.allclose(res.model.plant.d, res.params["d"])
