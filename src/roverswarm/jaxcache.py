"""JAX's compiled programs: the persistent cache shared by the CLI and the tests, the traced
programs kept beside it, and their release.

JAX compiles once per new shape and configuration; caching compiled programs on disk makes
the second run of a command (or of the test suite) skip most compilation. What the cache
cannot skip is tracing the Python function and lowering it to the StableHLO that keys it:
seconds for a training chunk, in every new process. :func:`stored_jit` keeps that traced
program too (``jax.export``), so a new process reads it instead.
"""

from __future__ import annotations

import ctypes
import functools
import gc
import hashlib
import importlib.metadata
import inspect
import os
import pickle
import shutil
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

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
    for stored in _STORED:
        stored._programs.clear()
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


STORE = "exported"
"""The folder of :func:`stored_jit`'s programs inside the compilation cache's directory (JAX's
cache reads only its own files there)."""

_SWITCHES = (
    "jax_enable_x64",
    "jax_default_matmul_precision",
    "jax_default_prng_impl",
    "jax_threefry_partitionable",
    "jax_numpy_rank_promotion",
    "jax_numpy_dtype_promotion",
)
"""JAX's settings that change what a function traces to."""


@functools.lru_cache(maxsize=1)
def _fingerprint() -> str:
    """What besides its arguments decides the program a function traces to: this package's
    source, the traced libraries' versions, the backend and JAX's numerics settings."""
    source = hashlib.sha256()
    package = Path(__file__).parent
    for path in sorted(package.rglob("*.py")):
        source.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    versions = [f"{name} {importlib.metadata.version(name)}" for name in ("jax", "jaxlib", "flax", "optax", "numpy")]
    switches = [f"{name} {getattr(jax.config, name)}" for name in _SWITCHES]
    return "\n".join([source.hexdigest(), *versions, jax.default_backend(), *switches])


def stable_name(static: Any) -> str | None:
    """Text naming ``static`` that is the same in every process, or None: a function that names
    itself (its ``stored_name``: a closure built from what the text says), a module-level
    function by its module and name, anything else by its ``repr`` unless that holds an
    address (a lambda, a closure, a bound method, an object without a ``repr`` of its own)."""
    named = getattr(static, "stored_name", None)
    if named is not None:
        return named
    name = getattr(static, "__qualname__", "")
    plain = callable(static) and not inspect.ismethod(static) and getattr(static, "__closure__", None) is None
    if plain and name and "<" not in name:
        return f"{static.__module__}.{name}"
    text = repr(static)
    return None if " at 0x" in text else text


class StoredJit:
    """A function of :func:`stored_jit`: call it as the jitted function."""

    def __init__(self, fun: Callable, static_argnums: tuple[int, ...], donate_argnums: tuple[int, ...]):
        functools.update_wrapper(self, fun)
        self.static_argnums, self.donate_argnums = static_argnums, donate_argnums
        self._programs: dict[Hashable, Callable[[list], Any]] = {}
        _STORED.append(self)

    def __call__(self, *args):
        static = tuple(args[i] for i in self.static_argnums)
        dynamic = [a for i, a in enumerate(args) if i not in self.static_argnums]
        leaves, tree = jax.tree.flatten(dynamic)
        key = (static, tree, tuple(jax.typeof(leaf) for leaf in leaves))
        if key not in self._programs:
            self._programs[key] = self._program(static, tree, leaves)
        return self._programs[key](leaves)

    def _cache_size(self) -> int:
        """Programs held in this process (as a jitted function's ``_cache_size``)."""
        return len(self._programs)

    def _program(self, static: tuple, tree: Any, leaves: list) -> Callable[[list], Any]:
        """The compiled call (flat arguments -> the function's result), read from the store or
        traced, exported and written there; a function JAX cannot export (a host callback, say)
        is jitted as it is."""
        named = [stable_name(self.__wrapped__), *map(stable_name, static)]
        text = "\n".join(map(str, [*named, tree, *map(jax.typeof, leaves), _fingerprint()]))
        stable = None not in named and " at 0x" not in text
        path = _store_path(hashlib.sha256(text.encode()).hexdigest()) if stable else None
        donated = self._donated_leaves(tree)

        def flat(*flat_leaves):
            dynamic = jax.tree.unflatten(tree, flat_leaves)
            given, rest = iter(static), iter(dynamic)
            places = range(len(static) + len(dynamic))
            return self.__wrapped__(*(next(given) if i in self.static_argnums else next(rest) for i in places))

        found = _read(path)
        if found is None:
            out_trees = []

            def flat_out(*flat_leaves):
                out_leaves, out_tree = jax.tree.flatten(flat(*flat_leaves))
                out_trees.append(out_tree)
                return out_leaves

            try:
                serialized = jax.export.export(jax.jit(flat_out))(*leaves).serialize()
            except Exception:  # not exportable: compiled as it is, never stored
                plain = jax.jit(flat, donate_argnums=donated)
                return lambda flat_leaves: plain(*flat_leaves)
            _write(path, serialized, out_trees[0])
            # run as read back: the program a later process reads, compiled once for both
            found = jax.export.deserialize(serialized), out_trees[0]
        exported, out_tree = found
        call = jax.jit(exported.call, donate_argnums=donated)
        return lambda flat_leaves: jax.tree.unflatten(out_tree, call(*flat_leaves))

    def _donated_leaves(self, tree: Any) -> tuple[int, ...]:
        """The flat positions of the donated arguments' leaves (``tree``: of the non-static arguments)."""
        counts = [child.num_leaves for child in tree.children()]
        places = [i for i in range(len(counts) + len(self.static_argnums)) if i not in self.static_argnums]
        donated, start = [], 0
        for place, count in zip(places, counts):
            if place in self.donate_argnums:
                donated.extend(range(start, start + count))
            start += count
        return tuple(donated)


