"""Strict test configuration: float64 everywhere, warnings from jaxlift are errors,
and no persistent compilation cache (the command line's, docs/data.md): tests that
call the CLI must not read or fill a user's cache, and must measure a cold start."""

import os

import jax
import pytest

os.environ["JAXLIFT_CACHE"] = "off"
jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True)
def _float64_guard():
    assert jax.config.read("jax_enable_x64"), "tests must run in float64"
    yield


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code():
    """Drop JAX's compiled functions after each test module: every model structure and
    log length is compiled anew, and a whole CI run in one process kept them all (it
    ended in a segmentation fault inside XLA's compiler, late in the run)."""
    yield
    jax.clear_caches()
