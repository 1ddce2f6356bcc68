"""Gauge pressure end to end: a log whose ``pressure_pa`` is the model's (gauge) ``p``
plus sensor noise reads back, in CSV and in MDF 4, and compares with the model with a
residual centred on 0, not on 101325 Pa: no atmospheric offset is added or subtracted
between the log and the model, in the fit's residuals, the report's residual
diagnostics or the fit metrics."""

import math

import jax
import numpy as np
from asammdf import MDF, Signal

import jaxlift as jl
from jaxlift.analysis.residuals import residual_diagnostics
from jaxlift.calibrate.experiment import make_experiments
from jaxlift.model.constants import P_ATM
from jaxlift.workflows.fit import chi2n, simulate_logs


def _measured_log():
    """4 s at 500 kg: a hold, 2 s lifting at pwm 0.4, a hold; simulated with the nominal
    model and measured with the measurement model's noise, pressure sensor included."""
    t = np.round(np.arange(401) * 0.01, 9)
    pwm = np.where((t > 1.0) & (t < 3.0), 0.4, 0.0)
    full = np.full(t.size, 1.0)
    plan = jl.Log(time_s=t, pwm=pwm, height_m=0.5 * full, load_kg=500.0 * full, name="plan")
    inputs = jl.Inputs.from_log(plan)
    sol = jl.simulate(jl.Plant(), jl.make_effects([]), inputs)
    assert sol.ok
    key = jax.random.PRNGKey(15)
    log = jl.to_log(sol, inputs, jl.MeasurementModel(), key, with_pressure=True, name="gauge")
    assert np.all(np.asarray(sol.pressure) > 1e6)  # gauge, several MPa for 500 kg
    return log


def test_pressure_residual_is_centred_on_zero(tmp_path):
    made = _measured_log()
    csv = tmp_path / "gauge.csv"
    jl.write_log(csv, made, float_format="%.17g")
    mf4 = tmp_path / "gauge.mf4"
    with MDF(version="4.10") as mdf:
        mdf.append([Signal(made.column(c), made.time_s, name=c) for c in made.columns[1:]])
        mdf.save(mf4, overwrite=True)
    sigma = float(jl.MeasurementModel().sigma_pressure)
    for path in (csv, mf4):
        log = jl.read_log(path)
        np.testing.assert_array_equal(log.pressure_pa, made.pressure_pa)
        bound = 4 * sigma / math.sqrt(log.n)  # 4 standard errors of the mean: 1e4 Pa
        # the fit's residuals: the logged pressure as it is, against the model's p
        (exp,) = make_experiments([log])
        np.testing.assert_array_equal(np.asarray(exp.y[2]), log.pressure_pa)
        sol = jl.simulate(jl.Plant(), jl.make_effects([]), exp.inputs)
        r = np.asarray(exp.scaled_residuals(sol)[2]) * float(exp.sigma[2])
        assert abs(np.mean(r)) < bound < P_ATM / 10, np.mean(r)
        assert 0.8 * sigma < np.std(r) < 1.2 * sigma
        # the report's residual diagnostics
        d = residual_diagnostics(log, sol.height, sol.speed, sol.pressure)["pressure"]
        assert abs(d["mean"] * d["sigma"]) < bound
        # the fit metrics (workflows.fit): chi2/N near 1; 1 atm off would add (P_ATM/sigma)^2/3
        (sim,) = simulate_logs({}, [], [log])
        np.testing.assert_allclose(sim["pressure"], np.asarray(sol.pressure))
        assert chi2n(log, sim) < 1.5
