"""The shape of what is missing (issue: effects outside the eight): the sparse
regression finds a planted law; the missing-signal estimate recovers laws hidden in
synthetic logs -- a force law, a flow law and an input nonlinearity, none of them among
the eight -- against a target computed from the true and the fitted model's vector
fields (not from the code under test)."""

from typing import ClassVar

import jax
import numpy as np
import pytest
from outside_laws import DutySaturation, EarlyRelief, SealFriction, missing_targets

import jaxlift as jl
from jaxlift.analysis.laws import dependence, explain
from jaxlift.calibrate.fit import fit
from jaxlift.model.sequences import ramped_sequence

SECTIONS = {
    "thesis-like": [
        (0.0, 2.0),
        (0.5, 5.0),
        (0.25, 6.0),
        (0.0, 3.0),
        (0.6, 5.0),
        (0.0, 3.0),
        (0.35, 6.0),
        (0.0, 2.0),
    ],  # fmt: skip
    "steps": [
        (0.0, 1.5),
        (0.3, 4.0),
        (0.0, 2.0),
        (0.55, 3.0),
        (0.2, 5.0),
        (0.0, 2.0),
        (0.45, 4.0),
        (0.0, 2.0),
    ],  # fmt: skip
}


def _log(law, load, seed, x0, sections, name, ramp_s=0.5):
    ts, pwm = ramped_sequence(SECTIONS[sections], ramp_s=ramp_s)
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
    effects = () if law is None else (law,)
    sol = jl.simulate(jl.Plant(), effects, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
    assert bool(sol.ok)
    log = jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(seed),
                    with_pressure=True, name=name)  # fmt: skip
    return log, inputs


def _targets(law, result, shape_log, inputs):
    lg = shape_log
    return missing_targets(law, result.params, result.effects, inputs, lg.t, lg.x, lg.v, lg.p)


def _truth() -> jl.FitResult:
    """The nominal (true) model as a fit result: what the shape estimate and the targets
    read of one (the model, parameters, effects and offsets)."""
    truth = jl.FitResult.__new__(jl.FitResult)
    truth.model, truth.effects, truth.x0_offsets = jl.Model.build(), [], {}
    truth.params = {k: float(v) for k, v in truth.model.values().items()}
    return truth


