"""Gain tuning: tuned beats the thesis gains, robust beats nominal on held-out draws,
the cost as a sum of squares (what LM tunes), parameter draws from the least-squares
covariance and from a posterior directory, CVaR, CLI.

Short references (13 s, through the first stage shift) and small budgets; the
robust-vs-nominal comparison is marked slow.
"""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.control.closed_loop import simulate_closed_loop
from jaxlift.control.controller import PID, THESIS_PID, ScheduledPID, load_gains
from jaxlift.control.cost import (
    FAILED_COST,
    closed_loop_costs,
    draw_weights,
    robust_objective,
    stack_references,
    stage_noise_amplification,
    tuning_cost,
    tuning_residuals,
)
from jaxlift.control.draws import batch_models, evaluate_draws, parameter_draws
from jaxlift.control.gains import GainSpace
from jaxlift.control.performance import noise_amplification
from jaxlift.control.reference import Reference
from jaxlift.control.tune import tune_gains, tune_multistart

CALIBRATED = {"beta": 4.0e8, "cf_con": 1.0, "cf_in": 13.5, "cf_out": 770.0, "d": 560.0}
PLANT = jl.with_params(jl.Plant(), (), CALIBRATED)[0]
REF = Reference.from_sections(
    [(0.0, 1.0), (0.025, 4.0), (0.09, 3.0), (0.025, 4.0), (0.0, 2.0)], m_load=1000.0, x0=1.25
)
START = PID().with_gains({**THESIS_PID, "K_aw": 15.0})
THESIS = PID().with_gains(THESIS_PID)
# a deliberately wide "fit": beta +-30 %, friction and damping +-25 %, motor map +-3 %
STDERR = {"beta": 1.2e8, "d": 140.0, "cf_out": 190.0, "cf_con": 0.5, "k1": 0.06, "k2": 0.06}


@pytest.fixture(scope="module")
def fit_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fit")
    values = {k: float(v) for k, v in jl.get_params(PLANT).items()}
    jl.save_params_json(d / "params.json", values, comment="test fit")
    (d / "metrics.json").write_text(json.dumps({"effects": [], "stderr": STDERR}))
    return d


@pytest.fixture(scope="module")
def posterior_dir(tmp_path_factory):
    """A minimal `jaxlift posterior` output: settings + posterior.nc (2 chains x 20
    draws of beta and d, seeded), the other parameters at the calibrated values."""
    import xarray as xr

    d = tmp_path_factory.mktemp("posterior")
    values = {k: float(v) for k, v in jl.get_params(PLANT).items()}
    problem = {"names": ["beta", "d", "noise_speed"], "effects": [], "values": values}
    (d / "posterior_settings.json").write_text(json.dumps({"problem": problem}))
    rng = np.random.default_rng(3)
    post = xr.Dataset(
        {
            "beta": (("chain", "draw"), rng.normal(4.0e8, 0.2e8, (2, 20))),
            "d": (("chain", "draw"), rng.normal(560.0, 30.0, (2, 20))),
            "noise_speed": (("chain", "draw"), rng.normal(1e-3, 1e-4, (2, 20))),
        }
    )
    xr.DataTree.from_dict({"posterior": post}).to_netcdf(d / "posterior.nc", engine="h5netcdf")
    jl.save_params_json(d / "params.json", values, comment="test posterior")
    return d


def _cost(ctrl, plant=PLANT):
    sol = simulate_closed_loop(plant, (), ctrl, REF).check()
    return float(tuning_cost(ctrl, plant, sol))


@pytest.mark.slow
def test_tuned_gains_beat_thesis_gains():
    res = tune_gains(START, PLANT, (), [REF], steps=12)
    thesis = _cost(THESIS)
    tuned = _cost(res.controller)  # re-simulated at the default (tighter) tolerance
    assert res.best_cost < res.initial_cost
    assert tuned < 0.7 * thesis, (tuned, thesis)
    assert res.n_failed == 0 and len(res.history) == res.n_evaluations <= 14
    # deterministic
    again = tune_gains(START, PLANT, (), [REF], steps=3)
    first = tune_gains(START, PLANT, (), [REF], steps=3)
    assert again.controller.gain_values() == first.controller.gain_values()


def test_gain_space_roundtrip_and_floors():
    space = GainSpace.for_controller(PID().with_gains(THESIS_PID))  # K_aw = 0
    theta = space.to_theta(space.template)
    assert np.all(np.isfinite(theta))
    back = space.from_theta(theta).gain_values()
    assert back["K_aw"] == pytest.approx(15.0)  # floor: I / P
    assert back["P"] == pytest.approx(20.0) and back["D"] == pytest.approx(2.0)
    with pytest.raises(jl.ParameterError, match="cannot tune.*Kp"):
        GainSpace.for_controller(START, ["P", "Kp"])


