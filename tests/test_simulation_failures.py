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
