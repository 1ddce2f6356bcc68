"""The posterior notebook runs end to end (small budget: a short chain)."""

import pytest
from test_notebooks import ROOT, _run_notebook


@pytest.mark.slow
def test_03_posterior(tmp_path, monkeypatch):
    nb, out = _run_notebook(ROOT / "calibration" / "03_posterior.py", tmp_path, monkeypatch)
    for f in ("report.html", "report.md", "chain.h5", "posterior.nc", "params.json"):
        assert (out / f).exists(), f
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "gas by volume" in text and "converged: False after 30 steps" in text
    # the result object shows as a table, and carries the DataTree for ArviZ
    html = "".join(o.get("data", {}).get("text/html", "") for c in nb.cells
                   if c.cell_type == "code" for o in c.get("outputs", []))  # fmt: skip
    assert "<table" in html and "beta" in html
    for group in ("log_likelihood", "observed_data", "posterior", "posterior_predictive", "prior"):
        assert group in text.split("DataTree groups:")[1].splitlines()[0], group
