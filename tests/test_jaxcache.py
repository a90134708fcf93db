"""Compiled programs are released: the suite and long grids rely on it to stay under Linux's
limit of memory mappings per process."""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import pytest

from roverswarm.jaxcache import release_compiled_programs


def _mappings() -> int:
    with open("/proc/self/maps") as f:
        return sum(1 for _ in f)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="counts /proc/self/maps")
def test_released_programs_give_back_their_memory_mappings():
    release_compiled_programs()
    before = _mappings()

    @jax.jit
    def f(x):
        return jnp.sin(x) @ jnp.cos(x).T

    for n in range(2, 42):  # 40 shapes: 40 programs kept alive by the jit cache
        f(jnp.ones((n, 3))).block_until_ready()
    grown = _mappings() - before
    assert grown > 100, f"40 programs added only {grown} mappings; the premise of this test no longer holds"
    release_compiled_programs()
    assert _mappings() - before < grown / 4
