"""Diagnosis: data generated with a known hidden effect get that effect; data with
nothing hidden get "none". Small problems: 2 logs of a 75 s thesis-like sequence that
crosses both stage shifts; fits start at the truth of the baseline parameters (the
fit from nominal values is tested in test_fit.py)."""

import jax
import numpy as np
import pytest

import jaxlift as jl
from jaxlift._diagnose import diagnose, screen_effects, switch_parameter
from jaxlift._fit import fit
from jaxlift._sequences import ramped_sequence

TRUTH = dict(
    k1=2.05, k2=1.95, k3=1.80, z1=-2.6, z2=-3.3, z3=-4.4,
    beta=0.5e9, cf_con=22.0, cf_in=14.0, cf_out=700.0, d=420.0,
)  # fmt: skip

SECTIONS = [
    (0.0, 2.0), (0.45, 6.0), (0.2, 8.0), (0.0, 4.0), (0.5, 7.0), (0.2, 8.0),
    (0.55, 8.0), (0.0, 4.0), (0.5, 8.0), (0.2, 10.0), (0.0, 6.0),
]  # fmt: skip


def _logs(hidden: dict[str, float], effects=(), seeds=(1, 2)):
    plant, effs = jl.with_params(jl.Plant(), jl.make_effects(effects), {**TRUTH, **hidden})
    ts, pwm = ramped_sequence(SECTIONS)
    out = []
    for load, seed in zip((600.0, 1400.0), seeds):
        inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), 0.05)
        sol = jl.simulate(plant, effs, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
        out.append(
            jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(seed), name=f"l{load:.0f}")
        )
    return out


def test_switch_parameters():
    assert switch_parameter("stick_slip") == "dFs"
    assert switch_parameter("mast_compliance") == "ks_inv"
    assert {switch_parameter(n) for n in jl.EFFECTS} == {
        "dFs", "tau_m", "kappa", "C_L", "alpha0", "C_h", "ks_inv", "tau_d",
    }  # fmt: skip


@pytest.fixture(scope="module")
def leaky():
    logs = _logs({"C_L": 2e-13}, effects=("leakage",))
    base = fit(logs, init=TRUTH, free="all", staged=False, n_starts=1)
    return logs, base


@pytest.fixture(scope="module")
def clean():
    logs = _logs({})
    base = fit(logs, init=TRUTH, free="all", staged=False, n_starts=1)
    return logs, base


@pytest.mark.extended
def test_screen_ranks_hidden_leakage_first(leaky):
    logs, base = leaky
    ranking = screen_effects(base, logs)
    assert ranking[0].effect == "leakage", [(s.effect, s.z) for s in ranking]
    assert ranking[0].z > 5


@pytest.mark.extended
def test_screen_finds_nothing_when_nothing_is_hidden(clean):
    logs, base = clean
    ranking = screen_effects(base, logs)
    assert all(s.z < 3 for s in ranking), [(s.effect, s.z) for s in ranking]


@pytest.mark.extended
def test_verdict_leakage_and_error_falls(leaky):
    logs, base = leaky
    held_out = _logs({"C_L": 2e-13}, effects=("leakage",), seeds=(7, 8))[1:]
    d = diagnose(logs, held_out, base=base)
    assert d.verdict == "leakage"
    top = d.ranking[0]
    assert top.effect == "leakage" and top.delta_bic < -10
    assert top.heldout_chi2_after <= 0.5 * top.heldout_chi2_before
    assert abs(top.fitted_params["C_L"] / 2e-13 - 1) < 0.2


@pytest.mark.extended
def test_verdict_none_when_nothing_is_hidden(clean):
    logs, base = clean
    d = diagnose(logs, base=base)
    assert d.verdict == "none"