_STORED: list[StoredJit] = []
"""Every :class:`StoredJit`: :func:`release_compiled_programs` lets go of their programs."""


def stored_jit(
    fun: Callable | None = None, *, static_argnums: tuple[int, ...] = (), donate_argnums: tuple[int, ...] = ()
):
    """``jax.jit(fun, static_argnums, donate_argnums)`` whose traced programs are kept on disk
    (``jax.export``, beside the compilation cache): a new process reads a program it has
    traced before instead of tracing and lowering it again (a training chunk: about 4 s), and
    the compilation cache then finds it compiled. Every call runs the exported program as the
    store holds it (serialised and read back even when just traced), so the numbers never
    depend on what the store held, and one compiled program serves both. A program is found
    again only for the same function, static arguments (compared by ``repr``; functions by
    name), argument shapes and types, package source, library versions and JAX settings.
    Decorator: ``@stored_jit(static_argnums=(0,))``."""
    if fun is None:
        return functools.partial(stored_jit, static_argnums=static_argnums, donate_argnums=donate_argnums)
    return StoredJit(fun, static_argnums, donate_argnums)


def _store_dir() -> Path | None:
    """The folder of the stored programs (None when the compilation cache is off)."""
    directory = jax.config.jax_compilation_cache_dir
    return Path(directory) / STORE if directory else None


KEEP_VERSIONS = 4
"""Source versions (:func:`_fingerprint`) whose stored programs are kept, the most recently
used: each version's programs are a folder of their own, about 13 MB after a test suite, read
by no other version."""


def _store_path(digest: str) -> Path | None:
    """Where the program of ``digest`` is kept (None: nowhere): in this source version's folder."""
    directory = _store_dir()
    return None if directory is None else _version_dir(directory, _fingerprint()) / f"{digest}.program"


@functools.lru_cache(maxsize=None)
def _version_dir(store: Path, fingerprint: str) -> Path:
    """The folder of ``fingerprint``'s programs in ``store``, once per process: marked as used
    now, and the folders of all but the :data:`KEEP_VERSIONS` most recently used versions
    removed, with the programs of the store's first layout (files at its top, session 72). A
    store that cannot be written stops nothing (:func:`_write` then keeps nothing); a program
    another process reads from a folder removed at that moment is traced again (:func:`_read`)."""
    folder = store / hashlib.sha256(fingerprint.encode()).hexdigest()[:16]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)
        versions = sorted((p for p in store.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime, reverse=True)
        stale = [p for p in versions[KEEP_VERSIONS:] if p != folder]
        for path in stale:
            shutil.rmtree(path, ignore_errors=True)
        for path in store.glob("*.program"):
            path.unlink(missing_ok=True)
    except OSError:
        pass
    return folder


def _read(path: Path | None) -> tuple[jax.export.Exported, Any] | None:
    """The stored (exported program, result tree) at ``path``, or None (none there, or unreadable)."""
    if path is None or not path.exists():
        return None
    try:
        serialized, out_tree = pickle.loads(path.read_bytes())
        return jax.export.deserialize(bytearray(serialized)), out_tree
    except Exception:  # written by another version, or cut short: traced again and rewritten
        return None


def _write(path: Path | None, serialized: bytearray, out_tree: Any) -> None:
    """Keep the program at ``path``, atomically (another process may read or write it at once);
    a store that cannot be written (read-only, full) keeps nothing and stops nothing. Not
    :func:`roverswarm.storage.atomic_write`: its one temporary name per path would be shared by
    two processes storing the same program at once, and its failure is the user's error."""
    if path is None:
        return
    partial = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial.write_bytes(pickle.dumps((bytes(serialized), out_tree)))
        os.replace(partial, path)
    except OSError:
        if partial.exists():
            partial.unlink()
