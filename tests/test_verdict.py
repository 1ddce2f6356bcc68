"""The verdict and its confidence: none / a winner / undecided between two, with the
evidence and a separating experiment; a candidate that fails is reported, not fatal."""

import math

import numpy as np
import pytest

import jaxlift as jl
from jaxlift.calibrate import diagnose as dg
from jaxlift.calibrate.diagnose import EffectScreen, decide, refit_starts, separating_experiment


def _screen(effect, dbic, before=2.0, after=1.1):
    s = EffectScreen(effect, dg.switch_parameter(effect), 8.0, 1e-15, 100.0, 1.0)
    s.delta_bic, s.heldout_chi2_before, s.heldout_chi2_after = dbic, before, after
    s.fitted_params = {s.parameter: 1.0}
    s.fitted_stderr = {s.parameter: 0.1}
    return s


def test_none_when_nothing_passes():
    assert decide([], 10.0) == ("none", [], [])


def test_a_clear_winner():
    verdict, between, reasons = decide(
        [_screen("hose_compliance", -250.0), _screen("entrained_air", -120.0)], 10.0
    )
    assert (verdict, between, reasons) == ("hose_compliance", [], [])


def test_undecided_when_the_best_two_are_within_the_threshold():
    verdict, between, reasons = decide(
        [_screen("entrained_air", -240.0), _screen("hose_compliance", -246.0)], 10.0
    )
    assert verdict == "undecided"
    assert between == ["hose_compliance", "entrained_air"]  # best first
    text = " ".join(reasons)
    assert "6.0 apart" in text and "held-out chi2/N 2 -> 1.1" in text
    assert "pressure" in reasons[-1]  # the experiment that separates air from hoses


def test_separating_experiments_are_specific():
    assert "10 mm/s" in separating_experiment("stick_slip", "mast_compliance")
    assert "steps of the duty" in separating_experiment("input_delay", "motor_inertia")
    assert "valve shut" in separating_experiment("motor_droop", "leakage")
    generic = separating_experiment("motor_droop", "input_delay")
    assert "differ most" in generic


@pytest.fixture(scope="module")
def short_fit():
    log = jl.read_log("data/lift_500kg.csv")
    n = 3000
    short = jl.Log(
        time_s=log.time_s[:n], pwm=log.pwm[:n], height_m=log.height_m[:n],
        load_kg=log.load_kg[:n], speed_mps=log.speed_mps[:n], name="short",
    )  # fmt: skip
    return [short], jl.fit([short], free="beta,d,cf_con", n_starts=1)


def test_a_screen_that_fails_is_reported_and_the_others_go_on(short_fit, monkeypatch):
    logs, base = short_fit
    real = dg.Problem.residuals_at

    def failing_for_leakage(self, theta):
        r = real(self, theta)
        if "leakage" in [e.name for e in self.effects]:
            return np.full_like(r, np.nan)  # what a failed simulation gives
        return r

    monkeypatch.setattr(dg.Problem, "residuals_at", failing_for_leakage)
    ranking = dg.screen_effects(base, logs, candidates=["leakage", "hose_compliance"])
    by = {s.effect: s for s in ranking}
    assert "simulation failed" in by["leakage"].failure and "C_L" in by["leakage"].failure
    assert math.isnan(by["leakage"].z)
    assert by["hose_compliance"].failure is None and math.isfinite(by["hose_compliance"].z)
    assert ranking[-1].effect == "leakage"  # failures rank last
    assert "failure" in by["leakage"].as_dict()


def test_every_effect_declares_the_range_a_vehicle_can_have():
    for name, cls in jl.EFFECTS.items():
        info = cls.param_infos()[dg.switch_parameter(name)]
        assert info.typical is not None and info.typical_why, name
        lo, hi = info.typical
        assert info.nesting < lo < hi <= info.upper, name
        assert hi / lo >= 10, name  # a range, not a point


@pytest.mark.parametrize("effect", list(jl.EFFECTS))
def test_refit_starts_cover_the_typical_range(effect):
    par = dg.switch_parameter(effect)
    lo, hi = jl.EFFECTS[effect].param_infos()[par].typical
    starts = refit_starts(effect, screen_estimate=math.sqrt(lo * hi))
    values = sorted(s[par] for s in starts)
    assert values[0] == pytest.approx(lo) and values[-1] == pytest.approx(hi)
    # from a huge or a useless screen estimate too: kept inside the range
    assert lo <= refit_starts(effect, 1e30)[0][par] <= hi
    assert lo <= refit_starts(effect, float("nan"))[0][par] <= hi
    # two-parameter effects: the second parameter spans its range as well
    for name, info in jl.EFFECTS[effect].param_infos().items():
        if name != par and info.typical:
            seconds = sorted(s[name] for s in starts if name in s)
            assert seconds[0] == pytest.approx(info.typical[0])
            assert seconds[-1] == pytest.approx(info.typical[1])
