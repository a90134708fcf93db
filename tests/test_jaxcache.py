"""Compiled programs are released: the suite and long grids rely on it to stay under Linux's
limit of memory mappings per process. The on-disk cache keeps every program, the smallest too."""

from __future__ import annotations

import dataclasses
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


@dataclasses.dataclass(frozen=True)
class Scale:
    """A static argument: a frozen dataclass, as the learner families' configs are."""

    factor: float

    def times(self, x: jax.Array) -> jax.Array:
        return x * self.factor


def apply(f, x: jax.Array) -> jax.Array:
    return f(x)


TRACED: list[Scale] = []
"""Every trace of :func:`scaled_sum` (by its static argument)."""


def scaled_sum(scale: Scale, tree: dict, bias: jax.Array):
    TRACED.append(scale)
    total = jnp.sin(tree["x"]).sum() * scale.factor + bias
    return {"total": total, "pair": (tree["x"] * 2, None), "y": tree["y"] + 1}


STORED = jaxcache.stored_jit(scaled_sum, static_argnums=(0,), donate_argnums=(1,))


def _args():
    return {"x": jnp.linspace(0.0, 3.0, 7), "y": jnp.arange(4)}, jnp.float32(0.5)


@pytest.fixture
def store(tmp_path, monkeypatch):
    """The store in a folder of this test's own, empty, and no program of :data:`STORED` in memory."""
    monkeypatch.setattr(jaxcache, "_store_dir", lambda: tmp_path)
    STORED._programs.clear()
    TRACED.clear()
    yield tmp_path
    STORED._programs.clear()


def _programs(store) -> list:
    """The programs kept in ``store``, of every source version."""
    return sorted(store.rglob("*.program"))


def _equal(a, b) -> bool:
    return jax.tree.structure(a) == jax.tree.structure(b) and all(
        np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))
    )


def test_a_stored_program_gives_jax_jits_numbers_and_a_new_process_reads_it_without_tracing(store):
    """The result of ``jax.jit`` (its tree, its bits); donated arguments are consumed as jit
    consumes them; after the programs in memory are released (as in a new process) the
    function is not traced again, and another static argument is traced and stored apart."""
    expected = jax.jit(scaled_sum, static_argnums=(0,))(Scale(1.5), *_args())
    TRACED.clear()
    tree, bias = _args()
    assert _equal(STORED(Scale(1.5), tree, bias), expected)
    assert tree["x"].is_deleted() and not bias.is_deleted()
    assert TRACED == [Scale(1.5)] and len(_programs(store)) == 1
    release_compiled_programs()
    assert _equal(STORED(Scale(1.5), *_args()), expected) and TRACED == [Scale(1.5)]
    STORED(Scale(2.0), *_args())
    assert TRACED == [Scale(1.5), Scale(2.0)] and len(_programs(store)) == 2


def test_a_program_of_other_source_or_an_unreadable_one_is_traced_again(store, monkeypatch):
    expected = STORED(Scale(1.5), *_args())
    (path,) = _programs(store)
    path.write_bytes(path.read_bytes()[:100])  # cut short
    STORED._programs.clear()
    assert _equal(STORED(Scale(1.5), *_args()), expected) and len(TRACED) == 2
    assert path.stat().st_size > 100  # written again, whole
    monkeypatch.setattr(jaxcache, "_fingerprint", lambda: "another version of the package")
    STORED._programs.clear()
    assert _equal(STORED(Scale(1.5), *_args()), expected) and len(TRACED) == 3
    assert len(_programs(store)) == 2


def test_the_store_keeps_the_programs_of_the_most_recently_used_source_versions(store):
    """Each source version's programs are a folder of their own; the first program a process
    keeps marks its version's folder as used and removes all but the KEEP_VERSIONS most
    recently used, and the programs of the store's first layout (files at its top)."""
    (store / "first-layout.program").write_bytes(b"read by no version")
    older = [store / f"version-{age}" for age in range(jaxcache.KEEP_VERSIONS + 2)]
    for age, folder in enumerate(older):  # version-0 used last
        folder.mkdir()
        (folder / "kept.program").write_bytes(b"a program")
        os.utime(folder, (1e9 - age, 1e9 - age))
    STORED(Scale(1.5), *_args())
    kept = sorted(p.name for p in store.iterdir())
    (current,) = set(kept) - {folder.name for folder in older}
    assert kept == sorted([current, *(f"version-{age}" for age in range(jaxcache.KEEP_VERSIONS - 1))])
    assert [p.parent.name for p in _programs(store)].count(current) == 1


HOST_CALLS: list[int] = []


def doubled_on_the_host(x: jax.Array) -> jax.Array:
    def double(v):
        HOST_CALLS.append(v.size)
        return v * 2

    return jax.pure_callback(double, jax.ShapeDtypeStruct(x.shape, x.dtype), x)


def test_what_cannot_be_stored_is_jitted_as_it_is(store, monkeypatch):
    """A closure as the static argument (no name that is the same in every process), a host
    callback (JAX does not export it), no store (the compilation cache off): the numbers of
    ``jax.jit``, nothing written."""
    stored = jaxcache.stored_jit(lambda f, x: f(x) + 1, static_argnums=(0,))
    offset = 3.0
    assert float(stored(lambda x: x * offset, jnp.float32(2.0))) == 7.0
    assert _programs(store) == []
    # bound methods: named by their repr, which holds their object's (a qualified name alone
    # gave both the first's program)
    applied = jaxcache.stored_jit(apply, static_argnums=(0,))
    assert [float(applied(Scale(k).times, jnp.float32(2.0))) for k in (2.0, 5.0)] == [4.0, 10.0]
    assert len(_programs(store)) == 2
    HOST_CALLS.clear()
    assert np.array_equal(jaxcache.stored_jit(doubled_on_the_host)(jnp.arange(3.0)), [0.0, 2.0, 4.0])
    assert HOST_CALLS == [3]
    monkeypatch.setattr(jaxcache, "_store_dir", lambda: None)
    assert _equal(STORED(Scale(3.0), *_args()), jax.jit(scaled_sum, static_argnums=(0,))(Scale(3.0), *_args()))
    assert len(_programs(store)) == 2


def test_a_store_that_cannot_be_written_keeps_nothing_and_stops_nothing(store, monkeypatch):
    """A store folder that cannot be made (here a file stands in its way; or a read-only or
    full disk): the program runs, and nothing is left behind."""
    (store / "taken").write_text("a file, not a folder")
    monkeypatch.setattr(jaxcache, "_store_dir", lambda: store / "taken" / "exported")
    assert _equal(STORED(Scale(1.5), *_args()), jax.jit(scaled_sum, static_argnums=(0,))(Scale(1.5), *_args()))
    assert [p.name for p in store.iterdir()] == ["taken"]
