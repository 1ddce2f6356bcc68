"""A log that a model cannot simulate is reported, named and left out of a report's
per-log sections; it never ends a job (issue 13: measured, a diagnosis died when the
baseline could not simulate a held-out log with a duty saturation hidden)."""

import pytest

import jaxlift as jl
from jaxlift.workflows.fit import _log_metrics, simulate_logs

ABSURD = {"d": 1e9}  # viscous damping [N s/m] so stiff that the solver runs out of steps


def test_simulate_logs_raises_or_records_the_failure_by_log():
    log = jl.read_log("data/lift_500kg.csv")
    with pytest.raises(jl.SimulationError, match="lift_500kg.csv: the ODE solver failed"):
        simulate_logs(ABSURD, [], [log])
    why: dict[str, str] = {}
    good, bad = (
        simulate_logs({}, [], [log], failures=why),
        simulate_logs(ABSURD, [], [log], failures=why),
    )
    assert good[0] is not None and bad == [None]
    assert list(why) == ["lift_500kg"] and "maximum number of solver steps" in why["lift_500kg"]
    assert _log_metrics(log, None, why["lift_500kg"]) == {"failed": why["lift_500kg"]}


def test_fit_summary_shows_the_fitted_value_when_only_the_nominal_run_failed():
    """Coverage case_052's fit_2 left the mast at the nominal values but was fitted to
    chi2/N 1.006; ``jaxlift fit`` printed only "not simulated (...)" for it, hiding the
    good fit. Each side is reported on its own."""
    from jaxlift.cli.main import fit_log_line

    why = "the fork left the mast's range [0, x_max] at t = 87.67 s (height 4.511 m)"
    ok = {"chi2_per_sample": 1.006, "rms_speed_mmps": 3.1}
    line = fit_log_line("fit_2", {"role": "fitted", "before": {"failed": why}, "after": ok})
    assert "1.01" in line and "3.10" in line and "nominal values not simulated" in line
    assert why in line
    line = fit_log_line("fit_2", {"role": "fitted", "before": ok, "after": {"failed": why}})
    assert "not simulated with the fitted values" in line and why in line
    assert "1.01" not in line
    both = {"chi2_per_sample": 191000.0, "rms_speed_mmps": 6.91}
    line = fit_log_line("fit_1", {"role": "fitted", "before": both, "after": ok})
    assert "1.91e+05 ->" in line and "1.01 " in line and "failed" not in line