# ---------------------------------------------------------------- sparse regression
def test_explain_finds_a_planted_law_and_flags_model_terms():
    rng = np.random.default_rng(0)
    n = 3000
    v = np.abs(rng.normal(0.05, 0.04, n)) * np.sign(rng.uniform(-0.2, 1, n))
    states = {"t": np.linspace(0, 60, n), "x": rng.uniform(0, 4, n), "v": v,
              "p": rng.uniform(3e6, 18e6, n), "a": rng.normal(0, 0.2, n),
              "u": rng.uniform(0, 0.6, n)}  # fmt: skip
    sgn = np.tanh(v / 1e-3)
    y = -6e-5 * states["p"] * sgn + 300.0 * sgn + rng.normal(0, 20.0, n)
    law = explain(y, states, name="force", unit="N")
    assert set(law.coefs) == {"1", "p sign(v)", "sign(v)"}, law.describe()
    assert law.leading == "p sign(v)"  # the new term, not the model's own sign(v)
    assert law.coefs["p sign(v)"] == pytest.approx(-6e-5, rel=0.05)
    assert "sign(v)" in law.model_terms and law.r2 > 0.95
    assert "p sign(v)" in law.describe()
    # a signal that depends on nothing in the library: no term explains it
    noise = explain(rng.normal(0, 1, n), states)
    assert noise.r2 < 0.02 and len(noise.coefs) == 2
    up = v > 0.002  # lifting: the law is -6e-5 p + 300, a function of p alone
    dep = dependence(y[up], {k: s[up] for k, s in states.items()})
    assert max(dep, key=lambda k: dep[k]["r2"]) == "p" and dep["p"]["r2"] > 0.9
    assert law.alternatives == []  # these data move both ways: p sign(v) is told from p
    # logs that only lift: p sign(v) = p wherever the fork moves, so the two terms are
    # named as indistinguishable, whichever leads
    only_up = {**states, "v": np.abs(v) + 0.01}
    y_up = -6e-5 * only_up["p"] * np.tanh(only_up["v"] / 1e-3) + rng.normal(0, 20.0, n)
    law_up = explain(y_up, only_up, name="force", unit="N")
    assert {law_up.leading, *law_up.alternatives} >= {"p", "p sign(v)"}, law_up.describe()
    assert "cannot be told from" in law_up.describe()
    # logs that lift and rest, holding the load at the pressure of lifting, with the
    # law's mean over lifting absorbed by cf_con in the fit: p sign(v) + a shift of
    # sign(v) is then p + a constant (the outside-the-eight study's seal friction),
    # though the two columns are far from collinear (the rests differ)
    rest = rng.uniform(size=n) < 0.3
    lift = {**states, "v": np.where(rest, 0.0, np.abs(v) + 0.01),
            "p": np.where(rest, 10.5e6 + rng.normal(0, 2e5, n), states["p"])}  # fmt: skip
    sg = np.tanh(lift["v"] / 1e-3)
    y_lift = -6e-5 * (lift["p"] - np.mean(lift["p"][~rest])) * sg + rng.normal(0, 20.0, n)
    law_lift = explain(y_lift, lift, name="force", unit="N")
    assert {law_lift.leading, *law_lift.alternatives} >= {"p", "p sign(v)"}, law_lift.describe()
    assert abs(np.corrcoef(lift["p"], lift["p"] * sg)[0, 1]) < 0.9
    # a term that only shares the model's own sign(v) with the law is no alternative
    # (pressure within ±15 %: p sign(v) is mostly sign(v), and so is a duty that is
    # higher while lifting; the law's terms p sign(v) and sign(v) tell them apart)
    flat = {
        **lift,
        "p": 10.5e6 + rng.normal(0, 1.5e6, n),
        "u": 0.3 + 0.1 * (~rest) + rng.uniform(0, 0.1, n),
    }
    law_sg = explain(-6e-5 * flat["p"] * sg + 900.0 * sg + rng.normal(0, 15.0, n), flat,
                     name="force", unit="N")  # fmt: skip
    assert set(law_sg.coefs) == {"1", "sign(v)", "p sign(v)"}, law_sg.describe()
    assert law_sg.alternatives == [], law_sg.describe()
    assert abs(np.corrcoef(flat["u"], sg)[0, 1]) > 0.8  # u is mostly sign(v)
    with pytest.raises(ValueError, match="same length"):
        explain(y, states, weights=np.ones(3))


# ---------------------------------------------------------------- the estimate
@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_a_hidden_force_is_recovered_when_the_parameters_are_right():
    """Seal friction hidden, the model at the true parameters: the estimated force is
    the law (correlation >= 0.9, the issue's criterion: the law jumps where the speed
    changes sign, the smooth estimate cannot), the flow is not needed, the fit reaches
    the noise."""
    law = SealFriction()
    made = [_log(law, m, s, 0.3, "steps", f"seal_{m:.0f}") for m, s in ((400.0, 1), (1400.0, 2))]
    truth = _truth()
    shape = jl.estimate_missing_shape(truth, [lg for lg, _ in made])
    assert shape.needed == {"force": True, "flow": False}, (shape.evidence, shape.shares)
    assert shape.dominant == "force"
    # the flow alone explains part of it: with the jumps where the duty changes, a flow
    # that steps as a lift starts imitates part of a friction that steps there
    # (measured: share 0.29; 0.0 with a smooth flow alone). Its evidence is negative.
    assert shape.shares["force"] > 0.9 and 0.0 <= shape.shares["flow"] < 0.5, shape.shares
    assert shape.evidence["flow"] < 0.0, shape.evidence
    for lg in shape.logs:
        hidden = -law.mu * lg.p * np.tanh(lg.v / 1e-3)
        assert np.corrcoef(hidden, lg.force)[0, 1] >= 0.9
        assert lg.chi2n_before > 2.0 and lg.chi2n_after < 1.1
        assert np.all(lg.force_sd > 0)
    laws = shape.laws()
    assert laws["force"].leading == "p sign(v)", laws["force"].describe()
    assert laws["force"].coefs["p sign(v)"] == pytest.approx(-law.mu, rel=0.15)
    table = shape.table()
    assert list(table.index) == ["force", "flow"] and "p sign(v)" in shape._repr_html_()


