"""Compiled programs are released: the suite and long grids rely on it to stay under Linux's
limit of memory mappings per process. The on-disk cache keeps every program, the smallest too."""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm import jaxcache
from roverswarm.jaxcache import CROWDED, memory_mappings, release_compiled_programs


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="counts /proc/self/maps")
def test_released_programs_give_back_their_memory_mappings(monkeypatch):
    release_compiled_programs()
    before = memory_mappings()

    @jax.jit
    def f(x):
        return jnp.sin(x) @ jnp.cos(x).T

    for n in range(2, 42):  # 40 shapes: 40 programs kept alive by the jit cache
        f(jnp.ones((n, 3))).block_until_ready()
    grown = memory_mappings() - before
    assert grown > 100, f"40 programs added only {grown} mappings; the premise of this test no longer holds"
    release_compiled_programs(only_if_crowded=True)  # far from crowded: kept
    assert memory_mappings() - before >= grown * 0.9 and memory_mappings() < CROWDED
    monkeypatch.setattr(jaxcache, "CROWDED", before + grown // 2)  # now crowded: released
    release_compiled_programs(only_if_crowded=True)
    assert memory_mappings() - before < grown / 4


def test_the_disk_cache_keeps_even_the_quickest_program(tmp_path):
    """A one-addition program (compiled in milliseconds) is written to the cache: a warm run
    loads the small programs too instead of compiling them again."""
    script = (
        "import jax, jax.numpy as jnp\n"
        "from roverswarm.jaxcache import enable_compilation_cache\n"
        "enable_compilation_cache()\n"
        "jax.jit(lambda x: x + 1)(jnp.zeros(3)).block_until_ready()\n"
    )
    env = {**os.environ, "ROVERSWARM_JAX_CACHE": str(tmp_path)}
    subprocess.run([sys.executable, "-c", script], env=env, check=True, timeout=120)
    assert any(name.startswith("jit__lambda") for name in os.listdir(tmp_path)), os.listdir(tmp_path)


def _resident_mb() -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) // 1024 for line in status if line.startswith("VmRSS"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status; trims glibc's heap")
def test_released_memory_goes_back_to_the_system():
    """What a process frees in small blocks stays in glibc's heap (resident) until trimmed:
    released programs left a test worker at 2.6 GB instead of 0.4 GB."""
    blocks = [np.ones(8000) for _ in range(4000)]  # 256 MB in 64 kB blocks, below mmap's threshold
    last = blocks.pop()  # kept: the top of the heap stays in use, so freeing does not shrink it
    before = _resident_mb()
    del blocks
    freed = _resident_mb()
    assert before - freed < 64, "freed blocks left the heap untrimmed; the premise of this test no longer holds"
    release_compiled_programs()
    assert freed - _resident_mb() > 192, f"resident {freed} MB before the release, {_resident_mb()} MB after"
    assert last.sum() == 8000
