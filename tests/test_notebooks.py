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
    monkeypatch.setenv("MPLBACKEND", "Agg")
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