class DutyFlowLoss(jl.AbstractStatelessEffect):
    """A flow lost in proportion to the duty (a pump law the model has wrong): a missing
    flow that steps when the duty does."""

    k: float = 3e-6  # m^3/s per unit duty (~3 % of the pump's flow)
    name: ClassVar[str] = "test_duty_flow_loss"

    def extra_flow(self, plant, z, sig):
        return -self.k * sig.u


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_a_missing_flow_that_steps_with_the_duty_is_followed_by_the_jumps(monkeypatch):
    """The duty steps (20 ms ramps) and the missing flow with it. The marginal
    likelihood turns the jumps on (a smooth flow alone cannot step), and the estimate
    follows the steps: correlation >= 0.99 and an RMS error less than half of the
    estimate without jumps (measured, pooled: 0.999 and about 3e-8 m^3/s with jumps; 0.949 and
    2.0e-7 without). Only the flow is needed."""
    from jaxlift.calibrate import shape as shape_mod

    law = DutyFlowLoss()
    made = [_log(law, 400.0, 1, 0.3, "thesis-like", "duty_loss_a", ramp_s=0.02),
            _log(law, 1400.0, 2, 0.0, "steps", "duty_loss_b", ramp_s=0.02)]  # fmt: skip
    truth = _truth()

    def errors(shape):
        err, tgt, est = [], [], []
        for lg, (_, inputs) in zip(shape.logs, made):
            _, Q = _targets(law, truth, lg, inputs)
            err.append(lg.flow - Q)
            tgt.append(Q)
            est.append(lg.flow)
            assert lg.chi2n_before > 10.0 and lg.chi2n_after < 1.1
        corr = np.corrcoef(np.concatenate(tgt), np.concatenate(est))[0, 1]
        return corr, np.sqrt(np.mean(np.concatenate(err) ** 2))

    shape = jl.estimate_missing_shape(truth, [lg for lg, _ in made])
    assert np.isfinite(shape.log10_q_jump), shape.log10_q_jump
    assert shape.needed == {"force": False, "flow": True}, (shape.evidence, shape.shares)
    corr, rms = errors(shape)
    monkeypatch.setattr(shape_mod, "LOG10_QJ_GRID", np.array([]))  # no jumps
    smooth = jl.estimate_missing_shape(truth, [lg for lg, _ in made])
    assert smooth.log10_q_jump == -np.inf
    corr_smooth, rms_smooth = errors(smooth)
    assert corr >= 0.99 and rms < 0.5 * rms_smooth, (corr, rms, corr_smooth, rms_smooth)


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_nothing_missing_needs_no_signal_and_no_jumps():
    """The true model, nothing hidden: neither signal is needed, no jumps are chosen,
    and the fit stays at the noise."""
    made = [_log(None, 400.0, 1, 0.3, "thesis-like", "null_a"),
            _log(None, 1400.0, 2, 0.0, "steps", "null_b")]  # fmt: skip
    shape = jl.estimate_missing_shape(_truth(), [lg for lg, _ in made])
    assert shape.needed == {"force": False, "flow": False}, (shape.evidence, shape.shares)
    assert shape.log10_q_jump == -np.inf
    for lg in shape.logs:
        assert lg.chi2n_before < 1.1 and abs(lg.chi2n_after - lg.chi2n_before) < 0.05