def test_scheduled_local_coordinates_give_the_same_loop():
    """A run at one load sees a scheduled PID only through its 11 gains at that load
    (what the LM Jacobian is taken in): the flat controller built from them has the
    same gains at that load, at every height; the chain rule maps 11 -> 20."""
    space = GainSpace.for_controller(ScheduledPID.from_pid(START))
    rng = np.random.default_rng(2)
    theta = jnp.asarray(space.to_theta(space.template) + 0.3 * rng.normal(size=20))
    full = space.from_theta(theta)
    for m in (500.0, 900.0, 1500.0):
        vals = space.local_values(theta, m)
        local = space.local_controller(vals)
        for x in (0.4, 1.5, 2.2, 3.0, 4.0):
            a = np.asarray(full.gains(PLANT, jnp.asarray(x), m))
            b = np.asarray(local.gains(PLANT, jnp.asarray(x), 2.0 * m))  # flat in the load
            np.testing.assert_allclose(b, a, rtol=1e-12)
        assert float(local.N) == pytest.approx(float(full.N))
        J = np.asarray(jax.jacfwd(space.local_values)(theta, m))
        assert J.shape == (11, 20) and np.all(J[:, space.names.index("K_aw")][:10] == 0)
    # at 500 kg only the 500 kg coordinates matter
    J = np.asarray(jax.jacfwd(space.local_values)(theta, 500.0))
    assert np.all(J[:9, [i for i, n in enumerate(space.names) if n.endswith("@1500")]] == 0)


def test_parameter_draws_from_least_squares(fit_dir):
    a = parameter_draws(50, 7, fit_dir=fit_dir)
    b = parameter_draws(50, 7, fit_dir=fit_dir)
    c = parameter_draws(50, 8, fit_dir=fit_dir)
    assert "least-squares covariance" in a.source and "independently" in a.source
    assert a.draws == b.draws and a.draws != c.draws
    beta = np.array([d["beta"] for d in a.draws])
    assert np.all(beta > 0) and 0.2 < np.std(np.log(beta)) < 0.45  # se 1.2e8 / 4e8 = 0.3
    assert all(d["cf_con"] >= 0 for d in a.draws)  # at its bound: drawn in physical units
    assert {d["A1"] for d in a.draws} == {float(PLANT.A1)}  # not fitted: fixed
    miss = parameter_draws(5, 0, posterior_dir=fit_dir / "nowhere", fit_dir=fit_dir)
    assert "not usable" in miss.source or "least-squares" in miss.source
    with pytest.raises(jl.ParameterError, match="fit directory"):
        parameter_draws(5, 0)


def test_parameter_draws_from_a_posterior_directory(posterior_dir, fit_dir):
    a = parameter_draws(30, 5, posterior_dir=posterior_dir, fit_dir=fit_dir)
    assert a.source.startswith("posterior samples") and a.effects == []
    assert a.draws == parameter_draws(30, 5, posterior_dir=posterior_dir).draws
    assert a.draws != parameter_draws(30, 6, posterior_dir=posterior_dir).draws
    import xarray as xr

    with xr.open_datatree(posterior_dir / "posterior.nc", engine="h5netcdf") as tree:
        stored = set(np.asarray(tree["posterior"]["beta"]).ravel().tolist())
    assert {d["beta"] for d in a.draws} <= stored  # the stored samples themselves
    assert len({d["beta"] for d in a.draws}) == 30  # without replacement (40 stored)
    assert {d["cf_out"] for d in a.draws} == {float(PLANT.cf_out)}  # not sampled: fixed
    assert all("noise_speed" not in d for d in a.draws)  # likelihood noise: not a parameter
    plants, _ = batch_models(PLANT, (), a.draws)
    assert np.asarray(plants.beta).shape == (30,)


