"""JAX's compiled programs: the persistent cache shared by the CLI and the tests, and their release.

JAX compiles once per new shape and configuration; caching compiled programs on disk makes
the second run of a command (or of the test suite) skip most compilation.
"""

from __future__ import annotations

import ctypes
import functools
import gc
import os
from pathlib import Path

import jax


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on the on-disk cache at ``path`` (default ``$ROVERSWARM_JAX_CACHE`` or
    ``~/.cache/roverswarm/jax``). Returns the directory used; ``ROVERSWARM_JAX_CACHE=off``
    leaves the cache off (and returns None)."""
    if os.environ.get("ROVERSWARM_JAX_CACHE") == "off":
        return None
    directory = Path(path or os.environ.get("ROVERSWARM_JAX_CACHE") or Path.home() / ".cache" / "roverswarm" / "jax")
    directory.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    # every program, however quick to compile: the many small ones (eager operations, a
    # reset) were most of what a warm test suite still compiled; kept, they halved a warm
    # run of three test modules (79 s -> 40 s) for 11 MB of cache instead of 4
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return directory


CROWDED = 20_000
"""Memory mappings past which long commands release their compiled programs (Linux allows 65,530)."""


def memory_mappings() -> int:
    """Memory mappings this process holds (0 where ``/proc/self/maps`` does not exist)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


def release_compiled_programs(only_if_crowded: bool = False) -> None:
    """Drop every program JAX holds in memory (they are recompiled, or read from the on-disk
    cache, when next needed); with ``only_if_crowded``, only past :data:`CROWDED` mappings.

    Each compiled CPU program keeps about ten memory mappings for its code until it is
    released, and JAX keeps every program of a jitted function alive. A process that compiles
    thousands of them (a long grid or sweep, the test suite) reaches Linux's limit of 65,530
    mappings (``vm.max_map_count``), and the next compilation crashes with a segfault. Grids
    and sweeps release them after every run (``reproduce`` also after every run's evaluation;
    with ``--keep-programs``, and in a grid of runs under 5000 episodes, only when crowded:
    short runs would spend much of their time loading their programs again); the tests check
    after each module and release only when crowded.

    The memory the programs held goes back to the system (:func:`return_free_memory`)."""
    if only_if_crowded and memory_mappings() < CROWDED:
        return
    jax.clear_caches()
    gc.collect()
    return_free_memory()


@functools.lru_cache(maxsize=1)
def _glibc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc (macOS, musl): its allocator is left as it is
        return None


def return_free_memory() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``; nothing
    elsewhere). glibc keeps what a process frees in its arenas: a test worker held 2.6 GB after
    ``test_maddpg_update.py`` with its programs released, 0.4 GB once trimmed, and every
    ``fork`` of the worker copied the page tables of the rest."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)
