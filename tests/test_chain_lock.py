"""The chain's HDF5 file and other processes' locks on it: a chain must not die because
someone opens its file while it runs (a coverage run's chain did, of a script reading its
progress with h5py's default locking)."""

import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import jaxlift as jl
from jaxlift.posterior import sampler


def _hold(path, seconds: float) -> subprocess.Popen:
    """Another process that opens ``path`` with h5py (default locking) for ``seconds``;
    returns once it has the file open."""
    code = textwrap.dedent(f"""
        import sys, time, h5py
        with h5py.File({str(path)!r}, "r"):
            print("open", flush=True)
            time.sleep({seconds})
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "open"
    return proc


def _chain(tmp_path):
    path = tmp_path / "chain.h5"
    backend = sampler._ChainBackend(str(path), name="mcmc")
    backend.reset(4, 2)
    return path, backend


def test_a_write_waits_for_a_reader_and_goes_on(tmp_path):
    path, backend = _chain(tmp_path)
    reader = _hold(path, 1.5)
    t0 = time.perf_counter()
    with backend.open("a") as fh:  # emcee stores each step through this
        fh["mcmc"].attrs["written"] = 1
    waited = time.perf_counter() - t0
    reader.wait(timeout=30)
    assert waited > 0.5  # it did wait: the reader held the lock
    with backend.open() as fh:
        assert fh["mcmc"].attrs["written"] == 1
    assert backend.shape == (4, 2)


def test_a_lock_held_too_long_is_a_named_error(tmp_path, monkeypatch):
    path, backend = _chain(tmp_path)
    monkeypatch.setattr(sampler, "LOCK_WAIT_S", 0.3)
    reader = _hold(path, 5.0)
    try:
        with pytest.raises(jl.ChainFileLocked, match=r"chain\.h5.*locked.*resumes"):
            backend.open("a")
    finally:
        reader.kill()
        reader.wait(timeout=30)
    with backend.open("a") as fh:  # free again: nothing lost
        assert np.asarray(fh["mcmc"]["chain"]).shape == (0, 4, 2)
