"""A user's own effect, in their own file (``--effect-file``), from Python
(``register_effect``) or from an installed package (entry points ``jaxlift.effects``):
registered with checks that name what is wrong, then simulated, fitted, sampled, tuned
and diagnosed like the built-in eight."""

import json
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import jaxlift as jl
from jaxlift.cli.main import main
from jaxlift.model.effects import BUILT_IN, EFFECTS
from jaxlift.model.sequences import ramped_sequence

#: A turbulent (quadratic) loss, felt by the fork as a drag ``c_q v |v|``: an effect
#: that is not among the eight, written as a user would.
DRAG_FILE = '''
"""A turbulent flow loss in the lift line, felt on the fork as a quadratic drag."""
from typing import ClassVar

import jax
import jax.numpy as jnp

import jaxlift as jl


class TurbulentDrag(jl.AbstractStatelessEffect):
    c_q: jax.Array = jl.param(
        0.0, "N s^2/m^2", 0.0, 1e8, "quadratic drag coefficient", nesting=0.0,
        scale=1e4, typical=(1e3, 1e6),
        typical_why="a narrow fitting: 10 N to 10 kN at 0.1 m/s",
    )
    name: ClassVar[str] = "turbulent_drag"

    def extra_friction(self, plant, z, sig):
        return self.c_q * sig.v * jnp.abs(sig.v)
'''

TRUTH = dict(k1=1.95, k2=1.9, k3=1.75, z1=-2.8, z2=-3.2, z3=-4.4, beta=0.7e9, d=320.0)
DRAG = 4e5  # N s^2/m^2: 4 kN at 0.1 m/s, 1 kN at 0.05 m/s


@pytest.fixture(autouse=True)
def _registry():
    """Every test leaves the registry as it found it (the built-in eight)."""
    before = dict(EFFECTS)
    yield
    EFFECTS.clear()
    EFFECTS.update(before)


@pytest.fixture
def drag_file(tmp_path):
    path = tmp_path / "turbulent_drag.py"
    path.write_text(DRAG_FILE)
    return path


def _log(path, load, seed, c_q=DRAG, x0=0.0, sections=None):
    """A log with the drag hidden (``c_q``), written to ``path``."""
    sections = sections or [(0.0, 2.0), (0.55, 6.0), (0.3, 6.0), (0.0, 3.0), (0.7, 6.0),
                            (0.25, 7.0), (0.0, 4.0)]  # fmt: skip
    ts, pwm = ramped_sequence(sections, ramp_s=0.5)
    effs = jl.make_effects("turbulent_drag")
    plant, effs = jl.with_params(jl.Plant(), effs, {**TRUTH, "c_q": c_q})
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, load), x0)
    sol = jl.simulate(plant, effs, inputs, rtol=1e-8, atol=(1e-9, 1e-9, 1e-2))
    assert bool(sol.ok)
    log = jl.to_log(sol, inputs, jl.MeasurementModel(), jax.random.key(seed), name=path.stem)
    jl.write_log(path, log)
    return str(path)


def test_effect_file_registers_and_simulates(drag_file):
    assert jl.load_effect_file(drag_file) == ["turbulent_drag"]
    assert list(EFFECTS)[-1] == "turbulent_drag"  # after the eight
    assert jl.load_effect_file(drag_file) == ["turbulent_drag"]  # loading again is fine
    infos = jl.all_param_infos(["turbulent_drag"])
    assert infos["c_q"].unit == "N s^2/m^2" and infos["c_q"].typical == (1e3, 1e6)
    ts, pwm = ramped_sequence([(0.0, 1.0), (0.6, 5.0)])
    inputs = jl.Inputs.from_arrays(ts, pwm, np.full_like(ts, 800.0), 0.5)
    base = jl.simulate(jl.Plant(), (), inputs)
    off = jl.simulate(jl.Plant(), jl.make_effects("turbulent_drag"), inputs)
    on = jl.simulate(jl.Plant(), jl.make_effects("turbulent_drag", {"c_q": 1e6}), inputs)
    np.testing.assert_allclose(np.asarray(off.ys), np.asarray(base.ys), rtol=1e-12)  # nesting
    assert float(np.max(on.pressure)) > float(np.max(base.pressure)) + 1e4 / jl.Plant().A1


