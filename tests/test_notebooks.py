"""The calibration notebooks run end to end (small budget)."""

import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run_notebook(path: pathlib.Path, tmp_path, monkeypatch):
    jupytext = pytest.importorskip("jupytext")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("JAXLIFT_NOTEBOOK_BUDGET", "small")
    monkeypatch.setenv("JAXLIFT_ROOT", str(ROOT))
    monkeypatch.setenv("JAXLIFT_NOTEBOOK_OUT", str(tmp_path / "out"))
    # no MPLBACKEND: the kernel's own (inline) backend, as in a user's notebook
    monkeypatch.delenv("MPLBACKEND", raising=False)
    nb = jupytext.read(path)
    client = nbclient.NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    return nb, tmp_path / "out"


@pytest.mark.slow
def test_01_fit_and_compare(tmp_path, monkeypatch):
    nb, out = _run_notebook(ROOT / "calibration" / "01_fit_and_compare.py", tmp_path, monkeypatch)
    assert (out / "report.html").exists() and (out / "params.json").exists()
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "chi2/N after the fit" in text
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    # figures inline, and the fit shown as a table (its _repr_html_)
    assert any("image/png" in o.get("data", {}) for o in outputs)
    html = [o["data"]["text/html"] for o in outputs if "text/html" in o.get("data", {})]
    assert any("<b>Fit</b>" in h and "stderr" in h for h in html)
    assert "RMS speed error per log" in text


@pytest.mark.extended
def test_02_find_missing_physics(tmp_path, monkeypatch):
    """The whole iterative diagnosis of the shipped logs (~15 min on 2 cores: not in CI;
    run with ``-m extended``)."""
    nb, out = _run_notebook(
        ROOT / "calibration" / "02_find_missing_physics.py", tmp_path, monkeypatch
    )
    assert (out / "diagnosis.json").exists() and (out / "report.html").exists()
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "verdict:" in text
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    plain = [o["data"].get("text/plain", "") for o in outputs if "data" in o]
    table = next(p for p in plain if "elpd" in p)  # az.compare's table
    first = table.splitlines()[1]
    assert first.startswith("diagnosed"), table  # LOO agrees with the dBIC verdict
