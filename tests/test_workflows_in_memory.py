"""A notebook can go from logs to the workflows' objects without naming a folder:
``out_dir=None`` writes into a temporary folder that is removed with the result
(issue 15)."""

import gc
import pathlib

import pytest
from helpers import head

import jaxlift as jl

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_posterior_without_a_folder():
    # the first 25 s of a shipped log (the folder's lifetime does not need the whole
    # run: the whole log took ~250 s here)
    logs = [head(jl.read_log(ROOT / "data" / "lift_500kg.csv"), 2500)]
    truth = jl.load_params_json(ROOT / "data" / "truth.json", jl.all_param_infos("all"))
    params = {k: v for k, v in truth.items() if k in jl.all_param_infos(())}
    res = jl.run_posterior(logs, params=params, n_walkers=16, max_steps=40, chunk=20,
                           n_predictive=4, n_loglik=8, conditioning="conditional")  # fmt: skip
    folder = res.out_dir
    assert folder.is_dir() and folder.name.startswith("jaxlift-posterior-")
    tree = res.datatree
    assert {"posterior", "observed_data", "log_likelihood"} <= set(tree.children)
    assert "beta" in res.table().index
    del res
    gc.collect()
    assert not folder.exists()  # removed with the result
    assert tree["posterior"]["beta"].size > 0  # the loaded tree outlives the folder
