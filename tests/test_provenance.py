"""Every command's output folder says what made it: ``provenance.json`` with the
command line, package versions, seeds and the SHA-256 of every input file."""

import hashlib
import json

from jaxlift.cli.main import main


def test_simulate_writes_provenance(tmp_path):
    out = tmp_path / "sim" / "run.csv"
    out.parent.mkdir()
    log = "data/lift_500kg.csv"
    assert main(["simulate", log, "--out", str(out)]) == 0
    rec = json.loads((out.parent / "provenance.json").read_text())
    assert rec["command"] == ["jaxlift", "simulate", log, "--out", str(out)]
    assert rec["exit_code"] == 0
    assert rec["versions"]["jaxlift"] and rec["versions"]["jax"] and rec["versions"]["diffrax"]
    digest = hashlib.sha256(open(log, "rb").read()).hexdigest()
    assert rec["inputs"] == [{"path": log, "sha256": digest}]


def test_compilation_cache_folder(monkeypatch, tmp_path):
    from jaxlift.cli.common import cache_dir

    monkeypatch.setenv("JAXLIFT_CACHE", "off")
    assert cache_dir() is None
    monkeypatch.setenv("JAXLIFT_CACHE", str(tmp_path / "c"))
    assert cache_dir() == str(tmp_path / "c")
    monkeypatch.delenv("JAXLIFT_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache_dir() == str(tmp_path / "jaxlift" / "jax")
