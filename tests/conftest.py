"""Shared test setup: JAX's persistent compilation cache and small shared configurations."""

from __future__ import annotations

import pytest

from roverswarm.jaxcache import enable_compilation_cache

enable_compilation_cache()


@pytest.fixture(scope="session")
def paper3():
    from roverswarm.env import get_scenario

    return get_scenario("paper-3")