def _undamped(args) -> bool:
    """Whether the smoother's arguments are an undamped pass's: R covers only the
    measured rows (a damped pass adds the states and signals as pseudo-measurements)."""
    return args[8].shape[0] == args[6].shape[0] and args[6].shape[0] < args[6].shape[1]


@pytest.mark.slow  # fast loop: 34 s and 29 s beside one other worker (measured 2026-12-07)
def test_damped_passes_move_a_log_whose_gauss_newton_steps_are_all_rejected(monkeypatch):
    """Where the linearisation is poor (measured: a large duty saturation, one log
    stalled at chi2/N 180), every Gauss--Newton step, halved four times, makes the fit
    worse. Here that is forced: the undamped smoother's step is turned back and made 20
    times longer, so each of its halvings is rejected. The damped (Levenberg--Marquardt)
    passes must still reach the noise and the hidden force; without them the log stays
    where the baseline left it."""
    from jaxlift.calibrate import shape as shape_mod

    smooth = shape_mod._smooth

    def reversed_step(*args):
        ll, w, sd, de0, chi2 = smooth(*args)
        if _undamped(args):
            # undamped (R covers only the measured rows): reverse the step, x20
            wbar = args[3]
            return ll, wbar - 20.0 * (w - wbar), sd, -20.0 * de0, chi2
        return ll, w, sd, de0, chi2

    monkeypatch.setattr(shape_mod, "_smooth", reversed_step)
    law = SealFriction()
    made = [_log(law, 400.0, 1, 0.3, "steps", "seal_damped")]
    truth = _truth()
    (lg,) = jl.estimate_missing_shape(truth, [made[0][0]]).logs
    assert lg.chi2n_before > 2.0 and lg.chi2n_after < 1.1, (lg.chi2n_before, lg.chi2n_after)
    hidden = -law.mu * lg.p * np.tanh(lg.v / 1e-3)
    assert np.corrcoef(hidden, lg.force)[0, 1] >= 0.9
    monkeypatch.setattr(shape_mod, "DAMPED_TRIES", 0)
    (lg,) = jl.estimate_missing_shape(truth, [made[0][0]], iterations=3).logs
    assert lg.chi2n_after == pytest.approx(lg.chi2n_before)


@pytest.mark.slow  # fast loop: 34 s and 29 s beside one other worker (measured 2026-12-07)
def test_steps_that_each_raise_the_misfit_a_little_do_not_add_up(monkeypatch):
    """A step may raise a log's chi2/N by 1 % (the smoother trades misfit for
    smoothness), but not 1 % per pass on top of the last: measured on the quadratic drag
    of test_unexplained, chi2/N climbed from 1.33 to 1.41 over 13 passes. Forced here:
    the undamped smoother's step is replaced by one that adds 3 N of force each pass, on
    a log with nothing missing. Each such step raises chi2/N by less than 1 % of the
    last pass's (so the old rule accepted all 15, ending at 1.10); the fit may end at
    most 1 % above the lowest it reached."""
    from jaxlift.calibrate import shape as shape_mod

    smooth = shape_mod._smooth

    def creeping_step(*args):
        ll, w, sd, de0, chi2 = smooth(*args)
        if _undamped(args):
            wbar = np.asarray(args[3])  # undamped: 3 N more force than now, everywhere
            return ll, wbar + np.array([3.0, 0.0]), sd, 0.0 * de0, chi2
        return ll, w, sd, de0, chi2

    monkeypatch.setattr(shape_mod, "_smooth", creeping_step)
    made = _log(None, 400.0, 1, 0.3, "thesis-like", "null_creep")
    (lg,) = jl.estimate_missing_shape(_truth(), [made[0]]).logs
    assert lg.chi2n_before < 1.01
    assert lg.chi2n_after <= lg.chi2n_before * 1.01 + 1e-3, (lg.chi2n_before, lg.chi2n_after)


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_without_a_pressure_sensor_a_signal_not_needed_is_held_at_zero():
    """A log without pressure: a free flow and a free force could trade along what the
    log cannot see (a straight-line flow drifts the pressure, the force makes up for
    it; measured before the fix: the pressure estimate at -21..29 MPa against a true
    0..19, the force uncorrelated with the law, 0.05). The flow is not needed, so it is
    held at zero: the pressure stays the model's, and the force is the law's (seen only
    through the dynamics here, so less sharply than with a sensor: >= 0.7, not 0.9)."""
    law = SealFriction()
    ts, pwm = ramped_sequence(SECTIONS["thesis-like"], ramp_s=0.5)
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, 1400.0), 0.3)
    sol = jl.simulate(jl.Plant(), (law,), inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
    log = jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(2),
                    with_pressure=False, name="no_pressure")  # fmt: skip
    truth = _truth()
    shape = jl.estimate_missing_shape(truth, [log])
    (lg,) = shape.logs
    assert not shape.with_pressure
    assert shape.needed == {"force": True, "flow": False}, (shape.evidence, shape.shares)
    assert np.max(np.abs(lg.flow)) < 1e-7  # held (the pump delivers ~1e-4 m^3/s)
    p_true = np.asarray(sol.pressure)
    assert np.sqrt(np.mean((lg.p - p_true) ** 2)) < 1e6, (lg.p.min(), lg.p.max())
    hidden = -law.mu * p_true * np.tanh(lg.v / 1e-3)
    assert np.corrcoef(hidden, lg.force)[0, 1] >= 0.7
    assert lg.chi2n_before > 2.0 and lg.chi2n_after < 1.3


