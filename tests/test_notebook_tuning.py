"""The gain-tuning notebook (studies/gain_tuning.py) runs end to end (small budget)."""

import json
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_gain_tuning_notebook(tmp_path, monkeypatch):
    jupytext = pytest.importorskip("jupytext")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("JAXLIFT_NOTEBOOK_BUDGET", "small")
    monkeypatch.setenv("JAXLIFT_ROOT", str(ROOT))
    monkeypatch.setenv("JAXLIFT_NOTEBOOK_OUT", str(tmp_path / "out"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = jupytext.read(ROOT / "studies" / "gain_tuning.py")
    client = nbclient.NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    out = tmp_path / "out"
    assert (out / "report.html").exists()
    gains = json.loads((out / "gains.json").read_text())
    assert {"P", "I", "D", "N", "K_aw"} <= set(gains)
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "tuned cost" in text and "held-out cost" in text
