"""Strict test configuration: float64 everywhere, warnings from jaxlift are errors, and
a persistent compilation cache private to the test session.

The cache (JAX's, as the command line uses it: docs/data.md) lives in a fresh temporary
folder made when the session starts and removed when it ends, so every run starts cold
and never reads or fills a user's cache (``~/.cache/jaxlift``). Within the session it is
shared by the pytest-xdist workers and by the command-line subprocesses the tests start
(both inherit ``JAXLIFT_TEST_CACHE`` and ``JAXLIFT_CACHE``): a model structure compiled
by one test module is loaded, not compiled again, by the next, after
``jax.clear_caches()`` (below) and in another process. ``JAXLIFT_TEST_CACHE=off`` runs
without it; ``JAXLIFT_TEST_CACHE=DIR`` keeps it in ``DIR`` (kept after the run: a
developer's loop can reuse it; a cached compilation gives the same numbers).
"""

import os
import shutil
import tempfile

import jax
import pytest

from jaxlift.cli.common import setup_jax

_OWNER = "_JAXLIFT_TEST_CACHE_OWNER"  # pid of the process that made the folder


def _session_cache() -> str:
    """The cache folder of this test session ("off": none). Made by the first process
    that imports this file (pytest's controller), inherited by its workers."""
    where = os.environ.get("JAXLIFT_TEST_CACHE", "").strip()
    if not where:
        where = tempfile.mkdtemp(prefix="jaxlift-test-cache-")
        os.environ["JAXLIFT_TEST_CACHE"] = where
        os.environ[_OWNER] = str(os.getpid())
    return where


os.environ["JAXLIFT_CACHE"] = _session_cache()
setup_jax()  # float64 and the cache folder, exactly as the command line sets them up


def pytest_sessionfinish(session, exitstatus):
    if os.environ.get(_OWNER) == str(os.getpid()):  # the controller, not a worker
        shutil.rmtree(os.environ["JAXLIFT_TEST_CACHE"], ignore_errors=True)


@pytest.fixture(autouse=True)
def _float64_guard():
    assert jax.config.read("jax_enable_x64"), "tests must run in float64"
    yield


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code():
    """Drop JAX's compiled functions after each test module: every model structure and
    log length is compiled anew, and a whole CI run in one process kept them all (it
    ended in a segmentation fault inside XLA's compiler, late in the run). With the
    session's cache, a structure seen before is loaded from disk instead."""
    yield
    jax.clear_caches()
