"""Parameters: one description each, transforms, parameter files."""

import json
import math

import numpy as np
import pytest

import jaxlift as jl

MODEL_MD_NOMINAL = {
    "u_batt": 24, "k1": 1.9, "k2": 1.8, "k3": 1.7, "z1": -3.0, "z2": -3.5, "z3": -4.0,
    "disp": 43e-6, "eta_v": 0.95, "A1": 28.27e-4, "A2": 22.68e-4, "A3": 22.68e-4,
    "ratio": 2, "m_st1": 100, "m_st2": 145, "m_st3": 140, "V0": 2.0e-3, "beta": 1.4e9,
    "cf_con": 10, "cf_in": 16, "cf_out": 545, "d": 300,
}  # fmt: skip


def test_plant_nominals_are_model_md():
    infos = jl.param_infos(jl.Plant)
    assert set(infos) == set(MODEL_MD_NOMINAL)
    for name, value in MODEL_MD_NOMINAL.items():
        assert infos[name].nominal == pytest.approx(value), name
        assert float(jl.get_params(jl.Plant())[name]) == pytest.approx(value)
        assert infos[name].unit


@pytest.mark.parametrize("name", sorted(jl.all_param_infos("all")))
def test_transform_round_trip(name):
    info = jl.all_param_infos("all")[name]
    x = info.nominal if info.nominal != info.lower else (info.scale or 1.0)
    theta = jl.to_unconstrained(info, x)
    assert math.isfinite(float(theta))
    np.testing.assert_allclose(float(jl.from_unconstrained(info, theta)), x, rtol=1e-12)


def test_parameter_file_round_trip_and_errors(tmp_path):
    path = tmp_path / "p.json"
    jl.save_params_json(path, {"beta": 5e8, "dFs": 120.0}, comment="note")
    plant, effects = jl.load_model(path)  # effects inferred from the file
    assert [e.name for e in effects] == ["stick_slip"]
    assert float(plant.beta) == 5e8 and float(effects[0].dFs) == 120.0

    path.write_text(json.dumps({"betta": 1e9}))
    with pytest.raises(jl.ParameterError, match="betta"):
        jl.load_model(path)
    path.write_text(json.dumps({"beta": -1.0}))
    with pytest.raises(jl.ParameterError, match="beta.*bounds"):
        jl.load_model(path)
    path.write_text(json.dumps({"beta": "soft"}))
    with pytest.raises(jl.ParameterError, match="expected a number"):
        jl.load_model(path)
    path.write_text("{not json")
    with pytest.raises(jl.ParameterError, match="not a valid JSON"):
        jl.load_model(path)
    path.write_text(json.dumps({"C_h": 1e-12}))
    with pytest.raises(jl.ParameterError, match="not switched on"):
        jl.load_model(path, effects="leakage")


def test_with_params_rejects_unknown_names():
    with pytest.raises(jl.ParameterError, match="dFs"):
        jl.with_params(jl.Plant(), (), {"dFs": 1.0})
    with pytest.raises(ValueError, match="C_l"):
        jl.make_effects("leakage", {"C_l": 1e-12})


def test_fit_stage_of_an_effect_parameter():
    """An effect parameter may name the stage of a staged fit it joins; motor droop's
    kappa joins the motor set (tests/test_fit.py shows why); a bad stage is refused."""
    stages = {n: i.stage for e in jl.EFFECTS.values() for n, i in e.param_infos().items()}
    assert stages.pop("kappa") == "motor"
    assert set(stages.values()) == {None}
    with pytest.raises(jl.ParameterError, match="'kappa'.*stage"):
        jl.ParamInfo("kappa", "-", 0.0, 0.0, 1.0, "x", stage="motors")
