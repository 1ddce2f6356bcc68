"""Strict test configuration: float64 everywhere, warnings from jaxlift are errors."""

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True)
def _float64_guard():
    assert jax.config.read("jax_enable_x64"), "tests must run in float64"
    yield