CASES = {
    # law, signal that carries it, the library term that leads (None: not in library)
    "seal_friction": (SealFriction(), "force", "p sign(v)"),
    "early_relief": (EarlyRelief(), "flow", None),
    "duty_saturation": (DutySaturation(), "flow", None),
}


@pytest.mark.slow
@pytest.mark.parametrize(
    "case",
    # duty saturation is a second law on the flow, whose path early relief already
    # takes in CI (~185 s): run with -m extended
    [pytest.param(c, marks=pytest.mark.extended) if c == "duty_saturation" else c for c in CASES],
)
def test_laws_outside_the_eight_are_recovered_from_a_nominal_fit(case):
    """As a user meets it: the baseline fitted from nominal values (it absorbs what its
    own parameters can), then the shape. The estimate matches what the fitted model
    lacks (correlation >= 0.9 over the range the logs visit, pooled: on a log where the
    law barely acts, e.g. a relief that the light load hardly cracks, the target is
    not much larger than the estimate's own uncertainty), on the right signal; the law's
    leading term is named where the library has it. (Not asserted: that the error is
    within the stated band. It is not where the law jumps, e.g. friction as the speed
    changes sign: the band is conditional on a smooth signal.)"""
    law, signal, term = CASES[case]
    made = [_log(law, 500.0, 11, 0.3, "thesis-like", f"{case}_a"),
            _log(law, 1500.0, 12, 0.0, "steps", f"{case}_b")]  # fmt: skip
    logs = [lg for lg, _ in made]
    result = fit(logs, n_starts=2)
    assert result.chi2 / result.n_residuals > 2.0  # the law matters at this size
    shape = jl.estimate_missing_shape(result, logs)
    assert shape.dominant == signal and shape.needed[signal], (shape.evidence, shape.shares)
    targets, estimates = [], []
    for lg, (_, inputs) in zip(shape.logs, made):
        F, Q = _targets(law, result, lg, inputs)
        target, est = (F if signal == "force" else Q), getattr(lg, signal)
        assert lg.chi2n_after < 1.2, (lg.chi2n_before, lg.chi2n_after)
        targets.append(target)
        estimates.append(est)
    assert np.corrcoef(np.concatenate(targets), np.concatenate(estimates))[0, 1] >= 0.9
    if term is not None:
        assert shape.laws()[signal].leading == term