def test_register_effect_from_python():
    from typing import ClassVar

    class Chain(jl.AbstractStatelessEffect):
        slack: jax.Array = jl.param(
            0.0, "N", 0.0, 1e4, "chain slack force", nesting=0.0, scale=10.0, typical=(1, 1e3)
        )
        name: ClassVar[str] = "chain_slack"

    assert jl.register_effect(Chain) is Chain and "chain_slack" in EFFECTS
    jl.unregister_effect("chain_slack")
    assert "chain_slack" not in EFFECTS
    with pytest.raises(jl.ParameterError, match="built in"):
        jl.unregister_effect("leakage")


def _edit(old: str, new: str) -> str:
    assert old in DRAG_FILE
    return DRAG_FILE.replace(old, new)


#: effect files with one thing wrong -> the message that must name it
BAD = {
    "syntax": ("x = (\n", r"line \d+: importing it failed: SyntaxError"),
    "nothing": ("import jaxlift\n", "defines no concrete subclass"),
    "taken name": (_edit('"turbulent_drag"', '"leakage"'), "'leakage' is taken"),
    "taken parameter": (_edit("c_q", "beta"), "'beta' is already a parameter of the plant"),
    "no range": (_edit("typical=(1e3, 1e6),", ""), "'c_q' has a nesting value but no typical"),
    "range out of bounds": (_edit("(1e3, 1e6)", "(1e3, 1e9)"), "inside its bounds"),
    "on by default": (_edit('0.0, "N s^2/m^2"', '5.0, "N s^2/m^2"'), "defaults must switch"),
    "no switch": (_edit("nesting=0.0,", ""), "no parameter has a nesting value"),
    "no name": (_edit('name: ClassVar[str] = "turbulent_drag"', ""), r"\['name'\] not set"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_effect_files_are_refused_with_the_reason(tmp_path, case):
    text, message = BAD[case]
    path = tmp_path / "mine.py"
    path.write_text(textwrap.dedent(text))
    with pytest.raises(jl.ParameterError, match=message) as info:
        jl.load_effect_file(path)
    assert str(path) in str(info.value)
    assert list(EFFECTS) == [c.name for c in BUILT_IN]  # nothing registered


def test_missing_effect_file_is_a_cli_error(tmp_path, capsys):
    rc = main(["simulate", "data/lift_500kg.csv", "--out", str(tmp_path / "s.csv"),
               "--effect-file", str(tmp_path / "nope.py")])  # fmt: skip
    assert rc == 2
    assert "nope.py: no such file" in capsys.readouterr().err


def test_entry_point_effects(tmp_path, monkeypatch):
    """An installed package declaring ``[project.entry-points."jaxlift.effects"]``."""
    (tmp_path / "mydrag.py").write_text(DRAG_FILE)
    dist = tmp_path / "mydrag-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: mydrag\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[jaxlift.effects]\ndrag = mydrag:TurbulentDrag\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert jl.load_entry_point_effects() == ["turbulent_drag"]
    assert "turbulent_drag" in EFFECTS
    (dist / "entry_points.txt").write_text("[jaxlift.effects]\nbroken = mydrag:Missing\n")
    with pytest.raises(jl.ParameterError, match="broken = mydrag:Missing.*package mydrag"):
        jl.load_entry_point_effects()


@pytest.mark.slow
def test_user_effect_in_simulate_fit_posterior_and_tune(drag_file, tmp_path, capsys):
    """Every command takes ``--effect-file``; the fit recovers the hidden drag (from
    nominal values), and the posterior and the tuning run on the model with it."""
    jl.load_effect_file(drag_file)
    logs = [_log(tmp_path / f"drag_{m:.0f}kg.csv", m, s) for m, s in ((600.0, 1), (1400.0, 2))]
    ef = ["--effect-file", str(drag_file)]
    EFFECTS.pop("turbulent_drag")  # the commands must load it themselves

    fit_dir = tmp_path / "fit"
    rc = main(["fit", *logs, "--effects", "turbulent_drag", "--starts", "2", "--out",
               str(fit_dir), *ef])  # fmt: skip
    assert rc == 0, capsys.readouterr().out
    params = json.loads((fit_dir / "params.json").read_text())
    stderr = json.loads((fit_dir / "metrics.json").read_text())["stderr"]["c_q"]
    assert abs(params["c_q"] - DRAG) < 4 * stderr and stderr < 0.3 * DRAG, (params["c_q"], stderr)

    rc = main(["simulate", logs[0], "--params", str(fit_dir / "params.json"), "--out",
               str(tmp_path / "sim.csv"), *ef])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0 and "turbulent_drag" in out

    post = tmp_path / "post"
    rc = main(["posterior", logs[0], "--params", str(fit_dir / "params.json"), "--walkers", "16",
               "--max-steps", "20", "--predictive", "4", "--out", str(post), *ef])  # fmt: skip
    assert rc in (0, 1)  # 1: not converged in 20 steps, which it says
    samples = json.loads((post / "posterior.json").read_text())
    assert "c_q" in json.dumps(samples)

    tune = tmp_path / "tune"
    rc = main(["tune", logs[1], "--params", str(fit_dir / "params.json"), "--time-scale", "0.15",
               "--steps", "1", "--robust-draws", "2", "--eval-draws", "2",
               "--no-report-noise", "--out", str(tune), *ef])  # fmt: skip
    assert rc == 0
    assert "turbulent_drag" in (tune / "report.md").read_text()


@pytest.mark.slow
def test_user_effect_is_diagnosed_like_the_built_in_ones(drag_file, tmp_path):
    """Hidden in logs that start on the bottom stop, diagnosed from nominal values by
    the CLI with the effect file: the verdict names it."""
    jl.load_effect_file(drag_file)  # to make the logs
    logs = [_log(tmp_path / f"d_{m:.0f}kg.csv", m, s, x0=0.0) for m, s in ((500.0, 3), (1600.0, 4))]
    held = _log(tmp_path / "held.csv", 1000.0, 5, x0=0.0)
    EFFECTS.pop("turbulent_drag")  # the command must load it itself
    out = tmp_path / "diag"
    # in its own process, as a user runs it (and without the test session's memory)
    argv = ["diagnose", *logs, "--validate", held, "--once", "--out", str(out),
            "--effect-file", str(drag_file)]  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "jaxlift", *argv], capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    d = json.loads((out / "diagnosis.json").read_text())
    ranking = [(r["effect"], r["delta_bic"]) for r in d["steps"][0]["ranking"]]
    assert d["verdict"] == "turbulent_drag", ranking
    top = d["steps"][0]["ranking"][0]
    # the held-out model error (chi2/N above the noise floor of 1) falls by 80 % or more
    before, after = top["heldout_chi2_before"] - 1, top["heldout_chi2_after"] - 1
    assert after <= 0.2 * before, (before, after)
    assert abs(top["fitted_params"]["c_q"] / DRAG - 1) < 0.2


@pytest.mark.slow  # fast loop: over ~15 s alone (measured 2026-12-03)
def test_a_parameter_pushed_past_its_upper_bound_is_held_there(drag_file, tmp_path, monkeypatch):
    """A ``log`` transform keeps a parameter above its lower bound only; the fit must
    hold one that the data push past its upper bound at that bound, refit the rest, say
    so, and write a parameter file that loads again (measured before: a stick-slip fit
    wrote v_s = 12.8 m/s, bound 0.2 m/s, and ``posterior --params`` refused the file)."""
    from typing import ClassVar

    import jax.numpy as jnp

    import jaxlift.calibrate.fit as fit_module

    jl.load_effect_file(drag_file)
    log = jl.read_log(_log(tmp_path / "drag.csv", 600.0, seed=3))  # hidden drag 4e5

    class CappedDrag(jl.AbstractStatelessEffect):
        """The same drag law, but its coefficient may not exceed 1e5 (a quarter of the
        truth): the data push it to the bound."""

        c_cap: jax.Array = jl.param(
            0.0, "N s^2/m^2", 0.0, 1e5, "capped quadratic drag", nesting=0.0, scale=1e4,
            typical=(1e3, 1e5),
        )  # fmt: skip
        name: ClassVar[str] = "capped_drag"

        def extra_friction(self, plant, z, sig):
            return self.c_cap * sig.v * jnp.abs(sig.v)

    jl.register_effect(CappedDrag)
    kw = dict(
        effects=["capped_drag"], free=["c_cap", "d"], init={**TRUTH, "c_cap": 1e4}, n_starts=1
    )
    res = jl.fit([log], **kw)
    upper = 1e5
    assert upper * (1 - 1e-6) < res.params["c_cap"] <= upper
    assert "held at its upper bound" in res.undetermined["c_cap"]
    assert res.stages[-1].chi2 / res.n_residuals < 1e3 and np.isfinite(res.params["d"])
    path = tmp_path / "fitted.json"
    jl.save_params_json(path, res.params)
    assert jl.load_params_json(path, jl.all_param_infos(["capped_drag"]))["c_cap"] <= upper
    # without the hold, the same fit leaves the bound (so the test above can fail)
    monkeypatch.setattr(fit_module, "_hold_at_upper_bounds", lambda problem, run, *a: run)
    assert jl.fit([log], **kw).params["c_cap"] > upper