def test_robust_objective_is_mean_plus_cvar():
    c = np.array([1.0, 2.0, 3.0, 4.0, 10.0])
    assert float(robust_objective(c, alpha=0.2)) == pytest.approx(4.0 + 10.0)
    assert float(robust_objective(c, alpha=0.4, tail_weight=0.5)) == pytest.approx(4.0 + 3.5)
    # the weights LM tunes with give the same objective (worst set held at the point)
    for alpha, tw in ((0.2, 1.0), (0.4, 0.5)):
        w = draw_weights(jnp.asarray(c), True, alpha, tw)
        assert float(jnp.sum(w * c)) == pytest.approx(float(robust_objective(c, alpha, tw)))
    assert float(jnp.sum(draw_weights(jnp.asarray(c), False) * c)) == pytest.approx(4.0)


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_residuals_sum_to_the_tuning_cost():
    """LM tunes ``sum(r**2)``: it must be the cost, for the plain and the scheduled PID
    (whose noise amplification differs per stage)."""
    sched = ScheduledPID.from_stage_gains(
        jnp.asarray([[20.0, 300.0, 2.0], [30.0, 300.0, 2.0], [180.0, 400.0, 2.0]]),
        jnp.asarray([[25.0, 300.0, 2.0], [30.0, 350.0, 2.0], [220.0, 400.0, 2.0]]),
        100.0,
        15.0,
    )
    for ctrl in (START, sched):
        sol = simulate_closed_loop(PLANT, (), ctrl, REF).check()
        r = tuning_residuals(ctrl, PLANT, sol)
        cost = float(tuning_cost(ctrl, PLANT, sol))
        assert float(jnp.sum(r**2)) == pytest.approx(cost, rel=1e-12)
        assert cost > 1.0
    # a plain PID amplifies the noise the same at every height: the cost is unchanged
    mid = noise_amplification(START, PLANT, 0.5 * PLANT.x_max, 1000.0)
    assert float(stage_noise_amplification(START, PLANT, 1000.0)) == pytest.approx(float(mid))
    per_stage = [float(noise_amplification(sched, PLANT, x, 1000.0)) for x in (0.75, 2.25, 3.75)]
    assert float(stage_noise_amplification(sched, PLANT, 1000.0)) == pytest.approx(
        math.sqrt(np.mean(np.square(per_stage)))
    )
    assert max(per_stage) > 1.5 * min(per_stage)  # stage 3's gains pay for their noise


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_evaluate_draws_same_per_draw_whatever_the_threads():
    """The draws of a robustness report run in chunks on threads (the last chunk padded
    with copies of the last draw): each draw's cost, flag and figures are those of the
    draw evaluated on its own, with its own noise realisation, for 1, 2 or 3 workers
    (3 draws in chunks of 2: one padded)."""
    draws = [dict(CALIBRATED, beta=b) for b in (3.0e8, 4.0e8, 5.5e8)]
    plants, effs = batch_models(PLANT, (), draws)
    seeds = np.array([[11], [12], [13]], dtype=np.uint32)  # a realisation per draw
    kw = dict(noise_seeds=seeds, sampled=True)
    runs = [evaluate_draws(THESIS, plants, effs, REF, workers=w, **kw) for w in (1, 2, 3)]
    for c, ok, fig in runs:
        assert c.shape == ok.shape == (3,) and ok.all()
        np.testing.assert_allclose(c, runs[0][0], rtol=1e-12)
        for a, b in zip(jax.tree.leaves(fig), jax.tree.leaves(runs[0][2]), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12)  # NaN (a stage not reached) = NaN
    # each draw alone, on its own seed: the same numbers
    for b in range(3):
        p1, e1 = batch_models(PLANT, (), draws[b : b + 1])
        c1, _, _ = evaluate_draws(THESIS, p1, e1, REF, noise_seeds=seeds[b : b + 1], sampled=True)
        np.testing.assert_allclose(c1[0], runs[0][0][b], rtol=1e-12)
    assert len(set(np.round(runs[0][0], 9))) == 3  # the draws differ: not one run copied


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_tune_multistart_threads_do_not_change_the_result():
    """The starts of a multistart tuning run side by side on threads: the same gains,
    objective and evaluations as one after the other (a small budget)."""
    draws = [dict(CALIBRATED, beta=b) for b in (3.5e8, 5.0e8)]
    plants, effs = batch_models(PLANT, (), draws)
    kw = dict(batched_plants=True, robust=True, steps=3)
    one, two = (tune_multistart([START, THESIS], plants, effs, [REF], workers=w, **kw)
                for w in (1, 2))  # fmt: skip
    assert one.n_evaluations == two.n_evaluations == 6
    assert one.best_cost == two.best_cost and one.message == two.message
    assert one.controller.gain_values() == two.controller.gain_values()
    assert one.controller.gain_values() != START.gain_values()  # it tuned


