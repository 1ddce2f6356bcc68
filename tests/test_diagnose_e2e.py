"""The promise, end to end, as a user runs it: ``jaxlift diagnose`` from nominal values
on logs it was never tuned on, with the verdict asserted.

The logs differ from the shipped ones in everything the user could vary: truth
parameters (away from nominal and from the shipped truth), loads, the input sequence
(steps and holds of other levels and lengths), the starting height (on the bottom end
stop, mid-mast) and the hidden effect's size. ``--once``: one diagnosis step (the
iteration to ``none`` is the detection-power study's, see ``studies/DETECTION.md``).
"""

import json

import jax
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.cli import main
from jaxlift.model.sequences import ramped_sequence

TRUTH = dict(
    k1=1.75, k2=1.7, k3=1.85, z1=-3.4, z2=-3.1, z3=-4.6,
    beta=0.8e9, cf_con=15.0, cf_in=18.0, cf_out=480.0, d=350.0,
)  # fmt: skip

# steps and holds of levels the shipped sequence does not use; ~75 s, up ~1.6 m
SECTIONS = [
    (0.0, 2.5), (0.38, 5.0), (0.0, 3.0), (0.6, 5.0), (0.25, 9.0), (0.0, 4.0),
    (0.5, 6.0), (0.3, 9.0), (0.0, 5.0), (0.42, 7.0), (0.22, 12.0), (0.0, 7.0),
]  # fmt: skip


def _write_logs(tmp_path, hidden, x0, loads=(450.0, 1650.0, 1100.0), seed=0):
    names = list(hidden)
    values = {k: v for eff in hidden.values() for k, v in eff.items()}
    plant, effects = jl.with_params(jl.Plant(), jl.make_effects(names), {**TRUTH, **values})
    ts, pwm = ramped_sequence(SECTIONS, ramp_s=0.5)
    paths = []
    for k, load in enumerate(loads):
        inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
        sol = jl.simulate(plant, effects, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
        assert bool(sol.ok)
        key = jax.random.key(1000 * seed + k)
        log = jl.to_log(sol, inputs, jl.MeasurementModel(), key, name=f"run{k}_{load:.0f}kg")
        path = tmp_path / f"{log.name}.csv"
        jl.write_log(path, log)
        paths.append(str(path))
    return paths


def _diagnose(tmp_path, paths):
    out = tmp_path / "diag"
    rc = main(["diagnose", *paths[:2], "--validate", paths[2], "--once", "--out", str(out)])
    assert rc == 0
    return json.loads((out / "diagnosis.json").read_text())


@pytest.mark.slow
def test_nothing_hidden_mid_mast(tmp_path):
    paths = _write_logs(tmp_path, {}, x0=0.6, seed=1)
    d = _diagnose(tmp_path, paths)
    assert d["verdict"] == "none", [(r["effect"], r["z"], r["delta_bic"]) for r in d["ranking"]]


@pytest.mark.slow
def test_leakage_hidden_starting_on_the_bottom_stop(tmp_path):
    paths = _write_logs(tmp_path, {"leakage": {"C_L": 3e-13}}, x0=0.0, seed=2)
    heights = [jl.read_log(p).height_m for p in paths]
    assert all(np.mean(h[:200]) < 1e-3 for h in heights)  # the holds read the stop
    d = _diagnose(tmp_path, paths)
    assert d["verdict"] == "leakage", [(r["effect"], r["delta_bic"]) for r in d["ranking"]]
    top = d["ranking"][0]
    assert top["effect"] == "leakage" and top["fitted_params"]["C_L"] == pytest.approx(
        3e-13, rel=0.2
    )


@pytest.mark.extended  # 5-7 min (stiff at v_s 5 mm/s); CI has leakage and air
def test_stick_slip_hidden_at_another_size(tmp_path):
    hidden = {"stick_slip": {"dFs": 320.0, "v_s": 0.005}}
    paths = _write_logs(tmp_path, hidden, x0=0.3, loads=(700.0, 1900.0, 300.0), seed=3)
    d = _diagnose(tmp_path, paths)
    assert d["verdict"] == "stick_slip", [(r["effect"], r["delta_bic"]) for r in d["ranking"]]


@pytest.mark.slow
def test_entrained_air_hidden_mid_mast(tmp_path):
    # the thesis's suspect: air, softer oil at low pressure, on other loads than the
    # shipped logs'; the fitted size within 30 % of the truth
    hidden = {"entrained_air": {"alpha0": 0.5}}
    paths = _write_logs(tmp_path, hidden, x0=0.45, loads=(350.0, 1800.0, 900.0), seed=4)
    d = _diagnose(tmp_path, paths)
    assert d["verdict"] == "entrained_air", [(r["effect"], r["delta_bic"]) for r in d["ranking"]]
    top = d["ranking"][0]
    assert top["fitted_params"]["alpha0"] == pytest.approx(0.5, rel=0.3)