@pytest.mark.slow
def test_failed_run_costs_finite_penalty_and_finite_gradient():
    """A batch in which one run fails (a stiff plant -- tiny oil volume, hard oil --
    needs ~4x the solver steps; the step limit allows 2x): its cost is the finite
    penalty, the other is untouched, and the gradient of the batch cost stays finite."""
    good = {k: float(v) for k, v in jl.get_params(PLANT).items()}
    bad = dict(good, V0=1e-5, beta=5e9)
    ctrl = THESIS
    plants, effs = batch_models(PLANT, (), [good, bad])
    n_good = int(simulate_closed_loop(PLANT, (), ctrl, REF).check().num_steps)
    kw = dict(max_steps=2 * n_good)
    c, ok, _ = evaluate_draws(ctrl, plants, effs, REF, **kw)
    assert ok.tolist() == [True, False]
    assert c[1] == FAILED_COST and np.isfinite(c[0]) and c[0] < FAILED_COST
    space = GainSpace.for_controller(ctrl, ["P", "I", "D"])
    refs = stack_references([REF])

    def batch_cost(theta):
        cc, _, _ = closed_loop_costs(
            space.from_theta(theta), plants, effs, refs, batched_plants=True, **kw
        )
        return jnp.mean(cc)

    g = jax.grad(batch_cost)(jnp.asarray(space.to_theta(ctrl)))
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0)


@pytest.mark.slow
def test_robust_tuning_has_better_worst_case_on_held_out_draws(fit_dir):
    """Robust tuning (mean + CVaR over 6 draws, from the nominal-tuned and from the
    starting gains, as `jaxlift tune` does) against nominal tuning (run to its own
    stop), on 16 held-out draws; tuned at the tolerance of the evaluation (at rtol 1e-5
    LM found nominal gains whose cost was 2.55 there and 2.90 at 1e-6).

    Usually a trade-off, the nominal-tuned gains staying better on the nominal plant
    (not asserted: see the end). Measured (this code, 2 cores): held-out worst case 13.58 -> 12.92,
    mean 4.46 -> 4.31; over 208 held-out draws in 13 blocks of 16 the worst case was
    lower in every block (ratios 0.90-1.00), the mean too, 71 % of the draws better:
    a modest effect (~5 %), but a real one; its size depends on the machine (2.6 % on
    another of the same kind), so only its direction is asserted."""
    draws = parameter_draws(6 + 16, 11, fit_dir=fit_dir)
    tune_set, held_out = draws.split(6)
    # Nominal tuning run to its own stop: the budget is a cap, not the subject. 25
    # evaluations sufficed here, but on another machine (16 cores, jax 0.11.2, 2026-12-04)
    # they were spent before LM stopped ("evaluation budget spent"): its path differs
    # with the CPU's rounding. A start that stops earlier uses no more.
    nominal = tune_gains(START, PLANT, (), [REF], steps=80, rtol=1e-6)
    assert nominal.message.startswith(("converged", "stalled")), nominal.message
    plants, effs = batch_models(PLANT, (), tune_set.draws)
    robust = tune_multistart(
        [nominal.controller, START], plants, effs, [REF], batched_plants=True, robust=True,
        steps=25, alpha=0.34, rtol=1e-6,
    )  # fmt: skip
    # tuning draws first, then the held-out ones (one batch: one compilation)
    hp, he = batch_models(PLANT, (), tune_set.draws + held_out.draws)
    c_nom, ok_nom, _ = evaluate_draws(nominal.controller, hp, he, REF)
    c_rob, ok_rob, _ = evaluate_draws(robust.controller, hp, he, REF)
    assert ok_rob.all() and ok_nom.all()
    # on the tuning draws the robust objective went down against the nominal gains'
    assert robust.best_cost < 0.97 * float(robust_objective(jnp.asarray(c_nom[:6]), alpha=0.34))
    c_nom, c_rob = c_nom[6:], c_rob[6:]
    # On held-out draws the claim is the direction, not a size: the 3 % margin asked
    # before sat inside machine-to-machine differences (4.9 % here, 2.6 % on another
    # machine of the same kind: LM paths differ with the CPU's rounding). Worst case,
    # the robust objective (mean + CVaR of the worst third) and mean must all be lower.
    assert c_rob.max() < c_nom.max(), (c_rob.max(), c_nom.max())
    obj = lambda c: float(robust_objective(jnp.asarray(c), alpha=0.34))
    assert obj(c_rob) < obj(c_nom), (obj(c_rob), obj(c_nom))
    assert c_rob.mean() < c_nom.mean(), (c_rob.mean(), c_nom.mean())
    # No assertion on the nominal plant: the robust gains usually pay a price there
    # (13.58 vs 12.92 above), but nominal tuning stops where LM stalls, and one run
    # (the bottom end stop and NaN-safe step control in, fresh clone) found robust-tuned
    # gains better on the nominal plant too (2.32 vs 2.38): a price is not a property.


@pytest.mark.slow
def test_cli_tune_and_control_simulate(tmp_path, fit_dir, posterior_dir):
    """`jaxlift tune --posterior DIR` (no --params: the posterior's calibrated model),
    robust tuning over two posterior draws, report over two more; then `control
    simulate` with the written gains."""
    from jaxlift.cli.main import main

    out = tmp_path / "tune"
    rc = main(
        ["tune", "data/lift_500kg.csv", "--posterior", str(posterior_dir),
         "--time-scale", "0.15", "--steps", "1", "--robust-draws", "2", "--eval-draws", "2",
         "--no-report-noise", "--out", str(out)]
    )  # fmt: skip
    assert rc == 0
    ctrl = load_gains(out / "gains.json")
    assert ctrl.gain_values().keys() == {"P", "I", "D", "N", "K_aw"}
    assert (out / "gains_robust.json").exists() and (out / "gains_nominal.json").exists()
    assert (out / "report.md").exists() and (out / "figures" / "response.png").exists()
    report = (out / "report.md").read_text()
    assert f"posterior samples from {posterior_dir}" in report
    assert str(posterior_dir / "params.json") in report
    summary = json.loads((out / "summary.json").read_text())
    assert summary["robustness"]["n_draws"] == 2
    sim = tmp_path / "sim"
    rc = main(
        ["control", "simulate", "--gains", str(out / "gains.json"), "--params",
         str(fit_dir / "params.json"), "--time-scale", "0.15", "--out", str(sim)]
    )  # fmt: skip
    assert rc == 0
    figs = json.loads((sim / "figures.json").read_text())
    assert figs["tracking_rms_mmps"] > 0
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"P": 20.0, "Q": 1.0}))
    assert main(["control", "simulate", "--gains", str(bad), "--out", str(sim)]) == 2


@pytest.mark.slow
def test_cli_tune_with_a_hand_written_parameter_file(tmp_path):
    """Issue #18: `jaxlift tune LOG --params truth.json` (a file not written by `jaxlift
    fit`) skipped robust tuning and the report. Now the draws come from stated spreads
    (said in the report), robust tuning runs, and the report judges whether it paid.
    Tuned as deployed by default: sampled, with noise (one seed here)."""
    from jaxlift.cli.main import main

    params = tmp_path / "truth.json"
    params.write_text(json.dumps(CALIBRATED))
    out = tmp_path / "tune"
    rc = main(
        ["tune", "data/lift_500kg.csv", "--params", str(params), "--time-scale", "0.15",
         "--steps", "2", "--robust-draws", "2", "--eval-draws", "3", "--noise-seeds", "1",
         "--out", str(out)]
    )  # fmt: skip
    assert rc == 0
    assert (out / "gains_robust.json").exists()
    report = (out / "report.md").read_text()
    assert "stated spreads" in report and "sampled at T_c = 0.01 s" in report
    assert "Does robust tuning pay?" in report
    summary = json.loads((out / "summary.json").read_text())
    assert summary["robustness"]["n_draws"] == 3
    assert any(k.endswith("@ 500 kg") for k in summary["robustness"]["cases"])
    assert "robust_vs_nominal" in summary["robustness"]


def test_robust_gains_recommended_only_where_they_hold_on_held_out_draws():
    from jaxlift.workflows.tune import recommended

    def verdict(*improvements):
        return {"cases": [{"case": f"{m} kg", "improvement": g}
                          for m, g in zip((500, 1500), improvements, strict=False)]}  # fmt: skip

    assert recommended(verdict(0.12, 0.0)) == ("robust-tuned", None)
    name, note = recommended(verdict(0.3, -0.01))
    assert name == "nominal-tuned" and "1500 kg" in note and "500 kg," not in note
    name, note = recommended({"cases": []})
    assert name == "robust-tuned" and "without a held-out" in note


def test_robust_verdict_has_a_one_line_form_for_the_summary():
    from jaxlift.workflows.tune import ROBUST_TARGET, robust_verdict

    def rows(nom_worst, rob_worst):
        return [{"gains": "nominal-tuned", "cost_worst": nom_worst, "cost_median": 1.0},
                {"gains": "robust-tuned", "cost_worst": rob_worst, "cost_median": 1.0}]  # fmt: skip

    v = robust_verdict({"cases": {"500 kg": rows(2.0, 1.9), "1500 kg": rows(3.0, 2.97)}})
    assert len(v["cases"]) == 2 and "\n" not in v["short"]
    assert "at most 5.0 %" in v["short"] and "2 cases" in v["short"]
    assert ("not reached" in v["short"]) == (0.05 < ROBUST_TARGET)
    assert len(v["short"]) < len(v["text"])  # the per-case figures stay in the section
